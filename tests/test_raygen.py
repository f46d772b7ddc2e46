"""Issue 18: training data on a local Ray cluster (``ray.init(num_cpus=2)``): the same
files and manifest as the local pool, a restarted driver skips finished items, a killed
worker's task is retried, and a task that keeps failing is recorded as failed (the
driver stops with one line naming it)."""

from __future__ import annotations

import functools
import json
from dataclasses import asdict, replace
import os
import shutil
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest

from ppmrecon import buffers as B
from ppmrecon.cli_common import run_main
from ppmrecon.errors import UsageError
from ppmrecon.train import cli as train_cli
from ppmrecon.train.datagen import (MANIFEST, DataConfig, GenerationError, describe_item, generate,
                                    work_item)

try:
    import ray
except ImportError:  # the suite installs it (scripts/setup.sh: the [distributed] extra)
    ray = None

needs_ray = pytest.mark.skipif(ray is None, reason="ray is not installed (pip install 'ppmrecon[distributed]')")

# One scene, two input seeds, two references of two chunks each: six work items.
TINY = DataConfig(scenes=1, first_seed=1, validation_every=2, resolution=(16, 16), photons=1024,
                  input_passes=(1, 2, 4), seeds=(0, 1), reference_passes=16, reference_photons=2048,
                  max_depth=5, reference_chunks=2)
ITEMS = 6


@pytest.fixture(scope="module")
def cluster():
    if ray is None:
        pytest.skip("ray is not installed")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    # the test's task wrappers live in this module, which Ray workers cannot import
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def local_data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("local")
    generate(TINY, root, workers=2, quiet=True)  # 2 workers: one Dr.Jit thread each, as a Ray task
    return root


def _images(root: Path) -> dict[str, list[np.ndarray]]:
    out = {}
    for path in sorted(root.glob("*/*.exr")):
        key = f"{path.parent.name}/{path.name}"
        if path.name.startswith("input_"):
            buf = B.read_buffers(path)
            out[key] = [buf.estimates, buf.variances, buf.radii, buf.albedo, buf.normal, buf.depth]
        else:
            out[key] = [B.read_rgb(path)[0]]
    return out


def _same_images(a: Path, b: Path) -> None:
    ia, ib = _images(a), _images(b)
    assert sorted(ia) == sorted(ib) and len(ia) == 9  # 6 inputs, 2 reference halves, their mean
    for key in ia:
        assert all(np.array_equal(x, y) for x, y in zip(ia[key], ib[key])), key


def _timeless(manifest: dict) -> dict:
    """The manifest without wall-clock figures."""
    drop = {"seconds", "render_seconds", "wall_seconds", "generation_seconds"}

    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in drop}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x
    return strip(manifest)


def _runner(**kw):
    from ppmrecon.train.raygen import RayRunner

    return RayRunner("auto", **kw)


@needs_ray
@pytest.mark.slow
def test_ray_generates_the_local_data_set_and_a_rerun_skips_it(cluster, local_data, tmp_path):
    root = tmp_path / "ray"
    manifest = generate(TINY, root, quiet=True, runner=_runner())
    _same_images(local_data, root)
    local = json.loads((local_data / MANIFEST).read_text())
    assert _timeless(json.loads(json.dumps(manifest))) == _timeless(local)
    scene = manifest["scenes"][0]
    assert sorted(scene["items"]) == ["inputs_s0", "inputs_s1", "reference_a_c01", "reference_a_c02",
                                      "reference_b_c01", "reference_b_c02"]
    assert [r["chunks"] for r in scene["references"]] == [2, 2] and scene["agreement"]["relmse"] > 0
    # a restarted driver finds everything done: no task is submitted
    calls = tmp_path / "calls"
    calls.mkdir()
    again = generate(TINY, root, quiet=True, runner=_runner(item=functools.partial(_counting, calls=calls)))
    assert list(calls.iterdir()) == [] and _timeless(again) == _timeless(manifest)


def _counting(job: dict, calls: Path) -> dict:
    (calls / f"{job['id']}-{job['kind']}-{job.get('seed')}-{job.get('half')}-{job.get('chunk')}").touch()
    return work_item(job)


def _dies_once(job: dict, marker: Path) -> dict:
    """Kill the worker process on the first attempt of input seed 0 (no exception: the
    process is gone, as when a node fails); render normally otherwise."""
    if job["kind"] == "inputs" and job["seed"] == 0 and not marker.exists():
        marker.touch()
        os._exit(1)
    return work_item(job)


def _always_fails(job: dict, calls: Path) -> dict:
    # one file per attempt, named uniquely: Ray runs the two items side by side, and a
    # name from the current count could be taken by both (the test then saw 2 files, not 3)
    (calls / f"attempt-{job['kind']}-{job.get('half')}-{job.get('chunk')}-{uuid.uuid4().hex}").touch()
    if job["kind"] == "reference" and job.get("half") == 1 and job.get("chunk") == 1:
        raise RuntimeError("injected failure\nsecond line of the message")
    return work_item(job)


def _partial_copy(local_data: Path, dest: Path, remove: list[str]) -> Path:
    shutil.copytree(local_data, dest)
    folder = next(p for p in dest.iterdir() if p.is_dir())
    for name in remove:
        (folder / name).unlink()
    return dest


@needs_ray
def test_a_killed_worker_is_retried_and_only_missing_items_run(cluster, local_data, tmp_path):
    root = _partial_copy(local_data, tmp_path / "partial",
                         [f"input_n000{n}_s0.exr" for n in (1, 2, 4)]
                         + ["reference_b.chunk02of02.npz", "reference_b.exr"])
    marker = tmp_path / "died"
    manifest = generate(TINY, root, quiet=True, runner=_runner(retries=1, item=functools.partial(_dies_once, marker=marker)))
    assert marker.exists()  # the first attempt did die
    _same_images(local_data, root)
    assert "failed" not in json.dumps(manifest)


@needs_ray
def test_a_task_that_keeps_failing_is_recorded_and_reported(cluster, local_data, tmp_path):
    root = _partial_copy(local_data, tmp_path / "partial", ["reference_b.chunk02of02.npz", "reference_b.exr", "input_n0002_s1.exr"])
    calls = tmp_path / "calls"
    calls.mkdir()
    with pytest.raises(GenerationError) as info:
        generate(TINY, root, quiet=True, runner=_runner(retries=1, item=functools.partial(_always_fails, calls=calls)))
    msg = str(info.value)
    assert len(msg.splitlines()) == 1
    assert "0000_caustics reference_b_c02" in msg and "2 attempt(s)" in msg and "injected failure" in msg
    assert len(list(calls.iterdir())) == 3   # inputs_s1 once, the failing chunk twice (1 retry)
    manifest = json.loads((root / MANIFEST).read_text())
    scene = manifest["scenes"][0]
    assert scene["items"]["reference_b_c02"]["failed"] == "RuntimeError: injected failure"
    assert "failed" not in scene["items"]["inputs_s1"]          # the other item finished
    assert "reference_b.exr" not in {f["file"] for f in scene["references"]}  # not merged from half the passes
    assert describe_item({"id": "x", "kind": "reference", "half": 1, "chunk": 1}) == "x reference_b_c02"
    # the rerun (healthy now) retries the failed item and completes the data set
    generate(TINY, root, quiet=True, runner=_runner())
    _same_images(local_data, root)


def test_ray_option_without_ray_installed_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    rc = run_main(train_cli.PROG, train_cli.main,
                  ["generate", "--config", "tiny", "--out", str(tmp_path / "d"), "--ray", "auto"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert "ppmrecon[distributed]" in err and "--ray" in err


def test_chunked_reference_is_the_single_render(local_data, tmp_path):
    """reference_a.exr merged from its two chunks equals the unchunked 16-pass render of
    the same seed (up to float32 rounding of the running mean)."""
    scene = json.loads((local_data / MANIFEST).read_text())["scenes"][0]
    whole = replace(TINY, reference_chunks=1)
    work_item({"kind": "reference", "half": 0, "id": scene["id"], "scene_seed": scene["seed"],
               "params": scene["params"], "folder": str(tmp_path), "config": asdict(whole)})
    # no "threads": dr.set_thread_count in this (pytest's) process makes Mitsuba's Bitmap.write
    # of an EXR deadlock in later tests
    single, header = B.read_rgb(tmp_path / "reference_a.exr")
    merged, merged_header = B.read_rgb(local_data / scene["id"] / "reference_a.exr")
    assert merged_header[B.H_PASSES] == header[B.H_PASSES] == 16 and merged_header["ppmrecon.data.chunks"] == 2
    assert single.max() > 0
    np.testing.assert_allclose(merged, single, rtol=0, atol=1e-5 * single.max())


@needs_ray
def test_generate_cli_with_ray(cluster, local_data, tmp_path, capsys):
    root = tmp_path / "done"
    shutil.copytree(local_data, root)
    config = tmp_path / "tiny.json"
    config.write_text(json.dumps(asdict(TINY)))
    args = ["generate", "--config", str(config), "--out", str(root), "--ray", "auto", "--quiet"]
    assert run_main(train_cli.PROG, train_cli.main, args) == 0
    assert f"data set {root}: 1 scenes, 6 inputs" in capsys.readouterr().out
    # another chunk count is another configuration: refused in one line
    assert run_main(train_cli.PROG, train_cli.main, args + ["--reference-chunks", "4"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "another configuration" in err


@needs_ray
def test_task_slots_follow_the_cluster_resources(cluster, monkeypatch):
    """GPU tasks: one per GPU (each also takes a CPU); CPU tasks: the other CPUs."""
    runner = _runner()
    assert runner.slots() == (0, 2)   # this test's cluster: 2 CPUs, no GPU
    cases = [({"CPU": 8, "GPU": 2}, {}, (2, 6)), ({"CPU": 8, "GPU": 2}, {"cpus_per_task": 2}, (2, 3)),
             ({"CPU": 8, "GPU": 2}, {"gpus": 0}, (0, 8)), ({"CPU": 2, "GPU": 2}, {}, (2, 0)),
             ({"CPU": 1}, {"cpus_per_task": 4}, (0, 1))]
    for resources, options, want in cases:
        monkeypatch.setattr(cluster, "cluster_resources", lambda r=resources: dict(r))
        assert _runner(**options).slots() == want, (resources, options)
    monkeypatch.setattr(cluster, "cluster_resources", lambda: {"CPU": 8})
    with pytest.raises(UsageError, match="--ray-gpus 1: the Ray cluster has 0 GPU"):
        _runner(gpus=1)


def test_a_raising_item_in_the_local_pool_comes_back_as_a_failure():
    from ppmrecon.train.datagen import _local_item

    res = _local_item({"kind": "inputs", "seed": 1, "id": "0007_glossy", "config": asdict(TINY)})
    assert res["error"] == "KeyError: 'folder'" and res["attempts"] == 1
    assert describe_item(res) == "0007_glossy inputs_s1"
