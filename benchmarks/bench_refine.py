"""A learned choice among consistent candidates on top of the shipped envelope (issue 12 study).

    .venv/bin/python benchmarks/bench_refine.py --data data/v3_cpu [--folds 4] [--steps 1500] \
        [--out benchmarks/results/refine]

Question: can a small network, trained on generated scenes, choose per pixel among images
that are each held inside the five estimates' range (so that any convex combination of
them is consistent, :func:`ppmrecon.model.guide.envelope`), and beat the shipped envelope
on scenes it never saw? Candidates, all clamped per channel into ``[min_k X_k, max_k X_k]``:

    the shipped envelope e; the shipped guide g (no anchor); OIDN's image of the despiked ~z^4;
    OIDN's image of ~y; ~z^1 .. ~z^4.

The network (three 3 x 3 convolutions of ``--width`` channels, ReLU, a 1 x 1 head that starts
at zero) reads scale-free features (log1p of every candidate and of ~y over the image's
radiance scale, log1p of each estimate's standard deviation of the mean over the scale,
albedo, normal, the band's width, log2 N / 10) and outputs softmax weights over the
candidates, with a prior logit of 3 on e (an untrained network is ~e). Loss per 64 x 64
crop: log relMSE(out) - log relMSE(e) + ``--lam`` (the same for 8x8-block means).

Every figure is held out: the scenes are split into ``--folds`` folds by scene index and
each fold is scored by the network trained on the other folds. The envelope has no trained
weights, so its figures over the same images are held out too; together with OIDN's image
of ~z^4 (not consistent) they are the baselines. Ratios are to the best single input of
the same image (geometric means; SPEC section 7 relMSE).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.metrics import relmse, relmse_blocks, relmse_map  # noqa: E402

CANDIDATES = ("envelope", "guide", "oidn(z4)", "oidn(y)", "z1", "z2", "z3", "z4")
PRIOR = 3.0        # logit of the envelope at start: softmax weight e^3 / (e^3 + 7) ~ 0.74
CROP, BATCH = 64, 8


def planes_rgb(planes: torch.Tensor) -> torch.Tensor:
    return planes[0, :3]


def prepare(path: Path, ref: np.ndarray, model) -> dict:
    """Candidates, features and scores of one buffer file (the shipped model's guard and guide)."""
    from ppmrecon.model.guard import band_bounds, guard_buffer, image_scale
    from ppmrecon.model.infer import buffer_guide, denoise

    buf = B.read_buffers(path)
    guided = guard_buffer(buf, model.guard)
    est = torch.from_numpy(np.ascontiguousarray(guided.estimates, np.float32)).permute(0, 3, 1, 2)
    scale = float(image_scale(est[None])) or 1.0
    plain = replace(model.guide, cross=0.0, y_weight=0.0)
    g = planes_rgb(buffer_guide(guided, model.guide, model.guard, scale))
    gz = planes_rgb(buffer_guide(guided, plain, model.guard, scale))
    gy = planes_rgb(buffer_guide(guided, replace(plain, source=0), model.guard, scale))
    env = torch.from_numpy(denoise(buf, model).rgb).permute(2, 0, 1)
    lo, hi = band_bounds(est[None, 0], est[None, 1:], 1.0)
    lo, hi = lo[0], hi[0]
    held = [torch.minimum(torch.maximum(c, lo), hi) for c in (env, g, gz, gy)]
    cands = torch.stack(held + list(est[1:]))
    sd = torch.from_numpy(np.ascontiguousarray(guided.variances, np.float32)).clamp(min=0).sqrt()
    passes = float(buf.header.get("ppmrecon.passes", 1))
    feats = torch.cat([torch.log1p(cands.flatten(0, 1) / scale), torch.log1p(est[0] / scale),
                       torch.log1p(sd / scale),
                       torch.from_numpy(np.ascontiguousarray(guided.albedo, np.float32)).permute(2, 0, 1),
                       torch.from_numpy(np.ascontiguousarray(guided.normal, np.float32)).permute(2, 0, 1),
                       torch.log1p((hi - lo) / scale),
                       torch.full((1, *lo.shape[1:]), math.log2(max(passes, 1.0)) / 10)])
    singles = [relmse(x, ref) for x in buf.estimates]
    singles8 = [relmse_blocks(x, ref) for x in buf.estimates]
    return {"feats": feats, "cands": cands, "ref": torch.from_numpy(np.ascontiguousarray(ref, np.float32)).permute(2, 0, 1),
            "best": min(singles), "best8": min(singles8), "passes": int(passes)}


class Chooser(nn.Module):
    """Features -> softmax weights over the candidates -> their convex combination."""

    def __init__(self, channels: int, candidates: int, width: int):
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(channels, width, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(width, width, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(width, width, 3, padding=1), nn.ReLU())
        self.head = nn.Conv2d(width, candidates, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        prior = torch.zeros(1, candidates, 1, 1)
        prior[0, 0] = PRIOR
        self.register_buffer("prior", prior)

    def forward(self, feats: torch.Tensor, cands: torch.Tensor) -> torch.Tensor:
        w = torch.softmax(self.head(self.body(feats)) + self.prior, 1)
        return (w.unsqueeze(2) * cands).sum(1)


def crop_relmse(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """relMSE per image of a (B, 3, H, W) batch, (B,)."""
    return relmse_map(x, ref, channel_axis=1).mean((-1, -2))


def fit(train: list[dict], steps: int, width: int, lam: float, seed: int) -> Chooser:
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = Chooser(train[0]["feats"].shape[0], len(CANDIDATES), width)
    opt = torch.optim.Adam(net.parameters(), lr=2e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    tiny = 1e-12
    for _ in range(steps):
        parts = []
        for _ in range(BATCH):
            it = train[rng.integers(len(train))]
            h, w = it["ref"].shape[1:]
            y0, x0 = rng.integers(0, h - CROP + 1), rng.integers(0, w - CROP + 1)
            box = (..., slice(y0, y0 + CROP), slice(x0, x0 + CROP))
            part = [it["feats"][box], it["cands"][box], it["ref"][box]]
            if rng.random() < 0.5:      # a mirror image (the normal's x stays: a small inconsistency)
                part = [p.flip(-1) for p in part]
            parts.append(part)
        feats, cands, ref = (torch.stack(p) for p in zip(*parts))
        out, env = net(feats, cands), cands[:, 0]
        loss = (torch.log(crop_relmse(out, ref) + tiny) - torch.log(crop_relmse(env, ref) + tiny)).mean()
        if lam:
            pool = lambda x: F.avg_pool2d(x, 8)   # noqa: E731
            loss = loss + lam * (torch.log(crop_relmse(pool(out), pool(ref)) + tiny)
                                 - torch.log(crop_relmse(pool(env), pool(ref)) + tiny)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return net


def geo(values) -> float:
    return float(np.exp(np.mean(np.log(values)))) if len(values) else float("nan")


def summarise(rows: list[dict], key: str) -> dict:
    r = np.array([row[key] for row in rows])
    r8 = np.array([row[key + "_8x8"] for row in rows])
    return {"images": len(rows), "ratio": geo(r), "worst": float(r.max()), "worse": int((r > 1).sum()),
            "ratio_8x8": geo(r8), "blocks_ok": int((r8 <= 1).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="a generated data set (ppmrecon-train generate)")
    ap.add_argument("--model", type=Path, default=ROOT / "ppmrecon/data/models/default.pt",
                    help="the checkpoint whose guard and guide make the envelope (default: the shipped one)")
    ap.add_argument("--folds", type=int, default=4)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--width", type=int, default=24)
    ap.add_argument("--lam", type=float, default=1.0, help="weight of the 8x8-block term of the loss")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "refine")
    args = ap.parse_args()
    from ppmrecon.model.checkpoint import load_checkpoint
    from ppmrecon.train.datagen import REFERENCE, load_manifest

    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    model = load_checkpoint(args.model).model
    items = []
    for n, scene in enumerate(load_manifest(args.data)["scenes"]):
        if not (args.data / scene["id"] / REFERENCE).is_file():
            continue
        ref, _ = B.read_rgb(args.data / scene["id"] / REFERENCE)
        for item in scene.get("inputs", []):
            it = prepare(args.data / scene["id"] / item["file"], ref, model)
            it.update(image=f"{scene['id']} {item['file']}", index=n, split=scene.get("split", "?"),
                      family=scene.get("family", "?"))
            items.append(it)
    print(f"{len(items)} images of {len({it['index'] for it in items})} scenes prepared "
          f"in {time.perf_counter() - t0:.0f}s", flush=True)
    rows = []
    for fold in range(args.folds):
        train = [it for it in items if it["index"] % args.folds != fold]
        net = fit(train, args.steps, args.width, args.lam, seed=fold)
        with torch.no_grad():
            for it in (it for it in items if it["index"] % args.folds == fold):
                out = net(it["feats"][None], it["cands"][None])[0].permute(1, 2, 0).numpy()
                ref = it["ref"].permute(1, 2, 0).numpy()
                row = {"image": it["image"], "family": it["family"], "split": it["split"], "passes": it["passes"]}
                for name, img in (("chooser", out), ("envelope", it["cands"][0].permute(1, 2, 0).numpy()),
                                  ("oidn(z4)", it["cands"][2].permute(1, 2, 0).numpy())):
                    row[name] = relmse(img, ref) / it["best"]
                    row[name + "_8x8"] = relmse_blocks(img, ref) / it["best8"]
                rows.append(row)
        print(f"fold {fold + 1}/{args.folds} done ({time.perf_counter() - t0:.0f}s)", flush=True)
    names = ("chooser", "envelope", "oidn(z4)")
    groups = {"all": rows, "val split": [r for r in rows if r["split"] == "val"],
              **{f"N = {n}": [r for r in rows if r["passes"] == n] for n in sorted({r["passes"] for r in rows})},
              **{f"family {f}": [r for r in rows if r["family"] == f] for f in sorted({r["family"] for r in rows})}}
    summary = {g: {n: summarise(rs, n) for n in names} for g, rs in groups.items() if rs}
    minutes = (time.perf_counter() - t0) / 60
    write_json(args.out / "refine.json", {"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows,
                                          "summary": summary, "minutes": minutes})
    cmd = f"benchmarks/bench_refine.py --data {args.data} --folds {args.folds} --steps {args.steps}" \
          f" --width {args.width} --lam {args.lam:g}"
    lines = ["# A learned choice among consistent candidates (issue 12 study)", "",
             f"Generated by `{cmd}` in {minutes:.1f} min on {torch.get_num_threads()} threads. "
             f"{len(rows)} images; every figure held out ({args.folds}-fold by scene). Ratios: relMSE and "
             "8x8-block relMSE over the best single input of the same image (geometric means). "
             "*worse*: images above their best input; *8x8 ok*: images whose 8x8 ratio is <= 1. "
             "`oidn(z4)`: OIDN's image of the guarded, despiked ~z^4 held in the band (the guide without ~y or the anchor).", "",
             "| images | n | " + " | ".join(f"{n}: ratio (worst, worse) / 8x8 (ok)" for n in names) + " |",
             "|---|---:|" + "---|" * len(names)]
    for g, per in summary.items():
        cells = [f"{s['ratio']:.3f} ({s['worst']:.2f}, {s['worse']}) / {s['ratio_8x8']:.2f} ({s['blocks_ok']})"
                 for s in (per[n] for n in names)]
        lines.append(f"| {g} | {per[names[0]]['images']} | " + " | ".join(cells) + " |")
    write_text(args.out / "refine.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
