"""Randomised training scenes, deterministic by (family, seed) (SPEC section 6).

Four families cover what the network must learn; every scene is a closed room with a
random size, wall colours, procedural floor texture and camera:

``caustics``       glass spheres and slabs, a water height field, smooth metal
                   reflectors, one small area light: sharp caustics (LS+DE paths)
``glossy``         rough conductors and rough plastics (alpha 0.05..0.4) on the floor,
                   walls and objects, area or spot light: noisy glossy gather points
``indirect``       the light faces a wall or the ceiling, or hides behind a partition:
                   most of the image is lit by interreflection
``textured_light`` spot lights that project procedural textures, coloured area lights:
                   photons uniform in density but not in colour

A scene is described by a small JSON-able ``params`` dict (what the manifest stores);
:func:`build_scene` turns params into a Mitsuba scene dict. No third-party data.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

FAMILIES: tuple[str, ...] = ("caustics", "glossy", "indirect", "textured_light")


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


def sample_params(family: str, seed: int) -> dict[str, Any]:
    """Random parameters of scene ``seed`` of ``family`` (deterministic)."""
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family '{family}' (choose {', '.join(FAMILIES)})")
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


# ---------------------------------------------------------------------------- building

def _bsdf(m: dict[str, Any]) -> dict[str, Any]:
    kind = m["kind"]
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": m["albedo"]}}
    if kind == "glass":
        return {"type": "dielectric", "int_ior": m["ior"], "ext_ior": 1.0}
    if kind == "mirror":
        return {"type": "conductor", "material": m["material"]}
    if kind == "roughmetal":
        return {"type": "roughconductor", "material": m["material"], "alpha": m["alpha"],
                "distribution": m["distribution"]}
    if kind == "roughplastic":
        return {"type": "roughplastic", "alpha": m["alpha"],
                "diffuse_reflectance": {"type": "rgb", "value": m["albedo"]}}
    raise ValueError(kind)


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
    for k, (o, n, up, (sx, sy)) in enumerate(walls):
        bsdf: dict[str, Any] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": params["walls"][k]}}
        if k == 0 and params.get("floor_material"):
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
        c, s = obj["center"], obj["size"]
        if obj["shape"] == "sphere":
            shape: dict[str, Any] = {"type": "sphere", "center": c, "radius": s}
        else:
            shape = {"type": "cube", "to_world": T().translate(c) @ T().rotate([0, 1, 0], obj["angle"]) @ T().scale(s)}
        shape["bsdf"] = _bsdf(obj["material"])
        scene[f"object{k}"] = shape
    if params.get("water"):
        scene["water"] = _water_mesh(mi, params["water"], w, d)
    for k, light in enumerate(params["lights"]):
        if light["type"] == "area":
            x, y, z = light["position"]
            s = light["size"]
            scene[f"light{k}"] = {
                "type": "rectangle",
                "to_world": T().look_at(origin=[x, y, z], target=light.get("target", [x, 0, z]), up=[0, 0, 1])
                @ T().scale([s, s, 1]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": light["radiance"]}}}
        else:
            spot: dict[str, Any] = {
                "type": "spot", "cutoff_angle": light["cutoff"], "beam_width": light["cutoff"] * 0.75,
                "intensity": {"type": "rgb", "value": light["intensity"]},
                "to_world": T().look_at(origin=light["position"], target=light["target"], up=[0, 0, 1])}
            if light.get("texture"):
                spot["texture"] = {"type": "bitmap", "bitmap": mi.Bitmap(_projection_texture(light["texture"])),
                                   "raw": True}
            scene[f"light{k}"] = spot
    return scene


def family_of(index: int) -> str:
    """Families in round-robin order, so any prefix of a data set covers all four."""
    return FAMILIES[index % len(FAMILIES)]
