"""benchmarks/guide_by_passes.py: per-N figures of a bench_guide report, and a pass-count rule."""
import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "guide_by_passes.py"


def _variant(ratio: float, ratio_8x8: float) -> dict:
    return {"relmse": ratio, "relmse_8x8": ratio_8x8, "ratio": ratio, "ratio_8x8": ratio_8x8,
            "relmse_scaled": ratio, "ratio_scaled": ratio, "seconds": 0.0, "deciding_pixels": 0}


def _row(passes: int, a: tuple, b: tuple) -> dict:
    return {"image": f"0000_x input_n{passes:04d}_s0.exr", "scene": "0000_x", "family": "x", "passes": passes,
            "best_single": 1.0, "best_single_8x8": 1.0, "best_single_scaled": 1.0, "best_single_name": "z4",
            "variants": {"a": _variant(*a), "b": _variant(*b)}}


def _run(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    report = tmp_path / "guide.json"
    report.write_text(json.dumps({"scenes": [], "validation": [_row(16, (0.5, 1.0), (0.8, 2.0)),
                                                                _row(256, (0.9, 1.5), (0.6, 0.5))]}))
    return subprocess.run([sys.executable, str(SCRIPT), str(report), *args], capture_output=True, text=True)


def test_rule_takes_each_variant_on_its_side_of_n0(tmp_path):
    out = _run(tmp_path, "--by-passes", "a,b,64")
    assert out.returncode == 0, out.stderr
    rule = [line for line in out.stdout.splitlines() if line.startswith("| a below N = 64, b from it |")]
    assert len(rule) == 1
    cells = [c.strip() for c in rule[0].split("|")[1:-1]]
    # geomeans of (0.5, 0.6) and (1.0, 0.5): a's image at N = 16, b's at N = 256
    assert cells[2] == f"{(0.5 * 0.6) ** 0.5:.3f}" and cells[7] == f"{(1.0 * 0.5) ** 0.5:.3f}"
    per_n = [line for line in out.stdout.splitlines() if line.startswith("| 256 |")]
    assert per_n[0].endswith("| 0.600 / 0.500, 0 worse |")


def test_unknown_variant_is_one_line_and_nonzero(tmp_path):
    out = _run(tmp_path, "--by-passes", "a,nope,64")
    assert out.returncode != 0 and "no variant 'nope'" in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_images_of_keeps_only_what_the_other_report_scored(tmp_path):
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"scenes": [], "validation": [_row(256, (0.1, 0.1), (0.1, 0.1))]}))
    out = _run(tmp_path, "--images-of", str(other))
    assert out.returncode == 0, out.stderr
    assert "(1 images)" in out.stdout and "| 16 |" not in out.stdout
    assert "| 256 | 1 | 0.900 / 1.500, 0 worse | 0.600 / 0.500, 0 worse |" in out.stdout
    missing = _run(tmp_path, "--images-of", str(tmp_path / "nope.json"))
    assert missing.returncode != 0 and "nope.json" in missing.stderr and len(missing.stderr.strip().splitlines()) == 1
