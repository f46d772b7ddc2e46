"""Training pipeline: data generation -> fit -> denoise end to end, augmentation of
normals, refusal of corrupt or partial data-set items; the data set's two references,
their agreement, firefly counts, resuming, and version-1 manifests."""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest
import torch

from ppmrecon.backend import choose_variant

choose_variant()

import mitsuba as mi  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.data import CONFIGS as CONFIGS_DIR  # noqa: E402
from ppmrecon.model import checkpoint as C  # noqa: E402
from ppmrecon.model.guide import GuideConfig  # noqa: E402
from ppmrecon.model import cli as denoise_cli  # noqa: E402
from ppmrecon.render.eye import trace_eye  # noqa: E402
from ppmrecon.train import cli as train_cli  # noqa: E402
from ppmrecon.train.augment import transform_image, transform_normals  # noqa: E402
from ppmrecon.errors import UsageError  # noqa: E402
from ppmrecon.metrics import firefly_count, firefly_mask, relmse  # noqa: E402
from ppmrecon.train.datagen import (LEGACY_CONFIG, MANIFEST_VERSION, REFERENCE, REFERENCE_HALVES,  # noqa: E402
                                    DataConfig, estimate, generate, input_name, plan, project)
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


# ------------------------------------------------------------ data set v2 (issue 12)

CONFIGS = CONFIGS_DIR / "data"


def test_firefly_mask_is_scale_free_and_ignores_faint_noise_on_black():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.5, 1.0, (32, 32, 3))
    ref[:8] = 0.0                                     # black in the reference
    est = ref * rng.uniform(0.8, 1.2, ref.shape)      # ordinary noise: no firefly
    est[:8] = 1e-3 * ref[8:].mean()                   # faint noise on black: below the floor
    est[20, 5] = 50 * ref[20, 5]                      # a firefly on a lit pixel
    est[2, 3] = 1.0                                   # and one on black
    assert firefly_mask(est, ref).shape == (32, 32)
    assert set(zip(*np.nonzero(firefly_mask(est, ref)))) == {(20, 5), (2, 3)}
    for scale in (1e-4, 1e4):
        assert firefly_count(est * scale, ref * scale) == 2


def test_generate_writes_two_references_agreement_fireflies_and_budgets(tiny_data):
    root, _ = tiny_data
    manifest = json.loads((root / "manifest.json").read_text())
    assert manifest["version"] == MANIFEST_VERSION == 2
    for s in manifest["scenes"]:
        folder = root / s["id"]
        (a, _), (b, _) = (B.read_rgb(folder / n) for n in REFERENCE_HALVES)
        ref, _ = B.read_rgb(folder / REFERENCE)
        assert np.allclose(ref, 0.5 * (a + b), rtol=1e-6, atol=0)  # the training reference is the mean
        assert not np.array_equal(a, b)                              # of two independent renders
        assert len({f["seed"] for f in s["references"]}) == 2
        assert [f["passes"] for f in s["references"]] == [TINY.reference_passes] * 2
        agree = s["agreement"]
        assert agree["relmse"] == pytest.approx(0.5 * (relmse(a, b) + relmse(b, a)))
        assert 0 < agree["relmse_trimmed"] <= agree["relmse"] * (1 + 1e-9)
        assert agree["mean_relmse_estimate"] == pytest.approx(agree["relmse"] / 4)
        m = float(ref.mean())
        assert agree["relmse_normalised"] == pytest.approx(0.5 * (relmse(a / m, b / m) + relmse(b / m, a / m)))
        for f in s["inputs"]:
            buf = B.read_buffers(folder / f["file"])
            y, z4 = firefly_mask(buf.estimates[0], ref), firefly_mask(buf.estimates[4], ref)
            assert (f["fireflies"], f["fireflies_y"], f["fireflies_z4"]) == \
                (int((y | z4).sum()), int(y.sum()), int(z4.sum()))
        assert set(s["items"]) == {"inputs_s0", "inputs_s1", "reference_a", "reference_b"}
        assert s["items"]["inputs_s0"]["passes"] == max(TINY.input_passes)
        assert s["items"]["reference_b"]["photons"] == TINY.reference_photons
        assert all(item["wall_seconds"] >= item["render_seconds"] > 0 for item in s["items"].values())
        assert 1e-4 <= s["params"]["radiance_scale"] <= 1e4


def test_rerun_redoes_only_what_is_missing(tiny_data, tmp_path):
    root, _ = tiny_data
    data = tmp_path / "data"
    shutil.copytree(root, data)
    before = json.loads((data / "manifest.json").read_text())
    first, second = before["scenes"][0]["id"], before["scenes"][1]["id"]
    (data / second / REFERENCE_HALVES[1]).unlink()
    (data / second / input_name(4, 0)).unlink()
    untouched = (data / first / REFERENCE).stat().st_mtime_ns
    after = generate(TINY, data, workers=1, quiet=True)
    s0, s1 = after["scenes"]
    assert s0["items"] == before["scenes"][0]["items"] and s0["agreement"] == before["scenes"][0]["agreement"]
    assert (data / first / REFERENCE).stat().st_mtime_ns == untouched
    old = before["scenes"][1]["items"]
    assert s1["items"]["inputs_s1"] == old["inputs_s1"] and s1["items"]["reference_a"] == old["reference_a"]
    assert s1["items"]["inputs_s0"] != old["inputs_s0"] and s1["items"]["reference_b"] != old["reference_b"]
    assert (data / second / REFERENCE_HALVES[1]).is_file() and (data / second / input_name(4, 0)).is_file()
    assert s1["agreement"]["relmse"] > 0 and all("fireflies" in f for f in s1["inputs"])
    assert len(s1["inputs"]) == 6


def test_version1_manifest_is_read_and_completed(tiny_data, tmp_path):
    """A data set written by manifest version 1 (one reference, no agreement, items or
    firefly counts; a config without the new keys) still trains, and rerunning
    ``generate`` with the version-1 values of the new keys renders nothing but adds the
    firefly counts; another configuration is refused."""
    root, _ = tiny_data
    data = tmp_path / "v1"
    shutil.copytree(root, data)
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["version"] = 1
    for key in LEGACY_CONFIG:
        manifest["config"].pop(key)
    for s in manifest["scenes"]:
        for key in ("references", "agreement", "items"):
            s.pop(key)
        s["reference"].pop("renders")
        for f in s["inputs"]:
            for key in ("fireflies", "fireflies_y", "fireflies_z4"):
                f.pop(key)
        for name in REFERENCE_HALVES:
            (data / s["id"] / name).unlink()
    (data / "manifest.json").write_text(json.dumps(manifest))
    warnings = []
    assert len(load_split(data, "train", warn=warnings.append)) == 6 and not warnings

    with pytest.raises(UsageError, match="another configuration"):
        generate(TINY, data, workers=1, quiet=True)
    legacy = DataConfig(**{**asdict(TINY), **LEGACY_CONFIG})
    t = time.perf_counter()
    done = generate(legacy, data, workers=1, quiet=True)
    assert time.perf_counter() - t < 5.0
    assert done["version"] == 2
    assert [s["id"] for s in done["scenes"]] == [s["id"] for s in manifest["scenes"]]
    assert all("fireflies" in f for s in done["scenes"] for f in s["inputs"])
    assert not any((data / s["id"] / REFERENCE_HALVES[0]).exists() for s in done["scenes"])


def test_a_data_set_grows_with_more_scenes_and_never_shrinks(tiny_data, tmp_path):
    """The same configuration with more scenes keeps every finished scene (no render,
    same files) and adds the new ones; fewer scenes are refused in one line."""
    root, _ = tiny_data
    data = tmp_path / "grown"
    shutil.copytree(root, data)
    before = json.loads((data / "manifest.json").read_text())
    first = before["scenes"][0]
    stamp = (data / first["id"] / first["inputs"][0]["file"]).stat().st_mtime_ns
    with pytest.raises(UsageError, match="can only grow"):
        generate(replace(TINY, scenes=TINY.scenes - 1), data, workers=1, quiet=True)
    grown = generate(replace(TINY, scenes=TINY.scenes + 1), data, workers=1, quiet=True)
    assert [s["id"] for s in grown["scenes"][:-1]] == [s["id"] for s in before["scenes"]]
    assert grown["scenes"][-1]["inputs"] and grown["scenes"][-1]["references"]
    assert (data / first["id"] / first["inputs"][0]["file"]).stat().st_mtime_ns == stamp
    assert grown["config"]["scenes"] == TINY.scenes + 1


def test_scenes_not_generated_yet_are_one_warning_not_one_per_file(tiny_data, tmp_path):
    """A growing data set lists scenes that have no item yet: they are skipped with one
    summary line; a scene with some items missing still names each missing file."""
    root, _ = tiny_data
    data = tmp_path / "growing"
    shutil.copytree(root, data)
    manifest = json.loads((data / "manifest.json").read_text())
    before = len(load_split(data, "train"))
    scene = next(s for s in manifest["scenes"] if s["split"] == "train")
    for n in range(2):                                 # two planned scenes, not started
        manifest["scenes"].append({"id": f"99{n}_planned", "family": scene["family"], "seed": 99 + n,
                                   "split": "train", "params": scene["params"]})
    dropped = scene["inputs"].pop()                    # one item of a started scene missing
    (data / "manifest.json").write_text(json.dumps(manifest))
    warnings = []
    assert len(load_split(data, "train", warn=warnings.append)) == before - 1
    assert [w for w in warnings if "not generated yet" in w] == [
        f"{data}: skipping 2 train scene(s) not generated yet (rerun `ppmrecon-train generate` to complete them)"]
    assert [w for w in warnings if "partial item" in w] == [
        f"skipping {data / scene['id'] / dropped['file']}: partial item (not in the manifest; "
        "rerun `ppmrecon-train generate`)"]


#: Every shipped data set, loaded, and the hold-outs' seeds kept apart from them.
SHIPPED_SETS = ("cpu", "tiny", "v2", "v2_cpu", "holdout", "holdout_n1024", "holdout_s16", "holdout_n1024_s16",
                "holdout_n1024_s17", "holdout_s18")


@pytest.mark.parametrize("name", SHIPPED_SETS)
def test_data_configs_load(name):
    DataConfig.load(CONFIGS / f"{name}.json")


def test_v2_configs_are_the_issue_12_sets():
    full, cpu = DataConfig.load(CONFIGS / "v2.json"), DataConfig.load(CONFIGS / "v2_cpu.json")
    assert len(full.families) >= 8 and full.scenes >= 200 and min(full.resolution) >= 128
    assert full.input_passes == (4, 16, 64, 256, 1024) and len(full.seeds) >= 2
    assert full.references == 2 and full.reference_passes > 1024 and full.radiance_log10 == (-4, 4)
    assert cpu.families == full.families and max(cpu.input_passes) <= 256 and cpu.references == 2
    # version-1 sets stay what they were
    for name in ("cpu", "tiny"):
        old = asdict(DataConfig.load(CONFIGS / f"{name}.json"))
        assert json.loads(json.dumps({k: old[k] for k in LEGACY_CONFIG})) == LEGACY_CONFIG


def _other_sets_seeds(name: str) -> dict[str, set[int]]:
    """The scene seeds of every shipped data set but ``name``, each counted to at least 32
    scenes (a set grown with ``--scenes``, as the first hold-out was, keeps its seeds)."""
    out = {}
    for other in SHIPPED_SETS:
        if other != name:
            cfg = DataConfig.load(CONFIGS / f"{other}.json")
            out[other] = set(range(cfg.first_seed, cfg.first_seed + max(cfg.scenes, 32)))
    return out


@pytest.mark.parametrize("name", ["holdout", "holdout_s16", "holdout_s18"])
def test_holdout_config_shares_no_scene_seed_with_a_training_set(name):
    """A hold-out set's scenes (seeds first_seed .. first_seed + scenes - 1) are none of
    the shipped training sets' nor another hold-out's (the first one grown to 32 scenes
    included), and it has every family of the issue-12 sets."""
    hold = DataConfig.load(CONFIGS / f"{name}.json")
    held = set(range(hold.first_seed, hold.first_seed + hold.scenes))
    for other, seeds in _other_sets_seeds(name).items():
        assert not held & seeds, other
    assert hold.families == DataConfig.load(CONFIGS / "v2.json").families
    assert hold.scenes >= 2 * len(hold.families)


@pytest.mark.parametrize("name", ["holdout_n1024", "holdout_n1024_s16"])
def test_n1024_holdout_is_new_scenes_with_references_far_beyond_its_longest_input(name):
    """An N = 1024 hold-out: scene seeds no other shipped set uses (the first hold-out grown
    to 32 scenes included), issue-12 families (the first one all of them, one scene each at
    least), inputs up to 1024 passes, all validation, and each reference at least 16x the
    photons of the longest input."""
    deep = DataConfig.load(CONFIGS / f"{name}.json")
    seeds = set(range(deep.first_seed, deep.first_seed + deep.scenes))
    for other, theirs in _other_sets_seeds(name).items():
        assert not seeds & theirs, other
    families = DataConfig.load(CONFIGS / "v2.json").families
    assert set(deep.families) <= set(families) and deep.scenes >= len(deep.families)
    assert name != "holdout_n1024" or deep.families == families
    assert max(deep.input_passes) == 1024 and deep.validation_every == 1 and deep.references == 2
    assert deep.reference_passes * deep.reference_photons >= 16 * 1024 * deep.photons


def test_data_config_rejects_unknown_family_and_a_thin_reference():
    with pytest.raises(UsageError, match="nope"):
        DataConfig(families=("glossy", "nope")).validate()
    with pytest.raises(UsageError, match="16x"):
        DataConfig(reference_passes=16).validate()


def test_fit_with_the_block_loss_term_and_a_bad_weight(tiny_data, tmp_path):
    """lowfreq_weight adds the 8x8 block-mean term to Eq. 8 (a short run trains and logs a
    finite loss); a negative weight is one line naming the file."""
    root, _ = tiny_data
    cfg = tmp_path / "train.json"
    cfg.write_text(json.dumps({"preset": "tiny", "lowfreq_weight": 0.5, "epochs": 1, "steps_per_epoch": 2,
                               "batch": 2, "lr": 1e-3}))
    run = tmp_path / "run"
    assert train_cli.main(["fit", str(root), "--out", str(run), "--config", str(cfg), "--quiet"]) == 0
    assert np.isfinite(json.loads((run / "history.json").read_text())[-1]["loss"])
    cfg.write_text(json.dumps({"lowfreq_weight": -1}))
    with pytest.raises(UsageError, match="lowfreq_weight must be a number >= 0"):
        train_cli.main(["fit", str(root), "--out", str(tmp_path / "run2"), "--config", str(cfg), "--quiet"])


def test_fit_selects_by_per_image_ratio_on_every_pass_count(tiny_data, tmp_path):
    """select "ratio" + val_passes 0: validation covers every N of the data set and
    best.pt is the epoch with the lowest geometric-mean ratio to the best single input."""
    root, _ = tiny_data
    cfg = tmp_path / "train.json"
    cfg.write_text(json.dumps({"preset": "tiny", "select": "ratio", "val_passes": 0, "epochs": 2,
                               "steps_per_epoch": 2, "batch": 2, "lr": 1e-3, "guard": {"enabled": True}}))
    run = tmp_path / "run"
    assert train_cli.main(["fit", str(root), "--out", str(run), "--config", str(cfg), "--quiet"]) == 0
    history = json.loads((run / "history.json").read_text())
    manifest = json.loads((root / "manifest.json").read_text())
    n_val = sum(len(s["inputs"]) for s in manifest["scenes"] if s["split"] == "val")
    assert n_val > 1
    ratios = [h["val"]["image_ratio"] for h in history]
    assert all(r > 0 and np.isfinite(r) for r in ratios)
    best_epoch = int(np.argmin(ratios)) + 1
    assert C.load_checkpoint(run / "best.pt").meta["epochs"] == best_epoch
    cfg.write_text(json.dumps({"select": "best"}))
    with pytest.raises(UsageError, match="select must be one of relmse, ratio"):
        train_cli.main(["fit", str(root), "--out", str(tmp_path / "run2"), "--config", str(cfg), "--quiet"])


def test_scenes_with_unconverged_references_can_be_left_out(tiny_data, tmp_path):
    """max_disagreement drops a scene whose two reference halves disagree (manifest
    agreement.relmse_trimmed) by more than the bound, with a warning naming it."""
    root, _ = tiny_data
    data = tmp_path / "data"
    shutil.copytree(root, data)
    manifest = json.loads((data / "manifest.json").read_text())
    train = [s for s in manifest["scenes"] if s["split"] == "train"]
    assert all(s["agreement"]["relmse_trimmed"] < 1.0 for s in train)
    train[0]["agreement"]["relmse_trimmed"] = 2.5
    (data / "manifest.json").write_text(json.dumps(manifest))
    everything = load_split(data, "train")
    warnings = []
    kept = load_split(data, "train", warn=warnings.append, max_disagreement=1.0)
    assert {s.scene for s in everything} - {s.scene for s in kept} == {train[0]["id"]}
    assert len(kept) < len(everything) and any(train[0]["id"] in w and "disagree" in w for w in warnings)


def test_guided_fit_starts_from_the_guide_and_resumes(tiny_data, tmp_path, capsys):
    """With a guide in the config the samples carry it, the head starts at zero (the guide
    alone), that start is validated as epoch 0 and can be best.pt; training moves the head,
    the checkpoint carries the guide, and a resumed run continues."""
    root, _ = tiny_data
    cfg = tmp_path / "train.json"
    cfg.write_text(json.dumps({"preset": "tiny", "select": "ratio", "val_passes": 0, "epochs": 1,
                               "steps_per_epoch": 3, "batch": 2, "lr": 1e-2, "guard": {"enabled": True},
                               "guide": {"enabled": True}, "features": {"scale_free": True}}))
    run = tmp_path / "run"
    assert train_cli.main(["fit", str(root), "--out", str(run), "--config", str(cfg)]) == 0
    assert "epoch 0 (the guide alone)" in capsys.readouterr().out
    samples = load_split(root, "val", guide=GuideConfig(enabled=True))
    assert samples and all(s.guide is not None and s.guide.shape[1:] == s.y.shape[1:] for s in samples)
    model = C.load_checkpoint(run / "model.pt").model
    assert model.guide.enabled and float(model.head.weight.detach().abs().sum()) > 0
    best = C.load_checkpoint(run / "best.pt")
    history = json.loads((run / "history.json").read_text())
    assert best.meta["epochs"] in (0, 1) and best.model.guide.enabled
    if best.meta["epochs"] == 0:
        assert best.meta["val"]["image_ratio"] <= history[0]["val"]["image_ratio"]
    cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "epochs": 2}))
    assert train_cli.main(["fit", str(root), "--out", str(run), "--config", str(cfg), "--resume", "--quiet"]) == 0
    assert [h["epoch"] for h in json.loads((run / "history.json").read_text())] == [1, 2]


def test_guide_aware_fit_reads_the_guide_and_tempers_its_prior(tiny_data, tmp_path):
    """With the guide as input channels and a learned temperature, the model's first
    layer takes 3 more channels and its head one more; untrained (zero head: tau = 0, no
    correction) it is exactly the guide alone; a fit moves the temperature channel; the
    checkpoint denoises a buffer file, and refuses to run with the guide off."""
    from ppmrecon.model.features import FeatureConfig
    from ppmrecon.model.guard import DEFAULT_ON
    from ppmrecon.model.guide import DEFAULT_GUIDE
    from ppmrecon.model.infer import denoise
    from ppmrecon.model.kpn import build

    root, _ = tiny_data
    plain = build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON, DEFAULT_GUIDE)
    aware = build("tiny", FeatureConfig(scale_free=True, guide=True), DEFAULT_ON,
                  GuideConfig(enabled=True, cross=2.0, temperature=True))
    assert aware.body[0].in_channels == plain.body[0].in_channels + 3
    assert aware.head.out_channels == plain.head.out_channels + 1
    with pytest.raises(ValueError, match="guide"):
        build("tiny", FeatureConfig(guide=True))
    first = json.loads((root / "manifest.json").read_text())["scenes"][0]
    buf = B.read_buffers(root / first["id"] / first["inputs"][0]["file"])
    torch.manual_seed(0)
    for m in (plain, aware):   # a nonzero body: the zero head alone must cancel it
        for p in m.body.parameters():
            p.data.normal_(0, 0.3)
    np.testing.assert_allclose(denoise(buf, aware).rgb, denoise(buf, plain).rgb, rtol=1e-5, atol=1e-6)

    cfg = tmp_path / "train.json"
    cfg.write_text(json.dumps({"preset": "tiny", "select": "ratio", "val_passes": 0, "epochs": 1,
                               "steps_per_epoch": 3, "batch": 2, "lr": 1e-2, "guard": {"enabled": True},
                               "guide": {"enabled": True, "temperature": True},
                               "features": {"scale_free": True, "guide": True}}))
    run = tmp_path / "run"
    assert train_cli.main(["fit", str(root), "--out", str(run), "--config", str(cfg), "--quiet"]) == 0
    model = C.load_checkpoint(run / "model.pt").model
    assert model.features.guide and model.guide.temperature
    assert float(model.head.weight.detach()[-1].abs().sum()) > 0     # tau's filter moved
    assert np.isfinite(denoise(buf, model).rgb).all()
    with pytest.raises(UsageError, match="guide off"):
        denoise(buf, model, guide=GuideConfig())


def _chooser_config(tmp_path: Path, **overrides) -> Path:
    cfg = {"steps": 8, "batch": 2, "crop": 16, "lr": 0.01, "width": 4, "layers": 2, "save_every": 4, **overrides}
    path = tmp_path / "chooser.json"
    path.write_text(json.dumps(cfg))
    return path


@pytest.fixture(scope="module")
def envelope_model(tmp_path_factory) -> Path:
    from ppmrecon.model.features import FeatureConfig
    from ppmrecon.model.guard import DEFAULT_ON
    from ppmrecon.model.guide import DEFAULT_GUIDE
    from ppmrecon.model.kpn import build

    path = tmp_path_factory.mktemp("base") / "envelope.pt"
    C.save_checkpoint(path, build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON,
                                  replace(DEFAULT_GUIDE, mode="envelope", cross=0.0, y_weight=2.0)))
    return path


def test_chooser_trains_scores_its_validation_split_and_denoises(tiny_data, envelope_model, tmp_path, capsys):
    root, _ = tiny_data
    run = tmp_path / "run"
    args = ["chooser", str(root), "--out", str(run), "--config", str(_chooser_config(tmp_path)),
            "--base-model", str(envelope_model), "--quiet"]
    assert train_cli.main(args) == 0
    out = capsys.readouterr().out
    assert "chooser.pt after 8 steps on 6 images; validation (6 images)" in out
    history = json.loads((run / "history.json").read_text())
    assert [h["step"] for h in history["losses"]] == [4, 8] and history["finished"]
    v = history["validation"]
    assert v["images"] == 6 and 0 < v["chooser"]["ratio"] < 10 and 0 < v["envelope"]["ratio"] < 10
    ckpt = C.load_checkpoint(run / "chooser.pt")
    assert ckpt.model.guide.mode == "chooser" and ckpt.model.chooser.cfg.width == 4
    assert ckpt.meta["chooser"]["train_images"] == 6 and ckpt.meta["chooser"]["train_scenes"] == 1
    # a second run into the same folder must say --resume
    with pytest.raises(UsageError, match="--resume"):
        train_cli.main(args)
    exr = sorted(root.glob("*/input_*.exr"))[0]
    assert denoise_cli.main([str(exr), "--model", str(run / "chooser.pt"), "-o", str(tmp_path / "o.exr"),
                             "--quiet"]) == 0
    assert np.isfinite(B.read_rgb(tmp_path / "o.exr")[0]).all()


def test_chooser_resumed_is_the_run_that_never_stopped(tiny_data, envelope_model, tmp_path):
    from ppmrecon.train.chooser import ChooserTrainConfig, fit, prepare

    root, _ = tiny_data
    items = [it for it in prepare(root, C.load_checkpoint(envelope_model).model) if it.split == "train"]
    cfg = ChooserTrainConfig.load(_chooser_config(tmp_path))
    straight, _ = fit(items, cfg)
    state = tmp_path / "state.pt"
    first, hist = fit(items, cfg, state, max_seconds=0.0)            # stops at the first saved state
    assert [h["step"] for h in hist] == [4]
    resumed, hist = fit(items, cfg, state, resume=True)
    assert [h["step"] for h in hist] == [4, 8]
    for k, v in straight.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[k], v, rtol=0, atol=0)
    with pytest.raises(UsageError, match="other settings"):
        fit(items, replace(cfg, lr=0.02), state, resume=True)


def test_chooser_config_errors_are_one_line(tiny_data, tmp_path):
    from ppmrecon.train.chooser import ChooserTrainConfig

    with pytest.raises(UsageError, match="'crop' must be a multiple of 8"):
        ChooserTrainConfig.load(_chooser_config(tmp_path, crop=12))
    with pytest.raises(UsageError, match="'lr' must be a number > 0"):
        ChooserTrainConfig.load(_chooser_config(tmp_path, lr=0))
    with pytest.raises(UsageError, match="unknown key"):
        ChooserTrainConfig.load(_chooser_config(tmp_path, depth=2))
    # a data set that is not there: one line, and no empty run folder left behind
    with pytest.raises(UsageError, match="no such manifest"):
        train_cli.main(["chooser", str(tmp_path / "nothing"), "--out", str(tmp_path / "r0"), "--quiet"])
    assert not (tmp_path / "r0").exists()
    root, _ = tiny_data
    with pytest.raises(UsageError, match="smaller than the crop"):
        train_cli.main(["chooser", str(root), "--out", str(tmp_path / "r"), "--config",
                        str(_chooser_config(tmp_path, crop=32)), "--quiet"])


def test_projection_of_a_data_set_cost_counts_first_passes_chunks_and_finished_items():
    """generate --estimate's arithmetic: every item pays its first pass, then its other
    passes at the timed rate; each reference chunk pays a first pass of its own; a family's
    timings stand for all its scenes; finished items leave the remaining cost."""
    cfg = replace(TINY, scenes=4, families=("caustics", "glossy"), reference_chunks=2)
    t = {"caustics": {"input_first_seconds": 2.0, "input_pass_seconds": 0.5,
                      "reference_first_seconds": 3.0, "reference_pass_seconds": 0.25},
         "glossy": {"input_first_seconds": 1.0, "input_pass_seconds": 1.0,
                    "reference_first_seconds": 1.0, "reference_pass_seconds": 1.0}}
    scenes = plan(cfg)
    done = {scenes[0]["id"]: {"inputs_s0", "reference_a_c01"}}
    p = project(cfg, t, workers=2, done=done)
    n_in, (c1, c2) = max(cfg.input_passes), ((1, 32), (33, 64))
    caustics = 2 * (2.0 + (n_in - 1) * 0.5) + 2 * ((3.0 + (c1[1] - c1[0]) * 0.25) + (3.0 + (c2[1] - c2[0]) * 0.25))
    glossy = 2 * (1.0 + (n_in - 1)) + 2 * ((1.0 + 31) + (1.0 + 31))
    assert p["families"]["caustics"]["scene_seconds"] == pytest.approx(caustics)
    assert set(p["families"]["glossy"]["items"]) == {"inputs_s0", "inputs_s1", "reference_a_c01", "reference_a_c02",
                                                     "reference_b_c01", "reference_b_c02"}
    assert p["worker_seconds"] == pytest.approx(2 * caustics + 2 * glossy)
    assert p["wall_seconds"] == pytest.approx(p["worker_seconds"] / 2)
    assert p["input_seconds"] == pytest.approx(2 * 2 * (2.0 + 3 * 0.5) + 2 * 2 * (1.0 + 3))
    assert p["remaining_worker_seconds"] == pytest.approx(p["worker_seconds"] - (2.0 + 3 * 0.5) - (3.0 + 31 * 0.25))
    assert p["items_done"] == 2
    unchunked = project(replace(cfg, reference_chunks=1), t)
    assert unchunked["families"]["caustics"]["items"]["reference_b"] == pytest.approx(3.0 + 63 * 0.25)


def test_estimate_times_each_family_writes_nothing_and_sees_a_finished_data_set(tiny_data, tmp_path, capsys):
    root, _ = tiny_data
    before = sorted(p.name for p in root.rglob("*"))
    est = estimate(TINY, seconds=0.2, workers=2, out=root, quiet=True)
    assert sorted(p.name for p in root.rglob("*")) == before
    assert set(est["families"]) == {s["family"] for s in plan(TINY)}
    for f in est["families"].values():
        assert f["input_first_seconds"] > 0 and f["input_pass_seconds"] > 0
        assert f["reference_first_seconds"] > 0 and f["reference_pass_seconds"] > 0
    assert est["worker_seconds"] > 0 and est["items_done"] == 4 * TINY.scenes
    assert est["remaining_worker_seconds"] == 0.0
    manifest = json.loads((root / "manifest.json").read_text())
    took = sum(i["wall_seconds"] for s in manifest["scenes"] for i in s["items"].values())
    assert est["finished_seconds"] == pytest.approx(took)
    assert est["finished_projected_seconds"] == pytest.approx(est["worker_seconds"])
    # the CLI: a table and one summary line; --out is only needed without --estimate
    assert train_cli.main(["generate", "--config", "tiny", "--estimate", "--estimate-seconds", "0.1", "--workers", "1",
                           "--quiet"]) == 0
    out = capsys.readouterr().out.splitlines()
    tiny_families = {s["family"] for s in plan(DataConfig.load(CONFIGS_DIR / "data" / "tiny.json"))}
    assert out[1].split()[0] == "family" and len(out) == 3 + len(tiny_families)
    assert {line.split()[0] for line in out[2:-1]} == tiny_families
    assert "of worker time" in out[-1]
    with pytest.raises(UsageError, match="--out is required"):
        train_cli.main(["generate", "--config", "tiny"])
    with pytest.raises(UsageError, match="does not take --ray"):
        train_cli.main(["generate", "--config", "tiny", "--estimate", "--ray", "local"])
    with pytest.raises(UsageError, match="another configuration"):
        estimate(replace(TINY, photons=4096), seconds=0.1, out=root, quiet=True)
    # three workers for four items: the last round holds one, which must not wait for the others
    t = time.perf_counter()
    assert estimate(TINY, seconds=0.1, workers=3, quiet=True)["worker_seconds"] > 0
    assert time.perf_counter() - t < 60.0

