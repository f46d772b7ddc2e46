"""What OIDN is given for the envelope's guide, scored per image (issue 12).

    .venv/bin/python benchmarks/guide_inputs.py [--data data/v3_cpu ...] [--study benchmarks/results/guide_s7/cache]
        [--variants 'shipped,lightmap,...'] [--out benchmarks/results/guide_inputs]

The envelope (clamp into the range of each pixel's five guarded estimates, anchor, clamp) is
the shipped ``buffer_envelope`` in every variant; only the guide image changes, so each row
says what a different guide would bring (checked: the rebuilt shipped guide gives
``denoise``'s image exactly). All variants are consistent (the envelope holds any guide in
the range). Variants:

* ``shipped``: ``denoise`` (OIDN ``fast`` of the despiked ~z^4, mixed with OIDN(~y) by
  inverse local variances, ~y's times 2: ``guide.y_share``);
* ``pre F``: one OIDN of the same inverse-variance blend of the *inputs* (ratio F), not of
  the two OIDN images (half the OIDN time);
* ``swap S``: ~z^4's low frequencies moved towards ~y's before OIDN (Eq. 6 with uniform
  weights over a Gaussian of S px, weighted by the two low-passes' variances, ~z^4's with
  its neighbour correlation), then mixed with OIDN(~y) as shipped; ``swap S raw``: the same
  image as the guide without OIDN;
* ``clean_aux``: OIDN told that albedo and normal are noise-free (``clean_aux=True``);
* ``lightmap``: OIDN's ``RTLightmap`` filter (no albedo / normal) for both images;
  ``lightmap z4`` / ``lightmap y``: for that image only; ``lowmix S half``: RT's image of
  ~z^4 with the low frequencies (Gaussian S px) of RTLightmap's image of ~z^4 at half resolution;
* ``high``: both OIDN images at quality ``high``; ``high z4``: ~z^4's only;
* ``terms K`` (the one variant that changes the range, not the guide): each pixel's range
  widened to the terms of paper 002 Eq. 6 over a K x K window, ``~y_i + ~z^j_c - ~z^j_i`` for
  every j and i (each converges to x_c, so the envelope stays consistent); the shipped guide;
  ``terms K S``: widened only the share S of the way; ``terms K nM``: the share 1 / (1 + N / M)
  for a render of N passes (all the way at few passes, little at many); ``... cap``: each end
  moved out by at most the shipped range's width.

Per image: relMSE / 8x8-block relMSE over the best single input (``bench_guide.score_image``);
per group (study, data, N, family) the geometric means and the count worse than the best input.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_guide import PHOTONS, SEED, WIDTH, score_image  # noqa: E402
from study import REF_SEEDS, ref_path  # noqa: E402

import ppmrecon.model.guard as guard_module  # noqa: E402
import ppmrecon.model.guide as guide_module  # noqa: E402
from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint  # noqa: E402
from ppmrecon.model.guard import (correlated_lowpass_variance, gaussian_lowpass, guard_buffer,  # noqa: E402
                                  lowpass_variance, noise_correlation, passes_of)
from ppmrecon.model.guide import despike, oidn_image, planes, y_share  # noqa: E402
from ppmrecon.model.infer import _scale, buffer_envelope, buffer_guide_images, denoise  # noqa: E402
from ppmrecon.train.datagen import REFERENCE, load_manifest  # noqa: E402

VARIANTS = ("shipped", "pre 2", "pre 1", "swap 2", "swap 4", "swap 2 raw", "clean_aux", "lightmap",
            "lightmap z4", "lightmap y", "lowmix 2 half", "high", "high z4", "terms 3", "terms 5")
Oidn = Callable[..., np.ndarray]


def _finite(out) -> np.ndarray:
    return np.nan_to_num(np.asarray(out, np.float32), nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)


def rt(quality: str | None = None, clean_aux: bool = False) -> Oidn:
    """OIDN's RT filter as ``guide.oidn_image`` calls it, quality fixed (None: the caller's)."""
    def fn(c, albedo, normal, q="high"):
        return _finite(guide_module._pyoidn().denoise(
            np.ascontiguousarray(c, np.float32), np.ascontiguousarray(albedo, np.float32),
            np.ascontiguousarray(normal, np.float32), hdr=True, quality=quality or q, clean_aux=clean_aux))
    return fn


def lightmap(c, albedo=None, normal=None, q="high") -> np.ndarray:
    """OIDN's RTLightmap filter (HDR, no auxiliary images, one quality)."""
    return _finite(guide_module._pyoidn().denoise(np.ascontiguousarray(c, np.float32), hdr=True,
                                                  filter_type="RTLightmap"))


def lowmix(sigma: float) -> Oidn:
    """RT's image with the low frequencies of RTLightmap's image at half resolution."""
    def fn(c, albedo, normal, q="high"):
        h, w = c.shape[:2]
        full = torch.from_numpy(oidn_image(c, albedo, normal, q)).permute(2, 0, 1)
        small = F.avg_pool2d(torch.from_numpy(np.ascontiguousarray(c, np.float32)).permute(2, 0, 1)[None], 2,
                             ceil_mode=True)[0].permute(1, 2, 0).numpy()
        lm = F.interpolate(torch.from_numpy(lightmap(small)).permute(2, 0, 1)[None], scale_factor=2,
                           mode="bilinear", align_corners=False)[0, :, :h, :w]
        return (full + gaussian_lowpass((lm - full)[None], sigma)[0]).clamp(min=0).permute(1, 2, 0).numpy()
    return fn


def terms_bounds(k: int, share: float = 1.0, cap: bool = False) -> Callable:
    """``guard.band_bounds`` widened to Eq. 6's terms over a k x k window (replicate padding):
    for each j, ``~z^j_c + min_i (~y_i - ~z^j_i)`` and ``~z^j_c + max_i (~y_i - ~z^j_i)``; with
    ``share`` < 1 only that fraction of the way from the shipped ends to the terms' ends; with
    ``cap`` each end moves out by at most the shipped range's width (a ~y spike in the window
    would otherwise widen it by the spike's whole height)."""
    shipped_bounds = guard_module.band_bounds

    def bounds(y, z, band, y_out=None):
        lo0, hi0 = shipped_bounds(y, z, band, y_out)
        lo, hi = lo0, hi0
        pad = (k // 2,) * 4
        for j in range(z.shape[1]):
            zj = z[:, j]
            lo = torch.minimum(lo, zj - F.max_pool2d(F.pad(zj - y, pad, mode="replicate"), k, 1))
            hi = torch.maximum(hi, zj + F.max_pool2d(F.pad(y - zj, pad, mode="replicate"), k, 1))
        if cap:
            width = hi0 - lo0
            lo, hi = torch.maximum(lo, lo0 - width), torch.minimum(hi, hi0 + width)
        return torch.lerp(lo0, lo.clamp(min=0.0), share), torch.lerp(hi0, hi, share)
    return bounds


def per_call(*fns: Oidn) -> Oidn:
    """``guide_images`` denoises the source first, then ~y: one filter for each call."""
    calls: list[int] = []

    def fn(c, albedo, normal, q="high"):
        f = fns[min(len(calls), len(fns) - 1)]
        calls.append(1)
        return f(c, albedo, normal, q)
    return fn


def variants(buf: B.BufferFile, net, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    guard, guide = net.guard, net.guide
    out = {"shipped": denoise(buf, net).rgb}
    gb = guard_buffer(buf, guard)
    scale, floor = _scale(gb), guard.floor
    est = torch.from_numpy(np.ascontiguousarray(gb.estimates, np.float32)).permute(0, 3, 1, 2)
    var = torch.from_numpy(np.ascontiguousarray(gb.variances, np.float32))
    y, z4 = est[0], est[4]
    images = buffer_guide_images(gb, guide, guard, scale)[0]

    def envelope(g: torch.Tensor) -> np.ndarray:
        return buffer_envelope(gb, planes(g, guide, scale, floor), guard, guide, scale=scale).rgb

    def guide_with(fn: Oidn) -> torch.Tensor:
        shipped_oidn = guide_module.oidn_image
        guide_module.oidn_image = fn
        try:
            return buffer_guide_images(gb, guide, guard, scale)[0].guide
        finally:
            guide_module.oidn_image = shipped_oidn

    def oidn(x: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(oidn_image(x.permute(1, 2, 0).numpy(), gb.albedo, gb.normal,
                                           guide.quality)).permute(2, 0, 1)

    if not np.allclose(envelope(images.guide), out["shipped"], rtol=1e-5, atol=1e-7):
        sys.exit("guide_inputs: the rebuilt envelope differs from denoise (infer changed?)")
    source = despike(z4, y, floor * scale)
    w = y_share(gb.variances, guide.source, guide.y_weight)
    with torch.no_grad():
        for name in names:
            kind, *arg = name.split(" ")
            if name == "shipped":
                continue
            if kind == "terms":
                shipped_bounds = guard_module.band_bounds
                cap = "cap" in arg
                arg = [a for a in arg if a != "cap"]
                share = 1.0 if not arg[1:] else (1.0 / (1.0 + passes_of(buf) / float(arg[1][1:])) if arg[1][0] == "n"
                                                 else float(arg[1]))
                guard_module.band_bounds = terms_bounds(int(arg[0]), share, cap)
                try:
                    out[name] = denoise(buf, net).rgb
                finally:
                    guard_module.band_bounds = shipped_bounds
                continue
            if kind == "pre":
                g = oidn(torch.lerp(source, y, y_share(gb.variances, guide.source, float(arg[0]))))
            elif kind == "swap":
                sigma = float(arg[0])
                vz, vy = var[4][None, None], var[0][None, None]
                vz_lp = correlated_lowpass_variance(vz, noise_correlation(z4[None], vz, 3.0), sigma)[0]
                a = vz_lp / (vz_lp + lowpass_variance(vy, sigma)[0]).clamp(min=1e-30)
                swapped = (source + a * gaussian_lowpass((y - source)[None], sigma)[0]).clamp(min=0.0)
                g = swapped if arg[1:] == ["raw"] else torch.lerp(oidn(swapped), images.y, w)
            elif name == "clean_aux":
                g = guide_with(rt(clean_aux=True))
            elif name == "lightmap":
                g = guide_with(lightmap)
            elif name == "lightmap z4":
                g = guide_with(per_call(lightmap, oidn_image))
            elif name == "lightmap y":
                g = guide_with(per_call(oidn_image, lightmap))
            elif kind == "lowmix":
                g = guide_with(per_call(lowmix(float(arg[0])), oidn_image))
            elif name == "high":
                g = guide_with(rt("high"))
            elif name == "high z4":
                g = guide_with(per_call(rt("high"), oidn_image))
            else:
                sys.exit(f"guide_inputs: --variants: unknown {name!r} (have: {', '.join(VARIANTS)})")
            out[name] = envelope(g)
    return out


def data_images(folders: list[Path]) -> Iterator[tuple[str, str, int, B.BufferFile, np.ndarray]]:
    for data in folders:
        for scene in load_manifest(data)["scenes"]:
            if not scene.get("reference"):
                continue
            ref = B.read_rgb(data / scene["id"] / REFERENCE)[0]
            for item in scene.get("inputs", []):
                yield (f"{data.name}/{scene['id']} {item['file']}", scene.get("family", ""), item["passes"],
                       B.read_buffers(data / scene["id"] / item["file"]), ref)


def study_images(cache: Path, ref_cache: Path) -> Iterator[tuple[str, str, int, B.BufferFile, np.ndarray]]:
    """bench_guide.py's scene renders (its ``<out>/cache``) against its 1024-pass references."""
    for path in sorted(cache.glob(f"*_{WIDTH}_*x{PHOTONS}_s{SEED}_multi.exr")):
        key, rest = path.name.split(f"_{WIDTH}_", 1)
        passes = int(rest.split("x", 1)[0])
        refs = [ref_path(ref_cache, key, WIDTH, 1024, PHOTONS, s) for s in REF_SEEDS]
        if all(r.exists() for r in refs):
            ref = 0.5 * (B.read_rgb(refs[0])[0] + B.read_rgb(refs[1])[0])
            yield f"{key} N={passes}", "study", passes, B.read_buffers(path), ref


def groups(rows: list[dict]) -> dict[str, list[dict]]:
    out: dict[str, list[dict]] = defaultdict(list)
    for r in rows:
        study = r["family"] == "study"
        out["study" if study else "data"].append(r)
        out[("study" if study else "data") + f" N={r['passes']}"].append(r)
        if not study:
            out[r["family"]].append(r)
    return out


def table(rows: list[dict], names: list[str]) -> list[str]:
    lines = ["| group | images | " + " | ".join(names) + " |", "|---|---:|" + "---:|" * len(names)]
    for group, rs in groups(rows).items():
        cells = []
        for n in names:
            r = [x["variants"][n]["ratio"] for x in rs]
            r8 = [x["variants"][n]["ratio_8x8"] for x in rs]
            gm = math.exp(sum(map(math.log, r)) / len(r))
            gm8 = math.exp(sum(map(math.log, r8)) / len(r8))
            cells.append(f"{gm:.3f} / {gm8:.3f} / {sum(v > 1 for v in r)}")
        lines.append(f"| {group} | {len(rs)} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, action="append", default=[], help="a generated data set (repeatable)")
    ap.add_argument("--study", type=Path, default=None, help="bench_guide.py's render cache (<out>/cache)")
    ap.add_argument("--ref-cache", type=Path, default=ROOT / "docs" / "cache",
                    help="its references (default docs/cache)")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated (default all: {', '.join(VARIANTS)})")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "guide_inputs")
    args = ap.parse_args()
    names = tuple(v.strip() for v in args.variants.split(",") if v.strip())
    unknown = [n for n in names if n not in VARIANTS and n.split(" ")[0] not in ("pre", "swap", "lowmix", "terms")]
    if unknown:
        sys.exit(f"guide_inputs: --variants: unknown {', '.join(unknown)} (have: {', '.join(VARIANTS)})")
    names = ("shipped",) + tuple(n for n in names if n != "shipped")
    t0 = time.perf_counter()
    net = load_checkpoint(DEFAULT_MODEL).model
    sources = list(data_images(args.data)) + (list(study_images(args.study, args.ref_cache)) if args.study else [])
    if not sources:
        sys.exit("guide_inputs: no images (give --data or --study)")
    rows = []
    args.out.mkdir(parents=True, exist_ok=True)
    for name, family, passes, buf, ref in sources:
        images = variants(buf, net, names)
        row = score_image(buf, ref, {k: (lambda _b, v=v: v) for k, v in images.items()})
        rows.append({"image": name, "family": family, "passes": passes, **row})
        print(name + ": " + ", ".join(f"{k} {v['ratio']:.3f}/{v['ratio_8x8']:.3f}"
                                      for k, v in row["variants"].items()), flush=True)
        write_json(args.out / "guide_inputs.json", {"rows": rows})
    lines = ["# What OIDN is given for the envelope's guide (issue 12)", "",
             f"`{' '.join(sys.argv)}`, {len(rows)} images, {(time.perf_counter() - t0) / 60:.1f} min. "
             "Cells: geometric mean of relMSE / 8x8-block relMSE over each image's best single input, "
             "and the number of images worse than it.", "", *table(rows, list(names))]
    write_text(args.out / "guide_inputs.md", "\n".join(lines) + "\n")
    print(f"wrote {args.out / 'guide_inputs.md'}")


if __name__ == "__main__":
    main()
