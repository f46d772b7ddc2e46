"""Issue 18: exact merges of reference chunks (Welford/Chan, SPPM pass ranges), the
sharded patch sampler, and data-parallel training with DDP (two gloo processes give the
loss curve of one process with the same global batch, checkpoints from rank 0 only,
resume)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ppmrecon import buffers as B
from ppmrecon.cli_common import run_main
from ppmrecon.model.features import FeatureConfig
from ppmrecon.render.estimates import merge_welford
from ppmrecon.train import cli as train_cli
from ppmrecon.train.dataset import PatchSampler, Sample
from ppmrecon.train.datagen import reference_chunk_bounds
from tests.conftest import make_buffer


def _welford(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(mean, M2, n) of samples along axis 0, computed directly."""
    mean = x.mean(0)
    return mean, ((x - mean) ** 2).sum(0), x.shape[0]


def test_chan_merge_equals_the_statistics_of_the_concatenated_samples():
    rng = np.random.default_rng(3)
    x = rng.lognormal(size=(23, 3, 50))  # 23 passes of a 3 x 50 image, heavy-tailed
    cuts = [(0, 5), (5, 6), (6, 6), (6, 23)]   # includes a 1-sample and an empty part
    parts = [_welford(x[a:b]) if b > a else (np.zeros((3, 50)), np.zeros((3, 50)), 0) for a, b in cuts]
    mean, m2, n = merge_welford(parts)
    assert n == 23
    np.testing.assert_allclose(mean, x.mean(0), rtol=1e-12)
    np.testing.assert_allclose(m2 / (n - 1), x.var(0, ddof=1), rtol=1e-11)
    # two parts: the closed form of Chan et al.
    (ma, qa, na), (mb, qb, nb) = _welford(x[:9]), _welford(x[9:])
    m, q, k = merge_welford([(ma, qa, na), (mb, qb, nb)])
    d = mb - ma
    np.testing.assert_allclose(m, ma + d * nb / (na + nb), rtol=1e-14)
    np.testing.assert_allclose(q, qa + qb + d * d * na * nb / (na + nb), rtol=1e-14)
    assert k == na + nb
    # summing the M2s without the between-part term is wrong, and the test sees it
    assert not np.allclose(qa + qb, x.var(0, ddof=0) * 23, rtol=1e-3)
    with pytest.raises(ValueError, match="do not merge"):
        merge_welford([(ma, qa, na), (mb[:, :3], qb[:, :3], nb)])


def test_chunk_bounds_partition_the_passes():
    for passes, chunks in [(16, 1), (16, 3), (7, 7), (100, 8)]:
        bounds = reference_chunk_bounds(passes, chunks)
        covered = [i for a, b in bounds for i in range(a, b + 1)]
        assert covered == list(range(1, passes + 1)) and len(bounds) == chunks
        assert max(b - a for a, b in bounds) - min(b - a for a, b in bounds) <= 1


def test_sppm_pass_ranges_merge_to_the_single_run():
    """Passes 1-3 and 4-9 of one SPPM run, rendered by two renderers and merged, are the
    9-pass render (up to float32 rounding); two independent runs of 3 and 6 passes (what
    a naive split gives) are not, and CPPM, whose radii follow the gathered photons,
    refuses to start mid-run."""
    from ppmrecon.backend import choose_variant

    choose_variant()
    import mitsuba as mi

    from ppmrecon.render.integrator import Renderer, RenderSettings
    from ppmrecon.train.scenegen import build_scene, sample_params

    scene = mi.load_dict(build_scene(sample_params("caustics", 1, radiance_log10=None), 16, 16))

    def settings(passes: int, seed: int = 5, method: str = "sppm") -> RenderSettings:
        return RenderSettings(method=method, passes=passes, photons=1024, seed=seed, layout="single", max_depth=5)

    whole = Renderer(scene, settings(9))
    whole.run()
    parts, radii = [], []
    for first, last in [(1, 3), (4, 9)]:
        r = Renderer(scene, settings(last))
        r.start_at(first)
        r.run()
        parts.append((np.array(r.means[0].mean), np.array(r.means[0].m2), r.means[0].n))
        radii.append(np.array(r.controller.radii()[0]))
    mean, m2, n = merge_welford(parts)
    ref, ref_m2 = np.array(whole.means[0].mean), np.array(whole.means[0].m2)
    assert n == 9 and ref.max() > 0
    np.testing.assert_allclose(mean, ref, rtol=0, atol=1e-5 * ref.max())
    np.testing.assert_allclose(m2, ref_m2, rtol=0, atol=1e-5 * ref_m2.max())
    np.testing.assert_array_equal(radii[1], np.array(whole.controller.radii()[0]))

    naive = []
    for passes, seed in [(3, 5), (6, 6)]:
        r = Renderer(scene, settings(passes, seed))
        r.run()
        naive.append((np.array(r.means[0].mean), np.array(r.means[0].m2), r.means[0].n))
    assert np.abs(merge_welford(naive)[0] - ref).max() > 100 * np.abs(mean - ref).max()

    with pytest.raises(ValueError, match="adapts its radii"):
        Renderer(scene, settings(4, method="cppm")).start_at(2)


def _samples(n: int, sizes=None) -> list[Sample]:
    g = torch.Generator().manual_seed(0)
    c = FeatureConfig().n_channels
    out = []
    for i in range(n):
        h, w = (sizes or {}).get(i, (20, 24))
        t = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
        out.append(Sample(f"s{i}", "scene", 4, t(c, h, w), t(3, h, w), t(4, 3, h, w), t(3, h, w), index=i))
    return out


def test_shard_samplers_cut_exactly_the_single_process_batch():
    samples = _samples(5, sizes={3: (14, 30)})   # one smaller image: patches cut to the smallest
    one = PatchSampler(samples, patch=16, seed=7)
    catalog = [tuple(s.y.shape[-2:]) for s in samples]
    shards = [PatchSampler([s for s in samples if s.index % 2 == r], patch=16, seed=7, catalog=catalog,
                           positions=[s.index for s in samples if s.index % 2 == r]) for r in range(2)]
    for _ in range(4):
        full = one.batch(6)
        plans = [sh.plan(6) for sh in shards]
        assert plans[0] == plans[1]
        rows = plans[0]
        got = [None] * len(rows)
        for sh in shards:
            mine = sh.mine(rows)
            if mine:
                cut = sh.cut(mine)
                for k, row in enumerate(mine):
                    got[rows.index(row)] = [t[k] for t in cut]
        for j in range(4):
            assert torch.equal(torch.stack([g[j] for g in got]), full[j])


@pytest.fixture(scope="module")
def synthetic_data(tmp_path_factory) -> Path:
    """A data set of random buffer files (no rendering): 1 validation + 3 training scenes."""
    root = tmp_path_factory.mktemp("synthetic")
    config = {"input_passes": [4, 8, 16], "seeds": [0]}
    scenes = []
    for i, split in enumerate(["val", "train", "train", "train"]):
        sid = f"{i:04d}_synthetic"
        (root / sid).mkdir()
        rng = np.random.default_rng(i)
        B.write_rgb(root / sid / "reference.exr", rng.random((24, 24, 3), dtype=np.float32) * 2)
        inputs = []
        for n in config["input_passes"]:
            buf = make_buffer(24, 24, seed=100 * i + n)
            buf.header[B.H_PASSES] = n
            name = f"input_n{n:04d}_s0.exr"
            B.write_buffers(root / sid / name, buf)
            inputs.append({"file": name, "passes": n, "seed": 0})
        scenes.append({"id": sid, "split": split, "inputs": inputs})
    (root / "manifest.json").write_text(json.dumps({"version": 2, "config": config, "scenes": scenes}))
    return root


def _fit(data: Path, out: Path, procs: int, epochs: int, resume: bool = False, self_launch: bool = False) -> list[dict]:
    """``fit`` in ``procs`` processes: torchrun, or (``self_launch``) ``--ddp --nproc-per-node``."""
    args = ["fit", str(data), "--out", str(out), "--epochs", str(epochs), "--steps-per-epoch", "4",
            "--batch", "6", "--lr", "1e-3", "--threads", "1", "--quiet"] + (["--resume"] if resume else [])
    if procs == 1:
        cmd = [sys.executable, "-m", "ppmrecon.train"] + args
    elif self_launch:
        cmd = [sys.executable, "-m", "ppmrecon.train"] + args + ["--ddp", "--nproc-per-node", str(procs)]
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={procs}",
               "-m", "ppmrecon.train"] + args + ["--ddp"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads((out / "history.json").read_text())


def _curve(history: list[dict]) -> np.ndarray:
    return np.array([x for h in history for x in h["step_losses"]])


@pytest.mark.slow
def test_two_gloo_processes_train_as_one_with_the_same_global_batch(synthetic_data, tmp_path):
    one = _fit(synthetic_data, tmp_path / "one", 1, 2)
    two = _fit(synthetic_data, tmp_path / "two", 2, 2)
    assert [h["ranks"] for h in two] == [2, 2] and len(_curve(two)) == 8
    np.testing.assert_allclose(_curve(two), _curve(one), rtol=1e-4)
    assert abs(two[-1]["val"]["output"] / one[-1]["val"]["output"] - 1) < 1e-4
    assert two[-1]["val_images"] == one[-1]["val_images"] and len(one[-1]["val_images"]) == 1
    # rank 0 alone wrote the run folder: the same files as one process, nothing else
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == sorted(p.name for p in (tmp_path / "one").iterdir())
    # the models agree too
    a = torch.load(tmp_path / "one" / "model.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "two" / "model.pt", weights_only=True)["state_dict"]
    assert all(torch.allclose(a[k], b[k], rtol=1e-4, atol=1e-6) for k in a)
    # resume continues both the same way (this time fit starts torchrun itself)
    one = _fit(synthetic_data, tmp_path / "one", 1, 3, resume=True)
    two = _fit(synthetic_data, tmp_path / "two", 2, 3, resume=True, self_launch=True)
    assert [h["epoch"] for h in two] == [1, 2, 3]
    np.testing.assert_allclose(_curve(two), _curve(one), rtol=1e-4)


def test_ddp_flag_outside_torchrun_is_one_line(synthetic_data, tmp_path, capsys, monkeypatch):
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(key, raising=False)
    rc = run_main(train_cli.PROG, train_cli.main, ["fit", str(synthetic_data), "--out", str(tmp_path / "r"), "--ddp"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1
    assert "--ddp" in err and "torchrun --nproc-per-node" in err
    assert not (tmp_path / "r").exists()
    rc = run_main(train_cli.PROG, train_cli.main, ["fit", str(synthetic_data), "--out", str(tmp_path / "r"),
                                                   "--nproc-per-node", "2"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "--nproc-per-node: only with --ddp" in err


class _OneProcessDist:
    """Stands in for rank ``rank`` of ``world`` without a process group: sums over ranks
    are the caller's business (the test adds the ranks' gradients itself)."""

    def __init__(self, rank: int, world: int):
        self.rank, self.world = rank, world

    def all_sum(self, values: list[float]) -> list[float]:
        return list(values)


def test_rank_losses_average_to_the_global_batch_gradient():
    """The per-rank scaled losses of two shards, back-propagated and averaged as DDP
    averages them, give the one-process gradient of the same batch; a rank with no row of
    the batch back-propagates zeros into every parameter (so DDP's all-reduce still fires)."""
    from ppmrecon.model.guard import GuardConfig
    from ppmrecon.model.kpn import build
    from ppmrecon.train.loop import TrainConfig, _step_loss

    samples = _samples(4)
    cfg = TrainConfig(batch=5, patch=16)
    torch.manual_seed(0)
    model = build("tiny", FeatureConfig(), GuardConfig())
    catalog = [tuple(s.y.shape[-2:]) for s in samples]

    def grads(loss: torch.Tensor) -> list[torch.Tensor]:
        model.zero_grad(set_to_none=True)
        loss.backward()
        return [p.grad.clone() for p in model.parameters()]

    one = PatchSampler(samples, patch=16, seed=3)
    want = grads(_step_loss(model, one, cfg, GuardConfig(), torch.device("cpu"), None)[0])
    per_rank = []
    for r in range(2):
        shard = PatchSampler([s for s in samples if s.index % 2 == r], patch=16, seed=3, catalog=catalog,
                             positions=[s.index for s in samples if s.index % 2 == r])
        per_rank.append(grads(_step_loss(model, shard, cfg, GuardConfig(), torch.device("cpu"),
                                         _OneProcessDist(r, 2))[0]))
    for w, a, b in zip(want, *per_rank):
        torch.testing.assert_close((a + b) / 2, w, rtol=1e-5, atol=1e-8)

    lonely = PatchSampler([samples[0]], patch=16, seed=3, catalog=catalog, positions=[0])
    lonely.plan = lambda size: [(1, 0, 0, 0, False, 16)] * size  # every row belongs to the other rank
    loss, total = _step_loss(model, lonely, cfg, GuardConfig(), torch.device("cpu"), _OneProcessDist(0, 2))
    assert loss.item() == 0.0 and total == 0.0
    assert all(g is not None and not g.any() for g in grads(loss))
