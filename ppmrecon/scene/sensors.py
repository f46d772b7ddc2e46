"""Mitsuba 0.6 sensors, films, samplers and reconstruction filters -> Mitsuba 3's
(0.6 documentation, sections 8.9 "Sensors", 8.12 "Films", 8.11 "Sample generators",
8.13 "Reconstruction filters").

``perspective``, ``thinlens`` and ``orthographic`` keep their parameters (``fov``,
``fovAxis``, ``focalLength``, ``nearClip``/``farClip``, ``apertureRadius``,
``focusDistance``, ``toWorld``); the renderer samples no other sensor. The reconstruction
filters have the same names and parameters in both versions.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from .common import Context, RuleList, child, float_of, params, plugins, remove

RULES = RuleList()

KNOWN_SENSORS = frozenset({"perspective", "thinlens", "orthographic", "telecentric", "spherical",
                           "irradiancemeter", "radiancemeter", "fluencemeter", "perspective_rdist"})
REFUSED_SENSORS = {t: "the ppmrecon renderer samples perspective, thinlens and orthographic sensors only"
                   for t in KNOWN_SENSORS - {"perspective", "thinlens", "orthographic"}}
KNOWN_FILMS = frozenset({"hdrfilm", "ldrfilm", "tiledhdrfilm", "mfilm"})
REFUSED_FILMS = {"mfilm": "Mitsuba 3 has no MATLAB/text film"}
KNOWN_FILTERS = frozenset({"box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos"})
KNOWN_SAMPLERS = frozenset({"independent", "stratified", "ldsampler", "halton", "hammersley", "sobol"})

#: 0.6 film options that only concerned 0.6's own image output; ppmrecon writes its own EXR.
FILM_DROPPED = frozenset({"banner", "highQualityEdges", "attachLog", "fileFormat", "pixelFormat",
                          "componentFormat", "tonemapMethod", "gamma", "exposure", "key", "burn",
                          "metadata", "label"})


@RULES.rule("shutter_time")
def shutter_time(root: ET.Element, ctx: Context) -> None:
    """0.6 sensor ``shutterOpen`` + ``shutterOpenTime`` (a duration) -> Mitsuba 3
    ``shutter_open`` + ``shutter_close`` (an end time)."""
    for el, _ in plugins(root, "sensor"):
        p = params(el)
        if "shutterOpen" not in p and "shutterOpenTime" not in p:
            continue
        start = float_of(p["shutterOpen"], ctx) if "shutterOpen" in p else 0.0
        length = float_of(p["shutterOpenTime"], ctx) if "shutterOpenTime" in p else 0.0
        remove(el, "shutterOpen", "shutterOpenTime")
        child(el, "float", "shutter_close", start + length, index=0)
        child(el, "float", "shutter_open", start, index=0)


@RULES.rule("sampler_types")
def sampler_types(root: ET.Element, ctx: Context) -> None:
    """0.6 samplers ``sobol``, ``ldsampler``, ``halton``, ``hammersley``, ``stratified`` ->
    ``independent`` with the same ``sample_count``; their ``dimension``/``scramble``
    options are dropped (ppmrecon draws its own random numbers; Mitsuba 3 has no
    ldsampler); noted."""
    for el, _ in plugins(root, "sampler"):
        if el.get("type") != "independent":
            ctx.note(f"sampler '{el.get('type')}' replaced by 'independent'")
            el.set("type", "independent")
            remove(el, "dimension", "scramble")


@RULES.rule("film_options")
def film_options(root: ET.Element, ctx: Context) -> None:
    """0.6-only film options (``banner``, ``highQualityEdges``, ``attachLog``,
    ``fileFormat``, ``pixelFormat``, ``componentFormat``, tone-mapping ``gamma``/
    ``exposure``/``key``/``burn``/``tonemapMethod``, ``metadata``, ``label``) -> dropped:
    they shaped 0.6's output file, and ppmrecon writes its own EXR; ``ldrfilm`` and
    ``tiledhdrfilm`` -> ``hdrfilm`` (same size, crop and reconstruction filter; noted)."""
    for el, _ in plugins(root, "film"):
        if el.get("type") != "hdrfilm":
            ctx.note(f"film '{el.get('type')}' replaced by 'hdrfilm'")
            el.set("type", "hdrfilm")
        remove(el, *FILM_DROPPED)
