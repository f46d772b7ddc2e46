"""Mitsuba 0.6 -> Mitsuba 3 import: the ordered table of rewrites on the XML tree.

Public scene collections (Bitterli's as converted for 0.6, the CPPM/FPPM papers' scenes)
are Mitsuba 0.6 XML, which Mitsuba 3 refuses (camelCase names, ``<srgb>``, 0.6-only
plugins, ...). :func:`translate` applies :data:`RULES`, small named rules gathered from
one module per plugin kind, in this order:

1. :mod:`.xml06` structure: ``<include>``, ``<default>``/``$name``, then the vocabulary
   check of :func:`known_constructs`, the version, the integrator, transforms, ``ref``;
2. :mod:`.spectra`: every colour form to linear ``<rgb>``;
3. :mod:`.xml06` parameter renames and numeric types;
4. :mod:`.textures`, :mod:`.bsdfs`, :mod:`.emitters`, :mod:`.shapes`, :mod:`.sensors`.

Every rule's docstring says which 0.6 construct becomes which Mitsuba 3 construct and
cites the 0.6 documentation section. What has no exact counterpart is approximated and
*noted* (``Context.note``: the notes are printed at load and stored in the buffer
header as ``ppmrecon.import_notes``), or refused with one line naming the element and
its line in the file. Unknown *parameters* of known plugins are left in place, and
Mitsuba 3 itself refuses them by name ("unreferenced property").
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from . import bsdfs, emitters, sensors, shapes, spectra, textures, xml06
from .common import Context, Lines, Rule, RuleList, walk

#: Plugin types per tag that the import knows (``None``: any type; subtree exempt).
KNOWN_06: dict[str, frozenset[str] | None] = {
    "integrator": None,
    "sensor": sensors.KNOWN_SENSORS,
    "film": sensors.KNOWN_FILMS,
    "rfilter": sensors.KNOWN_FILTERS,
    "sampler": sensors.KNOWN_SAMPLERS,
    "emitter": emitters.KNOWN,
    "shape": shapes.KNOWN,
    "bsdf": bsdfs.KNOWN,
    "texture": textures.KNOWN,
}
#: (tag, type) -> why it cannot be imported (known to 0.6, nothing to map it to).
REFUSED_06: dict[tuple[str, str], str] = {
    **{("bsdf", t): why for t, why in bsdfs.REFUSED.items()},
    **{("shape", t): why for t, why in shapes.REFUSED.items()},
    **{("sensor", t): why for t, why in sensors.REFUSED_SENSORS.items()},
    **{("film", t): why for t, why in sensors.REFUSED_FILMS.items()},
}
#: What the renderer does not simulate, in either dialect (refused by name).
MEDIUM_TAGS = ("medium", "phase", "subsurface", "volume")

_CHECK = RuleList()


@_CHECK.rule("known_constructs")
def known_constructs(root: ET.Element, ctx: Context) -> None:
    """Any tag, or plugin type of sensor/film/rfilter/sampler/emitter/shape/bsdf/texture,
    not in KNOWN_06 / xml06.KNOWN_TAGS (e.g. ``<animation>``, ``<bsdf type="hk">``,
    ``<texture type="wireframe">``) -> refused by name and line; known 0.6 plugins with
    no Mitsuba 3 counterpart (REFUSED_06: ``difftrans``, ``hair``, ``heightfield``,
    sensors the renderer does not sample) -> refused with the reason; participating
    media (``medium``, ``phase``, ``subsurface``) -> refused: not simulated. Nothing
    unknown is dropped."""
    for el, _ in walk(root):
        if el.tag in MEDIUM_TAGS:
            ctx.refuse(el, "cannot be imported: participating media are not simulated by the ppmrecon renderer")
        if el.tag in KNOWN_06:
            allowed = KNOWN_06[el.tag]
            if allowed is not None and el.get("type") not in allowed:
                ctx.refuse(el, "is not supported by the import layer")
            why = REFUSED_06.get((el.tag, el.get("type", "")))
            if why is not None:
                ctx.refuse(el, f"cannot be imported: {why}")
        elif el.tag not in xml06.KNOWN_TAGS:
            ctx.refuse(el, "is not supported by the import layer")


RULES: list[Rule] = [*xml06.EARLY[:2], *_CHECK, *xml06.EARLY[2:], *spectra.RULES, *xml06.LATE,
                     *textures.RULES, *bsdfs.RULES, *emitters.RULES, *shapes.RULES, *sensors.RULES]


def translate(root: ET.Element, label: str = "<string>", folder: Path | None = None,
              lines: Lines | None = None, ctx: Context | None = None) -> list[str]:
    """Rewrite a Mitsuba 0.6 scene tree into Mitsuba 3 form in place; returns the notes.

    ``lines`` maps elements to (file, line) for messages (see ``common.parse_xml``);
    ``ctx`` may be passed to keep its scratch folder (derived bitmaps) alive until the
    caller has loaded the scene and calls ``ctx.cleanup()``. Raises
    :class:`~ppmrecon.scene.common.SceneError` naming the first construct the table
    cannot translate.
    """
    ctx = ctx or Context()
    ctx.label, ctx.folder = label, folder
    if lines:
        ctx.lines.update(lines)
    for r in RULES:
        r.apply(root, ctx)
    return ctx.notes


def rule_by_name(name: str) -> Rule:
    for r in RULES:
        if r.name == name:
            return r
    raise KeyError(name)
