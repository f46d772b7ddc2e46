"""Mitsuba 0.6 emitters -> Mitsuba 3 emitters (0.6 documentation, section 8.8 "Emitters").

Same plugin and parameters: ``area``, ``point``, ``directional``, ``constant``,
``spot`` (with its projected texture), ``envmap`` (``cache`` dropped; a ``gamma``
override baked). Approximated, noted: ``sky``, ``sun`` and ``sunsky`` -> Mitsuba 3's
``sunsky`` (the same Hosek-Wilkie sky; 0.6's frame is Y-up, Mitsuba 3's Z-up),
``collimated`` -> a very narrow ``spot``. Refused: ``spot`` textures under another name.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

from .common import (Context, RuleList, child, float_of, param_float, params, plugins, remove)
from .textures import _bitmap_path, load_linear, write_derived

RULES = RuleList()

KNOWN = frozenset({"area", "point", "spot", "directional", "collimated", "constant", "envmap",
                   "sky", "sun", "sunsky"})

#: 0.6's sky/sun defaults (doc section 8.8: sun, sky, sunsky): Tokyo, 2010-07-10 15:00 local time.
SKY_DEFAULTS: dict[str, tuple[str, float]] = {
    "turbidity": ("turbidity", 3.0), "albedo": ("albedo", 0.15),
    "year": ("year", 2010), "month": ("month", 7), "day": ("day", 10),
    "hour": ("hour", 15.0), "minute": ("minute", 0.0), "second": ("second", 0.0),
    "latitude": ("latitude", 35.6894), "longitude": ("longitude", 139.6917), "timezone": ("timezone", 9.0),
}
_INT_KEYS = ("year", "month", "day")
#: Mitsuba 3's sunsky default sun aperture (degrees), scaled by 0.6's sunRadiusScale.
SUN_APERTURE_DEG = 0.5358
#: Half-angle (degrees) of the spot that stands in for a collimated beam.
COLLIMATED_CUTOFF_DEG = 0.05


@RULES.rule("spot_light")
def spot_light(root: ET.Element, ctx: Context) -> None:
    """0.6 ``<emitter type="spot">`` (doc section 8.8, spot) -> Mitsuba 3 ``spot``: ``cutoffAngle``/
    ``beamWidth`` -> ``cutoff_angle``/``beam_width`` (renamed earlier; same defaults, 20
    deg and 3/4 of it), ``intensity`` kept, and a projected ``<texture name="texture">``
    kept as is: both versions look it up at uv = 0.5 + 0.5 d.xy / (d.z tan(cutoff)) in the
    light's frame and multiply it into the intensity. A texture under another name is
    refused."""
    for el, _ in plugins(root, "emitter", ("spot",)):
        for c in el:
            if c.tag == "texture" and c.get("name") not in ("texture", "intensity"):
                ctx.refuse(c, "inside a spot light is not supported by the import layer")


@RULES.rule("envmap")
def envmap(root: ET.Element, ctx: Context) -> None:
    """0.6 ``envmap`` (doc section 8.8, envmap; ``filename``, ``scale``, ``toWorld``, ``gamma``,
    ``cache``) -> Mitsuba 3 ``envmap`` with the same file, scale and transform (both map
    the latitude-longitude image with +Y up); ``cache`` dropped; a ``gamma`` other than -1
    baked into a linear EXR (noted)."""
    for el, _ in plugins(root, "emitter", ("envmap",)):
        p = params(el)
        remove(el, "cache")
        if "gamma" not in p:
            continue
        gamma = float_of(p["gamma"], ctx)
        el.remove(p["gamma"])
        if gamma == -1:
            continue
        if not gamma > 0:
            ctx.refuse(p["gamma"], "must be -1 (sRGB) or positive")
        pixels, _ = load_linear(_bitmap_path(el, ctx), gamma)
        path = write_derived(ctx, pixels[..., :3] if pixels.shape[-1] >= 3 else pixels, "envmap")
        remove(el, "filename")
        child(el, "string", "filename", str(path), index=0)
        ctx.note(f"gamma {gamma:g} baked into a linear EXR", el)


def _sky_frame(el: ET.Element) -> None:
    """Prepend the Y-up (0.6) -> Z-up (Mitsuba 3 sunsky) rotation to ``to_world``."""
    tr = params(el).get("to_world")
    if tr is None:
        tr = child(el, "transform", "to_world")
    rot = ET.Element("rotate", {"x": "1", "angle": "-90"})
    rot.tail = "\n"
    tr.insert(0, rot)


@RULES.rule("sunsky")
def sunsky(root: ET.Element, ctx: Context) -> None:
    """0.6 ``sky`` (Hosek-Wilkie sky), ``sun`` (the solar disk) and ``sunsky`` (both)
    (doc section 8.8: sun, sky, sunsky) -> Mitsuba 3 ``sunsky`` (the same Hosek-Wilkie model): ``sky`` as
    ``sun_scale=0``, ``sun`` as ``sky_scale=0``; ``turbidity``, ``albedo``, date, time
    and location kept with 0.6's defaults made explicit (Tokyo, 2010-07-10 15:00),
    ``sunDirection`` -> ``sun_direction``; ``scale`` multiplies ``sun_scale`` and
    ``sky_scale`` (``sunScale``, ``skyScale``), ``sunRadiusScale`` scales
    ``sun_aperture``; 0.6's +Y-up frame becomes Mitsuba 3's +Z-up by a rotation prepended
    to ``to_world``. ``stretch``, ``extend`` and ``resolution`` (0.6 baked the sky into
    an image) are dropped. Noted: absolute radiance follows Mitsuba 3's model."""
    for el, _ in list(plugins(root, "emitter", ("sky", "sun", "sunsky"))):
        kind = el.get("type")
        p = params(el)
        scale = param_float(el, "scale", 1.0, ctx)
        sun_scale = scale * param_float(el, "sunScale", 1.0, ctx) * (0.0 if kind == "sky" else 1.0)
        sky_scale = scale * param_float(el, "skyScale", 1.0, ctx) * (0.0 if kind == "sun" else 1.0)
        radius = param_float(el, "sunRadiusScale", 1.0, ctx)
        dropped = [k for k in ("stretch", "extend", "resolution") if k in p]
        remove(el, "scale", "sunScale", "skyScale", "sunRadiusScale", "stretch", "extend", "resolution")
        # A sun direction (world space in both versions) overrides date, time and place.
        if "sunDirection" in p:
            p["sunDirection"].set("name", "sun_direction")
            remove(el, *(set(SKY_DEFAULTS) - {"turbidity", "albedo"}))
        for key, (name, default) in SKY_DEFAULTS.items():
            if key not in p and ("sunDirection" not in p or key in ("turbidity", "albedo")):
                value = int(default) if key in _INT_KEYS else float(default)
                child(el, "integer" if key in _INT_KEYS else "float", name, value)
        for key in ("year", "month", "day"):
            node = params(el).get(key)
            if node is not None and node.tag == "float":
                node.tag = "integer"
                node.set("value", str(int(float(node.get("value")))))
        if kind == "sun":
            remove(el, "albedo")
        extra = f"; dropped {', '.join(dropped)}" if dropped else ""
        what = {"sky": "sky only (sun_scale 0)", "sun": "sun only (sky_scale 0)", "sunsky": "sun and sky"}[kind]
        ctx.note(f"-> Mitsuba 3 'sunsky', {what}; Hosek-Wilkie radiance as Mitsuba 3 computes it{extra}", el)
        child(el, "float", "sun_scale", sun_scale)
        child(el, "float", "sky_scale", sky_scale)
        child(el, "float", "sun_aperture", SUN_APERTURE_DEG * radius)
        _sky_frame(el)
        el.set("type", "sunsky")


@RULES.rule("collimated")
def collimated(root: ET.Element, ctx: Context) -> None:
    """0.6 ``collimated`` (a single beam of ``power`` watts along +Z of ``toWorld``, doc
    section 8.8) -> Mitsuba 3 ``spot`` with a 0.05 degree cutoff (and beam width) and intensity
    power / (2 pi (1 - cos cutoff)), so that it emits the same power in a beam that
    widens by 0.09 % of the distance travelled; noted (Mitsuba 3 has no collimated beam)."""
    for el, _ in plugins(root, "emitter", ("collimated",)):
        p = params(el)
        node = p.get("power")
        if node is not None and node.tag not in ("rgb", "float"):
            ctx.refuse(node, "(a textured beam power) is not supported by the import layer")
        theta = math.radians(COLLIMATED_CUTOFF_DEG)
        solid = 2.0 * math.pi * (1.0 - math.cos(theta))
        power = [1.0, 1.0, 1.0] if node is None else \
            [float(v) for v in node.get("value", "1").replace(",", " ").split()] * (1 if node.tag == "rgb" else 3)
        ctx.note(f"collimated beam -> spot of {COLLIMATED_CUTOFF_DEG:g} degree half-angle, same power", el)
        remove(el, "power")
        el.set("type", "spot")
        child(el, "rgb", "intensity", [v / solid for v in power[:3]])
        child(el, "float", "cutoff_angle", COLLIMATED_CUTOFF_DEG)
        child(el, "float", "beam_width", COLLIMATED_CUTOFF_DEG)
