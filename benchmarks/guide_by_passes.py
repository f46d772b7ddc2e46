#!/usr/bin/env python3
"""Per-N figures of a ``bench_guide.py`` report, and a rule that picks a variant by N.

    benchmarks/guide_by_passes.py REPORT/guide.json [--only TEXT] [--by-passes LOW,HIGH,N0]
                                  [--images-of OTHER/guide.json]

prints, for every N of the report's images (literature scenes, or with ``--data`` the data
set's), the geometric means of relMSE and 8x8-block relMSE over the best input and the number
of images worse than it, per variant. ``--by-passes LOW,HIGH,N0`` adds the variant that takes
HIGH's image at N >= N0 and LOW's below (a pass-count rule needs no new render: each image of
the rule is one of the two variants'), and prints the report's summary table of the three.
``--only TEXT`` keeps the images whose name contains TEXT (one data set of a report on several);
``--images-of OTHER`` keeps the images that OTHER's report also scored (e.g. the scenes that have
a deep reference: the same images against the data set's own references and the deeper ones).
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_guide as BG  # noqa: E402


def by_passes(rows: list[dict], names: list[str]) -> list[str]:
    """One Markdown row per N: per variant, relMSE / 8x8 geomeans over the best input and the
    count of images worse than it (:func:`bench_guide.summary` of that N's images)."""
    groups: dict[int, list[dict]] = defaultdict(list)
    for row in rows:
        groups[row["passes"]].append(row)
    lines = ["| N | images | " + " | ".join(names) + " |", "|---:|---:|" + "---|" * len(names)]
    for n in sorted(groups):
        cells = [f"{s['geomean']:.3f} / {s['geomean_8x8']:.3f}, {s['worse_than_best']} worse"
                 for s in BG.summary(groups[n], names)]
        lines.append(f"| {n} | {len(groups[n])} | " + " | ".join(cells) + " |")
    return lines


def _read(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        sys.exit(f"guide_by_passes: {path}: cannot read a bench_guide report ({exc})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("report", type=Path, help="a guide.json written by bench_guide.py")
    ap.add_argument("--only", default="", help="keep the images whose name contains this text")
    ap.add_argument("--images-of", type=Path, default=None, metavar="OTHER",
                    help="keep the images that this other guide.json also scored")
    ap.add_argument("--by-passes", default=None, metavar="LOW,HIGH,N0",
                    help="add the variant that is HIGH at N >= N0 and LOW below")
    args = ap.parse_args()
    report = _read(args.report)
    other = _read(args.images_of) if args.images_of else None
    for key, title in (("scenes", "Literature scenes"), ("validation", "Data set images")):
        rows = [r for r in report.get(key, []) if args.only in r["image"]]
        if other is not None:
            kept = {r["image"] for r in other.get(key, [])}
            rows = [r for r in rows if r["image"] in kept]
        if not rows:
            continue
        names = list(rows[0]["variants"])
        if args.by_passes:
            try:
                low, high, n0 = args.by_passes.rsplit(",", 2)
                n0 = int(n0)
            except ValueError:
                sys.exit(f"guide_by_passes: --by-passes {args.by_passes!r}: expected LOW,HIGH,N0")
            for name in (low, high):
                if name not in names:
                    sys.exit(f"guide_by_passes: --by-passes: no variant {name!r} in {args.report} ({', '.join(names)})")
            rule = f"{low} below N = {n0}, {high} from it"
            for r in rows:
                r["variants"][rule] = r["variants"][high if r["passes"] >= n0 else low]
            names = [low, high, rule]
        print(f"## {title} ({len(rows)} images)\n")
        print("\n".join(by_passes(rows, names)))
        if args.by_passes:
            print()
            print("\n".join(BG.table(BG.summary(rows, names))))
        print()


if __name__ == "__main__":
    main()
