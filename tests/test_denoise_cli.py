"""``ppmrecon-denoise``: round trips, one-line errors and exit codes (SPEC section 9)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ppmrecon import buffers as B
from ppmrecon.model import checkpoint as C
from ppmrecon.model.cli import main
from ppmrecon.model.kpn import build
from tests.conftest import make_buffer


@pytest.fixture(autouse=True)
def no_shipped_model(monkeypatch, tmp_path):
    """Tests decide whether a default model exists, whatever the package ships."""
    monkeypatch.setattr(C, "DEFAULT_MODEL", tmp_path / "no-default" / "default.pt")
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.fixture
def model(tmp_path) -> Path:
    path = tmp_path / "tiny.pt"
    C.init_checkpoint(path, "tiny", seed=1)
    return path


@pytest.fixture
def buffer_path(tmp_path) -> Path:
    path = tmp_path / "scene.exr"
    buf = make_buffer(21, 34, seed=11)
    buf.estimates[:, 5, 5] = 1e8                    # a firefly
    B.write_buffers(path, buf)
    return path


def one_line_error(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("ppmrecon-denoise: error: "), err
    return lines[0]


def test_round_trip_writes_finite_rgb_next_to_input(buffer_path, model, capsys):
    assert main([str(buffer_path), "--model", str(model), "--quiet", "--threads", "1"]) == 0
    out = buffer_path.with_name("scene_denoised.exr")
    rgb, header = B.read_rgb(out)
    assert rgb.shape == (21, 34, 3) and np.isfinite(rgb).all()
    assert header["ppmrecon.denoiser"] == "tiny" and header[B.H_METHOD] == "sppm"
    channels, _ = B.read_channels(out)
    assert set(channels) == {"R", "G", "B"}
    assert capsys.readouterr().out == ""             # --quiet


def test_weights_layers_and_explicit_output(buffer_path, model, tmp_path, capsys):
    out = tmp_path / "sub" / "x.exr"
    out.parent.mkdir()
    assert main([str(buffer_path), "--model", str(model), "-o", str(out), "--weights-layers", "--threads", "1"]) == 0
    assert str(out) in capsys.readouterr().out
    channels, _ = B.read_channels(out)
    weights = np.stack([channels[f"weight.z{j}"] for j in range(1, 5)])
    assert (weights >= 0).all()
    np.testing.assert_allclose(weights.sum(0), 1.0, rtol=1e-5)


def test_output_matches_the_python_api_and_tiles_do_not_show(buffer_path, model, tmp_path):
    from ppmrecon.model.infer import denoise

    a, b = tmp_path / "a.exr", tmp_path / "b.exr"
    assert main([str(buffer_path), "--model", str(model), "-o", str(a), "-q", "--precision", "float32",
                 "--threads", "1"]) == 0
    assert main([str(buffer_path), "--model", str(model), "-o", str(b), "-q", "--precision", "float32",
                 "--tile", "7", "--threads", "1"]) == 0
    rgb_a, _ = B.read_rgb(a)
    rgb_b, _ = B.read_rgb(b)
    api = denoise(B.read_buffers(buffer_path), C.load_checkpoint(model).model, precision="float32").rgb
    scale = np.abs(rgb_a).max()
    np.testing.assert_allclose(rgb_b, rgb_a, rtol=1e-5, atol=1e-5 * scale)
    np.testing.assert_allclose(api, rgb_a, rtol=1e-6, atol=1e-6 * scale)


def test_missing_model_says_how_to_get_one(buffer_path, capsys):
    assert main([str(buffer_path)]) == 2
    line = one_line_error(capsys)
    assert "--model" in line and "ppmrecon-train" in line and "--init-checkpoint" in line


def test_shipped_default_model_is_picked_up(buffer_path, monkeypatch, tmp_path):
    default = tmp_path / "data" / "default.pt"
    default.parent.mkdir()
    C.init_checkpoint(default, "tiny")
    monkeypatch.setattr(C, "DEFAULT_MODEL", default)
    assert main([str(buffer_path), "-q", "--threads", "1"]) == 0
    assert buffer_path.with_name("scene_denoised.exr").exists()


def test_rgb_only_exr_names_missing_layers_and_the_render_command(tmp_path, model, capsys):
    path = tmp_path / "plain.exr"
    B.write_rgb(path, np.ones((4, 5, 3), np.float32))
    assert main([str(path), "--model", str(model)]) == 2
    line = one_line_error(capsys)
    assert str(path) in line and "missing layer" in line and "ppmrecon-render" in line
    assert not path.with_name("plain_denoised.exr").exists()


def test_corrupt_checkpoint(buffer_path, tmp_path, capsys):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"PK\x03\x04" + os.urandom(500))
    assert main([str(buffer_path), "--model", str(bad)]) == 2
    line = one_line_error(capsys)
    assert str(bad) in line and "corrupt" in line


def test_nonexistent_input(tmp_path, model, capsys):
    missing = tmp_path / "nope.exr"
    assert main([str(missing), "--model", str(model)]) == 2
    line = one_line_error(capsys)
    assert str(missing) in line and "no such file" in line


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_cuda(buffer_path, model, capsys):
    assert main([str(buffer_path), "--model", str(model), "--device", "cuda"]) == 2
    assert "CUDA" in one_line_error(capsys)


@pytest.mark.parametrize("argv,needle", [
    ([], "required: INPUT.exr"),
    (["--tile", "0", "x.exr"], "--tile"),
    (["x.exr", "--device", "tpu"], "--device"),
    (["x.exr", "--init-checkpoint", "m.pt"], "takes no INPUT"),
])
def test_usage_errors(argv, needle, capsys):
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err


def test_refuses_to_overwrite_input_or_write_non_exr(buffer_path, model, capsys):
    assert main([str(buffer_path), "--model", str(model), "-o", str(buffer_path)]) == 2
    assert "overwrite the input" in one_line_error(capsys)
    assert main([str(buffer_path), "--model", str(model), "-o", str(buffer_path.with_suffix(".png"))]) == 2
    assert ".exr" in one_line_error(capsys)


def test_non_finite_network_output_fails_without_writing(buffer_path, tmp_path, capsys):
    broken = build("tiny")
    with torch.no_grad():
        for p in broken.parameters():
            p.fill_(1e30)
    path = tmp_path / "broken.pt"
    C.save_checkpoint(path, broken)
    assert main([str(buffer_path), "--model", str(path), "--threads", "1"]) == 1
    assert "NaN/Inf" in one_line_error(capsys)
    assert not buffer_path.with_name("scene_denoised.exr").exists()


def test_init_checkpoint_presets_and_features(tmp_path, capsys):
    path = tmp_path / "small.pt"
    assert main(["--init-checkpoint", str(path), "--preset", "small", "--radius-features", "--pass-feature"]) == 0
    assert "small" in capsys.readouterr().out
    model, meta = C.load_checkpoint(path)
    assert model.preset.name == "small" and model.features.n_channels == 33 and meta["trained"] is False
    assert main(["--init-checkpoint", str(tmp_path / "x.pt"), "--preset", "huge"]) == 2
    assert "unknown model preset 'huge'" in one_line_error(capsys)
    guarded = tmp_path / "guarded.pt"
    assert main(["--init-checkpoint", str(guarded), "--scale-free-features", "--outlier-features",
                 "--guard", "on", "--quiet"]) == 0
    model, _ = C.load_checkpoint(guarded)
    assert model.guard.enabled and model.features.scale_free and model.features.n_channels == 30


def test_guard_flag_overrides_the_checkpoint(model, tmp_path):
    """--guard model/off/on on a one-pass 1e8 firefly in all five inputs at (5, 5)."""
    buffer_path = tmp_path / "firefly.exr"
    buf = make_buffer(21, 34, seed=11)
    buf.estimates[:, 5, 5] = 1e8
    buf.variances[:, 5, 5] = 1e16                  # one pass made it: sqrt(V) ~ X
    B.write_buffers(buffer_path, buf)
    guarded = tmp_path / "guarded.pt"
    assert main(["--init-checkpoint", str(guarded), "--guard", "on", "--quiet"]) == 0
    peak = {}
    for ckpt, choice in ((guarded, "model"), (guarded, "off"), (model, "model"), (model, "on"), (model, None)):
        out = tmp_path / f"{ckpt.stem}_{choice}.exr"
        flag = [] if choice is None else ["--guard", choice]
        assert main([str(buffer_path), "--model", str(ckpt), "-o", str(out), *flag,
                     "--quiet", "--threads", "1"]) == 0
        rgb, header = B.read_rgb(out)
        peak[ckpt.stem, choice] = float(rgb[5, 5].max())
        on = choice in ("on", None) or (choice == "model" and ckpt == guarded)
        assert header["ppmrecon.guard"] == ("on" if on else "off")
    assert peak["guarded", "off"] > 1e7 and peak["tiny", "model"] > 1e7       # straight through
    assert peak["guarded", "model"] < 10 and peak["tiny", "on"] < 10
    assert peak["tiny", None] == peak["tiny", "on"]                            # on by default

def test_console_script_is_installed(tmp_path):
    exe = shutil.which("ppmrecon-denoise", path=str(Path(sys.executable).parent))
    assert exe, "pip install -e . registers ppmrecon-denoise"
    help_run = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=120)
    assert help_run.returncode == 0 and "--weights-layers" in help_run.stdout
    bad = subprocess.run([exe, str(tmp_path / "nope.exr"), "--model", "m.pt"], capture_output=True, text=True,
                         timeout=120)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr


def test_progress_bar_for_tiled_runs_and_summary(buffer_path, model, capsys):
    assert main([str(buffer_path), "--model", str(model), "--tile", "8", "--threads", "1"]) == 0
    captured = capsys.readouterr()
    assert "denoise [" in captured.err and "15/15" in captured.err     # 3 x 5 tiles of 8 px
    assert "scene_denoised.exr: 34x21 denoised with 'tiny'" in captured.out


def test_several_inputs_and_patterns_load_the_model_once(model, tmp_path, monkeypatch, capsys):
    """Files and a quoted glob in one call: each output equals a one-file run, the model
    is loaded once, earlier *_denoised.exr outputs are not picked up by the pattern."""
    paths = []
    for k in range(3):
        path = tmp_path / f"snap_p{k:04d}.exr"
        B.write_buffers(path, make_buffer(9, 12, seed=k))
        paths.append(path)
    single = tmp_path / "single.exr"
    assert main([str(paths[1]), "--model", str(model), "-o", str(single), "--quiet", "--threads", "1"]) == 0
    loads = []
    real_load = C.load_checkpoint
    monkeypatch.setattr(C, "load_checkpoint", lambda *a, **k: loads.append(a) or real_load(*a, **k))
    pattern = str(tmp_path / "snap_p*.exr")
    assert main([str(paths[0]), pattern, "--model", str(model), "--threads", "1"]) == 0
    assert len(loads) == 1
    out = capsys.readouterr().out
    assert out.count("denoised with 'tiny'") == 3                  # paths[0] once, not twice
    for p in paths:
        assert p.with_name(p.stem + "_denoised.exr").is_file()
    a, _ = B.read_rgb(paths[1].with_name("snap_p0001_denoised.exr"))
    b, _ = B.read_rgb(single)
    np.testing.assert_array_equal(a, b)
    assert main([pattern, "--model", str(model), "--quiet", "--threads", "1"]) == 0   # outputs left out
    assert not list(tmp_path.glob("*_denoised_denoised.exr"))


def test_several_inputs_refusals_keep_earlier_outputs(model, tmp_path, capsys):
    good = tmp_path / "good.exr"
    B.write_buffers(good, make_buffer(9, 12, seed=1))
    rgb_only = tmp_path / "plain.exr"
    B.write_rgb(rgb_only, np.ones((9, 12, 3), np.float32))
    assert main([str(good), str(rgb_only), "--model", str(model), "-o", str(tmp_path / "x.exr")]) == 2
    assert "names one file but 2 inputs" in one_line_error(capsys)
    assert main([str(tmp_path / "none_*.exr"), "--model", str(model)]) == 2
    assert "no buffer file matches" in one_line_error(capsys)
    assert main([str(good), str(rgb_only), "--model", str(model), "--quiet", "--threads", "1"]) == 2
    assert "plain.exr" in one_line_error(capsys)
    assert B.read_rgb(tmp_path / "good_denoised.exr")[0].shape == (9, 12, 3)   # the first is kept
