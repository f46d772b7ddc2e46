"""Mitsuba 0.6 textures -> Mitsuba 3 textures (0.6 documentation, section 8.3 "Textures":
``bitmap``, ``checkerboard``, ``gridtexture``, ``scale``, ``vertexcolors``, ``wireframe``,
``curvature``).

Mitsuba 3 has ``bitmap``, ``checkerboard`` and ``mesh_attribute``. What it lacks is
baked: a bitmap channel, a gamma other than sRGB/linear, a scaled bitmap or a grid
texture become a *derived* float EXR (linear, ``raw``) in the translation's scratch
folder, which Mitsuba 3 reads at load time; every such bake is a note. ``wireframe`` and
``curvature`` depend on the mesh's triangles and are refused.
"""

from __future__ import annotations

import copy
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .common import (Context, RuleList, child, const_rgb, ensure_variant, float_of, fmt, floats,
                     param_float, params, plugins, remove, replace, walk)

RULES = RuleList()

KNOWN = frozenset({"bitmap", "checkerboard", "gridtexture", "scale", "vertexcolors"})

#: Side of the bitmap a grid texture is rasterised to (lines at least 2 pixels wide).
GRID_MIN_RES, GRID_MAX_RES = 1024, 8192


def _resolve(ctx: Context, name: str) -> Path:
    path = Path(name)
    if not path.is_absolute() and ctx.folder is not None:
        path = ctx.folder / path
    return path


def _bitmap_path(tex: ET.Element, ctx: Context) -> Path:
    node = params(tex).get("filename")
    if node is None:
        ctx.refuse(tex, "has no filename")
    path = _resolve(ctx, node.get("value", ""))
    if not path.is_file():
        ctx.refuse(node, f"refers to '{node.get('value')}', which does not exist")
    return path


def load_linear(path: Path, gamma: float) -> tuple[np.ndarray, list[str]]:
    """Pixels of an image file as linear float32 (H, W, C) and its channel names:
    ``gamma`` -1 decodes with the file's own curve (sRGB for 8-bit files, as 0.6 did),
    1 keeps the stored values, anything else decodes v ** gamma (0.6's override)."""
    ensure_variant()
    import mitsuba as mi
    bmp = mi.Bitmap(str(path))
    names = [f.name for f in bmp.struct_()]
    if gamma == -1:
        arr = np.array(bmp.convert(bmp.pixel_format(), mi.Struct.Type.Float32, False))
    else:
        arr = np.array(bmp.convert(bmp.pixel_format(), mi.Struct.Type.Float32, bmp.srgb_gamma()))
        if gamma != 1:
            arr = np.power(np.clip(arr, 0.0, None), gamma)
    arr = arr.reshape(arr.shape[0], arr.shape[1], -1).astype(np.float32)
    return arr, names


def write_derived(ctx: Context, pixels: np.ndarray, stem: str) -> Path:
    """Write linear float pixels (H, W, C) to a scratch EXR; returns its path."""
    ensure_variant()
    import mitsuba as mi
    path = ctx.scratch_file(stem)
    mi.Bitmap(np.ascontiguousarray(pixels, dtype=np.float32)).write(str(path))
    return path


def _set_derived(tex: ET.Element, path: Path) -> None:
    """Point a bitmap element at a derived (linear) file."""
    remove(tex, "filename", "raw")
    child(tex, "string", "filename", str(path), index=0)
    child(tex, "boolean", "raw", "true", index=1)


def _bitmap_gamma(tex: ET.Element, ctx: Context) -> float:
    p = params(tex)
    if "raw" in p and (p["raw"].get("value") or "").lower() == "true":
        return 1.0
    return float_of(p["gamma"], ctx) if "gamma" in p else -1.0


@RULES.rule("bitmap_options")
def bitmap_options(root: ET.Element, ctx: Context) -> None:
    """0.6 bitmap-texture options -> Mitsuba 3's: ``filterType`` ``ewa``/``trilinear``
    -> ``bilinear`` (Mitsuba 3 has no mip-mapping; noted), ``nearest``/``bilinear`` kept;
    ``wrapModeU``/``wrapModeV`` (equal) -> ``wrap_mode``; ``repeat``/``mirror``/``clamp``
    kept, ``zero``/``one`` -> ``clamp`` (noted: Mitsuba 3 has no constant border);
    ``gamma`` -1 (the file's curve) dropped, 1 -> ``raw=true``, any other gamma and
    ``channel="r|g|b|a|..."`` -> a derived linear EXR (noted); ``maxAnisotropy`` and
    ``cache`` dropped (no effect in Mitsuba 3). ``cache`` on ``envmap`` emitters too."""
    for el, _ in plugins(root, "emitter", ("envmap",)):
        remove(el, "cache")
    for el, _ in plugins(root, "texture", ("bitmap",)):
        p = params(el)
        remove(el, "maxAnisotropy", "cache")
        node = p.get("filter_type", p.get("filterType"))
        if node is not None:
            node.set("name", "filter_type")
            value = (node.get("value") or "").lower()
            if value in ("ewa", "trilinear"):
                ctx.note(f"filter '{value}' -> 'bilinear' (Mitsuba 3 has no mip-mapping)", el)
                node.set("value", "bilinear")
            elif value not in ("nearest", "bilinear"):
                ctx.refuse(node, f"has an unknown filter type '{value}'")
        wraps = [p[k] for k in ("wrap_mode", "wrapMode", "wrapModeU", "wrapModeV") if k in p]
        if wraps:
            values = {(w.get("value") or "").lower() for w in wraps}
            if len(values) != 1:
                ctx.refuse(el, "with different wrap modes in u and v is not supported by the import layer")
            value = values.pop()
            if value in ("zero", "one"):
                ctx.note(f"wrap mode '{value}' -> 'clamp' (Mitsuba 3 has no constant border)", el)
                value = "clamp"
            elif value not in ("repeat", "mirror", "clamp"):
                ctx.refuse(wraps[0], f"has an unknown wrap mode '{value}'")
            for w in wraps[1:]:
                el.remove(w)
            wraps[0].set("name", "wrap_mode")
            wraps[0].set("value", value)
        gamma = float_of(p["gamma"], ctx) if "gamma" in p else -1.0
        if not (gamma == -1 or gamma > 0):
            ctx.refuse(p["gamma"], "must be -1 (sRGB) or positive")
        channel = p.get("channel")
        if "gamma" in p:
            el.remove(p["gamma"])
        if channel is None and gamma in (-1.0, 1.0):
            if gamma == 1:
                child(el, "boolean", "raw", "true")
            continue
        pixels, names = load_linear(_bitmap_path(el, ctx), gamma)
        why = [f"gamma {gamma:g}"] if gamma not in (-1.0, 1.0) else []
        if channel is not None:
            want = (channel.get("value") or "").strip().upper()
            if want not in names:
                ctx.refuse(channel, f"names channel '{want.lower()}', but the image has {', '.join(names)}")
            pixels = pixels[..., names.index(want):names.index(want) + 1]
            el.remove(channel)
            why.append(f"channel '{want.lower()}'")
        _set_derived(el, write_derived(ctx, pixels, "bitmap"))
        ctx.note(f"{' and '.join(why)} baked into a linear EXR", el)


@RULES.rule("gridtexture")
def gridtexture(root: ET.Element, ctx: Context) -> None:
    """0.6 ``gridtexture`` (``color0`` background 0.2, ``color1`` lines 0.4,
    ``lineWidth`` 0.01 in uv units; lines where frac(u) or frac(v) is within lineWidth of
    an integer) -> a ``bitmap`` of the grid rasterised at 1024-8192 pixels a side (lines at
    least 2 pixels wide) with ``nearest`` filtering, noted. Textured colours are refused."""
    for el, parent in plugins(root, "texture", ("gridtexture",)):
        p = params(el)
        c0, c1 = const_rgb(p.get("color0"), 0.2), const_rgb(p.get("color1"), 0.4)
        for key, c in (("color0", c0), ("color1", c1)):
            if c is None:
                ctx.refuse(p[key], "(a textured grid colour) is not supported by the import layer")
        width = param_float(el, "lineWidth", 0.01, ctx)
        if not 0 < width < 0.5:
            ctx.refuse(el, f"needs 0 < lineWidth < 0.5, got {width:g}")
        res = int(min(GRID_MAX_RES, max(GRID_MIN_RES, np.ceil(2.0 / width))))
        t = (np.arange(res) + 0.5) / res
        t = np.where(t > 0.5, t - 1.0, t)
        line = np.abs(t) < width
        mask = (line[:, None] | line[None, :])[..., None]
        pixels = np.where(mask, np.asarray(c1, np.float32), np.asarray(c0, np.float32))
        new = ET.Element("texture", {k: v for k, v in el.attrib.items() if k != "type"})
        new.set("type", "bitmap")
        _set_derived(new, write_derived(ctx, pixels, "grid"))
        child(new, "string", "filter_type", "nearest")
        for c in el:  # uv scale/offset and anything left for later rules to judge
            if c.get("name") not in ("color0", "color1", "lineWidth"):
                new.append(c)
        ctx.note(f"rasterised to a {res}x{res} bitmap (nearest filtering)", el)
        if el in ctx.lines:
            ctx.lines[new] = ctx.lines[el]
        replace(parent, el, new)


def _by_id(root: ET.Element) -> dict[str, ET.Element]:
    return {el.get("id"): el for el in root.iter() if el.get("id") is not None and el.tag != "ref"}


def scaled(node: ET.Element, factor: float, ctx: Context, ids: dict[str, ET.Element]) -> ET.Element:
    """A copy of a colour or texture parameter multiplied by ``factor``: constants are
    multiplied, checkerboards scale both colours, bitmaps are baked into a derived EXR,
    references are followed; anything else is refused."""
    if node.tag == "ref":
        target = ids.get(node.get("id"))
        if target is None:
            ctx.refuse(node, f"refers to id '{node.get('id')}', which is not declared in the file")
        out = scaled(target, factor, ctx, ids)
        out.attrib.pop("id", None)
        if node.get("name") is not None:
            out.set("name", node.get("name"))
        return out
    out = copy.deepcopy(node)
    out.attrib.pop("id", None)
    if node.tag in ("rgb", "float"):
        out.set("value", fmt([v * factor for v in floats(node.get("value", ""))]))
        return out
    if node.tag == "texture" and node.get("type") == "checkerboard":
        p = params(out)
        for key, default in (("color0", 0.4), ("color1", 0.2)):
            if key in p:
                new = scaled(p[key], factor, ctx, ids)
                replace(out, p[key], new)
            else:
                child(out, "rgb", key, [default * factor] * 3)
        return out
    if node.tag == "texture" and node.get("type") == "bitmap":
        pixels, _ = load_linear(_bitmap_path(node, ctx), _bitmap_gamma(node, ctx))
        remove(out, "gamma")
        _set_derived(out, write_derived(ctx, pixels * factor, "scaled"))
        return out
    if node.tag == "texture" and node.get("type") == "scale":
        inner = [c for c in node if c.tag in ("texture", "rgb", "float", "ref") and c.get("name") != "scale"]
        if len(inner) != 1:
            ctx.refuse(node, "needs exactly one nested texture")
        out = scaled(inner[0], factor * param_float(node, "scale", 1.0, ctx), ctx, ids)
        if node.get("name") is not None:
            out.set("name", node.get("name"))
        return out
    ctx.refuse(node, "cannot be scaled by the import layer (constants, checkerboard and bitmap can)")


@RULES.rule("scale_texture")
def scale_texture(root: ET.Element, ctx: Context) -> None:
    """0.6 ``<texture type="scale">`` (``scale`` x a nested texture) -> the nested texture
    multiplied out: a constant times the factor, a checkerboard with both colours scaled,
    a bitmap baked into a scaled linear EXR (noted). Under a ``bumpmap`` it is left for
    the bump-map rule, which maps the factor onto Mitsuba 3's ``scale``."""
    ids = _by_id(root)
    for el, parent in plugins(root, "texture", ("scale",)):
        if parent is None or (parent.tag == "bsdf" and parent.get("type") == "bumpmap"):
            continue
        new = scaled(el, 1.0, ctx, ids)
        for key in ("id", "name"):
            if el.get(key) is not None:
                new.set(key, el.get(key))
        if any(c.tag == "texture" and c.get("type") == "bitmap" for c in new.iter()):
            ctx.note("scale baked into the bitmap", el)
        replace(parent, el, new)


#: PLY colour property types -> the factor that maps them to [0, 1], as 0.6 read them.
PLY_COLOR_SCALE = {"uchar": 1 / 255, "uint8": 1 / 255, "char": 1 / 255, "int8": 1 / 255,
                   "ushort": 1 / 65535, "uint16": 1 / 65535, "float": 1.0, "float32": 1.0, "double": 1.0}


def ply_color_scale(path: Path) -> float | None:
    """The factor of a PLY file's vertex colours (``red``/``r``), None when it has none."""
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").split()
            if line[:1] == ["end_header"]:
                return None
            if len(line) == 3 and line[0] == "property" and line[2] in ("red", "r"):
                return PLY_COLOR_SCALE.get(line[1])
    return None


def _owning_shapes(root: ET.Element, tex: ET.Element) -> list[ET.Element]:
    """Shapes that use the BSDF a texture sits in (by nesting or by ``<ref>``)."""
    parents = {c: p for p in root.iter() for c in p}
    node, owners = tex, []
    while node in parents:
        node = parents[node]
        if node.tag == "shape":
            return [node]
        if node.get("id") is not None:
            owners = [parents[r] for r in root.iter("ref") if r.get("id") == node.get("id") and r in parents]
    return [o for o in owners if o.tag == "shape"]


@RULES.rule("vertexcolors")
def vertexcolors(root: ET.Element, ctx: Context) -> None:
    """0.6 ``<texture type="vertexcolors">`` (the mesh's per-vertex colours, e.g. PLY
    red/green/blue, which 0.6 mapped to [0, 1]) -> Mitsuba 3 ``<texture
    type="mesh_attribute">`` with ``name="vertex_color"`` (the attribute Mitsuba 3's PLY
    loader fills) and ``scale`` 1/255 (1/65535) for 8-bit (16-bit) colours, which Mitsuba
    3 keeps unnormalised. Shapes with differently typed colours sharing it are refused."""
    for el, _ in plugins(root, "texture", ("vertexcolors",)):
        scales = set()
        for shape in _owning_shapes(root, el):
            fname = params(shape).get("filename")
            if shape.get("type") == "ply" and fname is not None:
                path = _resolve(ctx, fname.get("value", ""))
                if path.is_file():
                    scales.add(ply_color_scale(path))
        scales.discard(None)
        if len(scales) > 1:
            ctx.refuse(el, "is shared by PLY files whose colours have different types")
        el.set("type", "mesh_attribute")
        child(el, "string", "name", "vertex_color")
        if scales and scales != {1.0}:
            child(el, "float", "scale", scales.pop())


@RULES.rule("texture_uv_transform")
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
        v = {k: (float_of(p[k], ctx) if k in p else (1.0 if "scale" in k else 0.0))
             for k in ("uscale", "vscale", "uoffset", "voffset")}
        for k in keys:
            el.remove(p[k])
        tr = child(el, "transform", "to_uv")
        ET.SubElement(tr, "scale", {"x": f"{v['uscale']:.6g}", "y": f"{v['vscale']:.6g}"})
        ET.SubElement(tr, "translate", {"x": f"{v['uoffset']:.6g}", "y": f"{v['voffset']:.6g}"})
