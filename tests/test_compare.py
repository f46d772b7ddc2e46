"""``ppmrecon-compare`` (issue 14): numbers against a hand-computed case, area-averaged
references, the fitted slope, the plots, and one-line refusals."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ppmrecon import buffers as B
from ppmrecon.cli_common import run_main
from ppmrecon.compare import PROG, main
from tests.conftest import make_buffer


def compare(argv: list[str]) -> int:
    return run_main(PROG, main, argv)


def write(path: Path, img: np.ndarray, passes: int | None = None, **header) -> Path:
    if passes is not None:
        header[B.H_PASSES] = passes
    B.write_rgb(path, img.astype(np.float32), header={f"ppmrecon.{k}" if not k.startswith("ppmrecon.") else k: v
                                                      for k, v in header.items()})
    return path


@pytest.fixture
def hand_case(tmp_path):
    """Reference 1 everywhere (40x40); the estimate is 1 but 3 at (0, 0) and 2 at (5, 5)."""
    est = np.ones((40, 40, 3))
    est[0, 0], est[5, 5] = 3.0, 2.0
    return write(tmp_path / "ref.exr", np.ones((40, 40, 3))), write(tmp_path / "est.exr", est, passes=16)


def test_numbers_match_the_hand_computation(tmp_path, hand_case, capsys):
    """relMSE = (2^2 + 1^2) / 1.01 / 1600; 8x8 blocks: the one block holding both pixels
    has mean 1 + 3/64 (of 25 blocks); the trimmed figure drops round(1.6) = 2 pixels,
    exactly the two wrong ones; luminance ratio 1 + 3/1600. A reference at twice the
    resolution (area-averaged 2x2) gives the same numbers."""
    ref, est = hand_case
    expected = {"relmse": 5 / 1.01 / 1600, "relmse_8x8": (3 / 64) ** 2 / 1.01 / 25, "relmse_trimmed": 0.0,
                "luminance_ratio": 1 + 3 / 1600}
    big = write(tmp_path / "ref2.exr", np.ones((80, 80, 3)))
    for reference in (ref, big):
        out = tmp_path / f"{reference.stem}.json"
        assert compare([str(reference), str(est), "--json", str(out)]) == 0
        table = capsys.readouterr().out
        assert "est.exr" in table and f"{5 / 1.01 / 1600:.4e}" in table
        row, = json.loads(out.read_text())["scores"]
        assert row["passes"] == 16 and row["layer"] == "rgb"
        for key, value in expected.items():
            assert row[key] == pytest.approx(value, rel=1e-12, abs=1e-15), key
    assert compare([str(ref), str(est), "--json"]) == 0       # JSON on stdout instead of the table
    assert json.loads(capsys.readouterr().out)["scores"][0]["relmse"] == pytest.approx(expected["relmse"])


def test_buffer_files_score_each_estimate(tmp_path, capsys):
    buf = make_buffer(16, 24, seed=2)
    path = tmp_path / "buf.exr"
    B.write_buffers(path, buf)
    ref = write(tmp_path / "ref.exr", buf.estimates[2] * 1.5 + 0.1)
    assert compare([str(ref), str(path), "--layers", "y,z2", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["scores"]
    assert [r["layer"] for r in rows] == ["y", "z2"] and rows[0]["method"] == "sppm"
    r = buf.estimates[2].astype(np.float64) * 1.5 + 0.1
    e = buf.estimates[2].astype(np.float64)
    by_hand = (((e - r) ** 2).mean(-1) / (r.mean(-1) ** 2 + 0.01)).mean()
    assert rows[1]["relmse"] == pytest.approx(by_hand, rel=1e-6)
    assert rows[1]["luminance_ratio"] == pytest.approx(
        (e @ [0.212671, 0.715160, 0.072169]).mean() / (r @ [0.212671, 0.715160, 0.072169]).mean(), rel=1e-6)


def test_slope_and_plots(tmp_path, capsys):
    """Error exactly proportional to 1/passes: the fitted slope is -1; --plot writes the
    log-log PNG and the crop sheet."""
    rng = np.random.default_rng(0)
    ref = rng.random((32, 48, 3)) + 0.5
    write(tmp_path / "ref.exr", ref)
    for n in (4, 16, 64):
        write(tmp_path / f"run_p{n:04d}.exr", ref * (1 + 0.3 / np.sqrt(n)), passes=n, method="fppm")
    plot = tmp_path / "err.png"
    err16 = (((0.3 / 4) * ref) ** 2).mean(-1) / (ref.mean(-1) ** 2 + 0.01)
    target = 0.5 * float(err16.mean())  # half the 16-pass error: 32 passes on the fitted line
    assert compare([str(tmp_path / "ref.exr"), str(tmp_path / "run_p*.exr"), "--plot", str(plot),
                    "--json", str(tmp_path / "err.json"), "--target", repr(target)]) == 0
    fit, = json.loads((tmp_path / "err.json").read_text())["fits"]
    assert fit["series"] == "fppm rgb" and fit["points"] == 3
    assert fit["slope"] == pytest.approx(-1.0, abs=1e-4)
    assert fit["passes_for_target"] == pytest.approx(32.0, rel=1e-3) and fit["reached_at"] == 64
    out = capsys.readouterr().out
    assert "slope of log relMSE vs log passes, fppm rgb: -1.000" in out
    assert "measured: 64 passes; fit: ~32 passes" in out
    for png in (plot, tmp_path / "err_crops.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("ref_shape, words", [
    ((30, 40, 3), "aspect ratios differ"),
    ((60, 60, 3), "not an integer multiple"),
    ((20, 20, 3), "not an integer multiple"),
])
def test_reference_of_another_size_is_refused(tmp_path, hand_case, capsys, ref_shape, words):
    _, est = hand_case
    ref = write(tmp_path / "odd.exr", np.ones(ref_shape))
    keep = tmp_path / "old.json"
    keep.write_text("earlier results")
    capsys.readouterr()
    assert compare([str(ref), str(est), "--json", str(keep), "--plot", str(tmp_path / "p.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err and "odd.exr" in err, err
    assert keep.read_text() == "earlier results" and not (tmp_path / "p.png").exists()


def test_other_refusals(tmp_path, hand_case, capsys):
    ref, est = hand_case
    B.write_exr(tmp_path / "depth.exr", {"Z": np.ones((40, 40), np.float32)})
    cases = [
        ([str(ref), str(tmp_path / "depth.exr")], "neither an R,G,B image nor a buffer file"),
        ([str(ref), str(tmp_path / "none_*.exr")], "no EXR file matches"),
        ([str(ref), str(write(tmp_path / "nopasses.exr", np.ones((40, 40, 3)))), "--plot",
          str(tmp_path / "p.png")], "no file records its pass count"),
        ([str(ref), str(est), "--plot", str(tmp_path / "p.png"), "--crop", "30,30,20,20"], "outside"),
        ([str(tmp_path / "missing.exr"), str(est)], "no such file"),
    ]
    for argv, words in cases:
        capsys.readouterr()
        assert compare(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err, err
    assert not (tmp_path / "p.png").exists()
