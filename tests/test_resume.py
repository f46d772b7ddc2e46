"""Continuing renders (issue 14): ``--resume``, checkpoints, Ctrl-C, kill -9, snapshots
and the one-line refusals of a state that does not fit. All renders 16x16, 2^12 photons."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ppmrecon import buffers as B
from ppmrecon.cli_common import run_main
from ppmrecon.render import cli
from ppmrecon.render.state import read_state, state_path, write_state

ROOT = Path(__file__).resolve().parents[1]
BASE = ["cornell_caustics", "--resolution", "16x16", "--photons", "4096", "--seed", "3", "-q"]
#: Header keys that hold wall-clock times: the only ones a continued render may change.
TIMING = ("ppmrecon.render_seconds", "ppmrecon.seconds.")


def render(argv: list[str]) -> int:
    return run_main(cli.PROG, cli.main, argv)


def assert_same_render(a: Path, b: Path) -> None:
    """Same pixels in every channel, same header up to timings."""
    fa, fb = B.read_buffers(a), B.read_buffers(b)
    for (name, x), y in zip(fa.channels().items(), fb.channels().values()):
        assert np.array_equal(x, y), name
    ha = {k: v for k, v in fa.header.items() if not k.startswith(TIMING)}
    hb = {k: v for k, v in fb.header.items() if not k.startswith(TIMING)}
    assert ha == hb


@pytest.mark.parametrize("method", ["sppm", "cppm", "fppm", "appm"])
def test_resumed_render_equals_uninterrupted(tmp_path, method):
    """3 passes, then --resume --passes 3, equals a 6-pass render with the same seed;
    the snapshot at 2 equals a 2-pass render."""
    a, full, two = tmp_path / "a.exr", tmp_path / "full.exr", tmp_path / "two.exr"
    assert render(BASE + ["--method", method, "--passes", "3", "--snapshots", "2", "-o", str(a)]) == 0
    assert state_path(a).is_file() and (tmp_path / "a_p0002.exr").is_file()
    assert render(["--resume", str(a), "--passes", "3", "-q"]) == 0
    assert render(BASE + ["--method", method, "--passes", "6", "-o", str(full)]) == 0
    assert render(BASE + ["--method", method, "--passes", "2", "-o", str(two)]) == 0
    assert B.read_buffers(a).header[B.H_PASSES] == 6
    assert_same_render(a, full)
    assert_same_render(tmp_path / "a_p0002.exr", two)
    if method != "sppm":  # the controllers' statistics really moved some radii apart
        radii = B.read_buffers(a).radii
        assert np.unique(np.round(radii[4] / radii[0], 4)).size > 1


def test_snapshots_equal_separate_renders(tmp_path):
    """--snapshots 1..4 writes 1, 2, 4 during one render, each the same file as a
    separate render of that many passes; the last is the output itself."""
    out = tmp_path / "s.exr"
    assert render(BASE + ["--method", "fppm", "--snapshots", "1..4", "-o", str(out)]) == 0
    assert B.read_buffers(out).header[B.H_PASSES] == 4  # no --passes: up to the last snapshot
    for n in (1, 2, 4):
        single = tmp_path / f"sep{n}.exr"
        assert render(BASE + ["--method", "fppm", "--passes", str(n), "-o", str(single)]) == 0
        assert_same_render(cli.snapshot_path(out, n), single)
    assert not cli.snapshot_path(out, 3).exists()


def test_no_state(tmp_path, capsys):
    """--no-state writes the image alone (and removes a stale state of an earlier render)."""
    a = tmp_path / "a.exr"
    assert render(BASE + ["--passes", "1", "-o", str(a)]) == 0 and state_path(a).is_file()
    assert render(BASE + ["--passes", "1", "--no-state", "-o", str(a)]) == 0
    assert a.is_file() and not state_path(a).exists()
    capsys.readouterr()
    assert render(BASE + ["--passes", "1", "--no-state", "--checkpoint-every", "1", "-o", str(a)]) == 2
    assert "--no-state" in capsys.readouterr().err


def test_snapshot_lists():
    assert cli.snapshot_list("16,64,256") == (16, 64, 256)
    assert cli.snapshot_list("16..256") == (16, 32, 64, 128, 256)
    assert cli.snapshot_list("3, 8..20,8") == (3, 8, 16)
    for bad in ("0", "8..4", "x", "4,,8"):
        with pytest.raises(Exception):
            cli.snapshot_list(bad)
    assert cli.snapshot_path(Path("d/out.exr"), 16) == Path("d/out_p0016.exr")


def test_ctrl_c_finishes_the_pass_then_resumes(tmp_path, monkeypatch, request):
    """SIGINT during pass 2's gather: the pass completes, the file and state hold 2
    passes (exit 130, header 'interrupted'), and resuming to 4 equals a 4-pass render."""
    from ppmrecon.render import integrator

    # A run under nohup (or CI) inherits SIGINT ignored, and the renderer rightly leaves an
    # ignored SIGINT alone: give this test the interactive default.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    request.addfinalizer(lambda: signal.signal(signal.SIGINT, previous))
    calls = {"n": 0}
    real_gather = integrator.gather

    def gather_with_ctrl_c(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:  # pass 2, hit point A (two gathers per pass)
            signal.raise_signal(signal.SIGINT)
        return real_gather(*args, **kwargs)

    a, full = tmp_path / "a.exr", tmp_path / "full.exr"
    monkeypatch.setattr(integrator, "gather", gather_with_ctrl_c)
    assert render(BASE + ["--method", "cppm", "--passes", "10", "-o", str(a)]) == 130
    monkeypatch.setattr(integrator, "gather", real_gather)
    header = B.read_buffers(a).header
    assert header[B.H_PASSES] == 2 and header[B.H_STOPPED] == "interrupted"
    assert render(["--resume", str(a), "--passes", "2", "-q"]) == 0
    assert render(BASE + ["--method", "cppm", "--passes", "4", "-o", str(full)]) == 0
    assert_same_render(a, full)


def test_time_budget_then_resume(tmp_path):
    """The end of --time leaves a file and state that continue like any other."""
    a, full = tmp_path / "a.exr", tmp_path / "full.exr"
    assert render(BASE + ["--method", "sppm", "--time", "0.5", "-o", str(a)]) == 0
    done = B.read_buffers(a).header[B.H_PASSES]
    assert B.read_buffers(a).header[B.H_STOPPED] == "time budget"
    assert render(["--resume", str(a), "--passes", "1", "-q"]) == 0
    assert render(BASE + ["--method", "sppm", "--passes", str(done + 1), "-o", str(full)]) == 0
    assert_same_render(a, full)


def test_kill_during_a_pass_leaves_a_resumable_pair(tmp_path):
    """kill -9 of a render with --checkpoint-every 2 while it renders: the file and state
    on disk (the last checkpoint) continue to the same image as an uninterrupted render."""
    a, full = tmp_path / "a.exr", tmp_path / "full.exr"
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    # 2^16 photons: a pass takes long enough that the kill lands inside one.
    argv = [sys.executable, "-m", "ppmrecon.render.cli", *BASE[:3], "--photons", "65536", "--seed", "3", "-q",
            "--method", "fppm", "--passes", "1000", "--checkpoint-every", "2", "-o", str(a)]
    proc = subprocess.Popen(argv, cwd=tmp_path, env=env, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and proc.poll() is None:
            if state_path(a).is_file() and read_state(state_path(a)).passes >= 4:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.stderr.read().decode()
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    done = read_state(state_path(a)).passes
    assert done >= 4 and done % 2 == 0 and B.read_buffers(a).header[B.H_PASSES] in (done, done - 2)
    assert render(["--resume", str(a), "--passes", "1", "-q"]) == 0
    assert render(BASE[:3] + ["--photons", "65536", "--seed", "3", "-q", "--method", "fppm",
                              "--passes", str(done + 1), "-o", str(full)]) == 0
    assert_same_render(a, full)


# ------------------------------------------------------------------------ refusals

SCENE = ('<scene version="3.0.0"><sensor type="perspective"><transform name="to_world">'
         '<lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform><film type="hdrfilm">'
         '<integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>'
         '<shape type="rectangle"><bsdf type="diffuse"/></shape>'
         '<emitter type="point"><point name="position" x="0" y="0" z="{z}"/></emitter></scene>')


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}


def _refused(capsys, argv: list[str], *words: str) -> None:
    """The command exits 2 with one stderr line that contains ``words``."""
    capsys.readouterr()
    assert render(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for w in words:
        assert w in err, err


@pytest.fixture
def rendered(tmp_path):
    """A 2-pass render of a small scene file: (scene path, output path)."""
    scene = tmp_path / "s.xml"
    scene.write_text(SCENE.format(z=1))
    out = tmp_path / "a.exr"
    assert render([str(scene), "--passes", "2", "--photons", "256", "-q", "-o", str(out)]) == 0
    return scene, out


def test_state_of_a_changed_scene_is_refused(tmp_path, capsys, rendered):
    scene, out = rendered
    scene.write_text(SCENE.format(z=2))  # the light moved
    before = _snapshot(tmp_path)
    _refused(capsys, ["--resume", str(out), "--passes", "1"], "a.exr.state.npz", "another scene")
    assert _snapshot(tmp_path) == before


def test_state_of_another_output_or_version_is_refused(tmp_path, capsys, rendered):
    scene, out = rendered
    other = tmp_path / "b.exr"
    assert render([str(scene), "--passes", "3", "--photons", "256", "-q", "-o", str(other)]) == 0
    # b's state beside a's file: the content hash says they do not belong together
    a_state = state_path(out).read_bytes()
    state_path(out).write_bytes(state_path(other).read_bytes())
    before = _snapshot(tmp_path)
    _refused(capsys, ["--resume", str(out), "--passes", "1"], "does not belong to", "a.exr")
    assert _snapshot(tmp_path) == before
    # a state written by another ppmrecon version
    state_path(out).write_bytes(a_state)
    saved = read_state(state_path(out))
    write_state(state_path(out), dict(saved.meta, ppmrecon_version="0.0.1"), saved.arrays)
    before = _snapshot(tmp_path)
    _refused(capsys, ["--resume", str(out), "--passes", "1"], "written by ppmrecon 0.0.1")
    assert _snapshot(tmp_path) == before


def test_truncated_or_missing_state_is_refused(tmp_path, capsys, rendered):
    scene, out = rendered
    data = state_path(out).read_bytes()
    state_path(out).write_bytes(data[: len(data) // 2])
    before = _snapshot(tmp_path)
    _refused(capsys, ["--resume", str(out), "--passes", "1"], "truncated or corrupt")
    assert _snapshot(tmp_path) == before
    state_path(out).unlink()
    _refused(capsys, ["--resume", str(out), "--passes", "1"], "no render state")
    _refused(capsys, ["--resume", str(tmp_path / "none.exr"), "--passes", "1"], "no such file")


def test_resume_keeps_its_settings(tmp_path, capsys, rendered):
    """Options that define the render are refused with --resume (the state has them);
    a state whose arrays do not fit the film is refused too."""
    scene, out = rendered
    before = _snapshot(tmp_path)
    _refused(capsys, ["--resume", str(out), "--photons", "512", "--seed", "0"], "--photons, --seed",
             "cannot be given with --resume")
    saved = read_state(state_path(out))
    arrays = dict(saved.arrays)
    arrays["mean.0"] = arrays["mean.0"][:, :10]
    write_state(state_path(out), saved.meta, arrays)
    _refused(capsys, ["--resume", str(out), "--passes", "1"], "does not fit", "mean.0")
    assert {k: v for k, v in _snapshot(tmp_path).items() if not k.endswith(".npz")} == \
        {k: v for k, v in before.items() if not k.endswith(".npz")}


def test_single_baseline_resumes_too(tmp_path):
    """The --single baseline (a plain R,G,B file) continues like the buffer renders."""
    a, full = tmp_path / "a.exr", tmp_path / "full.exr"
    assert render(BASE + ["--single", "--passes", "2", "-o", str(a)]) == 0
    assert render(["--resume", str(a), "--passes", "1", "-q"]) == 0
    assert render(BASE + ["--single", "--passes", "3", "-o", str(full)]) == 0
    (ra, ha), (rf, hf) = B.read_rgb(a), B.read_rgb(full)
    assert np.array_equal(ra, rf) and ha[B.H_PASSES] == hf[B.H_PASSES] == 3
