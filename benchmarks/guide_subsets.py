"""Split a ``bench_guide.py`` result on a generated data set by scene index (issue 12).

    .venv/bin/python benchmarks/guide_subsets.py benchmarks/results/guide_s9_shipped/guide.json \
        --variants 'shipped mutual=0,shipped' --groups 'old=0-15' 'selection=16-28,36,39'

Each data-set image is put in the first group whose indices hold its scene's index (the
number its folder name starts with: ``0069_caustic_paths`` is 69); the rest form the group
``unselected``. Per group and variant: images, the geometric means of relMSE and 8x8-block
relMSE over the image's best single input, and the images above their best input (with the
same for relMSE on images divided by the reference's mean where the result has it); then the
images above their best input for any variant, one line each. Use it to tell the scenes a
setting was chosen on from those it never saw.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from pathlib import Path


def indices(text: str) -> set[int]:
    """'16-28,36,39' -> {16, ..., 28, 36, 39}."""
    out: set[int] = set()
    for part in text.split(","):
        lo, _, hi = part.partition("-")
        out |= set(range(int(lo), int(hi or lo) + 1))
    return out


def scene_index(scene: str) -> int:
    match = re.match(r"(\d+)_", scene.split("/")[-1])
    if not match:
        raise SystemExit(f"guide_subsets: scene '{scene}' does not start with its index")
    return int(match.group(1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result", type=Path, help="guide.json of benchmarks/bench_guide.py")
    ap.add_argument("--variants", required=True, help="comma-separated variant names of the result")
    ap.add_argument("--groups", nargs="*", default=[], metavar="NAME=I-J,K",
                    help="named groups of scene indices (the rest: 'unselected')")
    args = ap.parse_args()
    rows = json.loads(args.result.read_text())["validation"]
    names = [v.strip() for v in args.variants.split(",")]
    missing = [n for n in names if rows and n not in rows[0]["variants"]]
    if missing:
        raise SystemExit(f"guide_subsets: {args.result}: no variant {', '.join(missing)}")
    groups = [(g.split("=", 1)[0], indices(g.split("=", 1)[1])) for g in args.groups]
    by_group: dict[str, list[dict]] = {}
    for r in rows:
        i = scene_index(r["scene"])
        name = next((g for g, members in groups if i in members), "unselected")
        by_group.setdefault(name, []).append(r)
    print("| group | images | " + " | ".join(f"{n}: relMSE / 8x8, worse (scaled: relMSE, worse)" for n in names)
          + " |")
    print("|---|---:|" + "---|" * len(names))
    for name in [g for g, _ in groups] + ["unselected"]:
        members = by_group.get(name, [])
        if not members:
            continue
        cells = []
        for n in names:
            ratio = math.exp(sum(math.log(r["variants"][n]["ratio"]) for r in members) / len(members))
            blocks = math.exp(sum(math.log(r["variants"][n]["ratio_8x8"]) for r in members) / len(members))
            worse = sum(r["variants"][n]["ratio"] > 1 for r in members)
            cell = f"{ratio:.3f} / {blocks:.3f}, {worse}"
            if all("ratio_scaled" in r["variants"][n] for r in members):   # results since the tenth session
                scaled = math.exp(sum(math.log(r["variants"][n]["ratio_scaled"]) for r in members) / len(members))
                cell += f" ({scaled:.3f}, {sum(r['variants'][n]['ratio_scaled'] > 1 for r in members)})"
            cells.append(cell)
        print(f"| {name} | {len(members)} | " + " | ".join(cells) + " |")
    print()
    for r in rows:
        ratios = [r["variants"][n]["ratio"] for n in names]
        if max(ratios) > 1:
            print(f"- {r['image']}: " + ", ".join(f"{n} {x:.3f}" for n, x in zip(names, ratios)))


if __name__ == "__main__":
    main()
