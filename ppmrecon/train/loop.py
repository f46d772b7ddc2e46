"""The training loop: Adam on the relative log-L1 loss of the combined output (paper
002 Sec. 4.3, Eq. 8), a checkpoint and a validation pass every epoch, resumable.

Per step: B random 64x64 patches -> network logits -> consistent combiner (Eq. 6) ->
[the firefly guard's output band] -> loss against the reference. With ``guard`` on in
the config, the data are guarded when loaded and the guard is stored in every
checkpoint, so the model is trained on what ``ppmrecon-denoise`` feeds it.
Per epoch: full-image validation relMSE (SPEC section 7) of
the output and of every single input (~y, ~z^1..~z^4) on held-out scenes, a checkpoint
(``model.pt``, loadable by ``ppmrecon-denoise``), the best one so far (``best.pt``), the
optimiser state (``train_state.pt``) and ``history.json`` (with every step's loss).

Under torchrun the same loop runs data-parallel (:mod:`.distributed`): the data set is
sharded by rank and each step is the step one process takes with the same global batch.
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
from ..fileio import atomic_write, load_json_config, write_json
from ..metrics import relmse
from ..model.checkpoint import load_checkpoint, save_checkpoint
from ..model.combine import combine
from ..model.features import FeatureConfig, ModelInputs
from ..model.guard import GuardConfig, finish
from ..model.guide import ENVELOPE_MODES, GuideConfig, guided_logits
from ..model.infer import denoise_inputs
from ..model.kpn import build
from .dataset import PatchSampler, Sample, load_split
from .distributed import Dist
from .loss import block_log_l1, relative_log_l1

STATE = "train_state.pt"
SELECT = ("relmse", "ratio")
MODEL = "model.pt"
BEST = "best.pt"
HISTORY = "history.json"
#: Validation of the untrained guided model (the guide alone), written before epoch 1.
GUIDE_ALONE = "guide_alone.json"


@dataclass
class TrainConfig:
    """Training settings (``ppmrecon/data/configs/train/*.json``, ``--config NAME``); paper defaults where it gives them."""

    preset: str = "tiny"
    features: dict[str, bool] = field(default_factory=dict)
    #: firefly guard settings (GuardConfig fields; {} = off, {"enabled": true} = the defaults)
    guard: dict[str, Any] = field(default_factory=dict)
    #: denoiser guide settings (GuideConfig fields; {} = off): the network learns a
    #: correction to the guide's prior logits and starts as the guide alone
    guide: dict[str, Any] = field(default_factory=dict)
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


def _validate(model: torch.nn.Module, samples: list[Sample], device: torch.device,
              dist: Dist | None = None) -> dict[str, float]:
    """Mean relMSE over the validation images of the output and of each single input, and
    ``image_ratio``: the geometric mean over images of output / best single input. With
    ``dist``, ``samples`` is this rank's shard and the sums are taken over all ranks."""
    model.eval()
    out = {"output": 0.0, **{name: 0.0 for name in ESTIMATES}}
    log_ratio = 0.0
    count = len(samples)
    for s in samples:
        inputs = ModelInputs(s.features[None], s.y[None], s.z[None], None if s.guide is None else s.guide[None])
        rgb = denoise_inputs(inputs, model, tile=None, device=device).rgb
        ref = s.reference.permute(1, 2, 0).numpy()
        mine = relmse(rgb, ref)
        out["output"] += mine
        singles = [relmse(img.permute(1, 2, 0).numpy(), ref) for img in [s.y] + list(s.z)]
        for name, value in zip(ESTIMATES, singles):
            out[name] += value
        log_ratio += math.log(max(mine, 1e-30) / max(min(singles), 1e-30))
    model.train()
    if dist is not None:
        keys = list(out)
        sums = dist.all_sum([out[k] for k in keys] + [log_ratio, float(count)])
        out, log_ratio, count = dict(zip(keys, sums[:-2])), sums[-2], int(sums[-1])
    if not count:
        return {}
    out = {k: v / count for k, v in out.items()}
    out["image_ratio"] = math.exp(log_ratio / count)
    out["best_single"] = min(out[name] for name in ESTIMATES)
    out["best_single_name"] = min(ESTIMATES, key=lambda n: out[n])  # type: ignore[assignment]
    out["ratio"] = out["output"] / max(out["best_single"], 1e-12)
    return out


def _step_loss(model: torch.nn.Module, sampler: PatchSampler, cfg: TrainConfig, guard: GuardConfig,
               dev: torch.device, dist: Dist | None) -> tuple[torch.Tensor, float]:
    """(loss to back-propagate, the global batch's loss) of one step. Alone: Eq. 8 (+ the
    block term) of the batch. Data-parallel: this rank's rows' loss scaled so that DDP's
    gradient average over ranks is the gradient of the whole batch's loss."""
    rows = sampler.plan(cfg.batch)
    mine = sampler.mine(rows) if dist is not None else rows
    if not mine:  # no row of this batch in our shard: a zero loss that still reaches every parameter
        g = next(iter(sampler.local))   # train() made sure every rank holds a sample
        h, w = sampler.catalog[g]
        feats = sampler.cut([(g, 0, 0, 0, False, min(rows[0][5], h, w))])[0].to(dev)
        return model(feats).sum() * 0.0, dist.all_sum([0.0])[0]
    feats, y, z, ref, *guide = (t.to(dev) for t in sampler.cut(mine))
    logits = model(feats)
    if guide:                    # the network's logits correct the guide's prior (inference does the same)
        logits = guided_logits(logits, y, z, guide[0], _unwrap(model).window, _unwrap(model).guide)
    pred = combine(y, z, logits, method="unfold")
    if guard.enabled:     # anchor + band as inference applies them (Eq. 8 clips at 0 itself)
        pred = finish(pred, y, z, guard)
    loss = relative_log_l1(pred, ref)
    if cfg.lowfreq_weight:
        loss = loss + cfg.lowfreq_weight * block_log_l1(pred, ref)
    if dist is None:
        return loss, loss.item()
    share = len(mine) / len(rows)   # rows are equal-sized patches: the batch mean is the share-weighted mean
    total = dist.all_sum([loss.item() * share])[0]
    return loss * (share * dist.world), total


def _unwrap(model: torch.nn.Module) -> torch.nn.Module:
    """The KPN itself, also inside DistributedDataParallel."""
    return model.module if hasattr(model, "module") else model


def _sharded_sampler(samples: list[Sample], cfg: TrainConfig, features: FeatureConfig,
                     dist: Dist | None) -> PatchSampler:
    """The patch sampler; data-parallel, over the catalogue of every rank's shard."""
    if dist is None:
        return PatchSampler(samples, cfg.patch, features, augment=True, seed=cfg.seed)
    shards = dist.gather([(s.index, tuple(s.y.shape[-2:])) for s in samples])
    order = sorted((index, rank, shape) for rank, shard in enumerate(shards) for index, shape in shard)
    empty = [r for r, shard in enumerate(shards) if not shard]
    if order and empty:
        raise UsageError(f"{len(order)} training samples for {dist.world} ranks: rank(s) "
                         f"{', '.join(map(str, empty))} would hold none; use fewer processes")
    position = {index: g for g, (index, _, _) in enumerate(order)}
    return PatchSampler(samples, cfg.patch, features, augment=True, seed=cfg.seed,
                        catalog=[shape for _, _, shape in order], positions=[position[s.index] for s in samples])


def train(data: str | os.PathLike, out: str | os.PathLike, cfg: TrainConfig, resume: bool = False,
          device: str = "cpu", quiet: bool = False, warn: Callable[[str], None] | None = None,
          max_seconds: float | None = None, dist: Dist | None = None) -> list[dict[str, Any]]:
    """Train (or resume training) on data set ``data``, writing checkpoints into ``out``.

    ``dist``: this process's rank in a data-parallel run (:mod:`.distributed`): the data
    are sharded by rank, rank 0 writes the run folder, and every rank returns the same
    history."""
    out = Path(out)
    main = dist is None or dist.main
    if main:
        out.mkdir(parents=True, exist_ok=True)
    dev = dist.device(device) if dist is not None else torch.device(device)
    quiet = quiet or not main
    try:
        features = FeatureConfig.from_dict(cfg.features)
        guard = GuardConfig.from_dict(cfg.guard)
        guide = GuideConfig.from_dict(cfg.guide)
    except (TypeError, ValueError) as exc:
        raise UsageError(f"training config: {exc}") from None
    if guide.enabled and guide.mode in ENVELOPE_MODES:
        raise UsageError(f"training config: guide mode '{guide.mode}' runs no Eq. 6 network, there is nothing to "
                         "train here; train with mode 'weights' and ship with scripts/ship_model.py --guide-mode "
                         "envelope (the chooser trains with `ppmrecon-train chooser`)")
    torch.manual_seed(cfg.seed)
    shard = (dist.rank, dist.world) if dist is not None else None
    train_samples = load_split(data, "train", features, warn=warn, guard=guard,
                               max_disagreement=cfg.max_reference_disagreement, shard=shard, guide=guide)
    config = json.loads((Path(data) / "manifest.json").read_text()).get("config", {})
    passes = sorted(config.get("input_passes", []))
    val_passes = cfg.val_passes if cfg.val_passes is not None else (passes[len(passes) // 2] if passes else None)
    val_samples = load_split(data, "val", features, passes=val_passes or None, warn=warn, guard=guard,
                             max_disagreement=cfg.max_reference_disagreement, shard=shard, guide=guide)
    sampler = _sharded_sampler(train_samples, cfg, features, dist)

    model = build(cfg.preset, features, guard, guide).to(dev)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    history: list[dict[str, Any]] = []
    start_epoch = 0
    if resume:
        src = dist.replicate(out, (STATE, MODEL, HISTORY)) if dist is not None else out
        state_path = src / STATE
        if not state_path.exists():
            raise UsageError(f"{out / STATE}: nothing to resume (no training state in {out})")
        state = torch.load(state_path, map_location=dev, weights_only=True)
        model = load_checkpoint(src / MODEL, map_location=dev).model.to(dev)
        opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
        opt.load_state_dict(state["optimizer"])
        start_epoch = int(state["epoch"])
        history = json.loads((src / HISTORY).read_text()) if (src / HISTORY).exists() else []
        sampler.rng = np.random.default_rng([cfg.seed, start_epoch])
        torch.manual_seed(cfg.seed + start_epoch)
    model.train()
    # DDP averages the gradients over the ranks in backward (and broadcasts rank 0's
    # weights now); checkpoints and validation use the plain module.
    net = model
    if dist is not None:
        net = torch.nn.parallel.DistributedDataParallel(
            model, device_ids=[dist.local_rank] if dev.type == "cuda" else None)

    n_params = sum(p.numel() for p in model.parameters())
    key = "output" if cfg.select == "relmse" else "image_ratio"
    # Only epochs validated on the same images compare (a resumed run may see a grown data set).
    val_ids = sorted(s.name for s in val_samples)
    if dist is not None:
        val_ids = sorted(name for shard_ids in dist.gather(val_ids) for name in shard_ids)
    n_train = len(sampler.catalog)
    best = min((h["val"][key] for h in history
                if h.get("val") and key in h["val"] and h.get("val_images") == val_ids), default=math.inf)
    if guide.enabled and start_epoch == 0 and not history:
        # the guide alone (the zero-initialised head) is a candidate too: best.pt is
        # never worse on validation than the model one starts from
        val0 = _validate(model, val_samples, dev, dist)
        if main and val0:
            write_json(out / GUIDE_ALONE, {"val": val0, "val_images": val_ids})
        if val0 and val0[key] < best:
            best = val0[key]
            if main:
                save_checkpoint(out / BEST, model, {"trained": False, "epochs": 0, "preset": cfg.preset,
                                                    "train_config": asdict(cfg), "data": str(data),
                                                    "val": dict(val0), "train_seconds": 0.0})
        if val0 and not quiet:
            print(f"epoch 0 (the guide alone): val relMSE {val0['output']:.4f} vs best input "
                  f"{val0['best_single']:.4f}, per image {val0['image_ratio']:.3f}x", flush=True)
    t_start = time.perf_counter()
    label = f"ppmrecon-train {cfg.preset} ({n_params} params{f', {dist.world} ranks' if dist else ''})"
    progress = Progress(label, total=cfg.epochs * cfg.steps_per_epoch, quiet=quiet)
    for epoch in range(start_epoch, cfg.epochs):
        t0 = time.perf_counter()
        losses = []
        for step in range(cfg.steps_per_epoch):
            loss, value = _step_loss(net, sampler, cfg, guard, dev, dist)
            if not math.isfinite(value):
                raise UsageError(f"epoch {epoch + 1} step {step + 1}: the loss became {value}; "
                                 "lower --lr or check the data set")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if cfg.grad_clip:
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
            opt.step()
            losses.append(value)
            progress.update(epoch * cfg.steps_per_epoch + step + 1, epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.4f}")
        step_seconds = time.perf_counter() - t0
        val = _validate(model, val_samples, dev, dist)
        record = {"epoch": epoch + 1, "loss": float(np.mean(losses)), "seconds": time.perf_counter() - t0,
                  "step_seconds": step_seconds,
                  "val_passes": val_passes, "val": val, "val_images": val_ids, "step_losses": losses,
                  "ranks": dist.world if dist is not None else 1}
        history.append(record)
        meta = {"trained": True, "epochs": epoch + 1, "preset": cfg.preset, "train_config": asdict(cfg),
                "data": str(data), "train_images": n_train, "val_images": len(val_ids),
                "val": {k: v for k, v in val.items()}, "train_seconds": sum(h["seconds"] for h in history)}
        if main:
            save_checkpoint(out / MODEL, model, meta)
        if val and val[key] < best:
            best = val[key]
            if main:
                save_checkpoint(out / BEST, model, meta)
        if main:
            state = {"optimizer": opt.state_dict(), "epoch": epoch + 1}
            atomic_write(out / STATE, lambda tmp: torch.save(state, tmp))
            write_json(out / HISTORY, history)
        if not quiet:
            progress.close()
            v = (f" val relMSE {val['output']:.4f} vs best input {val['best_single']:.4f} ({val['best_single_name']}),"
                 f" per image {val['image_ratio']:.3f}x") if val else ""
            print(f"epoch {epoch + 1}/{cfg.epochs}: loss {record['loss']:.4f}{v} [{record['seconds']:.1f}s]", flush=True)
        stop = max_seconds is not None and time.perf_counter() - t_start > max_seconds
        if dist is not None:
            stop = bool(dist.broadcast(stop))  # rank 0's clock decides, or the ranks would part ways
        if stop:
            break
    progress.close()
    return history
