"""Randomised training scenes, deterministic by (family, seed) (SPEC section 6).

Eight families cover what the network must learn; every scene is a closed room with a
random size, wall colours, procedural floor texture and camera. The first four (issue 1):

``caustics``       glass spheres and slabs, a water height field, smooth metal
                   reflectors, one small area light: sharp caustics (LS+DE paths)
``glossy``         rough conductors and rough plastics (alpha 0.05..0.4) on the floor,
                   walls and objects, area or spot light: noisy glossy gather points
``indirect``       the light faces a wall or the ceiling, or hides behind a partition:
                   most of the image is lit by interreflection
``textured_light`` spot lights that project procedural textures, coloured area lights:
                   photons uniform in density but not in colour

Four more (issue 12) produce on purpose what real scenes have and the first four lack:

``bright_emitters``        tiny, very bright sphere lights seen directly and through
                           mirrors, glass and near-specular glossy surfaces: eye-path
                           fireflies in ~y and every ~z^j
``caustic_paths``          small lights inside glass spheres, behind glass slabs, above a
                           water surface, next to metal rings (cardioids), point lights:
                           rare L(S)+D paths
``glossy_interreflection`` rough conductors and plastics (alpha 0.01..0.5, log-uniform)
                           on walls, floor, panels and objects facing each other
``texture_leaks``          high-frequency procedural albedo (numpy bitmaps, fine
                           checkerboards) and a light behind a partition that leaks
                           through a thin slit or a gap under it

Every family can also draw a global radiance scale 10^U(lo, hi) (default -4..4) applied
to all emitters, from its own random stream: the other parameters of a seed do not
depend on it, and without it (``radiance_log10=None``) the first four families give
exactly the parameters they always did, so data sets made before stay valid.

A scene is described by a small JSON-able ``params`` dict (what the manifest stores);
:func:`build_scene` turns params into a Mitsuba scene dict. No third-party data.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: The families of the first data sets, in their original order (their index seeds the
#: random stream, so new families are only ever appended).
LEGACY_FAMILIES: tuple[str, ...] = ("caustics", "glossy", "indirect", "textured_light")
FAMILIES: tuple[str, ...] = LEGACY_FAMILIES + ("bright_emitters", "caustic_paths", "glossy_interreflection",
                                               "texture_leaks")
#: Default decades of the global radiance scale (10^U(-4, 4)).
RADIANCE_LOG10: tuple[float, float] = (-4.0, 4.0)


# ------------------------------------------------------------------------ parameters

def _colour(rng: np.random.Generator, lo: float = 0.1, hi: float = 0.85) -> list[float]:
    hue = rng.uniform(0, 1)
    sat = rng.uniform(0.0, 0.8)
    val = rng.uniform(lo, hi)
    # HSV -> RGB, enough for pleasant random albedos
    k = (np.array([5.0, 3.0, 1.0]) + hue * 6.0) % 6.0
    rgb = val - val * sat * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
    return [round(float(c), 4) for c in rgb]


def _material(rng: np.random.Generator, kind: str) -> dict[str, Any]:
    if kind == "diffuse":
        return {"kind": "diffuse", "albedo": _colour(rng)}
    if kind == "glass":
        return {"kind": "glass", "ior": round(float(rng.uniform(1.3, 1.7)), 3)}
    if kind == "mirror":
        return {"kind": "mirror", "material": str(rng.choice(["Ag", "Al", "Au", "Cu"]))}
    if kind == "roughmetal":
        return {"kind": "roughmetal", "material": str(rng.choice(["Ag", "Al", "Au", "Cu"])),
                "alpha": round(float(rng.uniform(0.05, 0.4)), 3),
                "distribution": str(rng.choice(["ggx", "beckmann"]))}
    if kind == "roughplastic":
        return {"kind": "roughplastic", "albedo": _colour(rng),
                "alpha": round(float(rng.uniform(0.05, 0.4)), 3)}
    raise ValueError(kind)


def sample_params(family: str, seed: int,
                  radiance_log10: tuple[float, float] | None = RADIANCE_LOG10) -> dict[str, Any]:
    """Random parameters of scene ``seed`` of ``family`` (deterministic).

    ``radiance_log10`` = (lo, hi) adds ``radiance_scale`` = 10^U(lo, hi), drawn from a
    stream of its own, which multiplies every emitter; ``None`` leaves it out (scale 1).
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family '{family}' (choose {', '.join(FAMILIES)})")
    if family in LEGACY_FAMILIES:
        p = _legacy_params(family, seed)
    else:
        p = _NEW_FAMILIES[family](np.random.default_rng([FAMILIES.index(family), seed]), family, seed)
    if radiance_log10 is not None:
        lo, hi = radiance_log10
        u = np.random.default_rng([FAMILIES.index(family), seed, 0x5CA1E]).uniform(lo, hi)
        p["radiance_scale"] = float(f"{10.0 ** u:.4g}")
    return p


def _legacy_params(family: str, seed: int) -> dict[str, Any]:
    """The first four families, draw for draw as they were made (data sets depend on it)."""
    rng = np.random.default_rng([FAMILIES.index(family), seed])
    w, h, d = (round(float(v), 3) for v in (rng.uniform(2.0, 4.0), rng.uniform(2.0, 3.0), rng.uniform(2.5, 4.0)))
    p: dict[str, Any] = {
        "family": family, "seed": seed, "room": [w, h, d],
        "walls": [_colour(rng, 0.3, 0.85) for _ in range(6)],
        "floor_texture": {"scale": round(float(rng.uniform(2, 12)), 2),
                          "colours": [_colour(rng, 0.2, 0.8), _colour(rng, 0.2, 0.8)]}
        if rng.uniform() < 0.6 else None,
    }
    # camera near the front wall looking at a random point in the back half
    p["camera"] = {
        "origin": [round(float(rng.uniform(-0.35, 0.35) * w), 3), round(float(rng.uniform(0.3, 0.8) * h), 3),
                   round(d / 2 - 0.15, 3)],
        "target": [round(float(rng.uniform(-0.25, 0.25) * w), 3), round(float(rng.uniform(0.1, 0.5) * h), 3),
                   round(float(rng.uniform(-0.5, 0.0) * d), 3)],
        "fov": round(float(rng.uniform(40, 70)), 1),
    }
    objects: list[dict[str, Any]] = []

    def place(radius: float) -> list[float]:
        return [round(float(rng.uniform(-0.4, 0.4) * w), 3), round(radius, 3),
                round(float(rng.uniform(-0.45, 0.1) * d), 3)]

    if family == "caustics":
        kinds = ["glass", "glass", "mirror", "diffuse", "roughplastic"]
        for _ in range(int(rng.integers(2, 5))):
            r = float(rng.uniform(0.15, 0.45))
            objects.append({"shape": str(rng.choice(["sphere", "sphere", "cube"])), "center": place(r),
                            "size": round(r, 3), "angle": round(float(rng.uniform(0, 90)), 1),
                            "material": _material(rng, str(rng.choice(kinds)))})
        if rng.uniform() < 0.5:
            p["water"] = {"height": round(float(rng.uniform(0.3, 0.8)), 3),
                          "extent": round(float(rng.uniform(0.5, 0.9)), 3),
                          "waves": [[round(float(rng.uniform(0.008, 0.03)), 4), round(float(rng.uniform(0.25, 0.9)), 3),
                                     round(float(rng.uniform(0, 360)), 1), round(float(rng.uniform(0, 6.28)), 3)]
                                    for _ in range(4)]}
        p["lights"] = [{"type": "area", "size": round(float(rng.uniform(0.05, 0.2)), 3),
                        "position": [round(float(rng.uniform(-0.3, 0.3) * w), 3), round(h - 0.01, 3),
                                     round(float(rng.uniform(-0.3, 0.2) * d), 3)],
                        "radiance": [round(float(v), 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(60, 200)]}]
    elif family == "glossy":
        kinds = ["roughmetal", "roughplastic", "roughplastic", "diffuse"]
        for _ in range(int(rng.integers(2, 5))):
            r = float(rng.uniform(0.2, 0.5))
            objects.append({"shape": str(rng.choice(["sphere", "cube"])), "center": place(r), "size": round(r, 3),
                            "angle": round(float(rng.uniform(0, 90)), 1),
                            "material": _material(rng, str(rng.choice(kinds)))})
        p["floor_material"] = _material(rng, str(rng.choice(["roughmetal", "roughplastic"])))
        p["lights"] = [_random_light(rng, w, h, d, spot=rng.uniform() < 0.5)]
    elif family == "indirect":
        for _ in range(int(rng.integers(1, 4))):
            r = float(rng.uniform(0.2, 0.5))
            objects.append({"shape": str(rng.choice(["sphere", "cube"])), "center": place(r), "size": round(r, 3),
                            "angle": round(float(rng.uniform(0, 90)), 1),
                            "material": _material(rng, str(rng.choice(["diffuse", "diffuse", "roughplastic"])))})
        # a spot aimed at the ceiling or a wall, or an area light facing the ceiling
        light = _random_light(rng, w, h, d, spot=rng.uniform() < 0.6)
        light["target"] = [round(float(rng.uniform(-0.4, 0.4) * w), 3), round(h, 3),
                           round(float(rng.uniform(-0.4, 0.4) * d), 3)] if rng.uniform() < 0.5 else \
            [round(-w / 2, 3), round(float(rng.uniform(0.3, 0.9) * h), 3), round(float(rng.uniform(-0.4, 0.4) * d), 3)]
        light["position"][1] = round(float(rng.uniform(0.3, 0.7) * h), 3)
        p["lights"] = [light]
    else:  # textured_light
        for _ in range(int(rng.integers(1, 4))):
            r = float(rng.uniform(0.2, 0.5))
            objects.append({"shape": str(rng.choice(["sphere", "cube"])), "center": place(r), "size": round(r, 3),
                            "angle": round(float(rng.uniform(0, 90)), 1),
                            "material": _material(rng, str(rng.choice(["diffuse", "roughplastic", "glass"])))})
        lights = [_random_light(rng, w, h, d, spot=True)]
        lights[0]["texture"] = {"pattern": str(rng.choice(["stripes", "checker", "rings", "blobs"])),
                                "frequency": round(float(rng.uniform(2, 10)), 2),
                                "colours": [_colour(rng, 0.2, 1.0), _colour(rng, 0.2, 1.0)]}
        if rng.uniform() < 0.6:
            extra = _random_light(rng, w, h, d, spot=False)
            extra["radiance"] = [round(float(v), 2) for v in np.array(_colour(rng, 0.5, 1.0)) * rng.uniform(5, 30)]
            lights.append(extra)
        p["lights"] = lights
    p["objects"] = objects
    return p


def _random_light(rng: np.random.Generator, w: float, h: float, d: float, spot: bool) -> dict[str, Any]:
    pos = [round(float(rng.uniform(-0.35, 0.35) * w), 3), round(float(rng.uniform(0.75, 0.95) * h), 3),
           round(float(rng.uniform(-0.3, 0.3) * d), 3)]
    if spot:
        return {"type": "spot", "position": pos,
                "target": [round(float(rng.uniform(-0.3, 0.3) * w), 3), 0.0, round(float(rng.uniform(-0.4, 0.2) * d), 3)],
                "cutoff": round(float(rng.uniform(20, 45)), 1),
                "intensity": [round(float(v), 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(10, 40)]}
    return {"type": "area", "size": round(float(rng.uniform(0.1, 0.4)), 3), "position": pos,
            "radiance": [round(float(v), 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(10, 40)]}


# ---------------------------------------------------------------- issue-12 families

def _r(x: float, n: int = 3) -> float:
    return round(float(x), n)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(math.log(lo), math.log(hi))))


def _room(rng: np.random.Generator, family: str, seed: int) -> dict[str, Any]:
    """Room, wall colours, optional floor checkerboard and camera, drawn as the first four
    families draw them (camera near the front wall, looking into the back half)."""
    w, h, d = (_r(v) for v in (rng.uniform(2.0, 4.0), rng.uniform(2.0, 3.0), rng.uniform(2.5, 4.0)))
    p: dict[str, Any] = {
        "family": family, "seed": seed, "room": [w, h, d],
        "walls": [_colour(rng, 0.3, 0.85) for _ in range(6)],
        "floor_texture": {"scale": _r(rng.uniform(2, 12), 2),
                          "colours": [_colour(rng, 0.2, 0.8), _colour(rng, 0.2, 0.8)]}
        if rng.uniform() < 0.6 else None,
    }
    p["camera"] = {
        "origin": [_r(rng.uniform(-0.35, 0.35) * w), _r(rng.uniform(0.3, 0.8) * h), _r(d / 2 - 0.15)],
        "target": [_r(rng.uniform(-0.25, 0.25) * w), _r(rng.uniform(0.1, 0.5) * h), _r(rng.uniform(-0.5, 0.0) * d)],
        "fov": _r(rng.uniform(40, 70), 1),
    }
    return p


def _inside(p: dict[str, Any], x: np.ndarray, margin: float) -> list[float]:
    """``x`` clamped into the room, ``margin`` away from every wall."""
    w, h, d = p["room"]
    lo = np.array([-w / 2 + margin, margin, -d / 2 + margin])
    hi = np.array([w / 2 - margin, h - margin, d / 2 - margin])
    return [_r(v) for v in np.clip(x, lo, hi)]


def _in_view(rng: np.random.Generator, p: dict[str, Any], spread: float = 0.7) -> list[float]:
    """A point inside the camera's field of view (so it is seen directly), 0.5 m or more
    in front of the camera and at most a little beyond its target."""
    cam = p["camera"]
    o, t = np.array(cam["origin"], float), np.array(cam["target"], float)
    f = (t - o) / np.linalg.norm(t - o)
    right = np.cross(f, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, f)
    dist = rng.uniform(0.5, max(0.6, 1.1 * float(np.linalg.norm(t - o))))
    half = math.tan(math.radians(cam["fov"] / 2)) * dist * spread
    x = o + dist * f + right * rng.uniform(-half, half) + up * rng.uniform(-half, half)
    return _inside(p, x, 0.08)


def _contains(obj: dict[str, Any], x: list[float], margin: float) -> bool:
    """Whether point ``x`` lies within ``margin`` of the solid ``obj`` (sphere, cube, box;
    a bounding sphere for cubes and boxes is enough here)."""
    if obj["shape"] == "sphere":
        reach = obj["size"]
    elif obj["shape"] == "cube":
        reach = obj["size"] * math.sqrt(3)
    elif obj["shape"] == "box":
        reach = float(np.linalg.norm(obj["half"]))
    else:
        return False
    return float(np.linalg.norm(np.subtract(x, obj["center"]))) < reach + margin


def _without_hidden_lights(objects: list[dict[str, Any]], lights: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Drop objects that would swallow a light placed before them (a light inside a
    diffuse ball only wastes photons)."""
    return [o for o in objects if not any(
        _contains(o, light["position"], light.get("radius", 0.0) + 0.02) for light in lights
        if light["type"] in ("sphere", "point"))]


def _floor_spot(rng: np.random.Generator, p: dict[str, Any], radius: float) -> list[float]:
    """Centre of an object of ``radius`` resting on the floor in the back part of the room."""
    w, _, d = p["room"]
    return [_r(rng.uniform(-0.4, 0.4) * w), _r(radius), _r(rng.uniform(-0.45, 0.1) * d)]


def _sphere_light(rng: np.random.Generator, position: list[float], radius: float, power: float) -> dict[str, Any]:
    """A sphere emitter whose power (W, radiance x pi x area) is ``power``: the smaller the
    sphere, the brighter it looks."""
    area = 4 * math.pi * radius ** 2
    colour = np.array(_colour(rng, 0.7, 1.0)) / 0.85
    return {"type": "sphere", "position": position, "radius": _r(radius, 4),
            "radiance": [float(f"{v:.4g}") for v in colour * power / (math.pi * area)]}


def _point_light(rng: np.random.Generator, position: list[float], power: float) -> dict[str, Any]:
    colour = np.array(_colour(rng, 0.7, 1.0)) / 0.85
    return {"type": "point", "position": position,
            "intensity": [float(f"{v:.4g}") for v in colour * power / (4 * math.pi)]}


def _small_light(rng: np.random.Generator, position: list[float], r_max: float = 0.04) -> dict[str, Any]:
    """A small sphere light (radius 5 mm..r_max) or, one time in three, a point light."""
    power = _log_uniform(rng, 10.0, 200.0)
    if rng.uniform() < 1 / 3:
        return _point_light(rng, position, power)
    return _sphere_light(rng, position, _log_uniform(rng, 0.005, r_max), power)


def _glossy_material(rng: np.random.Generator, lo: float = 0.01, hi: float = 0.5) -> dict[str, Any]:
    """A rough conductor or plastic, roughness log-uniform in [lo, hi]."""
    alpha = _r(_log_uniform(rng, lo, hi), 4)
    if rng.uniform() < 0.5:
        return {"kind": "roughmetal", "material": str(rng.choice(["Ag", "Al", "Au", "Cu", "Cr"])),
                "alpha": alpha, "distribution": str(rng.choice(["ggx", "beckmann"]))}
    return {"kind": "roughplastic", "albedo": _colour(rng), "alpha": alpha}


def _albedo_texture(rng: np.random.Generator, fine: bool = True) -> dict[str, Any]:
    """A procedural albedo texture: a tile of ``cycles`` periods, repeated ``repeat``
    times across the surface's uv range (the bitmap is made in :func:`_albedo_bitmap`)."""
    c0 = _colour(rng, 0.05, 0.35)
    c1 = _colour(rng, 0.5, 0.9)
    return {"pattern": str(rng.choice(["checker", "stripes", "noise", "bricks", "dots", "blocks"])),
            "cycles": int(rng.integers(4, 17)), "repeat": _r(rng.uniform(2, 10) if fine else rng.uniform(1, 3), 2),
            "angle": _r(rng.uniform(0, 180), 1), "colours": [c0, c1] if rng.uniform() < 0.5 else [c1, c0],
            "seed": int(rng.integers(0, 2 ** 31 - 1)), "filter": str(rng.choice(["bilinear", "nearest"]))}


def _bright_emitters(rng: np.random.Generator, family: str, seed: int) -> dict[str, Any]:
    p = _room(rng, family, seed)
    w, h, d = p["room"]
    lights: list[dict[str, Any]] = []
    if rng.uniform() < 0.7:  # an ordinary fill light, so the room is not lit by fireflies alone
        lights.append({"type": "area", "size": _r(rng.uniform(0.1, 0.35)),
                       "position": [_r(rng.uniform(-0.3, 0.3) * w), _r(h - 0.01), _r(rng.uniform(-0.3, 0.2) * d)],
                       "radiance": [_r(v, 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(5, 30)]})
    for k in range(int(rng.integers(1, 5))):
        radius = _log_uniform(rng, 0.003, 0.03)
        power = _log_uniform(rng, 1.0, 100.0)
        if k == 0 or rng.uniform() < 0.5:  # seen directly
            pos = _in_view(rng, p)
        else:
            pos = _inside(p, np.array([rng.uniform(-0.5, 0.5) * w, rng.uniform(0.2, 0.95) * h,
                                       rng.uniform(-0.5, 0.3) * d]), 0.08)
        lights.append(_sphere_light(rng, pos, radius, power))
    objects: list[dict[str, Any]] = []
    for _ in range(int(rng.integers(2, 6))):
        r = float(rng.uniform(0.12, 0.4))
        kind = str(rng.choice(["mirror", "glass", "mirror", "glass", "sharp", "diffuse"]))
        # below alpha ~0.01 a gather point hardly ever meets a photon in its lobe: no
        # reference would converge
        mat = _glossy_material(rng, 0.01, 0.06) if kind == "sharp" else _material(rng, kind)
        objects.append({"shape": str(rng.choice(["sphere", "sphere", "cube"])), "center": _floor_spot(rng, p, r),
                        "size": _r(r), "angle": _r(rng.uniform(0, 90), 1), "material": mat})
    objects = _without_hidden_lights(objects, lights)
    if rng.uniform() < 0.6:  # a mirror on the back or a side wall shows the lights again
        wall = int(rng.choice([2, 4, 5]))
        hx, hy = _r(rng.uniform(0.3, 0.8)), _r(rng.uniform(0.25, 0.6))
        y = _r(rng.uniform(0.35, 0.65) * h)
        if wall == 2:
            centre, normal = [_r(rng.uniform(-0.2, 0.2) * w), y, _r(-d / 2 + 0.01)], [0, 0, 1]
        else:
            sx = -1 if wall == 4 else 1
            centre, normal = [_r(sx * (w / 2 - 0.01)), y, _r(rng.uniform(-0.35, 0.1) * d)], [-sx, 0, 0]
        mat = _material(rng, "mirror") if rng.uniform() < 0.7 else _glossy_material(rng, 0.01, 0.06)
        objects.append({"shape": "panel", "center": centre, "normal": normal, "half": [hx, hy], "material": mat})
    if rng.uniform() < 0.4:  # a near-specular floor: glossy highlights of tiny lights
        p["floor_material"] = _glossy_material(rng, 0.015, 0.1)
    p["objects"] = objects
    p["lights"] = lights
    return p


def _caustic_paths(rng: np.random.Generator, family: str, seed: int) -> dict[str, Any]:
    p = _room(rng, family, seed)
    w, h, d = p["room"]
    objects: list[dict[str, Any]] = []
    lights: list[dict[str, Any]] = []
    casters = list(rng.choice(["glass_light", "water", "ring", "slab"], size=int(rng.integers(1, 3)), replace=False))
    foci: list[list[float]] = []  # where each caster's caustic lands: the camera looks at one
    for caster in casters:
        if caster == "glass_light":  # a small light inside a glass sphere or cube
            r = float(rng.uniform(0.15, 0.35))
            centre = _floor_spot(rng, p, r)
            if rng.uniform() < 0.4:  # hanging
                centre[1] = _r(rng.uniform(0.4, 0.75) * h)
            shape = str(rng.choice(["sphere", "sphere", "cube"]))
            objects.append({"shape": shape, "center": centre, "size": _r(r), "angle": _r(rng.uniform(0, 90), 1),
                            "material": _material(rng, "glass")})
            lights.append(_small_light(rng, centre, r_max=0.25 * r))
            foci.append([centre[0], 0.5 * centre[1], centre[2]])
        elif caster == "water":  # a wavy water surface under a small light
            p["water"] = {"height": _r(rng.uniform(0.3, 0.8)), "extent": _r(rng.uniform(0.5, 0.9)),
                          "waves": [[_r(rng.uniform(0.008, 0.03), 4), _r(rng.uniform(0.25, 0.9)),
                                     _r(rng.uniform(0, 360), 1), _r(rng.uniform(0, 6.28))] for _ in range(4)]}
            pos = [_r(rng.uniform(-0.3, 0.3) * w), _r(h - rng.uniform(0.05, 0.4)), _r(rng.uniform(-0.3, 0.2) * d)]
            lights.append(_small_light(rng, pos))
            foci.append([pos[0], 0.0, pos[2]])
        elif caster == "ring":  # a metal ring on the floor lit from low elevation: a cardioid
            radius = float(rng.uniform(0.2, 0.45))
            base = _floor_spot(rng, p, 0.0)
            metal = _material(rng, "mirror") if rng.uniform() < 0.6 else _glossy_material(rng, 0.01, 0.06)
            metal["twosided"] = True
            objects.append({"shape": "ring", "center": base, "radius": _r(radius),
                            "height": _r(rng.uniform(0.05, 0.25)), "material": metal})
            foci.append(list(base))
            elev, azim = math.radians(rng.uniform(15, 45)), rng.uniform(0, 2 * math.pi)
            dist = rng.uniform(0.8, 1.6)
            pos = _inside(p, np.array(base) + dist * np.array([math.cos(elev) * math.cos(azim), math.sin(elev),
                                                               math.cos(elev) * math.sin(azim)]), 0.08)
            if rng.uniform() < 0.3:
                lights.append({"type": "spot", "position": pos, "target": [base[0], 0.05, base[2]],
                               "cutoff": _r(rng.uniform(10, 25), 1),
                               "intensity": [_r(v, 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(20, 80)]})
            else:
                lights.append(_small_light(rng, pos))
        else:  # a thick glass slab with a small light behind it (seen through the glass)
            half = [_r(rng.uniform(0.2, 0.5)), _r(rng.uniform(0.2, 0.5)), _r(rng.uniform(0.03, 0.1))]
            centre = [_r(rng.uniform(-0.3, 0.3) * w), _r(half[1] + rng.uniform(0.0, 0.4) * h),
                      _r(rng.uniform(-0.35, 0.0) * d)]
            objects.append({"shape": "box", "center": centre, "half": half, "angle": _r(rng.uniform(-30, 30), 1),
                            "material": _material(rng, "glass")})
            foci.append(list(centre))
            pos = _inside(p, np.array(centre) + [rng.uniform(-0.7, 0.7) * half[0], rng.uniform(-0.7, 0.7) * half[1],
                                                 -half[2] - rng.uniform(0.05, 0.4)], 0.08)
            lights.append(_small_light(rng, pos))
    extra = []
    for _ in range(int(rng.integers(0, 3))):  # receivers and more casters
        r = float(rng.uniform(0.12, 0.35))
        extra.append({"shape": str(rng.choice(["sphere", "cube"])), "center": _floor_spot(rng, p, r),
                      "size": _r(r), "angle": _r(rng.uniform(0, 90), 1),
                      "material": _material(rng, str(rng.choice(["glass", "diffuse", "roughplastic", "mirror"])))})
    objects += [o for o in _without_hidden_lights(extra, lights)
                if not any(_contains(o, c["center"], c.get("size", 0.0)) for c in objects if c["shape"] != "ring")]
    if rng.uniform() < 0.25:  # a weak fill light now and then
        lights.append({"type": "area", "size": _r(rng.uniform(0.1, 0.3)),
                       "position": [_r(rng.uniform(-0.3, 0.3) * w), _r(h - 0.01), _r(rng.uniform(-0.3, 0.2) * d)],
                       "radiance": [_r(v, 3) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(0.3, 3)]})
    p["casters"] = [str(c) for c in casters]
    focus = np.array(foci[int(rng.integers(0, len(foci)))]) + [rng.uniform(-0.2, 0.2), 0.0, rng.uniform(-0.2, 0.2)]
    p["camera"]["target"] = _inside(p, focus, 0.0)
    p["objects"] = objects
    p["lights"] = lights
    return p


def _glossy_interreflection(rng: np.random.Generator, family: str, seed: int) -> dict[str, Any]:
    p = _room(rng, family, seed)
    w, h, d = p["room"]
    walls: dict[str, Any] = {}
    if rng.uniform() < 0.7:
        walls["0"] = _glossy_material(rng)
    for k in (2, 4, 5):  # back, left, right
        if rng.uniform() < 0.45:
            walls[str(k)] = _glossy_material(rng)
    p["wall_materials"] = walls
    objects: list[dict[str, Any]] = []
    for _ in range(int(rng.integers(0, 3))):  # pairs of glossy panels facing each other
        hx, hy = _r(rng.uniform(0.2, 0.5)), _r(rng.uniform(0.2, 0.6))
        gap = rng.uniform(0.3, 0.9)
        turn = math.radians(rng.uniform(-35, 35))
        normal = np.array([math.cos(turn), 0.0, math.sin(turn)])  # roughly sideways: never towards the camera
        first = np.array([rng.uniform(-0.35, 0.1) * w, hy, rng.uniform(-0.4, 0.0) * d])
        second = first + gap * normal
        for c, n in ((first, normal), (second, -normal)):
            objects.append({"shape": "panel", "center": _inside(p, c, 0.05), "normal": [_r(v) for v in n],
                            "half": [hx, hy], "material": _glossy_material(rng)})
    for _ in range(int(rng.integers(2, 6))):
        r = float(rng.uniform(0.12, 0.4))
        mat = _glossy_material(rng) if rng.uniform() < 0.8 else _material(rng, "diffuse")
        objects.append({"shape": str(rng.choice(["sphere", "cube"])), "center": _floor_spot(rng, p, r),
                        "size": _r(r), "angle": _r(rng.uniform(0, 90), 1), "material": mat})
    p["objects"] = objects
    p["lights"] = [_random_light(rng, w, h, d, spot=rng.uniform() < 0.35)]
    return p


def _texture_leaks(rng: np.random.Generator, family: str, seed: int) -> dict[str, Any]:
    p = _room(rng, family, seed)
    w, h, d = p["room"]
    p["wall_textures"] = {"0": _albedo_texture(rng)}
    for k in range(1, 6):
        if rng.uniform() < 0.4:
            p["wall_textures"][str(k)] = _albedo_texture(rng)
    # a partition across the room with a thin gap; the main light is behind it
    zp, thick = _r(rng.uniform(-0.35, -0.05) * d), _r(rng.uniform(0.04, 0.12))
    gap = _r(_log_uniform(rng, 0.005, 0.08), 4)
    leak = str(rng.choice(["slit", "slit", "under", "top"]))
    x_gap = _r(rng.uniform(-0.3, 0.3) * w)
    wall_colour = _colour(rng, 0.3, 0.85)
    p["partition"] = {"z": zp, "thickness": thick, "gap": gap, "leak": leak, "x": x_gap,
                      "material": {"kind": "diffuse", "albedo": _albedo_texture(rng, fine=False)
                                   if rng.uniform() < 0.5 else wall_colour}}
    back = [-d / 2 + 0.05, zp - thick / 2 - 0.05]
    if rng.uniform() < 0.6 and leak != "top":  # a ceiling light sends next to nothing up through a top gap
        light = {"type": "area", "size": _r(rng.uniform(0.1, 0.3)),
                 "position": [_r(rng.uniform(-0.35, 0.35) * w), _r(h - 0.01), _r(rng.uniform(*back))],
                 "radiance": [_r(v, 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(20, 100)]}
    else:  # a spot aimed at the gap from behind
        aim = [x_gap, _r(gap / 2), zp] if leak == "under" else [x_gap, _r(h * rng.uniform(0.2, 0.8)), zp] \
            if leak == "slit" else [x_gap, _r(h - gap / 2), zp]
        light = {"type": "spot", "position": [_r(rng.uniform(-0.35, 0.35) * w), _r(rng.uniform(0.3, 0.9) * h),
                                              _r(rng.uniform(*back))],
                 "target": aim, "cutoff": _r(rng.uniform(15, 40), 1),
                 "intensity": [_r(v, 2) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(20, 80)]}
    lights = [light]
    # a dim light on the camera's side; one scene in five has none: leaked light only (few
    # photons reach that side, so those references converge slowly)
    if rng.uniform() < 0.8:
        lights.append({"type": "area", "size": _r(rng.uniform(0.1, 0.3)),
                       "position": [_r(rng.uniform(-0.3, 0.3) * w), _r(h - 0.01),
                                    _r(rng.uniform(zp + 0.3, d / 2 - 0.3))],
                       "radiance": [_r(v, 3) for v in np.array(_colour(rng, 0.9, 1.0)) * rng.uniform(0.5, 5)]})
    objects: list[dict[str, Any]] = []
    for _ in range(int(rng.integers(1, 4))):  # textured objects in front of the partition
        r = float(rng.uniform(0.12, 0.35))
        lo, hi = zp + thick / 2 + r + 0.05, d / 2 - 0.9
        kind = str(rng.choice(["diffuse", "diffuse", "roughplastic"]))
        mat: dict[str, Any] = {"kind": kind, "albedo": _albedo_texture(rng)}
        if kind == "roughplastic":
            mat["alpha"] = _r(_log_uniform(rng, 0.02, 0.4), 4)
        objects.append({"shape": str(rng.choice(["sphere", "cube"])),
                        "center": [_r(rng.uniform(-0.4, 0.4) * w), _r(r), _r(rng.uniform(lo, max(lo, hi)))],
                        "size": _r(r), "angle": _r(rng.uniform(0, 90), 1), "material": mat})
    p["objects"] = objects
    p["lights"] = lights
    return p


_NEW_FAMILIES = {"bright_emitters": _bright_emitters, "caustic_paths": _caustic_paths,
                 "glossy_interreflection": _glossy_interreflection, "texture_leaks": _texture_leaks}


# ---------------------------------------------------------------------------- building

def _reflectance(albedo: list[float] | dict[str, Any]) -> dict[str, Any]:
    """An RGB constant, or a procedural bitmap texture (see :func:`_albedo_texture`)."""
    if isinstance(albedo, dict):
        import mitsuba as mi

        rep = albedo["repeat"]
        return {"type": "bitmap", "bitmap": mi.Bitmap(_albedo_bitmap(albedo)), "raw": True,
                "filter_type": albedo["filter"], "wrap_mode": "repeat",
                "to_uv": mi.ScalarTransform4f().scale([rep, rep, 1])}
    return {"type": "rgb", "value": albedo}


def _bsdf(m: dict[str, Any]) -> dict[str, Any]:
    kind = m["kind"]
    if kind == "diffuse":
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": _reflectance(m["albedo"])}
    elif kind == "glass":
        bsdf = {"type": "dielectric", "int_ior": m["ior"], "ext_ior": 1.0}
    elif kind == "mirror":
        bsdf = {"type": "conductor", "material": m["material"]}
    elif kind == "roughmetal":
        bsdf = {"type": "roughconductor", "material": m["material"], "alpha": m["alpha"],
                "distribution": m["distribution"]}
    elif kind == "roughplastic":
        bsdf = {"type": "roughplastic", "alpha": m["alpha"], "diffuse_reflectance": _reflectance(m["albedo"])}
    else:
        raise ValueError(kind)
    if m.get("twosided"):  # open shapes (rings) are seen from both sides
        bsdf = {"type": "twosided", "bsdf": bsdf}
    return bsdf


def _albedo_bitmap(tex: dict[str, Any], size: int = 128) -> np.ndarray:
    """A seamless tile (``size`` x ``size``, RGB in [0, 1]) of a procedural albedo pattern
    with ``cycles`` periods across it; deterministic given ``tex``."""
    n = tex["cycles"]
    u, v = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)
    pattern = tex["pattern"]
    rng = np.random.default_rng(tex["seed"])
    if pattern == "checker":
        t = ((np.floor(n * u) + np.floor(n * v)) % 2).astype(np.float64)
    elif pattern == "stripes":  # sharp stripes at an angle that keeps the tile seamless
        a, b = (n, 0) if tex["angle"] < 60 else (n, n // 2) if tex["angle"] < 120 else (0, n)
        t = (np.sin(2 * math.pi * (a * u + b * v)) > 0).astype(np.float64)
    elif pattern == "noise":  # band-limited periodic noise through the FFT
        f = np.fft.fftfreq(size) * size
        fx, fy = np.meshgrid(f, f)
        radius = np.hypot(fx, fy)
        spectrum = (rng.standard_normal((size, size)) + 1j * rng.standard_normal((size, size))) \
            * np.exp(-((radius - 2 * n) / n) ** 2)
        t = np.real(np.fft.ifft2(spectrum))
        t = np.clip(0.5 + 0.5 * t / (2 * t.std() + 1e-12), 0, 1)
    elif pattern == "bricks":
        rows = np.floor(n * v)
        x = n / 2 * u + 0.5 * (rows % 2)
        t = ((np.abs(n * v - rows - 0.5) < 0.4) & (np.abs(x - np.floor(x) - 0.5) < 0.45)).astype(np.float64)
    elif pattern == "dots":
        cu, cv = n * u - np.floor(n * u) - 0.5, n * v - np.floor(n * v) - 0.5
        t = (np.hypot(cu, cv) < 0.3).astype(np.float64)
    else:  # blocks: a random binary grid, like print seen from afar
        cells = rng.uniform(size=(4 * n, 4 * n)) < 0.5
        idx = (np.arange(size) * 4 * n) // size
        t = cells[idx][:, idx].astype(np.float64)
    c0, c1 = np.array(tex["colours"][0]), np.array(tex["colours"][1])
    return np.ascontiguousarray(c0 * (1 - t[..., None]) + c1 * t[..., None], dtype=np.float32)


def _projection_texture(tex: dict[str, Any], size: int = 128) -> np.ndarray:
    """A procedural RGB pattern for a spot light (values in [0, 1])."""
    u, v = np.meshgrid(np.linspace(-1, 1, size), np.linspace(-1, 1, size))
    f = tex["frequency"]
    if tex["pattern"] == "stripes":
        t = 0.5 + 0.5 * np.sin(f * math.pi * u)
    elif tex["pattern"] == "checker":
        t = ((np.floor(f * (u + 1)) + np.floor(f * (v + 1))) % 2).astype(np.float64)
    elif tex["pattern"] == "rings":
        t = 0.5 + 0.5 * np.cos(f * math.pi * np.hypot(u, v))
    else:  # blobs
        t = 0.5 + 0.25 * (np.sin(f * 2.1 * u + 1.3) + np.cos(f * 1.7 * v + 0.4))
    c0, c1 = np.array(tex["colours"][0]), np.array(tex["colours"][1])
    return (c0 * (1 - t[..., None]) + c1 * t[..., None]).astype(np.float32)


def _water_mesh(mi: Any, water: dict[str, Any], w: float, d: float) -> Any:
    """A dielectric height field (sum of four directional sine waves) across the room."""
    n = 48
    ex = water["extent"]
    xs, zs = np.meshgrid(np.linspace(-ex * w / 2, ex * w / 2, n), np.linspace(-ex * d / 2, ex * d / 2, n))
    ys = np.full_like(xs, water["height"])
    for amp, wavelength, angle, phase in water["waves"]:
        k = 2 * math.pi / wavelength
        ys += amp * np.sin(k * (math.cos(math.radians(angle)) * xs + math.sin(math.radians(angle)) * zs) + phase)
    verts = np.stack([xs, ys, zs], -1).reshape(-1, 3).astype(np.float32)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, e = i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                            np.stack([b, c, e], -1).reshape(-1, 3)]).astype(np.uint32)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "dielectric", "int_ior": 1.33, "ext_ior": 1.0})
    mesh = mi.Mesh("water", len(verts), len(faces), props=props, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(verts.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    mesh.recompute_vertex_normals()
    return mesh


def build_scene(params: dict[str, Any], width: int, height: int) -> dict[str, Any]:
    """The Mitsuba 3 scene dict of ``params`` at ``width`` x ``height`` (needs a variant set)."""
    import mitsuba as mi

    T = mi.ScalarTransform4f
    w, h, d = params["room"]
    cam = params["camera"]
    scene: dict[str, Any] = {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": cam["fov"], "fov_axis": "x",
                   "to_world": T().look_at(origin=cam["origin"], target=cam["target"], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}}},
    }
    # walls: floor, ceiling, back, front, left, right (normals into the room)
    walls = [([0, 0, 0], [0, 1, 0], [0, 0, -1], (w, d)), ([0, h, 0], [0, -1, 0], [0, 0, 1], (w, d)),
             ([0, h / 2, -d / 2], [0, 0, 1], [0, 1, 0], (w, h)), ([0, h / 2, d / 2], [0, 0, -1], [0, 1, 0], (w, h)),
             ([-w / 2, h / 2, 0], [1, 0, 0], [0, 1, 0], (d, h)), ([w / 2, h / 2, 0], [-1, 0, 0], [0, 1, 0], (d, h))]
    wall_materials = params.get("wall_materials") or {}
    wall_textures = params.get("wall_textures") or {}
    for k, (o, n, up, (sx, sy)) in enumerate(walls):
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": params["walls"][k]}}
        if str(k) in wall_materials:
            bsdf = _bsdf(wall_materials[str(k)])
        elif str(k) in wall_textures:
            bsdf = {"type": "diffuse", "reflectance": _reflectance(wall_textures[str(k)])}
        elif k == 0 and params.get("floor_material"):
            bsdf = _bsdf(params["floor_material"])
        elif k == 0 and params.get("floor_texture"):
            ft = params["floor_texture"]
            bsdf = {"type": "diffuse", "reflectance": {
                "type": "checkerboard", "color0": {"type": "rgb", "value": ft["colours"][0]},
                "color1": {"type": "rgb", "value": ft["colours"][1]}, "to_uv": T().scale([ft["scale"], ft["scale"], 1])}}
        target = [o[0] + n[0], o[1] + n[1], o[2] + n[2]]
        scene[f"wall{k}"] = {"type": "rectangle", "bsdf": bsdf,
                             "to_world": T().look_at(origin=o, target=target, up=up) @ T().scale([sx / 2, sy / 2, 1])}
    for k, obj in enumerate(params["objects"]):
        c, s = obj["center"], obj.get("size")
        if obj["shape"] == "sphere":
            shape: dict[str, Any] = {"type": "sphere", "center": c, "radius": s}
        elif obj["shape"] == "cube":
            shape = {"type": "cube", "to_world": T().translate(c) @ T().rotate([0, 1, 0], obj["angle"]) @ T().scale(s)}
        elif obj["shape"] == "box":
            shape = {"type": "cube", "to_world": T().translate(c) @ T().rotate([0, 1, 0], obj["angle"])
                     @ T().scale(obj["half"])}
        elif obj["shape"] == "panel":  # a one-sided rectangle facing along ``normal``
            nrm = obj["normal"]
            up = [0, 0, 1] if abs(nrm[1]) > 0.9 else [0, 1, 0]
            shape = {"type": "rectangle", "to_world": T().look_at(
                origin=c, target=[c[0] + nrm[0], c[1] + nrm[1], c[2] + nrm[2]], up=up)
                @ T().scale([obj["half"][0], obj["half"][1], 1])}
        elif obj["shape"] == "ring":  # an open vertical tube standing on the floor
            shape = {"type": "cylinder", "p0": c, "p1": [c[0], c[1] + obj["height"], c[2]], "radius": obj["radius"]}
        else:
            raise ValueError(obj["shape"])
        shape["bsdf"] = _bsdf(obj["material"])
        scene[f"object{k}"] = shape
    if params.get("partition"):
        scene.update(_partition(T, params["partition"], w, h))
    if params.get("water"):
        scene["water"] = _water_mesh(mi, params["water"], w, d)
    scale = float(params.get("radiance_scale", 1.0))

    def scaled(rgb: list[float]) -> list[float]:
        return [v * scale for v in rgb] if scale != 1.0 else rgb

    for k, light in enumerate(params["lights"]):
        if light["type"] == "sphere":
            scene[f"light{k}"] = {
                "type": "sphere", "center": light["position"], "radius": light["radius"],
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": scaled(light["radiance"])}}}
        elif light["type"] == "point":
            scene[f"light{k}"] = {"type": "point", "position": light["position"],
                                  "intensity": {"type": "rgb", "value": scaled(light["intensity"])}}
        elif light["type"] == "area":
            x, y, z = light["position"]
            s = light["size"]
            scene[f"light{k}"] = {
                "type": "rectangle",
                "to_world": T().look_at(origin=[x, y, z], target=light.get("target", [x, 0, z]), up=[0, 0, 1])
                @ T().scale([s, s, 1]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": scaled(light["radiance"])}}}
        else:
            spot: dict[str, Any] = {
                "type": "spot", "cutoff_angle": light["cutoff"], "beam_width": light["cutoff"] * 0.75,
                "intensity": {"type": "rgb", "value": scaled(light["intensity"])},
                "to_world": T().look_at(origin=light["position"], target=light["target"],
                                        up=_up_for(light["position"], light["target"]))}
            if light.get("texture"):
                spot["texture"] = {"type": "bitmap", "bitmap": mi.Bitmap(_projection_texture(light["texture"])),
                                   "raw": True}
            scene[f"light{k}"] = spot
    return scene


def _up_for(origin: list[float], target: list[float]) -> list[float]:
    """+z as the up vector of a light's frame (as always), +y where the light looks along z
    (look_at with a parallel up vector is degenerate)."""
    v = np.subtract(target, origin, dtype=float)
    return [0, 1, 0] if abs(v[2]) > 0.99 * (np.linalg.norm(v) + 1e-12) else [0, 0, 1]


def _partition(T: Any, part: dict[str, Any], w: float, h: float) -> dict[str, Any]:
    """A wall across the room at z = ``part["z"]`` with one thin gap: a vertical slit at
    x = ``part["x"]``, or a gap under it or above it. Its boxes reach 2 cm into the room's
    walls, so the gap is the only way through."""
    z, t, g, x = part["z"], part["thickness"], part["gap"], part["x"]
    m = 0.02
    boxes: list[tuple[float, float, float, float]] = []  # x0, x1, y0, y1
    if part["leak"] == "slit":
        boxes = [(-w / 2 - m, x - g / 2, -m, h + m), (x + g / 2, w / 2 + m, -m, h + m)]
    elif part["leak"] == "under":
        boxes = [(-w / 2 - m, w / 2 + m, g, h + m)]
    else:  # top
        boxes = [(-w / 2 - m, w / 2 + m, -m, h - g)]
    bsdf = _bsdf(part["material"])
    out = {}
    for k, (x0, x1, y0, y1) in enumerate(boxes):
        out[f"partition{k}"] = {"type": "cube", "bsdf": bsdf, "to_world": T().translate(
            [(x0 + x1) / 2, (y0 + y1) / 2, z]) @ T().scale([(x1 - x0) / 2, (y1 - y0) / 2, t / 2])}
    return out


def family_of(index: int, families: tuple[str, ...] | list[str] = FAMILIES) -> str:
    """``families`` in round-robin order, so any prefix of a data set covers them all
    (with :data:`LEGACY_FAMILIES`, the order of the first data sets)."""
    return families[index % len(families)]
