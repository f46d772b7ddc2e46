"""A learned choice among consistent candidates on top of the shipped envelope (issue 12 study).

    .venv/bin/python benchmarks/bench_refine.py --data data/v3_cpu [--folds 4] [--steps 1500] \
        [--out benchmarks/results/refine]

Question: can a small network, trained on generated scenes, choose per pixel among images
that are each held inside the five estimates' range (so that any convex combination of
them is consistent, :func:`ppmrecon.model.guide.envelope`), and beat the shipped envelope
on scenes it never saw? Candidates, all clamped per channel into ``[min_k X_k, max_k X_k]``:

    the shipped envelope e; the shipped guide g (no anchor); OIDN's image of the despiked ~z^4;
    OIDN's image of ~y; ~z^1 .. ~z^4.

The network is the shipped chooser (:mod:`ppmrecon.model.chooser`: three 3 x 3
convolutions of ``--width`` channels, softmax weights over the candidates with a prior on
e), trained as ``ppmrecon-train chooser`` trains it (:mod:`ppmrecon.train.chooser`, the
config ``--config``, default the shipped ``cpu``; loss per 64 x 64 crop: log relMSE(out) -
log relMSE(e) + lowfreq x the same for 8x8-block means).

Every figure is held out: the scenes are split into ``--folds`` folds by scene index and
each fold is scored by the network trained on the other folds. The envelope has no trained
weights, so its figures over the same images are held out too; it and OIDN's image of the
despiked ~z^4 held in the band are the baselines. Ratios are to the best single input of
the same image (geometric means; SPEC section 7 relMSE).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon.fileio import write_json, write_text  # noqa: E402

BASELINES = ("envelope", "oidn(z4)")
NAMES = ("chooser", *BASELINES)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="a generated data set (ppmrecon-train generate)")
    ap.add_argument("--model", type=Path, default=ROOT / "ppmrecon/data/models/default.pt",
                    help="the checkpoint whose guard and guide make the envelope (default: the shipped one)")
    ap.add_argument("--config", default="cpu", help="chooser training config: a shipped name or a JSON file")
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--width", type=int, default=None, help="the chooser's width (default: the config's)")
    ap.add_argument("--layers", type=int, default=None, help="the chooser's hidden layers (default: the config's)")
    ap.add_argument("--lam", type=float, default=None, help="weight of the 8x8-block term (default: the config's)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "refine")
    args = ap.parse_args()
    from ppmrecon.model.checkpoint import load_checkpoint
    from ppmrecon.train.chooser import ChooserTrainConfig, evaluate, fit, prepare, summary
    from ppmrecon.train.cli import builtin_configs

    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = ChooserTrainConfig.load(builtin_configs("chooser").get(args.config, args.config))
    cfg = replace(cfg, steps=args.steps, width=args.width or cfg.width, layers=args.layers or cfg.layers,
                  lowfreq=cfg.lowfreq if args.lam is None else args.lam)
    t0 = time.perf_counter()
    items = prepare(args.data, load_checkpoint(args.model).model, warn=print)
    scene_of = {it.name: it.name.split("/")[0] for it in items}
    index = {s: n for n, s in enumerate(sorted(set(scene_of.values())))}
    print(f"{len(items)} images of {len(index)} scenes prepared in {time.perf_counter() - t0:.0f}s", flush=True)
    rows = []
    for fold in range(args.folds):
        held = [it for it in items if index[scene_of[it.name]] % args.folds == fold]
        net, _ = fit([it for it in items if index[scene_of[it.name]] % args.folds != fold], replace(cfg, seed=fold))
        rows += evaluate(net, held, BASELINES)
        print(f"fold {fold + 1}/{args.folds} done ({time.perf_counter() - t0:.0f}s)", flush=True)
    groups = {"all": rows, "val split": [r for r in rows if r["split"] == "val"],
              **{f"N = {n}": [r for r in rows if r["passes"] == n] for n in sorted({r["passes"] for r in rows})},
              **{f"family {f}": [r for r in rows if r["family"] == f] for f in sorted({r["family"] for r in rows})}}
    summaries = {g: summary(rs, NAMES) for g, rs in groups.items() if rs}
    minutes = (time.perf_counter() - t0) / 60
    write_json(args.out / "refine.json", {"args": {k: str(v) for k, v in vars(args).items()}, "config": vars(cfg),
                                          "rows": rows, "summary": summaries, "minutes": minutes})
    cmd = (f"benchmarks/bench_refine.py --data {args.data} --config {args.config} --folds {args.folds} "
           f"--steps {args.steps}" + (f" --width {args.width}" if args.width else "")
           + (f" --layers {args.layers}" if args.layers else "")
           + (f" --lam {args.lam:g}" if args.lam is not None else ""))
    lines = ["# A learned choice among consistent candidates (issue 12)", "",
             f"Generated by `{cmd}` in {minutes:.1f} min on {torch.get_num_threads()} threads (chooser width "
             f"{cfg.width}, {cfg.layers} layers, {cfg.steps} steps, 8x8 weight {cfg.lowfreq:g}). "
             f"{len(rows)} images of {len(index)} scenes; every figure held out ({args.folds}-fold by scene). "
             "Ratios: relMSE and 8x8-block relMSE over the best single input of the same image (geometric "
             "means). *worse*: images above their best input; *8x8 ok*: images whose 8x8 ratio is <= 1. "
             "`oidn(z4)`: OIDN's image of the guarded, despiked ~z^4 held in the band (the guide without ~y "
             "or the anchor).", "",
             "| images | n | " + " | ".join(f"{n}: ratio (worst, worse) / 8x8 (ok)" for n in NAMES) + " |",
             "|---|---:|" + "---|" * len(NAMES)]
    for g, per in summaries.items():
        cells = [f"{s['ratio']:.3f} ({s['worst']:.2f}, {s['worse']}) / {s['ratio_8x8']:.2f} ({s['blocks_ok']})"
                 for s in (per[n] for n in NAMES)]
        lines.append(f"| {g} | {per['images']} | " + " | ".join(cells) + " |")
    write_text(args.out / "refine.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
