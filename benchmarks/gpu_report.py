"""Summarise what ``benchmarks/gpu_session.sh`` brought back from a GPU machine (issue 12).

    .venv/bin/python benchmarks/gpu_report.py --session benchmarks/results/gpu_s9 \
        --refs benchmarks/results/gpu_s9/refs --data data/v3_cpu [--history runs/gpu_s9/history.json]

- render timings (``render.json``): per-phase seconds of the same render on each backend, and
  how far the cuda_ad_rgb and llvm_ad_rgb files of the same seed are from each other;
- data generation (``manifest_*.json``): seconds per complete scene and the references' agreement;
- backend agreement of the training data: each GPU-rendered reference (the mean of two
  512-pass renders) against the CPU-rendered reference of the same scene in ``--data``. Pass i's
  random numbers depend only on (seed, i), so the two backends draw the same paths and their
  files differ by float rounding alone: the table sets that difference beside the reference's
  own noise (the mean's relMSE, about a quarter of the two halves' agreement);
- training (``--history``): epochs, seconds per 100 steps, the validation ratio curve.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.metrics import relmse  # noqa: E402
from ppmrecon.train.datagen import load_manifest  # noqa: E402


def normalised_relmse(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric relMSE of two images divided by their joint mean (datagen's agreement measure)."""
    m = max(float(np.mean(0.5 * (a + b))), 1e-30)
    return 0.5 * (relmse(a / m, b / m) + relmse(b / m, a / m))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--session", type=Path, required=True, help="folder with render.json and manifest_*.json")
    ap.add_argument("--refs", type=Path, default=None, help="GPU references <scene>_reference.exr")
    ap.add_argument("--data", type=Path, default=None, help="the CPU-rendered data set of the same config")
    ap.add_argument("--history", type=Path, default=None, help="history.json of the GPU training run")
    args = ap.parse_args()

    render = json.loads((args.session / "render.json").read_text())
    print("## Render timings (1280x720, 64 passes)\n")
    # files written before the first pass's k-NN radii were timed apart ("start") hold them in "grid"
    print("| file | variant | photons/pass | render s | eye | photons | start (k-NN radii) | grid | gather |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, r in render.items():
        if isinstance(r, dict):
            start = f"{r['seconds.start']:.2f}" if "seconds.start" in r else "in grid"
            print(f"| {name} | {r['variant']} | {r['photons_per_pass']} | {r['render_seconds']:.2f} | "
                  f"{r['seconds.eye']:.2f} | {r['seconds.photons']:.2f} | {start} | {r['seconds.grid']:.2f} | "
                  f"{r['seconds.gather']:.2f} |")
    same = render.get("cuda_vs_llvm_same_seed_relmse")
    if same:
        print(f"\ncuda vs llvm, same seed, relMSE per estimate (y, z1..z4): {', '.join(f'{v:.1e}' for v in same)}")
    for name, r in render.items():
        if isinstance(r, dict) and "relmse_vs_cuda_reference" in r:
            print(f"{name} vs the cuda single-bandwidth reference: "
                  f"{', '.join(f'{v:.4f}' for v in r['relmse_vs_cuda_reference'])}")

    print("\n## Data generation on the GPU\n")
    for mpath in sorted(args.session.glob("manifest_*.json")):
        man = json.loads(mpath.read_text())
        done = [s for s in man["scenes"] if s.get("reference")]
        secs = [s["seconds"] for s in done]
        agree = [s["agreement"]["relmse_normalised_trimmed"] for s in done]
        print(f"- {mpath.name}: {len(done)} of {len(man['scenes'])} scenes complete, item seconds per scene "
              f"median {np.median(secs):.0f} (sum over its four items); reference agreement (normalised, "
              f"trimmed) median {np.median(agree):.2g}, worst {max(agree):.2g}")

    if args.refs and args.data:
        cpu = {s["id"]: s for s in load_manifest(args.data)["scenes"] if s.get("reference")}
        gpu = {}
        for mpath in sorted(args.session.glob("manifest_*.json")):
            gpu.update({s["id"]: s for s in json.loads(mpath.read_text())["scenes"] if s.get("reference")})
        print("\n## GPU against CPU references of the same scenes\n")
        print("| scene | relMSE (normalised), GPU vs CPU reference | the reference's own noise | ratio |")
        print("|---|---:|---:|---:|")
        for path in sorted(args.refs.glob("*_reference.exr")):
            sid = path.name[: -len("_reference.exr")]
            if sid not in cpu or sid not in gpu:
                continue
            g, _ = B.read_rgb(path)
            c, _ = B.read_rgb(args.data / sid / "reference.exr")
            got = normalised_relmse(g, c)
            noise = 0.25 * cpu[sid]["agreement"]["relmse_normalised"]
            print(f"| {sid} | {got:.2e} | {noise:.2e} | {got / noise:.1e} |")

    if args.history and args.history.exists():
        h = json.loads(args.history.read_text())
        steps = [e["step_seconds"] / max(len(e.get("step_losses", [])), 1) * 100 for e in h]
        print(f"\n## Training on the GPU\n\n{len(h)} epochs in {sum(e['seconds'] for e in h):.0f} s, "
              f"median {np.median(steps):.2f} s per 100 steps; validation ratio to the best input "
              f"(per image, geometric mean) by epoch: "
              + ", ".join(f"{e['epoch']}: {e['val']['image_ratio']:.3f}" for e in h[::10] + [h[-1]]))


if __name__ == "__main__":
    main()
