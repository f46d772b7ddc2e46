"""Mitsuba 0.6 colour and spectrum properties -> Mitsuba 3 linear ``<rgb>``.

Mitsuba 0.6 documentation, section 6 "Scene file format", colour spectra: ``<rgb>`` is linear RGB,
``<srgb>`` is sRGB-encoded (``#rrggbb`` too), ``<spectrum value="v">`` is flat,
``<spectrum value="l1:v1, l2:v2, ...">`` is a wavelength:value list, ``<spectrum
filename="x.spd">`` reads such a list from a file, a plain list of N values is the
renderer's own discretisation (N = SPECTRUM_SAMPLES: RGB in the default build, N bins
over 360-830 nm in spectral builds), and ``<blackbody temperature="5000K">`` is
Planck's law in W m^-2 sr^-1 nm^-1. The ``intent`` attribute only steered 0.6's
spectral upsampling in spectral builds.

Spectra become linear sRGB the way 0.6's RGB mode computed them (CIE 1931, normalised by
the integral of y-bar, XYZ -> sRGB without white-point adaptation): Mitsuba 3 in RGB
mode would otherwise tint bare ``<spectrum>`` emitters by D65.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from .common import Context, RuleList, ensure_variant, floats, fmt, srgb_to_linear, walk

RULES = RuleList()

#: 0.6's visible range (SPECTRUM_MIN_WAVELENGTH, SPECTRUM_MAX_WAVELENGTH).
LAMBDA_MIN, LAMBDA_MAX = 360.0, 830.0
#: Samples per nanometre when a binned or blackbody spectrum is integrated.
_STEP_NM = 1.0
#: Planck's law constants as 0.6's BlackBodySpectrum used them (SI).
_C, _H, _K = 299792458.0, 6.62607004e-34, 1.38064852e-23


def spectrum_to_rgb(wavelengths: list[float], values: list[float]) -> list[float]:
    """Linear sRGB of a sampled spectrum as 0.6's RGB mode computed it (CIE 1931,
    normalised by the integral of y-bar, XYZ -> sRGB without chromatic adaptation)."""
    ensure_variant()
    import mitsuba as mi
    rgb = mi.spectrum_list_to_srgb(list(wavelengths), list(values), False, False)
    return [float(rgb[i]) for i in range(3)]


def _grid() -> list[float]:
    n = int(round((LAMBDA_MAX - LAMBDA_MIN) / _STEP_NM))
    return [LAMBDA_MIN + i * _STEP_NM for i in range(n + 1)]


def binned_to_rgb(values: list[float]) -> list[float]:
    """N values as N equal bins over [360, 830] nm, piecewise constant, -> linear sRGB."""
    n = len(values)
    width = (LAMBDA_MAX - LAMBDA_MIN) / n
    wl = _grid()
    return spectrum_to_rgb(wl, [values[min(int((w - LAMBDA_MIN) / width), n - 1)] for w in wl])


def planck(wavelength_nm: float, temperature: float) -> float:
    """Blackbody spectral radiance in W m^-2 sr^-1 nm^-1 (0.6's BlackBodySpectrum)."""
    lam = wavelength_nm * 1e-9
    return 2 * _H * _C * _C / (lam ** 5 * math.expm1(_H * _C / (_K * lam * temperature))) * 1e-9


def blackbody_to_rgb(temperature: float) -> list[float]:
    wl = _grid()
    return spectrum_to_rgb(wl, [planck(w, temperature) for w in wl])


def _hex_rgb(text: str) -> list[float] | None:
    m = re.fullmatch(r"#([0-9a-fA-F]{6})", text.strip())
    if not m:
        return None
    h = m.group(1)
    return [int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)]


@RULES.rule("srgb_to_rgb")
def srgb_to_rgb(root: ET.Element, ctx: Context) -> None:
    """``<srgb name value="r, g, b">`` (sRGB-encoded, or ``#rrggbb``) -> ``<rgb>`` with
    the linear values (inverse sRGB transfer curve), since 0.6 linearised ``<srgb>`` and
    Mitsuba 3's ``<rgb>`` is linear. A single value is broadcast to grey; ``intent``
    dropped (it only steered spectral upsampling, which RGB rendering does not do)."""
    for el, _ in walk(root):
        if el.tag != "srgb":
            continue
        text = el.get("value", "")
        try:
            vals = _hex_rgb(text) or floats(text)
        except ValueError:
            ctx.refuse(el, f"has an unreadable colour '{text}'")
        if len(vals) == 1:
            vals = vals * 3
        if len(vals) != 3:
            ctx.refuse(el, f"needs 1 or 3 values, got '{text}'")
        el.tag = "rgb"
        el.attrib.pop("intent", None)
        el.set("value", fmt([srgb_to_linear(v) for v in vals]))


@RULES.rule("rgb_values")
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
            el.set("value", fmt([srgb_to_linear(v) for v in hexed]))
            continue
        try:
            vals = floats(text)
        except ValueError:
            ctx.refuse(el, f"has an unreadable colour '{text}'")
        if len(vals) not in (1, 3):
            ctx.refuse(el, f"needs 1 or 3 values, got '{text}'")
        el.set("value", fmt(vals * 3 if len(vals) == 1 else vals))


@RULES.rule("blackbody")
def blackbody(root: ET.Element, ctx: Context) -> None:
    """``<blackbody name temperature="5000K" scale="s">`` -> ``<rgb>`` with the linear
    sRGB of Planck's law in W m^-2 sr^-1 nm^-1 (0.6's units) times ``scale`` (or
    ``multiplier``), integrated over 360-830 nm at 1 nm."""
    for el, _ in walk(root):
        if el.tag != "blackbody":
            continue
        text = (el.get("temperature") or "").strip()
        try:
            temperature = float(text[:-1] if text.upper().endswith("K") else text)
        except ValueError:
            ctx.refuse(el, f"has an unreadable temperature '{text}'")
        if not temperature > 0:
            ctx.refuse(el, f"needs a positive temperature, got '{text}'")
        unknown = set(el.attrib) - {"name", "temperature", "scale", "multiplier"}
        if unknown:
            ctx.refuse(el, f"has unknown attribute(s) {', '.join(sorted(unknown))}")
        try:
            scale = float(el.get("scale", el.get("multiplier", "1")))
        except ValueError:
            ctx.refuse(el, "has an unreadable scale")
        rgb = [v * scale for v in blackbody_to_rgb(temperature)]
        name = el.get("name")
        el.attrib.clear()
        el.tag = "rgb"
        if name is not None:
            el.set("name", name)
        el.set("value", fmt(rgb))


@RULES.rule("spectrum_values")
def spectrum_values(root: ET.Element, ctx: Context) -> None:
    """``<spectrum value="0.5">`` (a flat spectrum) -> ``<rgb value="0.5, 0.5, 0.5">``;
    ``<spectrum value="400:0.1, 500:0.5, ...">`` and ``<spectrum filename="x.spd">`` ->
    ``<rgb>`` with the spectrum's linear sRGB; a plain list of 3 values -> ``<rgb>`` as is
    (0.6's default RGB build took them as R, G, B); a plain list of N != 3 values -> N
    equal bins over 360-830 nm (0.6's spectral builds) -> linear sRGB, noted."""
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
            rgb = spectrum_to_rgb(list(wl), list(vs))
            del el.attrib["filename"]
        elif ":" in text:
            try:
                pairs = [p.split(":") for p in re.split(r"[,\s]+", text) if p]
                wl = [float(a) for a, _ in pairs]
                vs = [float(b) for _, b in pairs]
            except ValueError:
                ctx.refuse(el, f"has an unreadable wavelength:value list '{text}'")
            if len(wl) < 2 or any(b <= a for a, b in zip(wl, wl[1:])):
                ctx.refuse(el, "needs at least two wavelengths in increasing order")
            rgb = spectrum_to_rgb(wl, vs)
        else:
            try:
                vals = floats(text)
            except ValueError:
                ctx.refuse(el, f"has an unreadable value '{text}'")
            if not vals:
                ctx.refuse(el, "has no value")
            if len(vals) == 1:
                rgb = vals * 3
            elif len(vals) == 3:
                rgb = vals
                ctx.note("a 3-value spectrum read as linear R, G, B (0.6's default RGB build)", el)
            else:
                rgb = binned_to_rgb(vals)
                ctx.note(f"{len(vals)} spectral bins over 360-830 nm integrated to linear sRGB", el)
        el.tag = "rgb"
        el.set("value", fmt(rgb))
