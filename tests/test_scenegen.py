"""Training-scene families: deterministic, loadable, lit, camera in free space; the
first four families' parameters are pinned (existing data sets depend on them)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ppmrecon.backend import choose_variant

choose_variant()

import mitsuba as mi  # noqa: E402

from ppmrecon.render.integrator import Renderer, RenderSettings  # noqa: E402
from ppmrecon.train import scenegen as sg  # noqa: E402

NEW_FAMILIES = [f for f in sg.FAMILIES if f not in sg.LEGACY_FAMILIES]


def test_family_list_keeps_the_old_order():
    assert sg.FAMILIES[:4] == sg.LEGACY_FAMILIES == ("caustics", "glossy", "indirect", "textured_light")
    assert len(sg.FAMILIES) >= 8 and len(set(sg.FAMILIES)) == len(sg.FAMILIES)
    assert [sg.family_of(i, sg.LEGACY_FAMILIES) for i in range(6)] == \
        ["caustics", "glossy", "indirect", "textured_light", "caustics", "glossy"]
    assert [sg.family_of(i) for i in range(len(sg.FAMILIES))] == list(sg.FAMILIES)


# Values drawn by the version of scenegen that made the first data sets (seed 7).
PINNED = {
    "caustics": ([2.078, 2.777, 3.699], [-0.237, 2.195, 1.7], 57.2, 3, [172.08, 171.52, 169.23]),
    "glossy": ([2.719, 2.617, 3.467], [-0.032, 1.962, 1.584], 45.8, 2, [15.9, 22.81, 15.22]),
    "indirect": ([2.241, 2.757, 3.858], [-0.011, 1.937, 1.779], 58.7, 3, [3.55, 13.31, 17.7]),
    "textured_light": ([3.364, 2.6, 3.271], [-0.85, 0.862, 1.486], 69.2, 1, [28.47, 29.33, 18.54]),
}


@pytest.mark.parametrize("family", sg.LEGACY_FAMILIES)
def test_old_families_unchanged(family):
    room, origin, fov, n_objects, light = PINNED[family]
    p = sg.sample_params(family, 7, radiance_log10=None)
    assert p["room"] == room and p["camera"]["origin"] == origin and p["camera"]["fov"] == fov
    assert len(p["objects"]) == n_objects
    assert p["lights"][0].get("radiance", p["lights"][0].get("intensity")) == light
    assert "radiance_scale" not in p
    # the radiance scale comes from a stream of its own: nothing else moves
    scaled = sg.sample_params(family, 7)
    assert {k: v for k, v in scaled.items() if k != "radiance_scale"} == p


def test_radiance_scale_spans_eight_decades_and_scales_every_emitter():
    scales = [sg.sample_params(f, s)["radiance_scale"] for f in sg.FAMILIES for s in range(40)]
    assert 1e-4 <= min(scales) < 1e-3 and 1e3 < max(scales) <= 1e4
    p = sg.sample_params("caustic_paths", 3, radiance_log10=None)
    plain = sg.build_scene(p, 8, 8)
    scaled = sg.build_scene({**p, "radiance_scale": 1e3}, 8, 8)
    n = 0
    for key, light in plain.items():
        if key.startswith("light"):
            spec = light["emitter"]["radiance"] if "emitter" in light else light["intensity"]
            spec2 = scaled[key]["emitter"]["radiance"] if "emitter" in light else scaled[key]["intensity"]
            assert np.allclose(np.array(spec2["value"]), 1e3 * np.array(spec["value"]))
            n += 1
    assert n == len(p["lights"])


def _inside_object(x: np.ndarray, obj: dict) -> bool:
    if obj["shape"] == "sphere":
        return float(np.linalg.norm(x - obj["center"])) < obj["size"]
    if obj["shape"] in ("cube", "box"):
        half = obj["half"] if obj["shape"] == "box" else [obj["size"]] * 3
        a = math.radians(obj["angle"])
        v = x - obj["center"]  # into the box frame (rotation about y)
        local = [math.cos(a) * v[0] - math.sin(a) * v[2], v[1], math.sin(a) * v[0] + math.cos(a) * v[2]]
        return all(abs(c) < h for c, h in zip(local, half))
    return False


@pytest.mark.parametrize("family", sg.FAMILIES)
def test_camera_in_free_space_and_params_json(family):
    for seed in range(25):
        p = sg.sample_params(family, seed)
        assert json.loads(json.dumps(p)) == p  # the manifest stores params as JSON
        w, h, d = p["room"]
        o = np.array(p["camera"]["origin"])
        assert abs(o[0]) < w / 2 and 0 < o[1] < h and abs(o[2]) < d / 2
        assert np.linalg.norm(np.subtract(p["camera"]["target"], o)) > 0.5
        for obj in p["objects"]:
            assert not _inside_object(o, obj), (family, seed, obj)
        part = p.get("partition")
        if part:  # the camera is on the near side of the partition
            assert o[2] > part["z"] + part["thickness"] / 2


@pytest.mark.parametrize("family", sg.FAMILIES)
def test_family_builds_deterministically_and_is_lit(family):
    for seed in (0, 1, 2):
        assert sg.sample_params(family, seed) == sg.sample_params(family, seed)
        mi.load_dict(sg.build_scene(sg.sample_params(family, seed), 8, 8))
    p = sg.sample_params(family, 0)
    scene = mi.load_dict(sg.build_scene(p, 16, 16))
    res = Renderer(scene, RenderSettings(passes=2, photons=4096, max_depth=6, seed=1)).run()
    est = res.estimates
    assert np.isfinite(est).all()
    assert est.mean() > 0, family
    # scaled radiance: the image stays within a few decades of the scale
    assert est.mean() / p["radiance_scale"] > 1e-5, (family, est.mean(), p["radiance_scale"])


def test_albedo_textures_are_deterministic_and_high_frequency():
    rng = np.random.default_rng(5)
    for _ in range(12):
        tex = sg._albedo_texture(rng)
        a, b = sg._albedo_bitmap(tex), sg._albedo_bitmap(tex)
        assert a.dtype == np.float32 and a.shape == (128, 128, 3)
        assert np.array_equal(a, b) and 0.0 <= a.min() and a.max() <= 1.0
        # neighbouring texels differ somewhere: a pattern, not a flat colour
        assert max(np.abs(np.diff(a, axis=k)).max() for k in (0, 1)) > 0.05, tex["pattern"]
