"""Training pipeline: data generation -> fit -> denoise end to end, augmentation of
normals, and refusal of corrupt or partial data-set items."""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest
import torch

from ppmrecon.backend import choose_variant

choose_variant()

import mitsuba as mi  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.model import cli as denoise_cli  # noqa: E402
from ppmrecon.render.eye import trace_eye  # noqa: E402
from ppmrecon.train import cli as train_cli  # noqa: E402
from ppmrecon.train.augment import transform_image, transform_normals  # noqa: E402
from ppmrecon.train.datagen import DataConfig, generate, input_name  # noqa: E402
from ppmrecon.train.dataset import PatchSampler, load_split  # noqa: E402

TINY = DataConfig(scenes=2, first_seed=1, validation_every=2, resolution=(24, 24), photons=2048,
                  input_passes=(1, 2, 4), seeds=(0, 1), reference_passes=64, reference_photons=2048,
                  max_depth=5)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    root = tmp_path_factory.mktemp("data")
    t0 = time.perf_counter()
    generate(TINY, root, workers=1, quiet=True)
    return root, time.perf_counter() - t0


def test_end_to_end_generate_fit_denoise(tiny_data, tmp_path, capsys):
    root, gen_seconds = tiny_data
    t0 = time.perf_counter()
    manifest = json.loads((root / "manifest.json").read_text())
    assert [s["split"] for s in manifest["scenes"]] == ["val", "train"]
    for s in manifest["scenes"]:
        assert len(s["inputs"]) == 6 and s["reference"]["passes"] == 64
    # a rerun finds everything done and renders nothing
    t = time.perf_counter()
    generate(TINY, root, workers=1, quiet=True)
    assert time.perf_counter() - t < 5.0

    run = tmp_path / "run"
    rc = train_cli.main([ "fit", str(root), "--out", str(run), "--epochs", "2", "--steps-per-epoch", "3",
                         "--batch", "2", "--lr", "1e-3", "--quiet"])
    assert rc == 0
    history = json.loads((run / "history.json").read_text())
    assert [h["epoch"] for h in history] == [1, 2]
    assert history[-1]["val"]["output"] > 0 and np.isfinite(history[-1]["loss"])
    # resume continues from epoch 2
    assert train_cli.main(["fit", str(root), "--out", str(run), "--epochs", "3", "--steps-per-epoch", "3",
                           "--batch", "2", "--resume", "--quiet"]) == 0
    assert json.loads((run / "history.json").read_text())[-1]["epoch"] == 3

    src = root / manifest["scenes"][0]["id"] / input_name(2, 0)
    out = tmp_path / "denoised.exr"
    assert denoise_cli.main([str(src), "--model", str(run / "model.pt"), "--output", str(out), "--quiet"]) == 0
    rgb, _ = B.read_rgb(out)  # validates: finite and non-negative
    assert rgb.shape == (24, 24, 3)
    assert gen_seconds + time.perf_counter() - t0 < 120


def _axis_scene(angle: float) -> dict:
    """Camera on +z looking down -z with +y up; geometry turned by ``angle`` about z."""
    T = mi.ScalarTransform4f
    R = T().rotate([0, 0, 1], angle)
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40, "to_world": T().look_at(origin=[0, 0, 6], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}}},
        "ball": {"type": "sphere", "center": list(R @ mi.ScalarPoint3f(0.8, 0.4, 0)), "radius": 0.6,
                 "bsdf": {"type": "diffuse"}},
        "box": {"type": "cube", "to_world": R @ T().translate([-0.7, -0.5, 0]) @ T().rotate([1, 1, 0], 30) @ T().scale(0.45),
                "bsdf": {"type": "diffuse"}},
        "back": {"type": "rectangle", "to_world": R @ T().translate([0, 0, -1]) @ T().rotate([1, 0, 0], 25) @ T().scale(3),
                 "bsdf": {"type": "diffuse"}},
        "light": {"type": "point", "position": [0, 0, 5]},
    }


def _normal_map(angle: float) -> torch.Tensor:
    scene = mi.load_dict(_axis_scene(angle))
    maps = [np.asarray(trace_eye(scene, scene.sensors()[0], seed, 4).normal) for seed in range(16)]
    n = np.mean(maps, 0).reshape(3, 32, 32)
    return torch.from_numpy(n.astype(np.float32))


@pytest.mark.parametrize("turns", [1, 2, 3])
def test_rotated_normal_map_equals_normals_of_rotated_scene(turns):
    """Turning the image by k x 90 degrees (and its normals) matches rendering the scene
    turned by k x 90 degrees about the view axis; skipping the vector transform fails."""
    base, turned = _normal_map(0.0), _normal_map(90.0 * turns)
    moved = transform_image(base, turns, False)
    good = (transform_normals(moved, turns, False) - turned).abs().mean()
    bad = (moved - turned).abs().mean()
    assert good < 0.03, good
    assert bad > 5 * good


def test_flip_is_its_own_inverse_and_turns_compose():
    x = torch.randn(2, 3, 5, 7)
    assert torch.equal(transform_image(transform_image(x, 0, True), 0, True), x)
    assert torch.equal(transform_image(x, 1, False), torch.rot90(x, 1, dims=(-2, -1)))
    assert torch.equal(transform_image(transform_image(x, 1, False), 3, False), x)
    n = torch.randn(3, 4, 4)
    # (turn once after a flip) is a reflection: applied twice it is the identity, for
    # the pixels and for the vector components alike
    twice = transform_normals(transform_image(transform_normals(transform_image(n, 1, True), 1, True), 1, True), 1, True)
    assert torch.allclose(twice, n)


def test_corrupt_and_partial_items_are_reported_and_skipped(tiny_data, tmp_path):
    root, _ = tiny_data
    data = tmp_path / "data"
    shutil.copytree(root, data)
    manifest = json.loads((data / "manifest.json").read_text())
    train_id = manifest["scenes"][1]["id"]
    bad = data / train_id / input_name(4, 1)
    bad.write_bytes(bad.read_bytes()[:500])                      # truncated EXR
    gone = data / train_id / input_name(2, 1)
    gone.unlink()                                                 # listed but missing
    manifest["scenes"][1]["inputs"] = [f for f in manifest["scenes"][1]["inputs"] if f["file"] != input_name(1, 1)]
    (data / "manifest.json").write_text(json.dumps(manifest))    # promised but not listed
    warnings = []
    samples = load_split(data, "train", warn=warnings.append)
    names = {s.name.split("/")[-1] for s in samples}
    assert names == {input_name(n, 0) for n in (1, 2, 4)}
    text = "\n".join(warnings)
    for name in (input_name(4, 1), input_name(2, 1), input_name(1, 1)):
        assert name in text
    assert len(PatchSampler(samples, 16).batch(3)[0]) == 3
