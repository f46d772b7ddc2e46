"""The training loop: Adam on the relative log-L1 loss of the combined output (paper
002 Sec. 4.3, Eq. 8), a checkpoint and a validation pass every epoch, resumable.

Per step: B random 64x64 patches -> network logits -> consistent combiner (Eq. 6) ->
[the firefly guard's output band] -> loss against the reference. With ``guard`` on in
the config, the data are guarded when loaded and the guard is stored in every
checkpoint, so the model is trained on what ``ppmrecon-denoise`` feeds it.
Per epoch: full-image validation relMSE (SPEC section 7) of
the output and of every single input (~y, ~z^1..~z^4) on held-out scenes, a checkpoint
(``model.pt``, loadable by ``ppmrecon-denoise``), the best one so far (``best.pt``), the
optimiser state (``train_state.pt``) and ``history.json``.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..buffers import ESTIMATES
from ..cli_common import Progress
from ..errors import UsageError
from ..fileio import load_json_config, write_json
from ..metrics import relmse
from ..model.checkpoint import load_checkpoint, save_checkpoint
from ..model.combine import combine
from ..model.features import FeatureConfig, ModelInputs
from ..model.guard import GuardConfig, finish
from ..model.infer import denoise_inputs
from ..model.kpn import build
from .dataset import PatchSampler, Sample, load_split
from .loss import block_log_l1, relative_log_l1

STATE = "train_state.pt"
SELECT = ("relmse", "ratio")
MODEL = "model.pt"
BEST = "best.pt"
HISTORY = "history.json"


@dataclass
class TrainConfig:
    """Training settings (``ppmrecon/data/configs/train/*.json``, ``--config NAME``); paper defaults where it gives them."""

    preset: str = "tiny"
    features: dict[str, bool] = field(default_factory=dict)
    #: firefly guard settings (GuardConfig fields; {} = off, {"enabled": true} = the defaults)
    guard: dict[str, Any] = field(default_factory=dict)
    lr: float = 1e-4
    batch: int = 8
    patch: int = 64
    epochs: int = 20
    steps_per_epoch: int = 100
    seed: int = 0
    #: Validate on this input pass count (None: the middle one of the data set; 0: every one).
    val_passes: int | None = None
    #: What picks ``best.pt``: "relmse" (mean validation relMSE of the output) or "ratio"
    #: (geometric mean over validation images of output / best single input relMSE, so
    #: that no bright scene decides alone: issue 12 targets per-image ratios).
    select: str = "relmse"
    #: Skip scenes whose two references disagree by more than this trimmed relMSE (None: keep all).
    max_reference_disagreement: float | None = None
    grad_clip: float = 1.0
    #: Weight of the 8x8 block-mean term (:func:`.loss.block_log_l1`) added to Eq. 8.
    lowfreq_weight: float = 0.0

    @classmethod
    def load(cls, path: str | os.PathLike) -> "TrainConfig":
        cfg = load_json_config(path, cls, "training config")
        if not (isinstance(cfg.lowfreq_weight, (int, float)) and 0.0 <= cfg.lowfreq_weight < math.inf):
            raise UsageError(f"{path}: lowfreq_weight must be a number >= 0, got {cfg.lowfreq_weight!r}")
        if cfg.select not in SELECT:
            raise UsageError(f"{path}: select must be one of {', '.join(SELECT)}, got {cfg.select!r}")
        return cfg


def _validate(model: torch.nn.Module, samples: list[Sample], device: torch.device) -> dict[str, float]:
    """Mean relMSE over the validation images of the output and of each single input, and
    ``image_ratio``: the geometric mean over images of output / best single input."""
    if not samples:
        return {}
    model.eval()
    out = {"output": 0.0, **{name: 0.0 for name in ESTIMATES}}
    log_ratio = 0.0
    for s in samples:
        inputs = ModelInputs(s.features[None], s.y[None], s.z[None])
        rgb = denoise_inputs(inputs, model, tile=None, device=device).rgb
        ref = s.reference.permute(1, 2, 0).numpy()
        mine = relmse(rgb, ref)
        out["output"] += mine
        singles = [relmse(img.permute(1, 2, 0).numpy(), ref) for img in [s.y] + list(s.z)]
        for name, value in zip(ESTIMATES, singles):
            out[name] += value
        log_ratio += math.log(max(mine, 1e-30) / max(min(singles), 1e-30))
    out = {k: v / len(samples) for k, v in out.items()}
    out["image_ratio"] = math.exp(log_ratio / len(samples))
    out["best_single"] = min(out[name] for name in ESTIMATES)
    out["best_single_name"] = min(ESTIMATES, key=lambda n: out[n])  # type: ignore[assignment]
    out["ratio"] = out["output"] / max(out["best_single"], 1e-12)
    model.train()
    return out


def train(data: str | os.PathLike, out: str | os.PathLike, cfg: TrainConfig, resume: bool = False,
          device: str = "cpu", quiet: bool = False, warn: Callable[[str], None] | None = None,
          max_seconds: float | None = None) -> list[dict[str, Any]]:
    """Train (or resume training) on data set ``data``, writing checkpoints into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    dev = torch.device(device)
    try:
        features = FeatureConfig.from_dict(cfg.features)
        guard = GuardConfig.from_dict(cfg.guard)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"training config: {exc}") from None
    torch.manual_seed(cfg.seed)
    train_samples = load_split(data, "train", features, warn=warn, guard=guard,
                               max_disagreement=cfg.max_reference_disagreement)
    config = json.loads((Path(data) / "manifest.json").read_text()).get("config", {})
    passes = sorted(config.get("input_passes", []))
    val_passes = cfg.val_passes if cfg.val_passes is not None else (passes[len(passes) // 2] if passes else None)
    val_samples = load_split(data, "val", features, passes=val_passes or None, warn=warn, guard=guard,
                             max_disagreement=cfg.max_reference_disagreement)
    sampler = PatchSampler(train_samples, cfg.patch, features, augment=True, seed=cfg.seed)

    model = build(cfg.preset, features, guard).to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    history: list[dict[str, Any]] = []
    start_epoch = 0
    if resume:
        state_path = out / STATE
        if not state_path.exists():
            raise UsageError(f"{state_path}: nothing to resume (no training state in {out})")
        state = torch.load(state_path, map_location=dev, weights_only=True)
        model = load_checkpoint(out / MODEL, map_location=dev).model.to(dev)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
        opt.load_state_dict(state["optimizer"])
        start_epoch = int(state["epoch"])
        history = json.loads((out / HISTORY).read_text()) if (out / HISTORY).exists() else []
        sampler.rng = np.random.default_rng([cfg.seed, start_epoch])
        torch.manual_seed(cfg.seed + start_epoch)
    model.train()

    n_params = sum(p.numel() for p in model.parameters())
    key = "output" if cfg.select == "relmse" else "image_ratio"
    # Only epochs validated on the same images compare (a resumed run may see a grown data set).
    val_ids = sorted(s.name for s in val_samples)
    best = min((h["val"][key] for h in history
                if h.get("val") and key in h["val"] and h.get("val_images") == val_ids), default=math.inf)
    t_start = time.perf_counter()
    progress = Progress(f"ppmrecon-train {cfg.preset} ({n_params} params)", total=cfg.epochs * cfg.steps_per_epoch,
                        quiet=quiet)
    for epoch in range(start_epoch, cfg.epochs):
        t0 = time.perf_counter()
        losses = []
        for step in range(cfg.steps_per_epoch):
            feats, y, z, ref = (t.to(dev) for t in sampler.batch(cfg.batch))
            logits = model(feats)
            pred = combine(y, z, logits, method="unfold")
            if guard.enabled:     # anchor + band as inference applies them (Eq. 8 clips at 0 itself)
                pred = finish(pred, y, z, guard)
            loss = relative_log_l1(pred, ref)
            if cfg.lowfreq_weight:
                loss = loss + cfg.lowfreq_weight * block_log_l1(pred, ref)
            if not torch.isfinite(loss):
                raise UsageError(f"epoch {epoch + 1} step {step + 1}: the loss became {loss.item()}; "
                                 "lower --lr or check the data set")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            losses.append(loss.item())
            progress.update(epoch * cfg.steps_per_epoch + step + 1, epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.4f}")
        val = _validate(model, val_samples, dev)
        record = {"epoch": epoch + 1, "loss": float(np.mean(losses)), "seconds": time.perf_counter() - t0,
                  "val_passes": val_passes, "val": val, "val_images": val_ids}
        history.append(record)
        meta = {"trained": True, "epochs": epoch + 1, "preset": cfg.preset, "train_config": asdict(cfg),
                "data": str(data), "train_images": len(train_samples), "val_images": len(val_samples),
                "val": {k: v for k, v in val.items()}, "train_seconds": sum(h["seconds"] for h in history)}
        save_checkpoint(out / MODEL, model, meta)
        if val and val[key] < best:
            best = val[key]
            save_checkpoint(out / BEST, model, meta)
        torch.save({"optimizer": opt.state_dict(), "epoch": epoch + 1}, out / STATE)
        write_json(out / HISTORY, history)
        if not quiet:
            progress.close()
            v = (f" val relMSE {val['output']:.4f} vs best input {val['best_single']:.4f} ({val['best_single_name']}),"
                 f" per image {val['image_ratio']:.3f}x") if val else ""
            print(f"epoch {epoch + 1}/{cfg.epochs}: loss {record['loss']:.4f}{v} [{record['seconds']:.1f}s]", flush=True)
        if max_seconds is not None and time.perf_counter() - t_start > max_seconds:
            break
    progress.close()
    return history
