"""Mitsuba 0.6 XML structure: ``<include>``, ``<default>`` and ``$name`` parameters,
``<ref>``/``id``, transforms, the scene version, parameter names and numeric types.

These rules run first (``EARLY``: before anything looks at plugin types, so included
files and substituted parameters are checked like the rest) and after the colour rules
(``LATE``: renames, so that the plugin modules see Mitsuba 3 parameter names).
Mitsuba 0.6 documentation: section 6 "Scene file format" (property types, transformations,
instancing and references for ``ref``/``id``, including external files, default
parameter values).
"""

from __future__ import annotations

import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from .common import Context, RuleList, describe, floats, parse_xml, walk

EARLY = RuleList()
LATE = RuleList()

#: Structural tags of the 0.6 format (property types, transforms, references).
KNOWN_TAGS = frozenset({"scene", "float", "integer", "boolean", "string", "rgb", "srgb", "spectrum",
                        "blackbody", "point", "vector", "transform", "translate", "rotate", "scale",
                        "matrix", "lookat", "lookAt", "ref", "default", "alias", "include"})

#: 0.6 camelCase parameter names -> Mitsuba 3 names (plugins' own renames).
RENAMES: dict[str, str] = {
    "maxDepth": "max_depth", "rrDepth": "rr_depth", "sampleCount": "sample_count",
    "intIOR": "int_ior", "extIOR": "ext_ior",
    "specularReflectance": "specular_reflectance", "specularTransmittance": "specular_transmittance",
    "diffuseReflectance": "diffuse_reflectance",
    "alphaU": "alpha_u", "alphaV": "alpha_v", "sampleVisible": "sample_visible",
    "cutoffAngle": "cutoff_angle", "beamWidth": "beam_width", "samplingWeight": "sampling_weight",
    "fovAxis": "fov_axis", "focalLength": "focal_length", "nearClip": "near_clip", "farClip": "far_clip",
    "focusDistance": "focus_distance", "apertureRadius": "aperture_radius",
    "toWorld": "to_world", "shapeIndex": "shape_index", "faceNormals": "face_normals",
    "flipNormals": "flip_normals", "flipTexCoords": "flip_tex_coords",
    "cropOffsetX": "crop_offset_x", "cropOffsetY": "crop_offset_y",
    "cropWidth": "crop_width", "cropHeight": "crop_height",
    "filterType": "filter_type", "wrapMode": "wrap_mode",
}

#: Mitsuba 3 parameters that must be ``<integer>`` (0.6 files sometimes say ``<float>``).
INTEGER_PARAMS = frozenset({"width", "height", "sample_count", "shape_index", "max_depth", "rr_depth",
                            "crop_offset_x", "crop_offset_y", "crop_width", "crop_height", "lobes"})

_MAX_INCLUDE_DEPTH = 16


def _include_file(el: ET.Element, ctx: Context, base: Path | None, depth: int) -> list[ET.Element]:
    """The children of the ``<scene>`` in the file an ``<include>`` names, with their own
    includes expanded (relative names resolve against the including file's folder, then
    the main scene's folder, as 0.6's file resolver did)."""
    name = el.get("filename")
    if not name:
        ctx.refuse(el, "has no filename attribute")
    if depth > _MAX_INCLUDE_DEPTH:
        ctx.refuse(el, f"nests includes deeper than {_MAX_INCLUDE_DEPTH} levels (a cycle?)")
    candidates = [Path(name)] if os.path.isabs(name) else \
        [d / name for d in (base, ctx.folder) if d is not None]
    path = next((p for p in candidates if p.is_file()), None)
    if path is None:
        ctx.refuse(el, f"includes '{name}', which does not exist")
    root, lines = parse_xml(path.read_bytes(), str(path))
    ctx.lines.update(lines)
    if root.tag != "scene":
        ctx.refuse(el, f"includes '{name}', whose root element is <{root.tag}>, not <scene>")
    _expand(root, ctx, path.parent, depth + 1)
    return list(root)


def _expand(parent: ET.Element, ctx: Context, base: Path | None, depth: int) -> None:
    for i, c in reversed(list(enumerate(parent))):
        if c.tag == "include":
            parent[i:i + 1] = _include_file(c, ctx, base, depth)
        else:
            _expand(c, ctx, base, depth)


@EARLY.rule("include")
def include(root: ET.Element, ctx: Context) -> None:
    """``<include filename="part.xml"/>`` (0.6 doc section 6, including external files) -> the children of the included
    file's ``<scene>`` spliced in its place, recursively; a missing file, a root other
    than ``<scene>`` or nesting deeper than 16 levels is refused with the include's line."""
    _expand(root, ctx, ctx.folder, 0)


_PARAM = re.compile(r"\$(\w+)")


@EARLY.rule("defaults")
def defaults(root: ET.Element, ctx: Context) -> None:
    """``<default name="spp" value="64"/>`` + ``value="$spp"`` (0.6 doc section 6, default parameter values) -> every
    ``$name`` in every attribute replaced by its default and the ``<default>`` elements
    removed (Mitsuba 3 would apply them too, but the loader must see real values to
    check files and depths); a ``$name`` with no default is refused with its line."""
    values: dict[str, str] = {}
    for el in list(root.iter()):
        if el.tag == "default":
            if el.get("name") is None or el.get("value") is None:
                ctx.refuse(el, "needs name and value attributes")
            values.setdefault(el.get("name"), el.get("value"))
    for el in root.iter():
        for key, text in el.attrib.items():
            if "$" not in text:
                continue

            def sub(m: re.Match) -> str:
                if m.group(1) not in values:
                    ctx.refuse(el, f"uses parameter ${m.group(1)}, which has no <default> in the file")
                return values[m.group(1)]
            el.set(key, _PARAM.sub(sub, text))
    for parent in list(root.iter()):
        for c in list(parent):
            if c.tag == "default":
                parent.remove(c)


@EARLY.rule("scene_version")
def scene_version(root: ET.Element, ctx: Context) -> None:
    """``<scene version="0.x.y">`` -> ``<scene version="3.0.0">`` (after the rewrites
    below the tree is Mitsuba 3 XML; Mitsuba 3 would otherwise run its own partial
    0.x upgrade on top of ours)."""
    root.set("version", "3.0.0")


@EARLY.rule("integrator")
def integrator(root: ET.Element, ctx: Context) -> None:
    """0.6 ``<integrator type="sppm|ppm|path|...">`` -> left for the scene loader, which
    removes it, keeps ``maxDepth`` as LoadedScene.max_depth and every other parameter
    (``photonCount``, ``initialRadius``, ``alpha``, ``kNN``, ...) in
    LoadedScene.integrator_params, and puts ``<integrator type="path">`` with that
    ``max_depth`` (and ``hide_emitters`` from 0.6 ``hideEmitters``) in its place:
    Mitsuba 3 has no photon mapper and ppmrecon renders with its own. Its subtree is
    exempt from the other rules. An integrator anywhere but under <scene> is refused."""
    for el, parent in walk(root):
        for c in el:
            if c.tag == "integrator" and el is not root:
                ctx.refuse(c, f"inside {describe(el)} is not supported by the import layer")
    if any(c.tag == "integrator" for c in root):
        ctx.note("integrator replaced by Mitsuba 3 'path' (max_depth kept); its parameters are in integrator_params")


@EARLY.rule("transforms")
def transforms(root: ET.Element, ctx: Context) -> None:
    """0.6 transform operations (doc section 6, transformations) -> Mitsuba 3's, which share the syntax except:
    ``<lookAt>`` -> ``<lookat>`` (0.6 spelling); ``<matrix>`` must have 16 values (0.6
    refused anything else; Mitsuba 3 would also read 9); ``<scale>`` with both ``value``
    and x/y/z is refused, as 0.6 did; a ``<rotate>`` without ``angle`` is refused
    (0.6 required it; Mitsuba 3 would silently rotate by 0)."""
    for el, _ in walk(root):
        if el.tag == "lookAt":
            el.tag = "lookat"
        if el.tag == "matrix":
            try:
                n = len(floats(el.get("value", "")))
            except ValueError:
                ctx.refuse(el, f"has an unreadable value '{el.get('value')}'")
            if n != 16:
                ctx.refuse(el, f"needs 16 values (a 4x4 matrix, row by row), got {n}")
        if el.tag == "scale" and el.get("value") is not None and any(k in el.attrib for k in "xyz"):
            ctx.refuse(el, "has both value and x/y/z attributes")
        if el.tag == "rotate" and el.get("angle") is None:
            ctx.refuse(el, "has no angle attribute")


@EARLY.rule("references")
def references(root: ET.Element, ctx: Context) -> None:
    """``<ref id="x">`` (0.6 doc section 6, references) -> checked: every reference must name an ``id``
    declared in the file (0.6 and Mitsuba 3 share the syntax; a dangling one is refused
    here by id and line rather than by Mitsuba 3's internal property name); a duplicate
    ``id`` is refused as 0.6 refused it."""
    seen: dict[str, ET.Element] = {}
    for el in root.iter():
        i = el.get("id")
        if i is None or el.tag == "ref":
            continue
        if i in seen:
            ctx.refuse(el, f"reuses id '{i}' (first declared at {ctx.where(seen[i])})")
        seen[i] = el
    for el, _ in walk(root):
        if el.tag == "ref" and el.get("id") not in seen:
            ctx.refuse(el, f"refers to id '{el.get('id')}', which is not declared in the file")


@LATE.rule("param_renames")
def param_renames(root: ET.Element, ctx: Context) -> None:
    """camelCase parameter names -> the snake_case names Mitsuba 3 gave the same
    parameters (table RENAMES: ``maxDepth``->``max_depth``, ``sampleCount``->
    ``sample_count``, ``intIOR``->``int_ior``, ``specularReflectance``->
    ``specular_reflectance``, ``cutoffAngle``->``cutoff_angle``, ``fovAxis``->``fov_axis``,
    ``nearClip``->``near_clip``, ``toWorld``->``to_world`` (also on ``<transform>``),
    ``shapeIndex``->``shape_index``, ``faceNormals``->``face_normals``, ...). Names not in
    the table are left alone, so that Mitsuba 3 names any it does not know."""
    for el, _ in walk(root):
        name = el.get("name")
        if name in RENAMES:
            el.set("name", RENAMES[name])


@LATE.rule("numeric_types")
def numeric_types(root: ET.Element, ctx: Context) -> None:
    """``<float name="width" value="800">`` and other integer-typed Mitsuba 3 parameters
    (INTEGER_PARAMS) given as ``<float>`` -> ``<integer>`` (0.6 converted silently,
    Mitsuba 3 refuses); a non-integral value is refused. (``<integer>`` where Mitsuba 3
    wants a float is accepted by Mitsuba 3 as is.)"""
    for el, _ in walk(root):
        if el.tag == "float" and el.get("name") in INTEGER_PARAMS:
            try:
                value = float(el.get("value", "nan"))
            except ValueError:
                ctx.refuse(el, f"is not a number: '{el.get('value')}'")
            if not value.is_integer():
                ctx.refuse(el, f"must be an integer, got {el.get('value')}")
            el.tag = "integer"
            el.set("value", str(int(value)))


__all__ = ["EARLY", "LATE", "KNOWN_TAGS", "RENAMES", "INTEGER_PARAMS"]
