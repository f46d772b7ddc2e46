"""The README's Python quick start, run as it is written, and the picture it makes.

    python scripts/quickstart_figure.py [--passes 32] [--reference-passes 1024] [--resolution 160]

Renders the built-in ``cornell_caustics`` scene, denoises it with the shipped model,
compares input and output with a reference (~z^1 of a long render with another seed:
itself a PPM estimate, so not exact, but its error is far below the short render's)
and writes ``docs/figures/quickstart.png`` (input ~z^1 | denoised | reference) and
``docs/figures/quickstart.json`` (the scores and timings the README quotes).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import ppmrecon
from ppmrecon.fileio import write_text
from ppmrecon.preview import side_by_side, write_png

OUT = Path(__file__).resolve().parents[1] / "docs" / "figures"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--passes", type=int, default=32)
    ap.add_argument("--reference-passes", type=int, default=1024)
    ap.add_argument("--resolution", type=int, default=160)
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    # --- the quick start (README) ---
    t0 = time.perf_counter()
    buf = ppmrecon.render("cornell_caustics", passes=args.passes, resolution=args.resolution)
    t1 = time.perf_counter()
    rgb = ppmrecon.denoise(buf)                      # the shipped model
    t2 = time.perf_counter()
    ref = ppmrecon.render("cornell_caustics", passes=args.reference_passes, resolution=args.resolution,
                          seed=1).estimates[1]
    scores = {"input z1": ppmrecon.compare(buf, ref, layer="z1"), "denoised": ppmrecon.compare(rgb, ref)}
    # --- end of the quick start ---

    write_png(args.out / "quickstart.png", side_by_side([buf.estimates[1], rgb, ref]))
    report = {"scene": "cornell_caustics", "resolution": args.resolution, "passes": args.passes,
              "reference_passes": args.reference_passes, "render_seconds": round(t1 - t0, 2),
              "denoise_seconds": round(t2 - t1, 2), "scores": scores}
    write_text(args.out / "quickstart.json", json.dumps(report, indent=1) + "\n")
    for name, s in scores.items():
        print(f"{name}: relMSE {s['relmse']:.4g}, 8x8 {s['relmse_8x8']:.4g}, trimmed {s['relmse_trimmed']:.4g}")
    print(f"wrote {args.out / 'quickstart.png'} and quickstart.json")


if __name__ == "__main__":
    main()
