"""What each part of the anchor cascade (``GuideConfig.cascade``, :func:`ppmrecon.model.guide.cascade_aim`)
brings (issue 12, seventeenth session).

    .venv/bin/python benchmarks/anchor_cascade.py SET [--k K,...] [--out DIR]

SET is ``study`` (the renders of ``benchmarks/results/guide_s16_far/cache`` against the 1024-pass
references of ``docs/cache``), ``study_n1024`` (``guide_s16_far_n1024/cache``, 4096-pass
references) or a generated data set folder. Why: on ``holdout_n1024_s16``'s ``0001_caustic_paths``
the wide estimates carry a bandwidth bias beside a bright caustic far above their noise, and the
guide (OIDN of ~z^4), the range's upper end and the anchor's aim (~z^4 or ~z^3) all followed
them. The cascade steps the aim on down to ~z^2 and ~z^1 where that bias shows; per k, the
variants are

* ``no cascade``: the shipped settings with ``cascade`` 0 (as shipped before 2026-12-06);
* ``k=K aim``: the envelope anchored to the cascade's aim t, its range and guide as without it;
* ``k=K aim+range``: also the range of ~y and the pulled ~z^j;
* ``k=K``: also OIDN given t in place of ~z^4 (what ``GuideConfig.cascade = K`` ships; the
  image is ``denoise``'s with that setting; the shipped default has k = 4).

Per set: relMSE / 8x8-block relMSE over the best single input (geometric means), images
worse than it, by N.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_text  # noqa: E402
from ppmrecon.metrics import relmse, relmse_blocks  # noqa: E402
from range_oracle import data_renders, geomean, study_renders  # noqa: E402


def variants(buf: B.BufferFile, net, ks: list[float]) -> dict[str, np.ndarray]:
    """The image without the cascade and the cascade's three variants per k (module docstring),
    each (H, W, 3)."""
    from ppmrecon.model.guard import guard_buffer
    from ppmrecon.model.infer import _scale, buffer_aim, buffer_envelope, buffer_guide, buffer_guide_images

    guard, guide = net.guard, replace(net.guide, cascade=0.0)
    g = guard_buffer(buf, guard)
    scale = _scale(g)
    shipped_planes = buffer_guide(g, guide, guard, scale)
    out = {"no cascade": buffer_envelope(g, shipped_planes, guard, guide, scale=scale).rgb}
    z = torch.from_numpy(np.ascontiguousarray(g.estimates[1:], np.float32)).permute(0, 3, 1, 2)[None]
    for k in ks:
        cfg = replace(guide, cascade=k)
        aim = buffer_aim(g, cfg, guard)
        out[f"k={k:g} aim"] = buffer_envelope(g, shipped_planes, guard, cfg, scale=scale, aim=aim._replace(z=z)).rgb
        out[f"k={k:g} aim+range"] = buffer_envelope(g, shipped_planes, guard, cfg, scale=scale, aim=aim).rgb
        planes = buffer_guide_images(g, cfg, guard, scale, aim=aim)[1]
        out[f"k={k:g}"] = buffer_envelope(g, planes, guard, cfg, scale=scale, aim=aim).rgb
    return out


def renders(which: str):
    """(label, passes, buffer, reference) of a set (see the module docstring)."""
    if which in ("study", "study_n1024"):
        cache, ref_passes = ("guide_s16_far", 1024) if which == "study" else ("guide_s16_far_n1024", 4096)
        return study_renders(ROOT / "benchmarks" / "results" / cache / "cache", ROOT / "docs" / "cache", ref_passes)
    return data_renders(Path(which))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("set", help="study, study_n1024, or a generated data set folder")
    ap.add_argument("--k", default="4", help="comma-separated noise multiples k (default 4)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "anchor_cascade")
    args = ap.parse_args()
    from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint

    net = load_checkpoint(DEFAULT_MODEL).model
    ks = [float(k) for k in args.k.split(",")]
    rows: dict[int, dict[str, list[tuple[float, float]]]] = {}
    per_image = []
    for label, n, buf, ref in renders(args.set):
        best = min(relmse(e, ref) for e in buf.estimates)
        best8 = min(relmse_blocks(e, ref) for e in buf.estimates)
        scores = {k: (relmse(img, ref) / best, relmse_blocks(img, ref) / best8)
                  for k, img in variants(buf, net, ks).items()}
        for k, v in scores.items():
            rows.setdefault(n, {}).setdefault(k, []).append(v)
        per_image.append(f"| {label} | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in scores.values()) + " |")

    def cell(v: list[tuple[float, float]]) -> str:
        return f"{geomean([a for a, _ in v]):.3f} / {geomean([b for _, b in v]):.3f}, {sum(a > 1 for a, _ in v)} worse"

    names = list(next(iter(rows.values())))
    both = {k: [x for n in rows for x in rows[n][k]] for k in names}
    name = Path(args.set).name
    lines = [f"# The anchor cascade, part by part: `{name}` (issue 12)", "",
             f"Generated by `benchmarks/anchor_cascade.py {args.set} --k {args.k}`. relMSE / 8x8-block relMSE over "
             "the best single input, geometric means, and images worse than it.", "",
             "| N | " + " | ".join(names) + " |", "|---|" + "---|" * len(names),
             "| all | " + " | ".join(cell(both[k]) for k in names) + " |"]
    lines += [f"| {n} | " + " | ".join(cell(rows[n][k]) for k in names) + " |" for n in sorted(rows)]
    lines += ["", "| image | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)] + per_image
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / f"{name}.md", "\n".join(lines) + "\n")
    print("\n".join(lines[:6 + len(rows) + 1]))


if __name__ == "__main__":
    from ppmrecon.errors import UsageError

    try:
        main()
    except UsageError as exc:                               # a missing data set or manifest: one line
        sys.exit(f"anchor_cascade: {exc}")
