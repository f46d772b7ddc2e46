"""Mitsuba 0.6 shapes -> Mitsuba 3 shapes (0.6 documentation, section 8.1 "Shapes").

Same plugin and parameters (after the renames of :mod:`.xml06`): ``obj``, ``ply``,
``serialized`` (``shapeIndex``), ``sphere``, ``rectangle``, ``disk``, ``cube``,
``cylinder``, ``shapegroup`` + ``instance``. 0.6 mesh options without a Mitsuba 3
counterpart are dropped or mapped here. Refused: ``hair`` and ``heightfield`` (Mitsuba
3 has no such shapes).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from .common import Context, RuleList, float_of, params, plugins, replace

RULES = RuleList()

KNOWN = frozenset({"obj", "ply", "serialized", "sphere", "rectangle", "cube", "disk", "cylinder",
                   "shapegroup", "instance", "hair", "heightfield"})
REFUSED = {"hair": "Mitsuba 3 has no hair shape (its 'bsplinecurve' reads a different format)",
           "heightfield": "Mitsuba 3 has no height-field shape"}


@RULES.rule("mesh_options")
def mesh_options(root: ET.Element, ctx: Context) -> None:
    """0.6 mesh options without a Mitsuba 3 counterpart: ``maxSmoothAngle`` (crease
    angle for recomputed normals) -> ``face_normals=true`` when it is 0, else dropped
    (Mitsuba 3 keeps the file's normals or smooths all; noted); obj ``collapse`` dropped
    (merging the file's groups into one shape changes nothing that is rendered)."""
    for el, _ in plugins(root, "shape", ("obj", "ply", "serialized")):
        p = params(el)
        if "collapse" in p:
            el.remove(p["collapse"])
        if "maxSmoothAngle" in p:
            angle = float_of(p["maxSmoothAngle"], ctx)
            if angle <= 0 and "face_normals" not in p:
                replace(el, p["maxSmoothAngle"], ET.Element("boolean", {"name": "face_normals", "value": "true"}))
            else:
                el.remove(p["maxSmoothAngle"])
                ctx.note(f"maxSmoothAngle={angle:g} dropped: Mitsuba 3 has no crease angle", el)
