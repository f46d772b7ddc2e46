"""Reconstruction ablation at equal passes (issue 12): what the denoiser guide, its
tolerance, the anchor and the trained network each bring, against the best single input.

    .venv/bin/python benchmarks/bench_guide.py --scenes ../shared/scenes \
        [--data data/v2_cpu] [--model NAME=CKPT ...] [--passes 16,64,256] [--out benchmarks/results/guide]

Renders: the three literature scenes and the two built-in caustic scenes at width 128,
65536 photons per pass, five-chain SPPM at each N (seed 7; cached in ``<out>/cache``),
scored against the equal-time study's references (single-bandwidth SPPM, 1024 passes,
two seeds, cached in ``--ref-cache``, rendered there when missing). ``--data``: also every
validation image of a generated data set (never trained on) against its own reference;
``--split train`` / ``all`` scores its training images too, which are held out for whatever
has no trained weights (the envelope, OIDN, the guide alone), not for a trained network.

Variants (each is what ``ppmrecon.model.infer.denoise`` writes for that setting):
``kpn`` = a checkpoint as shipped (``--model``, repeatable); ``+guide`` = the same with the
guide forced on; ``NAME weights`` / ``NAME envelope`` = the same in the other guide mode (a chooser
checkpoint: ``NAME envelope``, the envelope without its chooser); ``NAME chooser`` = a
checkpoint that carries a chooser but does not run it by default, with it; ``NAME cross=C`` = an
envelope checkpoint with the guide's cross rule at C (0 = off); ``NAME y_spike=R`` = the same with
~y left out of the range where it is a lone spike R x above the ~z^j (0 = off); ``NAME anchor_window=W``
= the same with the anchor's noise correlation estimated over a W px window (0 = independent pixels);
``NAME confirm=C`` = the same with the guard's confirmation of ~y by a settled ~z^j at factor C (0 = off);
``NAME peers=M`` = the same with the guard's speckle-field test: no outlier where M unsettled
pixels of its 5 x 5 window are within 4x of it (0 = off);
``NAME anchor_noise=K`` = the same with the anchor acting on gaps beyond K x its noise (shipped 1);
``NAME anchor_settled=R`` = the same with the anchor acting only where its low-pass is settled (sd < R x level;
0 = off);
``NAME source=J`` = the same with OIDN's main input ~z^J (shipped 4); ``NAME anchor_source=M`` = the same
anchored to ~z^M; ``NAME y_weight=F`` = the same with OIDN(~y)'s weight F in the guide (0 = off);
``guide b=B`` = the guide alone (an untrained guided model: zero head) with tolerance beta
B and the default cross rule (2); ``guide cross=C`` = the same at beta 0.03 with cross C
(0 = off); ``guide K=K`` = the same with a K x K window (default
5); ``guide source=zJ`` = the same with OIDN's image of ~z^J as the guide (default ~z^4);
``noanchor`` = without the guard's low-frequency anchor; ``envelope k=K`` = the guide
itself held inside the range of each pixel's five estimates (``GuideConfig.mode =
"envelope"``, no network), its anchor acting where the gap to ~z^3's low-pass exceeds K x
that low-pass's variance (1e-6: the plain anchor; default K = 1), ``envelope anchor=zM``
the same anchored to ~z^M, ``envelope noanchor`` without it; ``envelope y=F`` the envelope of the guide
mixed with OIDN(~y) by inverse local variances, ~y's times F (``GuideConfig.y_weight``; F = 0:
``envelope k=1``), ``... noanchor`` without the anchor;
``oidn(z4)`` / ``oidn(y)`` = OIDN itself on ~z^4 / on ~y (not consistent; for scale).
Per image: relMSE and 8x8-block relMSE over the best single input's; per variant the
geometric mean, the worst, and how many images are worse than their best input.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_quality import LITERATURE, oidn  # noqa: E402
from deep_reference import DEEP, DEEP_HALVES, DEEP_RECORD  # noqa: E402
from study import BUILTIN, references, renderer  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.metrics import deciding_pixels, relmse, relmse_blocks, relmse_map, relmse_scaled  # noqa: E402

WIDTH, PHOTONS, REF_PASSES, SEED = 128, 65536, 1024, 7
BETAS = (0.01, 0.03, 0.1)
CROSS = (0.0, 4.0)          # the default, 2, is every 'guide b=...' row
SOURCES = (1, 2, 3)         # the estimate OIDN denoises for the guide (default ~z^4)
WINDOWS = (3, 7, 9)         # the combiner's window K for the guide alone (the default, 5, is 'guide b=0.03')
#: the envelope's anchor_noise k (1e-6: the plain anchor wherever there is any gap)
ENVELOPE_NOISE = (1e-6, 1.0, 4.0)
ENVELOPE_ANCHORS = (2, 4)   # the anchor's estimate ~z^m (default 3)
ENVELOPE_Y_WEIGHTS = (0.0, 1.0, 2.0, 4.0)   # weight of OIDN's image of ~y in the envelope's guide
Y_SPIKES = (0.0, 4.0, 8.0, 16.0)   # the envelope's lone-~y-spike factor (GuideConfig.y_spike; 0 = off)
#: the window (px) over which the anchor's noise correlation is estimated (GuideConfig.anchor_window; 0 = off)
ANCHOR_WINDOWS = (0.0, 1.5, 3.0, 5.0)
GUARD_PEERS = (0.0, 1.0, 2.0, 3.0, 4.0)   # the guard's speckle-field test (GuardConfig.peers; 0 = off)
GUARD_CONFIRMS = (0.0, 2.0, 4.0)   # the guard's confirmation of ~y by a settled ~z^j (GuardConfig.confirm; 0 = off)
#: the anchor's noise multiple k (GuideConfig.anchor_noise; larger: the anchor acts on larger gaps only)
ANCHOR_NOISES = (0.5, 1.0, 2.0, 4.0, 8.0)
#: the anchor only where its low-pass's standard deviation is below r0 x its level (GuideConfig.anchor_settled; 0 = off)
ANCHOR_SETTLED = (0.0, 0.5, 0.7, 1.0)


def rendered(loaded, key: str, passes: int, cache: Path) -> B.BufferFile:
    path = cache / f"{key}_{WIDTH}_{passes}x{PHOTONS}_s{SEED}_multi.exr"
    if not path.exists():
        t = time.perf_counter()
        res = renderer(loaded, key, "multi", "sppm", PHOTONS, SEED, passes=passes).run()
        B.write_buffers(path, res.buffer_file())
        print(f"{key}: N = {passes} in {time.perf_counter() - t:.0f}s", flush=True)
    return B.read_buffers(path)


def variants(models: dict) -> dict:
    """name -> function(buffer file) -> (H, W, 3)."""
    from ppmrecon.model.checkpoint import load_checkpoint
    from ppmrecon.model.features import FeatureConfig
    from ppmrecon.model.guard import DEFAULT_ON
    from ppmrecon.model.guide import DEFAULT_GUIDE, ENVELOPE_MODES, OIDN_QUALITIES, GuideConfig
    from ppmrecon.model.infer import denoise
    from ppmrecon.model.kpn import Preset, build, load_preset

    out = {"oidn(y)": lambda buf: oidn(buf, 0), "oidn(z4)": lambda buf: oidn(buf, 4)}
    for name, path in models.items():
        net = load_checkpoint(path).model
        guard = net.guard if net.guard.enabled else DEFAULT_ON
        out[name] = lambda buf, net=net, guard=guard: denoise(buf, net, guard=guard).rgb
        if not net.guide.enabled:
            out[f"{name} +guide"] = lambda buf, net=net, guard=guard: denoise(buf, net, guard=guard,
                                                                               guide=DEFAULT_GUIDE).rgb
        else:
            if not net.features.guide:   # a model that reads the guide cannot run without it
                out[f"{name} -guide"] = lambda buf, net=net, guard=guard: denoise(buf, net, guard=guard,
                                                                                   guide=GuideConfig()).rgb
            other = "weights" if net.guide.mode == "envelope" else "envelope"
            g = net.guide.in_mode(other)
            out[f"{name} {other}"] = lambda buf, net=net, guard=guard, g=g: denoise(buf, net, guard=guard, guide=g).rgb
            if net.chooser is not None and net.guide.mode != "chooser":
                g = net.guide.in_mode("chooser")
                out[f"{name} chooser"] = lambda buf, net=net, guard=guard, g=g: denoise(
                    buf, net, guard=guard, guide=g).rgb
            # one checkpoint setting changed at a time: (label, config, key, values, when)
            sweeps = (("y_spike", "guide", "y_spike", Y_SPIKES, net.guide.mode in ENVELOPE_MODES),
                      ("confirm", "guard", "confirm", GUARD_CONFIRMS, net.guide.mode in ENVELOPE_MODES),
                      ("peers", "guard", "peers", GUARD_PEERS, net.guide.mode in ENVELOPE_MODES),
                      ("anchor_window", "guide", "anchor_window", ANCHOR_WINDOWS, net.guide.mode in ENVELOPE_MODES),
                      ("anchor_noise", "guide", "anchor_noise", ANCHOR_NOISES, net.guide.mode in ENVELOPE_MODES),
                      ("anchor_settled", "guide", "anchor_settled", ANCHOR_SETTLED, net.guide.mode in ENVELOPE_MODES),
                      ("source", "guide", "source", (2, 3, 4), net.guide.mode in ENVELOPE_MODES),
                      ("anchor_source", "guide", "anchor_source", (1, 2, 3, 4), net.guide.mode in ENVELOPE_MODES),
                      ("y_weight", "guide", "y_weight", (0.0, 1.0, 2.0, 4.0),
                       net.guide.mode in ENVELOPE_MODES and bool(net.guide.source)),
                      ("cross", "guide", "cross", (0.0, 2.0, 4.0),
                       net.guide.mode in ENVELOPE_MODES and bool(net.guide.source)),
                      ("oidn", "guide", "quality", OIDN_QUALITIES, True))
            for label, which, key, values, when in sweeps:
                base = net.guide if which == "guide" else guard
                for value in values if when else ():
                    if value == getattr(base, key):
                        continue
                    try:
                        cfg = replace(base, **{key: value})
                    except ValueError:        # a value the rest of the settings rule out (cascade: anchor_source 1)
                        continue
                    g, gd = (cfg, guard) if which == "guide" else (net.guide, cfg)
                    shown = value if isinstance(value, str) else f"{value:g}"
                    out[f"{name} {label}={shown}"] = lambda buf, net=net, g=g, gd=gd: denoise(
                        buf, net, guard=gd, guide=g).rgb
        out[f"{name} noanchor"] = lambda buf, net=net, guard=guard: denoise(buf, net, guard=replace(guard, anchor=0)).rgb
    alone = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, DEFAULT_GUIDE)
    for beta in BETAS:
        g = replace(DEFAULT_GUIDE, beta=beta)
        out[f"guide b={beta:g}"] = lambda buf, g=g: denoise(buf, alone, guide=g).rgb
    out["guide b=0.03 noanchor"] = lambda buf: denoise(buf, alone, guard=replace(DEFAULT_ON, anchor=0)).rgb
    for cross in CROSS:
        g = replace(DEFAULT_GUIDE, cross=cross)
        out[f"guide cross={cross:g}"] = lambda buf, g=g: denoise(buf, alone, guide=g).rgb
    for source in SOURCES:
        g = replace(DEFAULT_GUIDE, source=source)
        out[f"guide source=z{source}"] = lambda buf, g=g: denoise(buf, alone, guide=g).rgb
    # the guide's envelope: OIDN's image held in the range of the five estimates, no network
    for k in ENVELOPE_NOISE:
        g = replace(DEFAULT_GUIDE, mode="envelope", anchor_noise=k)
        out[f"envelope k={k:g}"] = lambda buf, g=g: denoise(buf, alone, guide=g).rgb
    for m in ENVELOPE_ANCHORS:
        g = replace(DEFAULT_GUIDE, mode="envelope", anchor_source=m)
        out[f"envelope anchor=z{m}"] = lambda buf, g=g: denoise(buf, alone, guide=g).rgb
    for w in ENVELOPE_Y_WEIGHTS:
        g = replace(DEFAULT_GUIDE, mode="envelope", y_weight=w)
        out[f"envelope y={w:g}"] = lambda buf, g=g: denoise(buf, alone, guide=g).rgb
        out[f"envelope y={w:g} noanchor"] = lambda buf, g=g: denoise(buf, alone, guard=replace(DEFAULT_ON, anchor=0),
                                                                     guide=g).rgb
    g = replace(DEFAULT_GUIDE, mode="envelope")
    out["envelope noanchor"] = lambda buf, g=g: denoise(buf, alone, guard=replace(DEFAULT_ON, anchor=0), guide=g).rgb
    base = load_preset("tiny")
    for kw in WINDOWS:
        pre = Preset(f"tiny_k{kw}", base.layers, base.filters, base.kernel, kw, base.final_kernel)
        m = build(pre, FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, DEFAULT_GUIDE)
        out[f"guide K={kw}"] = lambda buf, m=m: denoise(buf, m).rgb
    return out


def reference_error(half_a: np.ndarray, half_b: np.ndarray) -> dict:
    """The reference's own error, estimated from its two independent halves a, b: the
    error of their mean R has expected square |a - b|^2 / 4 per pixel, so its relMSE (on
    R's denominators, as every score here) is that of ``R + (a - b) / 2`` against R; the
    same for 8x8 block means (linear). Every ratio of this benchmark includes it: where it
    is a large share of the best input's relMSE, a ratio cannot show much below 1."""
    half_a, half_b = np.asarray(half_a, np.float64), np.asarray(half_b, np.float64)
    ref = 0.5 * (half_a + half_b)
    off = ref + 0.5 * (half_a - half_b)
    return {"relmse": relmse(off, ref), "relmse_8x8": relmse_blocks(off, ref)}


def score_image(buf: B.BufferFile, ref: np.ndarray, fns: dict, ref_error: dict | None = None) -> dict:
    singles = [relmse(e, ref) for e in buf.estimates]
    singles_8 = [relmse_blocks(e, ref) for e in buf.estimates]
    best, best8 = min(singles), min(singles_8)
    best_map = relmse_map(buf.estimates[int(np.argmin(singles))], ref)
    best_scaled = min(relmse_scaled(e, ref) for e in buf.estimates)
    row = {"best_single": best, "best_single_8x8": best8, "best_single_scaled": best_scaled,
           "best_single_name": B.ESTIMATES[int(np.argmin(singles))], "variants": {}}
    if ref_error is not None:
        row["reference_error"] = ref_error
        row["reference_share"] = ref_error["relmse"] / best
        row["reference_share_8x8"] = ref_error["relmse_8x8"] / best8
    for name, fn in fns.items():
        t = time.perf_counter()
        img = fn(buf)
        e, e8 = relmse(img, ref), relmse_blocks(img, ref)
        es = relmse_scaled(img, ref)
        row["variants"][name] = {"relmse": e, "relmse_8x8": e8, "ratio": e / best, "ratio_8x8": e8 / best8,
                                 "relmse_scaled": es, "ratio_scaled": es / best_scaled,
                                 "seconds": time.perf_counter() - t,
                                 "deciding_pixels": deciding_pixels(relmse_map(img, ref) - best_map)}
        if ref_error is not None:
            row["variants"][name]["ratio_net"] = net_ratio(e, best, ref_error["relmse"])
    return row


#: The most pixels :func:`deciding_pixels` may count for a worse image to be called
#: decided by a few pixels (of 16384 at 128 x 128: 0.05%).
FEW_PIXELS = 8


#: A ratio net of the reference's error is only given where that error is below this
#: share of the best input's: above it, the difference of two noisy figures decides it.
NET_SHARE_LIMIT = 0.5


def net_ratio(err: float, best: float, ref_err: float) -> float | None:
    """relMSE / best with the reference's own error taken out of both (independent renders:
    E|x - R|^2 = E|x - T|^2 + E|R - T|^2 when R's error has no bias), i.e. an estimate of
    the ratio against the truth; None where the reference error is too large a share of
    the best input's to tell (:data:`NET_SHARE_LIMIT`). A value <= 0 (ours within the
    reference's own noise) is floored at 1e-3."""
    if ref_err >= NET_SHARE_LIMIT * best:
        return None
    return max(err - ref_err, 1e-3 * (best - ref_err)) / (best - ref_err)


def summary(rows: list[dict], names: list[str]) -> list[dict]:
    out = []
    for name in names:
        r = np.array([row["variants"][name]["ratio"] for row in rows])
        b = np.array([row["variants"][name]["ratio_8x8"] for row in rows])
        net = np.array([v for row in rows if (v := row["variants"][name].get("ratio_net")) is not None])
        sc = np.array([row["variants"][name]["ratio_scaled"] for row in rows])
        out.append({"variant": name, "images": len(rows), "geomean": float(np.exp(np.log(r).mean())),
                    "worst": float(r.max()), "geomean_8x8": float(np.exp(np.log(b).mean())),
                    "worst_8x8": float(b.max()), "worse_than_best": int((r > 1).sum()),
                    "at_most_half": int((r <= 0.5).sum()),
                    "worse_few_pixels": int(sum(1 for row in rows if row["variants"][name]["ratio"] > 1
                                                and row["variants"][name].get("deciding_pixels", FEW_PIXELS + 1)
                                                <= FEW_PIXELS)),
                    "block_not_worse": int((b <= 1).sum()),
                    "net_images": len(net), "net_geomean": float(np.exp(np.log(net).mean())) if len(net) else None,
                    "net_at_most_half": int((net <= 0.5).sum()),
                    "scaled_geomean": float(np.exp(np.log(sc).mean())), "scaled_worse": int((sc > 1).sum())})
    return out


def table(summ: list[dict]) -> list[str]:
    lines = ["| variant | images | relMSE / best: geomean | worst | worse than best | "
             f"of them decided by <= {FEW_PIXELS} px | <= 0.5x | "
             "8x8 / best: geomean | worst | 8x8 <= best | net of reference error: images | geomean | <= 0.5x | "
             "scaled: geomean | worse |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in summ:
        net = f"{s['net_geomean']:.3f}" if s.get("net_geomean") is not None else "-"
        lines.append(f"| {s['variant']} | {s['images']} | {s['geomean']:.3f} | {s['worst']:.2f} | "
                     f"{s['worse_than_best']} | {s.get('worse_few_pixels', '-')} | {s['at_most_half']} | {s['geomean_8x8']:.3f} | "
                     f"{s['worst_8x8']:.2f} | {s['block_not_worse']} | {s.get('net_images', 0)} | {net} | "
                     f"{s.get('net_at_most_half', 0)} | {s.get('scaled_geomean', math.nan):.3f} | "
                     f"{s.get('scaled_worse', '-')} |")
    return lines


def per_image_table(rows: list[dict], names: list[str]) -> list[str]:
    lines = ["| image | best input | reference error / best | " + " | ".join(names) + " |",
             "|---|---|---|" + "---|" * len(names)]
    for row in rows:
        cells = [f"{row['variants'][n]['ratio']:.2f} / {row['variants'][n]['ratio_8x8']:.2f}" for n in names]
        share = (f"{row['reference_share']:.2f} / {row['reference_share_8x8']:.2f}" if "reference_share" in row else "-")
        lines.append(f"| {row['image']} | {row['best_single_name']} {row['best_single']:.3g} | {share} | "
                     + " | ".join(cells) + " |")
    return lines


def family_table(rows: list[dict], names: list[str]) -> list[str]:
    """Per family and N: geometric means of relMSE / 8x8 ratio to the best input, and the
    reference's own error as a share of the best input's (median)."""
    groups: dict[tuple[str, int], list[dict]] = {}
    for row in rows:
        groups.setdefault((row["family"], row["passes"]), []).append(row)
    lines = ["| family | N | images | reference error / best (median) | " + " | ".join(names) + " |",
             "|---|---:|---:|---|" + "---|" * len(names)]
    for (family, n), members in sorted(groups.items()):
        cells = []
        for name in names:
            r = np.array([m["variants"][name]["ratio"] for m in members])
            b = np.array([m["variants"][name]["ratio_8x8"] for m in members])
            cells.append(f"{math.exp(np.log(r).mean()):.2f} / {math.exp(np.log(b).mean()):.2f}")
        shares = [m["reference_share"] for m in members if "reference_share" in m]
        shares8 = [m["reference_share_8x8"] for m in members if "reference_share_8x8" in m]
        share = f"{np.median(shares):.2f} / {np.median(shares8):.2f}" if shares else "-"
        lines.append(f"| {family} | {n} | {len(members)} | {share} | " + " | ".join(cells) + " |")
    return lines


def combined_variants(models: dict, chosen: str | None) -> dict:
    """The requested variants ``NAME key=value [key=value ...]`` that no sweep makes: checkpoint
    NAME as shipped with several guide (:class:`GuideConfig`) or guard (:class:`GuardConfig`)
    settings changed together, e.g. ``shipped anchor_source=4 y_weight=1``. A key of neither
    config, or a value it refuses, stops the benchmark with one line."""
    from dataclasses import fields

    from ppmrecon.model.checkpoint import load_checkpoint
    from ppmrecon.model.guard import DEFAULT_ON
    from ppmrecon.model.infer import denoise

    out = {}
    for name in [v.strip() for v in (chosen or "").split(",")]:
        head, *pairs = name.split()
        if head not in models or not pairs or not all("=" in p for p in pairs):
            continue
        net = load_checkpoint(models[head]).model
        guide, guard = net.guide, net.guard if net.guard.enabled else DEFAULT_ON
        for key, value in (p.split("=", 1) for p in pairs):
            which = "guide" if key in {f.name for f in fields(guide)} else "guard" if key in {
                f.name for f in fields(guard)} else None
            if which is None:
                sys.exit(f"bench_guide: --variants '{name}': '{key}' is no guide or guard setting")
            base = guide if which == "guide" else guard
            try:
                cfg = replace(base, **{key: _setting(getattr(base, key), value)})
            except (TypeError, ValueError) as exc:
                sys.exit(f"bench_guide: --variants '{name}': {exc}")
            guide, guard = (cfg, guard) if which == "guide" else (guide, cfg)
        out[name] = lambda buf, net=net, g=guide, gd=guard: denoise(buf, net, guard=gd, guide=g).rgb
    return out


def _setting(current: object, text: str) -> object:
    """``text`` read as the type of the setting's ``current`` value (true/false/1/0 for a
    switch: ``bool("0")`` would be True)."""
    if isinstance(current, bool):
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"a switch is true or false, got {text!r}")
        return text.lower() in ("true", "1")
    return type(current)(text)


def _data_settings(data: Path) -> str:
    """One line on how a data set's inputs and references were rendered, from its manifest."""
    from ppmrecon.train.datagen import load_manifest, stored_config

    cfg = stored_config(load_manifest(data))
    res = "x".join(str(r) for r in cfg["resolution"])
    return (f"`{data}`: {res}, inputs of {cfg['photons']} photons/pass at N = "
            f"{', '.join(str(n) for n in cfg['input_passes'])}, references of {cfg['reference_passes']} passes x "
            f"{cfg.get('reference_photons') or cfg['photons']} photons x 2 seeds")


def _deep_settings(data: list[Path], images: int) -> str:
    """One line on the deep references an ``--deep-references`` report scored against (the
    data sets' own references above are not used then), from their :data:`DEEP_RECORD`."""
    import json

    found = sorted(p for d in data for p in d.glob(f"*/{DEEP_RECORD}"))
    kinds = sorted({(r["passes_per_half"], r["photons"]) for r in (json.loads(p.read_text()) for p in found)})
    what = ", ".join(f"{n} passes x {j} photons" for n, j in kinds) or "none found"
    return (f"Scored against each scene's deep reference instead (`benchmarks/deep_reference.py`: two "
            f"independent single-bandwidth SPPM halves of {what}), on the {len(found)} scenes that have one "
            f"({images} images); the net ratios take the deep halves' own error. ")


def _subset(items: dict, chosen: str | None, option: str) -> dict:
    """The entries of ``items`` named in the comma-separated ``chosen`` (all if None);
    an unknown name stops the benchmark with one line."""
    if not chosen:
        return items
    wanted = [v.strip() for v in chosen.split(",")]
    unknown = [v for v in wanted if v not in items]
    if unknown:
        sys.exit(f"bench_guide: {option}: unknown {', '.join(unknown)} (have: {', '.join(items)})")
    return {v: items[v] for v in wanted}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=Path, required=True, help="folder of the literature scenes (../shared/scenes)")
    ap.add_argument("--data", type=Path, action="append", default=[],
                    help="a generated data set: score its validation images too (repeatable: several data sets, "
                         "their images named <folder>/<scene> ...)")
    ap.add_argument("--split", choices=("val", "train", "all"), default="val",
                    help="which images of --data (default val; 'train' and 'all' are held out only for "
                         "what has no trained weights: the envelope, OIDN, the guide alone)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=CKPT",
                    help="a checkpoint to score (repeat; default: the shipped default as 'default')")
    ap.add_argument("--passes", default="16,64,256", help="pass counts of the scene renders")
    ap.add_argument("--ref-cache", type=Path, default=ROOT / "docs" / "cache",
                    help="the equal-time study's reference cache (default: docs/cache)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "guide")
    ap.add_argument("--ref-passes", type=int, default=REF_PASSES,
                    help=f"passes of each scene reference (default {REF_PASSES}; longer ones for N = 1024)")
    ap.add_argument("--only", default=None, help="comma-separated scene keys to render (default: all five)")
    ap.add_argument("--deep-references", action="store_true",
                    help="score --data images against the scene's deep_reference.exr "
                         "(benchmarks/deep_reference.py) instead of its own reference; scenes without one are left out")
    ap.add_argument("--data-only", action="store_true",
                    help="score the --data images only (no scene renders or references)")
    ap.add_argument("--variants", default=None,
                    help="comma-separated variant names to score (default: all; e.g. 'shipped,shipped oidn=fast')")
    args = ap.parse_args()
    models = dict(m.split("=", 1) for m in args.model) or {"default": ROOT / "ppmrecon/data/models/default.pt"}
    (args.out / "cache").mkdir(parents=True, exist_ok=True)
    args.ref_cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    fns = variants(models)
    fns.update(combined_variants(models, args.variants))
    fns = _subset(fns, args.variants, "--variants")
    names = list(fns)
    scenes = {k: args.scenes / v for k, v in LITERATURE.items()}
    scenes.update({k: k for k in BUILTIN})
    scenes = {} if args.data_only else _subset(scenes, args.only, "--only")
    if args.data_only and not args.data:
        sys.exit("bench_guide: --data-only needs at least one --data folder")
    refs = references(scenes, WIDTH, PHOTONS, args.ref_passes, args.ref_cache)
    scene_rows = []
    for key, (loaded, pair) in refs.items():
        ref = 0.5 * (pair[0] + pair[1])
        ref_error = reference_error(pair[0], pair[1])
        for n in (int(p) for p in args.passes.split(",")):
            row = score_image(rendered(loaded, key, n, args.out / "cache"), ref, fns, ref_error)
            scene_rows.append({"image": f"{key} N={n}", "scene": key, "passes": n, **row})
            print(f"{key} N={n}: " + ", ".join(f"{k} {v['ratio']:.2f}" for k, v in row["variants"].items()), flush=True)
    val_rows = []
    from ppmrecon.train.datagen import REFERENCE, load_manifest

    for data in args.data:
        prefix = f"{data.name}/" if len(args.data) > 1 else ""
        for scene in load_manifest(data)["scenes"]:
            if args.split != "all" and scene.get("split") != args.split or not scene.get("reference"):
                continue
            if args.deep_references:
                if not (data / scene["id"] / DEEP).exists():
                    continue
                ref, _ = B.read_rgb(data / scene["id"] / DEEP)
                halves = [data / scene["id"] / h for h in DEEP_HALVES]
            else:
                ref, _ = B.read_rgb(data / scene["id"] / REFERENCE)
                halves = [data / scene["id"] / h["file"] for h in scene.get("references", [])]
            ref_error = (reference_error(*(B.read_rgb(h)[0] for h in halves))
                         if len(halves) == 2 and all(h.exists() for h in halves) else None)
            for item in scene.get("inputs", []):
                buf = B.read_buffers(data / scene["id"] / item["file"])
                row = score_image(buf, ref, fns, ref_error)
                val_rows.append({"image": f"{prefix}{scene['id']} {item['file']}", "scene": prefix + scene["id"],
                                 "family": scene.get("family", scene["id"].split("_", 1)[-1]),
                                 "passes": item["passes"], **row})
    if args.data:
        print(f"validation: {len(val_rows)} images", flush=True)
    report = {"models": {k: str(v) for k, v in models.items()}, "scenes": scene_rows, "validation": val_rows,
              "split": args.split, "data": [str(d) for d in args.data],
              "summary_scenes": summary(scene_rows, names) if scene_rows else [],
              "summary_validation": summary(val_rows, names) if val_rows else [],
              "minutes": (time.perf_counter() - t0) / 60}
    write_json(args.out / "guide.json", report)
    cmd = "benchmarks/bench_guide.py --scenes ../shared/scenes" + "".join(f" --data {d}" for d in args.data) \
        + (f" --split {args.split}" if args.split != "val" else "") \
        + "".join(f" --model {k}={v}" for k, v in models.items()) \
        + (f" --variants '{args.variants}'" if args.variants else "") \
        + (f" --passes {args.passes}" if args.passes != "16,64,256" else "") \
        + (f" --ref-passes {args.ref_passes}" if args.ref_passes != REF_PASSES else "") \
        + (f" --only {args.only}" if args.only else "") + (" --data-only" if args.data_only else "") \
        + (" --deep-references" if args.deep_references else "")
    if scene_rows:
        renders = (f"Width {WIDTH}, {PHOTONS} photons/pass, five-chain SPPM, seed {SEED}; references: "
                   f"single-bandwidth SPPM, {args.ref_passes} passes x 2 seeds "
                   "(their own noise is in every figure: at N = 256 the ratios are compressed towards 1). ")
    else:  # --data-only: the renders are the data sets' own, as their manifests state
        renders = "Renders and references: " + "; ".join(_data_settings(d) for d in args.data) + \
            " (the references' own noise is in every figure). "
        if args.deep_references:
            renders += _deep_settings(args.data, len(val_rows))
    lines = ["# Reconstruction ablation at equal passes (issue 12)", "",
             f"Generated by `{cmd}` in {report['minutes']:.1f} min. " + renders +
             "Ratios: relMSE (and 8x8-block relMSE) over the best single input of the same render. "
             "Issue 12 targets: <= 0.5x, and 8x8 <= 1x, on every image. "
             "Net of reference error: (ours - e) / (best - e) with e the reference's own relMSE from its two halves "
             f"(|a - b|^2 / 4; an estimate of the ratio against the truth, blind to the reference's bias), on the "
             f"images where e < {NET_SHARE_LIMIT:g} x the best input's. Scaled: the same ratio with both images "
             "divided by the reference's mean (`metrics.relmse_scaled`: plain relMSE's 0.01 is absolute, so on a "
             "dark scene it scores a few bright pixels alone and on a bright one a black pixel decides).", "",
             *(["## Literature scenes (never trained on) and built-in caustic scenes", "",
                *table(report["summary_scenes"])] if scene_rows else [])]
    if val_rows:
        which = {"val": "Validation images", "train": "Training-split images", "all": "All images"}[args.split]
        lines += ["", f"## {which} of {', '.join(f'`{d}`' for d in args.data)} (every N)", "",
                  *table(report["summary_validation"])]
        # the trained models and the guide alone, per family and N (every variant would not fit a page)
        chosen = [n for n in names if n in models or n in ("oidn(z4)", "guide b=0.03", "envelope k=1")]
        lines += ["", f"### Per family and N ({which.lower()})", "",
                  "Geometric means of relMSE / 8x8-block relMSE over the best input. Reference error: the "
                  "reference's own relMSE estimated from its two independent halves (|a - b|^2 / 4), as a share "
                  "of the best input's; near 1 a ratio cannot fall much below 1.", "",
                  *family_table(val_rows, chosen or names[:3])]
    if scene_rows:
        lines += ["", "## Per image (relMSE / 8x8 ratio to the best input)", "",
                  "Reference error / best: the reference's own relMSE (and 8x8-block relMSE), estimated from its "
                  "two seeds as |a - b|^2 / 4, over the best input's; it is part of every figure in the row.", "",
                  *per_image_table(scene_rows, names)]
    write_text(args.out / "guide.md", "\n".join(lines) + "\n")
    print(f"wrote {args.out / 'guide.md'}")


if __name__ == "__main__":
    main()
