"""Per-pass cost of two renderer versions, measured alternately (issue 20: what the
estimator fixes cost). Steady-state pass time = (T(N2) - T(N1)) / (N2 - N1) from the
headers' render seconds, which leaves the first pass's compilation and k-NN radii out;
versions alternate ``--repeats`` times so that a load on the machine hits both alike.

    python benchmarks/bench_pass_cost.py --scenes ../shared/scenes --before f4e8b06
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_estimators import DEFAULT_BEFORE, render, worktree  # noqa: E402

from ppmrecon.fileio import write_json  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", type=Path, default=None, help="folder of the literature scenes (adds box)")
    p.add_argument("--before", default=DEFAULT_BEFORE)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--photons", type=int, default=1 << 17)
    p.add_argument("--passes", type=int, nargs=2, default=(3, 11), metavar=("N1", "N2"))
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench_pass_cost")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "pass_cost.json")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    before = worktree(args.before, ROOT / "out" / "bench_estimators" / "before_src")
    scenes = ["cornell_caustics", "water_caustic"]
    if args.scenes is not None:
        scenes.append(str(args.scenes / "box" / "box.xml"))
    versions = [("before", before, []), ("after", ROOT, ["--direct", "none"]),
                ("after+direct=all", ROOT, ["--direct", "all"])]
    results: dict = {}
    n1, n2 = args.passes
    for scene in scenes:
        name = Path(scene).stem
        times: dict[str, list[float]] = {v: [] for v, _, _ in versions}
        for _ in range(args.repeats):
            for version, code, extra in versions:
                t = []
                for n in (n1, n2):
                    r = render(code, scene, args.work / f"{name}.exr",
                               ["--passes", str(n), "--photons", str(args.photons), "--resolution", str(args.width),
                                *extra])
                    t.append(float(r["header"]["ppmrecon.render_seconds"]))
                times[version].append((t[1] - t[0]) / (n2 - n1))
        results[name] = {v: {"median_pass_seconds": statistics.median(ts), "runs": ts} for v, ts in times.items()}
        print(name, {v: round(r["median_pass_seconds"], 4) for v, r in results[name].items()}, flush=True)
    write_json(args.out, {"width": args.width, "photons": args.photons, "passes": [n1, n2], "before": args.before,
                          "results": results})


if __name__ == "__main__":
    main()
