"""Training the chooser (:mod:`..model.chooser`): data set -> candidates -> loss -> loop.

    ppmrecon-train chooser data/v3_cpu --out runs/chooser [--config cpu] [--base-model CKPT] [--resume]

Every input of the data set is prepared once as inference prepares it (guard, OIDN guide,
envelope, candidates and features: :func:`..model.infer.chooser_inputs`), with the base
model's guard and guide. Each step draws ``batch`` crops of ``crop`` px (a mirror image
with probability 1/2, the normal's x turned with it) and minimises, per crop,

    log relMSE(yhat, ref) - log relMSE(e, ref) + lowfreq (log relMSE_8(yhat) - log relMSE_8(e))

with e the envelope and relMSE_8 that of 8 x 8 block means (SPEC section 7): the ratio
to the envelope, so that every crop counts alike whatever its radiance and noise. The
random stream of step k depends on (seed, k) alone, and the state (weights, Adam, schedule)
is written every ``save_every`` steps, so a resumed run is the run that never stopped.

Outputs in the run folder: ``state.pt`` (to resume), ``history.json`` (loss per
``save_every`` steps, validation figures), ``chooser.pt`` (the base model with the chooser
attached and the guide in mode "chooser", ready for ``ppmrecon-denoise --model``).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F

from .. import buffers as B
from ..errors import UsageError
from ..fileio import atomic_write, load_json_config, write_json
from ..metrics import relmse, relmse_blocks, relmse_map
from ..model.checkpoint import load_checkpoint, model_path, save_checkpoint
from ..model.chooser import CANDIDATES, FEATURE_NORMAL_X, Chooser, ChooserConfig
from ..model.guard import guard_buffer
from ..model.infer import buffer_aim, buffer_envelope, buffer_guide_images, chooser_inputs
from .datagen import REFERENCE, load_manifest

Warn = Callable[[str], None]


@dataclass
class ChooserTrainConfig:
    """Settings of ``ppmrecon-train chooser`` (JSON: ``ppmrecon/data/configs/chooser/``)."""

    steps: int = 3000
    batch: int = 8
    crop: int = 64
    lr: float = 2e-3
    lowfreq: float = 1.0
    width: int = 12
    layers: int = 2
    prior: float = 3.0
    seed: int = 0
    save_every: int = 250

    def validate(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("lr", "lowfreq", "prior"):
                kind = {"lr": "number > 0", "lowfreq": "number >= 0", "prior": "finite number"}[f.name]
                if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                        or (f.name == "lr" and value <= 0) or (f.name == "lowfreq" and value < 0):
                    raise UsageError(f"chooser config: '{f.name}' must be a {kind}, got {value!r}")
            elif f.name != "seed" and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
                raise UsageError(f"chooser config: '{f.name}' must be a positive integer, got {value!r}")
        if self.crop % 8:
            raise UsageError(f"chooser config: 'crop' must be a multiple of 8 (the 8x8 blocks), got {self.crop}")

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ChooserTrainConfig":
        cfg = load_json_config(path, cls, "chooser config")
        cfg.validate()
        return cfg

    def net(self) -> ChooserConfig:
        return ChooserConfig(width=self.width, layers=self.layers, prior=self.prior)


@dataclass
class Item:
    """One input of the data set, prepared as inference prepares it."""

    name: str
    split: str
    family: str
    passes: int
    features: torch.Tensor     # (C, H, W)
    candidates: torch.Tensor   # (K, 3, H, W); [0] is the envelope
    reference: torch.Tensor    # (3, H, W)
    best: float                # relMSE of the best single (raw) input
    best_8x8: float


def prepare(data: str | os.PathLike, model, warn: Warn | None = None) -> list[Item]:
    """Every input of every complete scene of the data set ``data`` (both splits) with the
    guard and guide of ``model`` (its guide taken in envelope mode). An unreadable input is
    reported through ``warn`` and skipped."""
    root = Path(data)
    warn = warn or (lambda msg: None)
    guide = model.guide.in_mode("envelope")
    if not guide.enabled:
        raise UsageError("the chooser needs a base model with the denoiser guide (its envelope is a candidate)")
    items = []
    for scene in load_manifest(root)["scenes"]:
        folder = root / scene["id"]
        if not (folder / REFERENCE).is_file():
            continue
        try:
            ref, _ = B.read_rgb(folder / REFERENCE)
        except UsageError as exc:
            warn(f"{scene['id']}: reference skipped ({exc})")
            continue
        for entry in scene.get("inputs", []):
            try:
                buf = B.read_buffers(folder / entry["file"])
            except UsageError as exc:
                warn(f"{scene['id']}/{entry['file']}: skipped ({exc})")
                continue
            if buf.shape != ref.shape[:2]:
                warn(f"{scene['id']}/{entry['file']}: skipped (size differs from the reference)")
                continue
            guarded = guard_buffer(buf, model.guard)
            aim = buffer_aim(guarded, guide, model.guard)      # once, for the guide and the envelope
            images, planes = buffer_guide_images(guarded, guide, model.guard, need_y=True, aim=aim)
            env = buffer_envelope(guarded, planes, model.guard, guide, aim=aim).rgb
            feats, cands, _, _ = chooser_inputs(guarded, env, images, guide=guide, guard=model.guard)
            items.append(Item(f"{scene['id']}/{entry['file']}", scene.get("split", "train"),
                              scene.get("family", "?"), int(entry.get("passes", 0)), feats, cands,
                              torch.from_numpy(np.ascontiguousarray(ref, np.float32)).permute(2, 0, 1),
                              min(relmse(x, ref) for x in buf.estimates),
                              min(relmse_blocks(x, ref) for x in buf.estimates)))
    return items


def _crop_relmse(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return relmse_map(x, ref, channel_axis=1).mean((-1, -2))


def loss(out: torch.Tensor, env: torch.Tensor, ref: torch.Tensor, lowfreq: float) -> torch.Tensor:
    """The module docstring's loss, averaged over the crops of a batch (B, 3, H, W)."""
    tiny = 1e-12
    value = (torch.log(_crop_relmse(out, ref) + tiny) - torch.log(_crop_relmse(env, ref) + tiny)).mean()
    if lowfreq:
        pool = [F.avg_pool2d(x, 8) for x in (out, env, ref)]
        value = value + lowfreq * (torch.log(_crop_relmse(pool[0], pool[2]) + tiny)
                                   - torch.log(_crop_relmse(pool[1], pool[2]) + tiny)).mean()
    return value


def batch(items: list[Item], cfg: ChooserTrainConfig, step: int) -> tuple[torch.Tensor, ...]:
    """The crops of step ``step``: (features, candidates, reference), from a random stream
    that depends on (seed, step) alone."""
    rng = np.random.default_rng([cfg.seed, step])
    parts = []
    for _ in range(cfg.batch):
        it = items[rng.integers(len(items))]
        h, w = it.reference.shape[1:]
        if h < cfg.crop or w < cfg.crop:
            raise UsageError(f"{it.name}: {w}x{h} is smaller than the crop ({cfg.crop} px)")
        y0, x0 = rng.integers(0, h - cfg.crop + 1), rng.integers(0, w - cfg.crop + 1)
        box = (..., slice(y0, y0 + cfg.crop), slice(x0, x0 + cfg.crop))
        feats, cands, ref = it.features[box], it.candidates[box], it.reference[box]
        if rng.random() < 0.5:
            feats = feats.flip(-1).clone()
            feats[FEATURE_NORMAL_X] = -feats[FEATURE_NORMAL_X]          # the mirror turns the normal with it
            cands, ref = cands.flip(-1), ref.flip(-1)
        parts.append((feats, cands, ref))
    return tuple(torch.stack(p) for p in zip(*parts))


def fit(items: list[Item], cfg: ChooserTrainConfig, state_path: Path | None = None, resume: bool = False,
        progress: Callable[[int, float], None] | None = None, max_seconds: float | None = None) -> tuple[Chooser, list[dict]]:
    """Train a chooser on ``items``; with ``state_path``, its state is saved every
    ``cfg.save_every`` steps and, with ``resume``, training continues from it. Returns the
    chooser and the loss history (mean over each ``save_every`` steps)."""
    torch.manual_seed(cfg.seed)
    net = Chooser(cfg.net())
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.steps)
    start, history = 0, []
    if resume and state_path is not None and state_path.is_file():
        state = torch.load(state_path, weights_only=True)
        if state.get("config") != asdict(cfg):
            raise UsageError(f"{state_path}: written with other settings; resume with the same config")
        net.load_state_dict(state["chooser"])
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        start, history = int(state["step"]), list(state["history"])
    # training seconds over every session of the run (the last entry carries the total)
    elapsed = history[-1].get("seconds", 0.0) if history else 0.0
    t0 = t_mark = time.perf_counter()
    running: list[float] = []
    for step in range(start, cfg.steps):
        feats, cands, ref = batch(items, cfg, step)
        value = loss(net(feats, cands), cands[:, 0], ref, cfg.lowfreq)
        if not torch.isfinite(value):
            raise UsageError(f"chooser training: the loss is not finite at step {step}")
        opt.zero_grad()
        value.backward()
        opt.step()
        sched.step()
        value = value.detach()
        running.append(float(value))
        done = step + 1
        if done % cfg.save_every == 0 or done == cfg.steps:
            elapsed += time.perf_counter() - t_mark
            t_mark = time.perf_counter()
            history.append({"step": done, "loss": float(np.mean(running)), "seconds": elapsed})
            running = []
            if state_path is not None:
                payload = {"step": done, "config": asdict(cfg), "chooser": net.state_dict(),
                           "opt": opt.state_dict(), "sched": sched.state_dict(), "history": history}
                atomic_write(state_path, lambda tmp: torch.save(payload, tmp))
            if max_seconds is not None and time.perf_counter() - t0 > max_seconds and done < cfg.steps:
                break
        if progress is not None:
            progress(done, float(value))
    return net.eval(), history


#: the candidates :func:`evaluate` scores beside the chooser by default
BASELINES = ("envelope",)


def evaluate(net: Chooser, items: list[Item], baselines: tuple[str, ...] = BASELINES) -> list[dict[str, Any]]:
    """Per item: relMSE and 8x8 relMSE of the chooser and of the candidates named in
    ``baselines`` (:data:`..model.chooser.CANDIDATES`) over the best input's."""
    rows = []
    with torch.no_grad():
        for it in items:
            ref = it.reference.permute(1, 2, 0).numpy()
            row = {"image": it.name, "family": it.family, "split": it.split, "passes": it.passes}
            images = [("chooser", net.predict(it.features[None], it.candidates[None])[0])]
            images += [(name, it.candidates[CANDIDATES.index(name)]) for name in baselines]
            for name, img in images:
                img = img.permute(1, 2, 0).numpy()
                row[name] = relmse(img, ref) / it.best
                row[name + "_8x8"] = relmse_blocks(img, ref) / it.best_8x8
            rows.append(row)
    return rows


def summary(rows: list[dict[str, Any]], names: tuple[str, ...] = ("chooser", *BASELINES)) -> dict[str, Any]:
    """Geometric means, worst and counts of :func:`evaluate`'s rows, per method."""
    out: dict[str, Any] = {"images": len(rows)}
    for name in names:
        r = np.array([row[name] for row in rows])
        r8 = np.array([row[name + "_8x8"] for row in rows])
        out[name] = {"ratio": float(np.exp(np.log(r).mean())), "worst": float(r.max()), "worse": int((r > 1).sum()),
                     "ratio_8x8": float(np.exp(np.log(r8).mean())), "blocks_ok": int((r8 <= 1).sum())}
    return out


def train_chooser(data: str | os.PathLike, out: str | os.PathLike, cfg: ChooserTrainConfig,
                  base_model: str | os.PathLike | None = None, resume: bool = False, warn: Warn | None = None,
                  progress: Callable[[int, float], None] | None = None,
                  max_seconds: float | None = None) -> dict[str, Any]:
    """The whole run: prepare, fit on the training split, score the validation split,
    write ``chooser.pt`` and ``history.json`` into ``out``. Returns the history."""
    cfg.validate()
    out = Path(out)
    state_path = out / "state.pt"
    if state_path.exists() and not resume:
        raise UsageError(f"{out}: a chooser run is already there; pass --resume to continue it, or another --out")
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out}: not a folder")
    base_path = model_path(base_model)
    base_ckpt = load_checkpoint(base_path)
    base = base_ckpt.model
    t0 = time.perf_counter()
    items = prepare(data, base, warn)
    train_items = [it for it in items if it.split == "train"]
    val_items = [it for it in items if it.split == "val"]
    if not train_items:
        raise UsageError(f"{data}: no complete training scene to train the chooser on")
    prepared = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)       # only once the inputs are known to be usable
    net, losses = fit(train_items, cfg, state_path, resume, progress, max_seconds)
    finished = bool(losses) and losses[-1]["step"] == cfg.steps
    history = {"config": asdict(cfg), "data": str(data), "base_model": str(base_path), "losses": losses,
               "train_images": len(train_items), "val_images": len(val_items), "finished": finished,
               "seconds": {"prepare": prepared, "session": time.perf_counter() - t0 - prepared}}
    if finished:
        rows = evaluate(net, val_items) if val_items else []
        history["validation"] = summary(rows) if rows else None
        history["validation_rows"] = rows
        base.chooser = net
        base.guide = replace(base.guide, mode="chooser")
        meta = {**base_ckpt.meta, "chooser": {
            "data": str(data), "config": asdict(cfg), "train_images": len(train_items),
            "train_scenes": len({it.name.split("/")[0] for it in train_items}),
            "val_scenes": len({it.name.split("/")[0] for it in val_items}),
            "seconds": prepared + (losses[-1].get("seconds", 0.0) if losses else 0.0),
            "validation": history["validation"], "base_model": str(base_path)}}
        save_checkpoint(out / "chooser.pt", base, meta)
    write_json(out / "history.json", history)
    return history
