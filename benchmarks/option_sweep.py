"""Is the reconstruction ever worse than its best input on a render made with options the
data sets never use? (issue 12: "never a worse image, on any render").

Every data set and hold-out is rendered with the defaults (SPPM, the constant kernel,
direct light by MIS everywhere, unbounded depth, 16384 photons per pass). This sweep
renders the project's own built-in scenes with one option changed at a time around those
defaults (the bandwidth controller, the kernel, the direct-light mode, k-NN, alpha, the
photon count, very few passes, a bounded path depth), denoises each render with the
shipped model and scores it, like ``bench_guide.py``, against the best of its own five
estimates on a reference of two independent single-bandwidth SPPM halves of the same
scene and path depth (whatever the options, every chain converges to that image).

    benchmarks/option_sweep.py --out benchmarks/results/option_sweep [--width 64]
        [--passes 4,64] [--ref-passes 1024] [--scenes water_caustic,glossy_spot,...]

Writes ``sweep.json`` and ``sweep.md`` (one row per render: the best input, our relMSE /
8x8 ratio, and how many pixels decide a worse image); renders and references are cached
under ``--out``/cache, so a rerun scores again in seconds.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_guide import FEW_PIXELS, reference_error, score_image  # noqa: E402
from study import references, renderer  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402

SCENES = ("water_caustic", "glossy_spot", "diffuse_glossy", "cornell_caustics")
#: name -> the settings it changes (RenderSettings fields; "method_params" as the CLI's).
OPTIONS: dict[str, dict] = {
    "default": {},
    "cppm": {"method": "cppm"},
    "fppm": {"method": "fppm"},
    "appm": {"method": "appm"},
    "direct=none": {"direct": "none"},
    "direct=glossy": {"direct": "glossy"},
    "epanechnikov": {"kernel": "epanechnikov"},
    "silverman": {"kernel": "silverman"},
    "cone": {"kernel": "cone"},
    "knn=5": {"knn": 5},
    "knn=80": {"knn": 80},
    "alpha=0.5": {"alpha": 0.5},
    "photons=2048": {"photons": 2048},
    "photons=131072": {"photons": 131072},
    "max_depth=3": {"max_depth": 3},
}
PHOTONS, SEED, REF_PHOTONS = 16384, 11, 65536
#: Random streams of the two reference halves (independent of every input's).
REF_SEEDS = (900001, 900002)


def reference(name: str, width: int, max_depth: int | None, passes: int, cache: Path) -> tuple[np.ndarray, dict]:
    """Mean of two independent single-bandwidth SPPM halves (``study.references``) at the
    scene's own path depth or ``max_depth``, and its own error."""
    key = f"{name}_d{max_depth}" if max_depth is not None else name
    depth = {} if max_depth is None else {"max_depth": max_depth}
    _, halves = references({key: name}, width, REF_PHOTONS, passes, cache, seeds=REF_SEEDS, **depth)[key]
    return 0.5 * (halves[0] + halves[1]), reference_error(*halves)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "option_sweep")
    ap.add_argument("--scenes", default=",".join(SCENES), help="built-in scenes, comma-separated")
    ap.add_argument("--options", default=",".join(OPTIONS), help="option sets, comma-separated: " + ", ".join(OPTIONS))
    ap.add_argument("--width", type=int, default=64)
    ap.add_argument("--passes", default="4,64", help="input pass counts, comma-separated")
    ap.add_argument("--ref-passes", type=int, default=1024)
    ap.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    args = ap.parse_args()

    from ppmrecon.api import load_model
    from ppmrecon.model.infer import denoise
    from ppmrecon.scene.loader import load_scene

    options = [o for o in args.options.split(",") if o]
    unknown = [o for o in options if o not in OPTIONS]
    if unknown:
        sys.exit(f"option_sweep.py: --options: unknown {', '.join(unknown)} (choose {', '.join(OPTIONS)})")
    cache = args.out / "cache"
    cache.mkdir(parents=True, exist_ok=True)
    net = load_model(args.model)
    fns = {"shipped": lambda buf: denoise(buf, net).rgb}
    rows = []
    for name in args.scenes.split(","):
        refs: dict = {}                                  # path depth -> (reference, its error)
        loaded = load_scene(name, resolution=args.width, warn=False)
        key = f"{name}_{args.width}"
        for option in options:
            settings = dict(OPTIONS[option])
            depth = settings.get("max_depth")
            if depth not in refs:
                refs[depth] = reference(name, args.width, depth, args.ref_passes, cache)
            ref, ref_err = refs[depth]
            method, photons = settings.pop("method", "sppm"), settings.pop("photons", PHOTONS)
            for passes in (int(p) for p in args.passes.split(",")):
                path = cache / f"{key}_{option}_n{passes}.exr"
                if not path.exists():
                    t = time.perf_counter()
                    res = renderer(loaded, name, "multi", method, photons, SEED, passes=passes, **settings).run()
                    B.write_buffers(path, res.buffer_file())
                    print(f"{key} {option} N = {passes} in {time.perf_counter() - t:.1f}s", flush=True)
                row = score_image(B.read_buffers(path), ref, fns, ref_err)
                row.update(scene=name, option=option, passes=passes)
                rows.append(row)
                v = row["variants"]["shipped"]
                print(f"{name:18s} {option:15s} N={passes:4d} best {row['best_single_name']:>2s} "
                      f"{row['best_single']:.3g}  ratio {v['ratio']:.3f}  8x8 {v['ratio_8x8']:.3f}  "
                      f"deciding {v['deciding_pixels']}", flush=True)

    ratios = np.array([r["variants"]["shipped"]["ratio"] for r in rows])
    worse = [r for r in rows if r["variants"]["shipped"]["ratio"] > 1.0]
    lines = ["# The reconstruction on renders with non-default options (`benchmarks/option_sweep.py`)", "",
             f"{len(rows)} renders at width {args.width}, N = {args.passes}, {PHOTONS} photons per pass unless the "
             f"option sets it; references: two {args.ref_passes}-pass x {REF_PHOTONS}-photon single-bandwidth "
             "SPPM halves per scene and path depth. Ratio = relMSE over the best of the render's five estimates.",
             "", f"Geometric mean ratio {np.exp(np.log(ratios).mean()):.3f}; worse than the best input: "
             f"{len(worse)} of {len(rows)} (of which decided by at most {FEW_PIXELS} px: "
             f"{sum(r['variants']['shipped']['deciding_pixels'] <= FEW_PIXELS for r in worse)}).", "",
             "| scene | option | N | best input | ratio | 8x8 | deciding px | reference share |",
             "|---|---|---:|---|---:|---:|---:|---:|"]
    for r in rows:
        v = r["variants"]["shipped"]
        lines.append(f"| {r['scene']} | {r['option']} | {r['passes']} | {r['best_single_name']} "
                     f"{r['best_single']:.3g} | {v['ratio']:.3f} | {v['ratio_8x8']:.3f} | {v['deciding_pixels']} | "
                     f"{r['reference_share']:.2f} |")
    by_option = {}
    for r in rows:
        by_option.setdefault(r["option"], []).append(r["variants"]["shipped"]["ratio"])
    lines += ["", "| option | renders | geometric mean ratio | worst | worse |", "|---|---:|---:|---:|---:|"]
    for option, rs in by_option.items():
        rs = np.array(rs)
        lines.append(f"| {option} | {len(rs)} | {np.exp(np.log(rs).mean()):.3f} | {rs.max():.3f} | {(rs > 1).sum()} |")
    write_json(args.out / "sweep.json", {"width": args.width, "passes": args.passes, "ref_passes": args.ref_passes,
                                         "rows": rows})
    write_text(args.out / "sweep.md", "\n".join(lines) + "\n")
    print("\n".join(lines[4:6]))


if __name__ == "__main__":
    main()
