"""Alternatives to the shipped envelope's anchor and guide source, scored per image (issue 12).

    .venv/bin/python benchmarks/envelope_alternatives.py [--data data/t0023 ...] [--deep-references]
        [--scene REF_A.exr REF_B.exr RENDER.exr ...] [--out benchmarks/results/envelope_alternatives]

Each variant is built from the shipped model's own pieces (its guard, its guide images, the
range of each pixel's five guarded estimates, :func:`ppmrecon.model.guard.anchor_where_biased`),
so that only the named step differs from ``ppmrecon.model.infer.denoise``:

* ``shipped``: ``denoise`` itself (the envelope: guide g clamped into the range, anchored to
  the low frequencies of its aim (~z^3, or per pixel towards ~z^4: ``guide.anchor_target``)
  where the gap exceeds their noise, clamped again);
* ``self anchor``: the anchor's target is g itself, ``e + G_sigma * (g - e)``: it returns the
  low frequencies that the clamp took from the guide, nothing of ~z^3's noise;
* ``iterated K``: the anchor and the clamp repeated K times (alternating projections onto the
  range and onto ~z^3's low frequencies: energy the clamp removes where the range is tight is
  pushed to neighbours with room);
* ``source extrapolated``: OIDN's source ~z^4 replaced by the zero-bandwidth extrapolation of
  ~z^3 and ~z^4 (Richardson on a kernel estimate's r^2 bias, with the per-pixel radii).

All are consistent (held in the range last). Per image: relMSE / 8x8-block relMSE over the
best single input; per variant the geometric mean and the count worse than the best input.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_guide import score_image, summary, table  # noqa: E402
from deep_reference import DEEP  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint  # noqa: E402
from ppmrecon.model.guard import anchor_low_frequencies, anchor_where_biased, band_bounds, guard_buffer  # noqa: E402
from ppmrecon.model.guide import anchor_target, y_spike_mask  # noqa: E402
from ppmrecon.model.infer import _scale, buffer_guide_images, denoise  # noqa: E402
from ppmrecon.train.datagen import REFERENCE, load_manifest  # noqa: E402

ITERATIONS = (2, 4)


def extrapolated(buf: B.BufferFile) -> np.ndarray:
    """``(r4^2 ~z^3 - r3^2 ~z^4) / (r4^2 - r3^2)`` per pixel (X = L + c r^2 solved for L), >= 0."""
    r3, r4 = (buf.radii[k].astype(np.float64)[..., None] ** 2 for k in (3, 4))
    d = np.where(r4 > r3, r4 - r3, 1.0)
    return np.clip((r4 * buf.estimates[3] - r3 * buf.estimates[4]) / d, 0.0, None).astype(np.float32)


def variants(buf: B.BufferFile, net) -> dict[str, np.ndarray]:
    guard, guide = net.guard, net.guide
    out = {"shipped": denoise(buf, net).rgb}
    g_buf = guard_buffer(buf, guard)
    scale = _scale(g_buf)
    est = torch.from_numpy(np.ascontiguousarray(g_buf.estimates, np.float32)).permute(0, 3, 1, 2)[None]
    y, z = est[:, 0], est[:, 1:]
    def variance_of(k: int) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(g_buf.variances[k], np.float32))[None, None]

    m = guide.anchor_source
    # the anchor's aim as the shipped envelope takes it (~z^m, or per pixel towards ~z^(m+1))
    target, var = anchor_target(z, variance_of(m), variance_of(m + 1) if m < z.shape[1] else None, guide,
                                guard.anchor)
    lo, hi = band_bounds(y, z, 1.0, y_spike_mask(y, z, guide, guard, scale))

    def held(x: torch.Tensor) -> torch.Tensor:
        return torch.minimum(torch.maximum(x, lo), hi)

    def anchored(x: torch.Tensor) -> torch.Tensor:
        return anchor_where_biased(x, target, var, guard.anchor, guide.anchor_noise,
                                   guide.anchor_window, guide.anchor_settled)

    g = buffer_guide_images(g_buf, guide, guard, scale)[0].guide[None]
    with torch.no_grad():
        e = held(g)
        out["self anchor"] = held(anchor_low_frequencies(e, g, guard.anchor))
        x = e
        for k in range(1, max(ITERATIONS) + 1):
            if k == 2 and not np.allclose(x[0].permute(1, 2, 0).numpy(), out["shipped"], rtol=1e-5, atol=0):
                # one round is the shipped envelope: the pieces here must rebuild it exactly
                sys.exit("envelope_alternatives: the rebuilt envelope differs from denoise (infer changed?)")
            x = held(anchored(x))
            if k in ITERATIONS:
                out[f"iterated {k}"] = x
        swapped = replace(g_buf, estimates=g_buf.estimates.copy())
        swapped.estimates[4] = extrapolated(g_buf)
        gx = buffer_guide_images(swapped, guide, guard, scale)[0].guide[None]
        out["source extrapolated"] = held(anchored(held(gx)))
    return {k: (v if isinstance(v, np.ndarray) else v[0].permute(1, 2, 0).numpy()) for k, v in out.items()}


def score(buf: B.BufferFile, ref: np.ndarray, net) -> dict:
    """bench_guide's per-image score of every variant (computed once, they share the guide)."""
    images = variants(buf, net)
    return score_image(buf, ref, {k: (lambda _buf, v=v: v) for k, v in images.items()})


def images(args) -> list[tuple[str, B.BufferFile, np.ndarray]]:
    out = []
    for data in args.data:
        for scene in load_manifest(data)["scenes"]:
            name = DEEP if args.deep_references else REFERENCE
            if not (data / scene["id"] / name).exists():
                continue
            ref = B.read_rgb(data / scene["id"] / name)[0]
            for item in scene.get("inputs", []):
                buf = B.read_buffers(data / scene["id"] / item["file"])
                out.append((f"{data.name}/{scene['id']} {item['file']}", buf, ref))
    for group in args.scene:
        ref = 0.5 * (B.read_rgb(group[0])[0] + B.read_rgb(group[1])[0])
        for render in group[2:]:
            out.append((Path(render).name, B.read_buffers(render), ref))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, action="append", default=[], help="a generated data set (repeatable)")
    ap.add_argument("--deep-references", action="store_true",
                    help="score --data images against deep_reference.exr (benchmarks/deep_reference.py)")
    ap.add_argument("--scene", nargs="+", action="append", default=[], metavar="EXR",
                    help="two reference EXRs, then buffer files scored against their mean (repeatable)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "envelope_alternatives")
    args = ap.parse_args()
    if any(len(g) < 3 for g in args.scene):
        sys.exit("envelope_alternatives: --scene takes two references and at least one buffer file")
    t0 = time.perf_counter()
    net = load_checkpoint(args.model).model
    rows = []
    for name, buf, ref in images(args):
        rows.append({"image": name, **score(buf, ref, net)})
        print(name + ": " + ", ".join(f"{k} {v['ratio']:.2f}/{v['ratio_8x8']:.2f}"
                                      for k, v in rows[-1]["variants"].items()), flush=True)
    if not rows:
        sys.exit("envelope_alternatives: no images (give --data or --scene)")
    names = list(rows[0]["variants"])
    lines = ["# Alternatives to the envelope's anchor and guide source (issue 12)", "",
             f"`{' '.join(sys.argv)}`, {len(rows)} images, {(time.perf_counter() - t0) / 60:.1f} min. "
             "relMSE / 8x8-block relMSE over each image's best single input (bench_guide.py's columns).", "",
             *table(summary(rows, names)),
             "", "| image | best | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for row in rows:
        lines.append(f"| {row['image']} | {row['best_single_name']} | " + " | ".join(
            f"{row['variants'][n]['ratio']:.2f} / {row['variants'][n]['ratio_8x8']:.2f}" for n in names) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "alternatives.json", {"rows": rows})
    write_text(args.out / "alternatives.md", "\n".join(lines) + "\n")
    print(f"wrote {args.out / 'alternatives.md'}")


if __name__ == "__main__":
    main()
