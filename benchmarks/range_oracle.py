"""Where the envelope's limit lies, by pass count: its guide or its range (issue 12).

    .venv/bin/python benchmarks/range_oracle.py [--data data/holdout_s16 ...]
        [--study benchmarks/results/guide_s16_far_n1024/cache --ref-cache docs/cache --ref-passes 4096]
        [--out benchmarks/results/range_oracle]

The shipped envelope is ``clamp(g, range)`` then the anchor (:func:`ppmrecon.model.guide.envelope`):
its error is bounded below by the best point of each pixel's range, and above by how far the
guide g leads it. Per image (scored against the reference, as ``bench_guide.py``) the ratios
over the best single input of:

* ``shipped``: ``denoise`` with the shipped model;
* ``guide``: the shipped guide image g itself (OIDN's, not consistent);
* ``oracle range``: the reference clamped into each pixel's range of its five guarded
  estimates, per channel (the best any guide could do with the bare clamp; the shipped anchor
  cascade holds the guide in the range of the pulled ~z^j, which lies inside this one);
* ``oracle terms``: the same in the range widened towards paper 002 Eq. 6's terms over the 3 x 3
  window, by the shipped share 1 / (1 + N / M) (``guide.terms_range``), the range the shipped
  guide was held in before the cascade;
* ``oracle terms all``: widened the whole way (share 1), each end by at most the range's width.

The two oracles read the reference, so they are bounds, not methods. An ``oracle`` ratio near
the shipped one says the range limits the envelope; far below it, the guide does.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.metrics import relmse, relmse_blocks  # noqa: E402
from study import REF_SEEDS, ref_path  # noqa: E402

VARIANTS = ("shipped", "guide", "oracle range", "oracle terms", "oracle terms all")


def images(buf: B.BufferFile, ref: np.ndarray, net) -> dict[str, np.ndarray]:
    """The five images of the module docstring for one render, each (H, W, 3)."""
    from ppmrecon.model.guard import band_bounds, guard_buffer, passes_of
    from ppmrecon.model.guide import N_RGB, terms_range, terms_share
    from ppmrecon.model.infer import _scale, buffer_aim, buffer_envelope, buffer_guide_images

    guard, guide = net.guard, net.guide
    guarded = guard_buffer(buf, guard)
    scale = _scale(guarded)
    aim = buffer_aim(guarded, guide, guard)                    # the cascade's, once (None where it is off)
    planes = buffer_guide_images(guarded, guide, guard, scale, aim=aim)[1]   # one OIDN run for both images
    est = torch.from_numpy(np.ascontiguousarray(guarded.estimates, np.float32)).permute(0, 3, 1, 2)[None]
    y, z = est[:, 0], est[:, 1:]
    lo, hi = band_bounds(y, z, 1.0, None)
    share = terms_share(passes_of(guarded), guide)
    r = torch.from_numpy(np.ascontiguousarray(ref, np.float32)).permute(2, 0, 1)[None]

    def clamp(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
        return torch.minimum(torch.maximum(r, a), b)[0].permute(1, 2, 0).numpy()

    return {"shipped": buffer_envelope(guarded, planes, guard, guide, scale=scale, aim=aim).rgb,
            "guide": planes[0, :N_RGB].permute(1, 2, 0).numpy(),
            "oracle range": clamp(lo, hi),
            "oracle terms": clamp(*terms_range(y, z, lo, hi, share)),
            "oracle terms all": clamp(*terms_range(y, z, lo, hi, 1.0))}


def score(buf: B.BufferFile, ref: np.ndarray, net) -> dict:
    """Ratios (relMSE and 8x8-block relMSE) of each variant over the best single input."""
    best = min(relmse(e, ref) for e in buf.estimates)
    best8 = min(relmse_blocks(e, ref) for e in buf.estimates)
    return {name: {"ratio": relmse(img, ref) / best, "ratio_8x8": relmse_blocks(img, ref) / best8}
            for name, img in images(buf, ref, net).items()}


def study_renders(cache: Path, ref_cache: Path, ref_passes: int) -> Iterator[tuple[str, int, B.BufferFile, np.ndarray]]:
    """(label, N, render, reference) of every render in a ``bench_guide.py`` cache
    (``KEY_WIDTH_NxPHOTONS_sSEED_multi.exr``) whose two references of ``ref_passes`` passes are
    in ``ref_cache`` (their mean is the reference)."""
    refs: dict[tuple[str, str, int], np.ndarray] = {}        # each scene's references read once, not per N
    for path in sorted(cache.glob("*_multi.exr")):
        key, width, passes_photons = path.name.rsplit("_", 4)[:3]
        n, photons = (int(v) for v in passes_photons.split("x"))
        pair = [ref_path(ref_cache, key, int(width), ref_passes, photons, seed) for seed in REF_SEEDS]
        if not all(p.exists() for p in pair):
            continue
        if (key, width, photons) not in refs:
            refs[key, width, photons] = 0.5 * (B.read_rgb(pair[0])[0] + B.read_rgb(pair[1])[0])
        yield f"{key} N={n}", n, B.read_buffers(path), refs[key, width, photons]


def data_renders(data: Path) -> Iterator[tuple[str, int, B.BufferFile, np.ndarray]]:
    """(label, N, input, reference) of every input of every complete scene of a generated data set."""
    from ppmrecon.train.datagen import REFERENCE, load_manifest

    for scene in load_manifest(data)["scenes"]:
        if not scene.get("reference"):
            continue
        ref, _ = B.read_rgb(data / scene["id"] / REFERENCE)
        for item in scene.get("inputs", []):
            yield (f"{scene['id']} {item['file']}", item["passes"], B.read_buffers(data / scene["id"] / item["file"]),
                   ref)


def geomean(values: list[float]) -> float:
    return math.exp(float(np.mean(np.log(values))))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, action="append", default=[],
                    help="a generated data set: every input of every scene (repeatable)")
    ap.add_argument("--study", type=Path, default=None,
                    help="a bench_guide.py render cache (<out>/cache) of the literature scenes")
    ap.add_argument("--ref-cache", type=Path, default=ROOT / "docs" / "cache",
                    help="the references of --study's scenes (bench_guide.py's --ref-cache)")
    ap.add_argument("--ref-passes", type=int, default=1024, help="passes of --study's references")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "range_oracle")
    args = ap.parse_args()
    if not args.data and args.study is None:
        ap.error("give --data and/or --study")
    from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint

    t0 = time.perf_counter()
    net = load_checkpoint(DEFAULT_MODEL).model
    rows = []
    if args.study is not None:
        for label, n, buf, ref in study_renders(args.study, args.ref_cache, args.ref_passes):
            rows.append({"set": "literature", "image": label, "passes": n, **score(buf, ref, net)})
    for data in args.data:
        for label, n, buf, ref in data_renders(data):
            rows.append({"set": data.name, "image": label, "passes": n, **score(buf, ref, net)})
    lines = ["# Where the envelope's limit lies: its guide or its range (issue 12)", "",
             f"Generated by `benchmarks/range_oracle.py" + "".join(f" --data {d}" for d in args.data)
             + (f" --study {args.study} --ref-passes {args.ref_passes}" if args.study else "")
             + f"` in {(time.perf_counter() - t0) / 60:.1f} min. Geometric means of relMSE / 8x8-block relMSE "
             "over the best single input; the oracles read the reference (bounds, not methods).", "",
             "| set | N | images | " + " | ".join(VARIANTS) + " |", "|---|---:|---:|" + "---|" * len(VARIANTS)]
    groups: dict[tuple[str, int], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["set"], row["passes"]), []).append(row)
    for (name, n), members in sorted(groups.items()):
        cells = [f"{geomean([m[v]['ratio'] for m in members]):.3f} / {geomean([m[v]['ratio_8x8'] for m in members]):.3f}"
                 for v in VARIANTS]
        lines.append(f"| {name} | {n} | {len(members)} | " + " | ".join(cells) + " |")
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "oracle.json", {"rows": rows})
    write_text(args.out / "oracle.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    from ppmrecon.errors import UsageError

    try:
        main()
    except UsageError as exc:                               # a missing data set or manifest: one line
        sys.exit(f"range_oracle: {exc}")
