"""Mitsuba 0.6 -> Mitsuba 3 import layer: an explicit table of rewrites on the XML tree.

The literature scenes (CPPM/FPPM/APPM papers) are Mitsuba 0.6 XML. Mitsuba 3 refuses
them (camelCase names, ``<srgb>``, the ``sppm`` integrator, the ``as`` microfacet
distribution, ``extEta`` ...), so :func:`translate` applies :data:`RULES`, a list of small
named rules, each a function whose docstring says which 0.6 construct it turns into
which Mitsuba 3 construct. The rules are generic (by construct), never by file.

What the table does not know is refused by name (``Mitsuba 0.6 element <xyz type="...">
is not supported by the import layer``), never dropped in silence: the first rule checks
every tag and plugin type against :data:`KNOWN_06`. Unknown *parameters* of known
plugins are left in place, and Mitsuba 3 itself refuses them by name ("unreferenced
property"). Lossy but harmless translations (dropped film options, ``as`` -> Beckmann...)
are reported in the notes that :func:`translate` returns.

Constructs identical in both dialects need no rule: ``<ref id>`` / ``<ref name id>``,
``twosided`` (one or two nested BSDFs; neither version nests transmissive ones),
``rectangle``/``cube``/``sphere``/``disk``/``cylinder`` geometry, ``<matrix>``,
``<translate>``, ``<rotate>``, ``<scale>``, ``<point>``, ``<vector>``, ``<default>``,
``<alias>``, the IOR names of ``int_ior``/``ext_ior`` (same table), conductor material
names. Colour semantics: 0.6 ``<rgb>`` is linear (as in Mitsuba 3), 0.6 ``<srgb>`` is
sRGB-encoded and is converted to linear here; spectra are converted to linear sRGB the
way 0.6's RGB mode did (CIE 1931, no white-point adaptation), because Mitsuba 3 in RGB
mode would tint bare ``<spectrum>`` emitters by D65.
"""

from __future__ import annotations

import inspect
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, NoReturn

import numpy as np

from .scene import SceneError, describe, ensure_variant

# --------------------------------------------------------------------------- vocabulary

#: Plugin types per tag that the table translates (``None``: any type; subtree exempt).
KNOWN_06: dict[str, frozenset[str] | None] = {
    "integrator": None,
    "sensor": frozenset({"perspective", "thinlens", "orthographic"}),
    "film": frozenset({"hdrfilm", "ldrfilm", "tiledhdrfilm"}),
    "rfilter": frozenset({"box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos"}),
    "sampler": frozenset({"independent", "stratified", "ldsampler", "halton", "hammersley", "sobol"}),
    "emitter": frozenset({"area", "point", "spot", "directional", "envmap", "constant"}),
    "shape": frozenset({"obj", "ply", "serialized", "sphere", "rectangle", "cube", "disk",
                        "cylinder", "shapegroup", "instance"}),
    "bsdf": frozenset({"diffuse", "dielectric", "thindielectric", "roughdielectric", "conductor",
                       "roughconductor", "plastic", "roughplastic", "twosided", "mask", "blendbsdf"}),
    "texture": frozenset({"bitmap", "checkerboard"}),
}
#: Non-plugin tags the table knows (properties, transforms, references).
KNOWN_TAGS = frozenset({"scene", "float", "integer", "boolean", "string", "rgb", "srgb", "spectrum",
                        "point", "vector", "transform", "translate", "rotate", "scale", "matrix",
                        "lookat", "lookAt", "ref", "default", "alias"})

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

#: 0.6 film options that only concerned 0.6's own image output; ppmrecon writes its own EXR.
FILM_DROPPED = frozenset({"banner", "highQualityEdges", "attachLog", "fileFormat", "pixelFormat",
                          "componentFormat", "tonemapMethod", "gamma", "exposure", "key", "burn",
                          "metadata", "label"})

#: 0.6's named indices of refraction (the same table Mitsuba 3 uses for int_ior/ext_ior).
IOR_TABLE: dict[str, float] = {
    "vacuum": 1.0, "helium": 1.000036, "hydrogen": 1.000132, "air": 1.000277,
    "carbon dioxide": 1.00045, "water": 1.3330, "acetone": 1.36, "ethanol": 1.361,
    "carbon tetrachloride": 1.461, "glycerol": 1.4729, "benzene": 1.501, "silicone oil": 1.52045,
    "bromine": 1.661, "water ice": 1.31, "fused quartz": 1.458, "pyrex": 1.470,
    "acrylic glass": 1.49, "polypropylene": 1.49, "bk7": 1.5046, "sodium chloride": 1.544,
    "amber": 1.55, "pet": 1.575, "diamond": 2.419,
}



# --------------------------------------------------------------------------- machinery

@dataclass
class Context:
    """State shared by the rules while translating one file."""

    label: str = "<string>"
    folder: Path | None = None
    notes: list[str] = field(default_factory=list)

    def refuse(self, el: ET.Element, why: str) -> NoReturn:
        raise SceneError(f"{self.label}: Mitsuba 0.6 element {describe(el)} {why}")

    def note(self, text: str) -> None:
        if text not in self.notes:
            self.notes.append(text)


@dataclass(frozen=True)
class Rule:
    """One rewrite of the table: ``apply(root, ctx)`` edits the tree in place."""

    name: str
    apply: Callable[[ET.Element, Context], None]

    @property
    def doc(self) -> str:
        return inspect.getdoc(self.apply) or ""


RULES: list[Rule] = []


def rule(name: str) -> Callable[[Callable[[ET.Element, Context], None]], Callable[[ET.Element, Context], None]]:
    """Register a function as the next rule of :data:`RULES` (order matters)."""
    def deco(fn: Callable[[ET.Element, Context], None]) -> Callable[[ET.Element, Context], None]:
        if not inspect.getdoc(fn):
            raise TypeError(f"rule {name} needs a docstring")
        RULES.append(Rule(name, fn))
        return fn
    return deco


def translate(root: ET.Element, label: str = "<string>", folder: Path | None = None) -> list[str]:
    """Rewrite a Mitsuba 0.6 scene tree into Mitsuba 3 form in place; returns the notes.

    Raises :class:`~ppmrecon.render.scene.SceneError` naming the first construct the
    table cannot translate.
    """
    ctx = Context(label=label, folder=folder)
    for r in RULES:
        r.apply(root, ctx)
    return ctx.notes


def rule_by_name(name: str) -> Rule:
    for r in RULES:
        if r.name == name:
            return r
    raise KeyError(name)


def walk(root: ET.Element) -> Iterator[tuple[ET.Element, ET.Element | None]]:
    """(element, parent) pairs, depth first, skipping integrator subtrees (left to the loader)."""
    stack: list[tuple[ET.Element, ET.Element | None]] = [(root, None)]
    while stack:
        el, parent = stack.pop()
        if el.tag == "integrator":
            continue
        yield el, parent
        stack.extend((c, el) for c in reversed(list(el)))


def params(el: ET.Element) -> dict[str, ET.Element]:
    """Direct child elements by their ``name`` attribute."""
    return {c.get("name"): c for c in el if c.get("name") is not None}


def _floats(text: str) -> list[float]:
    return [float(t) for t in re.split(r"[,\s]+", text.strip()) if t]


def _fmt(values: list[float]) -> str:
    return ", ".join(f"{v:.6g}" for v in values)


def _replace(parent: ET.Element, old: ET.Element, new: ET.Element) -> None:
    new.tail = old.tail
    parent[list(parent).index(old)] = new


def _float_of(el: ET.Element, ctx: Context) -> float:
    """A float from a float/integer/string property (string: a named IOR or a number)."""
    value = (el.get("value") or "").strip()
    if el.tag == "string" and value.lower() in IOR_TABLE:
        return IOR_TABLE[value.lower()]
    try:
        return float(value)
    except ValueError:
        ctx.refuse(el, f"has value '{value}', which is neither a number nor a known IOR name")


def srgb_to_linear(c: float) -> float:
    """sRGB transfer function inverse (IEC 61966-2-1), extended to c > 1 and c < 0."""
    s = math.copysign(1.0, c)
    c = abs(c)
    return s * (c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4)


def _hex_rgb(text: str) -> list[float] | None:
    m = re.fullmatch(r"#([0-9a-fA-F]{6})", text.strip())
    if not m:
        return None
    h = m.group(1)
    return [int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)]


def _spectrum_to_rgb(wavelengths: list[float], values: list[float]) -> list[float]:
    """Linear sRGB of a sampled spectrum as 0.6's RGB mode computed it (CIE 1931,
    normalised by the integral of y-bar, XYZ -> sRGB without chromatic adaptation)."""
    ensure_variant()
    import mitsuba as mi
    rgb = mi.spectrum_list_to_srgb(wavelengths, values, False, False)
    return [float(rgb[i]) for i in range(3)]


# --------------------------------------------------------------------------- the table

@rule("known_constructs")
def known_constructs(root: ET.Element, ctx: Context) -> None:
    """Any tag, or plugin type of sensor/film/rfilter/sampler/emitter/shape/bsdf/texture,
    not listed in KNOWN_06/KNOWN_TAGS (e.g. ``<blackbody>``, ``<include>``,
    ``<animation>``, ``<bsdf type="roughdiffuse">``, ``<shape type="heightfield">``)
    -> refused by name. Nothing unknown is dropped."""
    for el, _ in walk(root):
        if el.tag in KNOWN_06:
            allowed = KNOWN_06[el.tag]
            if allowed is not None and el.get("type") not in allowed:
                ctx.refuse(el, "is not supported by the import layer")
        elif el.tag not in KNOWN_TAGS:
            ctx.refuse(el, "is not supported by the import layer")


@rule("scene_version")
def scene_version(root: ET.Element, ctx: Context) -> None:
    """``<scene version="0.x.y">`` -> ``<scene version="3.0.0">`` (after the rewrites
    below the tree is Mitsuba 3 XML; Mitsuba 3 would otherwise run its own partial
    0.x upgrade on top of ours)."""
    root.set("version", "3.0.0")


@rule("integrator")
def integrator(root: ET.Element, ctx: Context) -> None:
    """0.6 ``<integrator type="sppm|ppm|path|...">`` -> left for the scene loader, which
    removes it, keeps ``maxDepth`` as LoadedScene.max_depth and every other parameter
    (``photonCount``, ``initialRadius``, ``alpha``, ``kNN``, ...) in
    LoadedScene.integrator_params, and puts ``<integrator type="path">`` with that
    ``max_depth`` (and ``hide_emitters`` from 0.6 ``hideEmitters``) in its place:
    Mitsuba 3 has no photon mapper and ppmrecon renders with its own. Its subtree is
    exempt from the other rules. An integrator anywhere but under <scene> is refused."""
    for el, parent in walk(root):
        for child in el:
            if child.tag == "integrator" and el is not root:
                ctx.refuse(child, f"inside {describe(el)} is not supported by the import layer")
    if any(c.tag == "integrator" for c in root):
        ctx.note("integrator replaced by Mitsuba 3 'path' (max_depth kept); its parameters are in integrator_params")


@rule("lookat_case")
def lookat_case(root: ET.Element, ctx: Context) -> None:
    """``<lookAt origin target up>`` (0.6 spelling) -> ``<lookat ...>``."""
    for el, _ in walk(root):
        if el.tag == "lookAt":
            el.tag = "lookat"


@rule("srgb_to_rgb")
def srgb_to_rgb(root: ET.Element, ctx: Context) -> None:
    """``<srgb name value="r, g, b">`` (sRGB-encoded, or ``#rrggbb``) -> ``<rgb>`` with
    the linear values (inverse sRGB transfer curve), since 0.6 linearised ``<srgb>`` and
    Mitsuba 3's ``<rgb>`` is linear. A single value is broadcast to grey."""
    for el, _ in walk(root):
        if el.tag != "srgb":
            continue
        text = el.get("value", "")
        try:
            vals = _hex_rgb(text) or _floats(text)
        except ValueError:
            ctx.refuse(el, f"has an unreadable colour '{text}'")
        if len(vals) == 1:
            vals = vals * 3
        if len(vals) != 3:
            ctx.refuse(el, f"needs 1 or 3 values, got '{text}'")
        el.tag = "rgb"
        el.attrib.pop("intent", None)
        el.set("value", _fmt([srgb_to_linear(v) for v in vals]))


@rule("rgb_values")
def rgb_values(root: ET.Element, ctx: Context) -> None:
    """``<rgb value="#rrggbb">`` -> linear ``<rgb>`` (hex colours are sRGB-encoded);
    ``<rgb intent="...">`` -> the ``intent`` attribute (0.6 spectral-upsampling hint)
    dropped; values normalised to "r, g, b" (1 value broadcast)."""
    for el, _ in walk(root):
        if el.tag != "rgb":
            continue
        el.attrib.pop("intent", None)
        text = el.get("value", "")
        hexed = _hex_rgb(text)
        if hexed is not None:
            el.set("value", _fmt([srgb_to_linear(v) for v in hexed]))
            continue
        try:
            vals = _floats(text)
        except ValueError:
            ctx.refuse(el, f"has an unreadable colour '{text}'")
        if len(vals) not in (1, 3):
            ctx.refuse(el, f"needs 1 or 3 values, got '{text}'")
        el.set("value", _fmt(vals * 3 if len(vals) == 1 else vals))


@rule("spectrum_values")
def spectrum_values(root: ET.Element, ctx: Context) -> None:
    """``<spectrum value="0.5">`` (bare number: a flat spectrum) -> ``<rgb value="0.5,
    0.5, 0.5">`` (Mitsuba 3 in RGB mode would tint a flat emitter spectrum by D65);
    ``<spectrum value="400:0.1, 500:0.5, ...">`` and ``<spectrum filename="x.spd">`` ->
    ``<rgb>`` with the spectrum's linear sRGB, computed as 0.6's RGB mode did. A list of
    plain numbers (0.6's binned form) is refused."""
    for el, _ in walk(root):
        if el.tag != "spectrum":
            continue
        if el.get("type") is not None:
            ctx.refuse(el, "(typed spectrum) is not supported by the import layer")
        el.attrib.pop("intent", None)
        text = (el.get("value") or "").strip()
        if el.get("filename") is not None:
            fname = Path(el.get("filename"))
            if not fname.is_absolute() and ctx.folder is not None:
                fname = ctx.folder / fname
            if not fname.exists():
                ctx.refuse(el, f"refers to '{el.get('filename')}', which does not exist")
            ensure_variant()
            import mitsuba as mi
            wl, vs = mi.spectrum_from_file(str(fname))
            rgb = _spectrum_to_rgb(list(wl), list(vs))
            del el.attrib["filename"]
        elif ":" in text:
            try:
                pairs = [p.split(":") for p in re.split(r"[,\s]+", text) if p]
                wl = [float(a) for a, _ in pairs]
                vs = [float(b) for _, b in pairs]
            except ValueError:
                ctx.refuse(el, f"has an unreadable wavelength:value list '{text}'")
            rgb = _spectrum_to_rgb(wl, vs)
        else:
            try:
                vals = _floats(text)
            except ValueError:
                ctx.refuse(el, f"has an unreadable value '{text}'")
            if len(vals) != 1:
                ctx.refuse(el, "with a plain list of values (0.6 binned spectrum) is not supported "
                               "by the import layer; use wavelength:value pairs")
            rgb = vals * 3
        el.tag = "rgb"
        el.set("value", _fmt(rgb))


@rule("param_renames")
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


@rule("numeric_types")
def numeric_types(root: ET.Element, ctx: Context) -> None:
    """``<float name="width" value="800">`` and other integer-typed Mitsuba 3 parameters
    (INTEGER_PARAMS) given as ``<float>`` -> ``<integer>`` (0.6 converted silently,
    Mitsuba 3 refuses); a non-integral value is refused. (``<integer>`` where Mitsuba 3
    wants a float is accepted by Mitsuba 3 as is.)"""
    for el, _ in walk(root):
        if el.tag == "float" and el.get("name") in INTEGER_PARAMS:
            value = float(el.get("value", "nan"))
            if not value.is_integer():
                ctx.refuse(el, f"must be an integer, got {el.get('value')}")
            el.tag = "integer"
            el.set("value", str(int(value)))


@rule("microfacet_distribution")
def microfacet_distribution(root: ET.Element, ctx: Context) -> None:
    """``<string name="distribution" value="as">`` (Ashikhmin-Shirley) and ``"phong"`` on
    rough BSDFs -> ``"beckmann"`` with the same alpha(s). 0.6 turned alpha into the
    Phong/AS exponent e = 2/alpha^2 - 2, which is Walter et al.'s (2007) match of the
    Beckmann lobe of width alpha (AS is the anisotropic Phong form); GGX with the same
    alpha would have much longer tails. ``beckmann``/``ggx`` are kept."""
    for el, parent in walk(root):
        if el.tag == "string" and el.get("name") == "distribution" and parent is not None \
                and parent.tag == "bsdf":
            value = (el.get("value") or "").strip().lower()
            if value in ("as", "phong"):
                el.set("value", "beckmann")
                ctx.note(f"microfacet distribution '{value}' mapped to 'beckmann' (same alpha)")
            elif value not in ("beckmann", "ggx"):
                ctx.refuse(el, f"has an unknown microfacet distribution '{value}'")


@rule("conductor_default_material")
def conductor_default_material(root: ET.Element, ctx: Context) -> None:
    """A 0.6 ``conductor``/``roughconductor`` with neither ``material`` nor ``eta``/``k``
    -> ``<string name="material" value="Cu">``: 0.6's default material was copper,
    Mitsuba 3's is ``none`` (a perfect mirror)."""
    for el, _ in walk(root):
        if el.tag == "bsdf" and el.get("type") in ("conductor", "roughconductor"):
            p = params(el)
            if "material" not in p and "eta" not in p and "k" not in p:
                mat = ET.Element("string", {"name": "material", "value": "Cu"})
                mat.tail = "\n"
                el.insert(0, mat)


@rule("conductor_ext_eta")
def conductor_ext_eta(root: ET.Element, ctx: Context) -> None:
    """``extEta`` (the exterior IOR, a number or a name like "air") on 0.6
    ``conductor``/``roughconductor`` -> folded into Mitsuba 3's relative ``eta``/``k``:
    dropped when it is 1 within 1e-3 (vacuum, air: < 0.03 % change) or the material is
    ``none``; otherwise eta and k (explicit, or those of the named material as Mitsuba 3
    tabulates them in RGB) are divided by it and written as ``<rgb name="eta|k">``."""
    for el, _ in walk(root):
        if el.tag != "bsdf" or el.get("type") not in ("conductor", "roughconductor"):
            continue
        p = params(el)
        ext_el = p.get("extEta", p.get("ext_eta"))
        if ext_el is None:
            continue
        ext = _float_of(ext_el, ctx)
        el.remove(ext_el)
        mat_el = p.get("material")
        material = (mat_el.get("value") if mat_el is not None else "none") or "none"
        if abs(ext - 1.0) <= 1e-3 or ("eta" not in p and material.lower() == "none"):
            ctx.note(f"conductor extEta={ext:g} dropped (relative IOR unchanged)")
            continue
        if ext <= 0:
            ctx.refuse(ext_el, "must be positive")
        if "eta" in p or "k" in p:
            for key in ("eta", "k"):
                if key not in p:
                    continue
                node = p[key]
                if node.tag not in ("rgb", "float"):
                    ctx.refuse(node, "must be a float or rgb value to fold extEta into it")
                vals = [v / ext for v in _floats(node.get("value", ""))]
                node.set("value", _fmt(vals))
            continue
        ensure_variant()
        import mitsuba as mi
        try:
            cond = mi.load_dict({"type": "conductor", "material": material})
        except Exception:
            ctx.refuse(mat_el if mat_el is not None else el, f"names an unknown conductor material '{material}'")
        tp = mi.traverse(cond)
        for key in ("eta", "k"):
            rgb = [float(v) / ext for v in np.asarray(tp[f"{key}.value"], dtype=np.float64).ravel()]
            if len(rgb) == 1:
                rgb = rgb * 3
            node = ET.Element("rgb", {"name": key, "value": _fmt(rgb)})
            node.tail = "\n"
            el.append(node)
        if mat_el is not None:
            el.remove(mat_el)
        ctx.note(f"conductor '{material}' in a medium of IOR {ext:g}: eta, k divided by it (RGB)")


@rule("sampler_types")
def sampler_types(root: ET.Element, ctx: Context) -> None:
    """0.6 samplers ``sobol``, ``ldsampler``, ``halton``, ``hammersley``, ``stratified`` ->
    ``independent`` with the same ``sample_count``; their ``dimension``/``scramble``
    options are dropped (ppmrecon draws its own random numbers; Mitsuba 3 has no
    sobol/halton)."""
    for el, _ in walk(root):
        if el.tag == "sampler" and el.get("type") != "independent":
            ctx.note(f"sampler '{el.get('type')}' replaced by 'independent'")
            el.set("type", "independent")
            for child in list(el):
                if child.get("name") in ("dimension", "scramble"):
                    el.remove(child)


@rule("film_options")
def film_options(root: ET.Element, ctx: Context) -> None:
    """0.6-only film options (``banner``, ``highQualityEdges``, ``attachLog``,
    ``fileFormat``, ``pixelFormat``, ``componentFormat``, tone-mapping ``gamma``/
    ``exposure``/``key``/``burn``/``tonemapMethod``, ``metadata``, ``label``) -> dropped:
    they shaped 0.6's output file, and ppmrecon writes its own EXR; ``ldrfilm`` and
    ``tiledhdrfilm`` -> ``hdrfilm`` (same size, crop and reconstruction filter)."""
    for el, _ in walk(root):
        if el.tag != "film":
            continue
        if el.get("type") != "hdrfilm":
            ctx.note(f"film '{el.get('type')}' replaced by 'hdrfilm'")
            el.set("type", "hdrfilm")
        for child in list(el):
            if child.get("name") in FILM_DROPPED:
                el.remove(child)


@rule("bitmap_options")
def bitmap_options(root: ET.Element, ctx: Context) -> None:
    """0.6 bitmap-texture options -> Mitsuba 3's: ``filter_type`` ``ewa``/``trilinear``
    -> ``bilinear`` (Mitsuba 3 has no mip-mapping), ``nearest`` kept; ``wrapModeU``/
    ``wrapModeV`` (equal) -> ``wrap_mode``; ``repeat``/``mirror``/``clamp`` kept
    (``zero``/``one`` refused); ``gamma`` -1 (from file) dropped, 1 -> ``raw=true``,
    others refused; ``maxAnisotropy`` and ``cache`` dropped (no effect in Mitsuba 3).
    ``cache`` on ``envmap`` emitters is dropped too."""
    for el, _ in walk(root):
        if el.tag == "emitter" and el.get("type") == "envmap":
            for child in list(el):
                if child.get("name") == "cache":
                    el.remove(child)
                elif child.get("name") == "gamma":
                    if _float_of(child, ctx) != -1:
                        ctx.refuse(child, "(a gamma override on an envmap) is not supported by the import layer")
                    el.remove(child)
        if el.tag != "texture" or el.get("type") != "bitmap":
            continue
        p = params(el)
        for key in ("maxAnisotropy", "cache"):
            if key in p:
                el.remove(p[key])
        if "filter_type" in p or "filterType" in p:
            node = p["filter_type"] if "filter_type" in p else p["filterType"]
            node.set("name", "filter_type")
            value = (node.get("value") or "").lower()
            if value in ("ewa", "trilinear", "bilinear"):
                node.set("value", "bilinear")
            elif value != "nearest":
                ctx.refuse(node, f"has an unknown filter type '{value}'")
        wraps = [p[k] for k in ("wrap_mode", "wrapMode", "wrapModeU", "wrapModeV") if k in p]
        if wraps:
            values = {(w.get("value") or "").lower() for w in wraps}
            if len(values) != 1:
                ctx.refuse(el, "with different wrap modes in u and v is not supported by the import layer")
            value = values.pop()
            if value not in ("repeat", "mirror", "clamp"):
                ctx.refuse(wraps[0], f"has wrap mode '{value}', which Mitsuba 3 does not offer")
            for w in wraps[1:]:
                el.remove(w)
            wraps[0].set("name", "wrap_mode")
            wraps[0].set("value", value)
        if "gamma" in p:
            g = _float_of(p["gamma"], ctx)
            if g == -1:
                el.remove(p["gamma"])
            elif g == 1:
                _replace(el, p["gamma"], ET.Element("boolean", {"name": "raw", "value": "true"}))
            else:
                ctx.refuse(p["gamma"], "(a gamma other than -1 or 1) is not supported by the import layer")


@rule("texture_uv_transform")
def texture_uv_transform(root: ET.Element, ctx: Context) -> None:
    """0.6 texture ``uscale``/``vscale``/``uoffset``/``voffset`` (uv' = uv * scale +
    offset) -> ``<transform name="to_uv"><scale x y/><translate x y/></transform>``."""
    for el, _ in walk(root):
        if el.tag != "texture":
            continue
        p = params(el)
        keys = [k for k in ("uscale", "vscale", "uoffset", "voffset") if k in p]
        if not keys:
            continue
        v = {k: (_float_of(p[k], ctx) if k in p else (1.0 if "scale" in k else 0.0))
             for k in ("uscale", "vscale", "uoffset", "voffset")}
        for k in keys:
            el.remove(p[k])
        tr = ET.Element("transform", {"name": "to_uv"})
        ET.SubElement(tr, "scale", {"x": f"{v['uscale']:.6g}", "y": f"{v['vscale']:.6g}"})
        ET.SubElement(tr, "translate", {"x": f"{v['uoffset']:.6g}", "y": f"{v['voffset']:.6g}"})
        tr.tail = "\n"
        el.append(tr)


@rule("spot_light")
def spot_light(root: ET.Element, ctx: Context) -> None:
    """0.6 ``<emitter type="spot">`` -> Mitsuba 3 ``spot``: ``cutoffAngle``/``beamWidth``
    -> ``cutoff_angle``/``beam_width`` (same defaults, 20 deg and 3/4 of it), ``intensity``
    kept (default 1 in both), and a projected ``<texture name="texture">`` kept as is:
    both versions look it up at uv = 0.5 + 0.5 * d.xy / (d.z tan(cutoff)) in the light's
    frame and multiply it into the intensity. A nested emitter texture under another name
    is refused."""
    for el, _ in walk(root):
        if el.tag != "emitter" or el.get("type") != "spot":
            continue
        for child in el:
            name = child.get("name")
            if name in ("cutoffAngle", "beamWidth"):
                child.set("name", RENAMES[name])
            if child.tag == "texture" and name not in ("texture", "intensity"):
                ctx.refuse(child, "inside a spot light is not supported by the import layer")


@rule("mesh_options")
def mesh_options(root: ET.Element, ctx: Context) -> None:
    """0.6 mesh options without a Mitsuba 3 counterpart: ``maxSmoothAngle`` (crease
    angle for recomputed normals) -> ``face_normals=true`` when it is 0, else dropped
    (Mitsuba 3 keeps the file's normals or smooths all); obj ``collapse`` dropped."""
    for el, _ in walk(root):
        if el.tag != "shape" or el.get("type") not in ("obj", "ply", "serialized"):
            continue
        p = params(el)
        if "collapse" in p:
            el.remove(p["collapse"])
        if "maxSmoothAngle" in p:
            angle = _float_of(p["maxSmoothAngle"], ctx)
            if angle <= 0 and "face_normals" not in p:
                _replace(el, p["maxSmoothAngle"], ET.Element("boolean", {"name": "face_normals", "value": "true"}))
            else:
                el.remove(p["maxSmoothAngle"])
                ctx.note(f"maxSmoothAngle={angle:g} dropped on {describe(el)}: Mitsuba 3 has no crease angle")


@rule("shutter_time")
def shutter_time(root: ET.Element, ctx: Context) -> None:
    """0.6 sensor ``shutterOpen`` + ``shutterOpenTime`` (a duration) -> Mitsuba 3
    ``shutter_open`` + ``shutter_close`` (an end time)."""
    for el, _ in walk(root):
        if el.tag != "sensor":
            continue
        p = params(el)
        if "shutterOpen" not in p and "shutterOpenTime" not in p:
            continue
        start = _float_of(p["shutterOpen"], ctx) if "shutterOpen" in p else 0.0
        length = _float_of(p["shutterOpenTime"], ctx) if "shutterOpenTime" in p else 0.0
        for k in ("shutterOpen", "shutterOpenTime"):
            if k in p:
                el.remove(p[k])
        for name, value in (("shutter_open", start), ("shutter_close", start + length)):
            node = ET.Element("float", {"name": name, "value": f"{value:.6g}"})
            node.tail = "\n"
            el.insert(0, node)


@rule("references")
def references(root: ET.Element, ctx: Context) -> None:
    """``<ref id="x">`` -> checked: every reference must name an ``id`` declared in the
    file (0.6 and Mitsuba 3 share the syntax; a dangling one is refused here by id rather
    than by Mitsuba 3's internal property name)."""
    ids = {el.get("id") for el in root.iter() if el.get("id") is not None and el.tag != "ref"}
    for el, _ in walk(root):
        if el.tag == "ref" and el.get("id") not in ids:
            ctx.refuse(el, f"refers to id '{el.get('id')}', which is not declared in the file")
