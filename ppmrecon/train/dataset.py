"""Training and validation samples from a generated data set, and 64x64 patch batches.

Every input buffer file of a scene is paired with that scene's reference. With the
firefly guard on, each buffer file is guarded first (:func:`..model.guard.guard_buffer`,
the same call inference makes), so ~y, ~z and the features are what the model will see
when it denoises. Network features are computed on the whole image (their per-image
normalisations must not see a crop), then patches are cut and augmented with one of the
eight flips/rotations, identically for every layer (normals turn with the image, see
:mod:`.augment`).

For data-parallel training (:mod:`.distributed`) each rank loads one shard: the usable
candidates (a split's listed inputs, in the order a single process loads them) with
index ``k % world == rank``. :class:`PatchSampler` then draws every global batch from
the *whole* data set's catalogue (sizes only) with the same random stream on every
rank, and each rank cuts the patches of the samples it holds: together the ranks cut
exactly the batch one process would.

A missing, corrupt or partial item (an unreadable EXR, NaN/Inf, a size that differs
from the reference, a scene without reference, inputs the manifest promised but that
are absent) is reported by name through ``warn`` and skipped, never trained on.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from .. import buffers as B
from ..errors import PpmreconError, UsageError
from ..model.features import FeatureConfig, from_buffer
from ..model.guard import GuardConfig, guard_buffer
from ..model.guide import GuideConfig
from .augment import transform_image, transform_normals
from .datagen import REFERENCE, input_name, load_manifest

Warn = Callable[[str], None]


@dataclass
class Sample:
    """One training pair: network input of a buffer file and the scene's reference."""

    name: str
    scene: str
    passes: int
    features: torch.Tensor   # (C, H, W)
    y: torch.Tensor          # (3, H, W) ~y (guarded when the guard is on)
    z: torch.Tensor          # (4, 3, H, W) ~z^1..~z^4 (likewise)
    reference: torch.Tensor  # (3, H, W)
    #: Position among the split's candidates (the shard key; see the module docstring).
    index: int = -1
    #: (4, H, W) the denoiser guide and its tolerance (:mod:`..model.guide`), or None
    guide: torch.Tensor | None = None


def load_split(root: str | os.PathLike, split: str, features: FeatureConfig = FeatureConfig(),
               passes: int | None = None, warn: Warn | None = None,
               guard: GuardConfig = GuardConfig(), max_disagreement: float | None = None,
               shard: tuple[int, int] | None = None, guide: GuideConfig = GuideConfig()) -> list[Sample]:
    """All usable samples of ``split`` ("train" or "val"), optionally of one pass count.

    ``max_disagreement``: skip scenes whose two reference halves disagree by more than
    this trimmed relMSE (manifest ``agreement.relmse_trimmed``): a reference that far from
    converged teaches its own noise.
    ``shard`` = (rank, world): load only the candidates with index % world == rank (the
    manifest-only warnings come from rank 0 alone).
    ``guide``: with it on, each sample carries the guide of its guarded buffer file, made
    as inference makes it (:func:`..model.infer.buffer_guide`).
    """
    from ..model.infer import buffer_guide   # infer imports the model package, not train
    root = Path(root)
    warn = warn or (lambda msg: None)
    manifest = load_manifest(root)
    config = manifest.get("config", {})
    rank, world = shard or (0, 1)
    main_warn = warn if rank == 0 else (lambda msg: None)
    samples: list[Sample] = []
    candidates = not_started = 0
    for scene in manifest.get("scenes", []):
        if scene.get("split") != split:
            continue
        folder = root / scene["id"]
        disagreement = (scene.get("agreement") or {}).get("relmse_trimmed")
        if max_disagreement is not None and disagreement is not None and disagreement > max_disagreement:
            main_warn(f"skipping scene {scene['id']}: its two references disagree by trimmed relMSE "
                      f"{disagreement:.3g} > {max_disagreement:g} (not converged)")
            continue
        promised = {input_name(n, s) for n in config.get("input_passes", []) for s in config.get("seeds", [])}
        listed = {f["file"]: f for f in scene.get("inputs", [])}
        if not listed and not scene.get("references") and not scene.get("reference"):
            not_started += 1                # a growing data set: counted, not listed file by file
            continue
        for name in sorted(promised - set(listed)):
            main_warn(f"skipping {folder / name}: partial item (not in the manifest; rerun `ppmrecon-train generate`)")
        entries = [(name, entry) for name, entry in sorted(listed.items())
                   if passes is None or entry.get("passes") == passes]
        mine = [(k, name, entry) for k, (name, entry) in enumerate(entries, candidates) if k % world == rank]
        candidates += len(entries)
        if not mine:
            continue
        try:
            ref_np, _ = B.read_rgb(folder / REFERENCE)
        except PpmreconError as exc:
            warn(f"skipping scene {scene['id']}: reference unusable ({exc})")
            continue
        reference = torch.from_numpy(ref_np).permute(2, 0, 1).contiguous()
        for index, name, entry in mine:
            path = folder / name
            try:
                buf = B.read_buffers(path)
            except PpmreconError as exc:
                warn(f"skipping {path}: {exc}")
                continue
            if buf.shape != tuple(ref_np.shape[:2]):
                warn(f"skipping {path}: size {buf.shape} differs from the reference {ref_np.shape[:2]}")
                continue
            try:
                guarded = guard_buffer(buf, guard)
                planes = buffer_guide(guarded, guide, guard)[0] if guide.enabled else None
                inputs = from_buffer(guarded, features, guide=None if planes is None else planes[None])
            except PpmreconError as exc:   # e.g. no pass count in the header
                warn(f"skipping {path}: {exc}")
                continue
            samples.append(Sample(str(path), scene["id"], int(entry.get("passes", 0)),
                                  inputs.features[0], inputs.y[0], inputs.z[0], reference, index, planes))
    if not_started:
        main_warn(f"{root}: skipping {not_started} {split} scene(s) not generated yet "
                  "(rerun `ppmrecon-train generate` to complete them)")
    return samples


#: One patch of a batch: (sample position in the catalogue, y0, x0, turns, flip, size).
Row = tuple[int, int, int, int, bool, int]


class PatchSampler:
    """Random augmented patches from a list of samples (deterministic given ``seed``).

    ``catalog``: the (height, width) of every sample of the whole training set, in the
    single-process order, when ``samples`` hold only this rank's shard; each sample's
    place in it is given by ``positions`` (same order as ``samples``). Without them the
    samples are the whole set. :meth:`plan` draws a global batch from the catalogue
    (identically on every rank), :meth:`cut` makes the patches of the rows a rank
    holds; :meth:`batch` is both, for one process."""

    def __init__(self, samples: list[Sample], patch: int = 64, features: FeatureConfig = FeatureConfig(),
                 augment: bool = True, seed: int = 0, catalog: list[tuple[int, int]] | None = None,
                 positions: list[int] | None = None):
        if catalog is None:
            catalog = [tuple(s.y.shape[-2:]) for s in samples]
            positions = list(range(len(samples)))
        if not catalog:
            raise UsageError("no usable training samples (see the warnings above)")
        self.samples = samples
        self.catalog = catalog
        self.local = dict(zip(positions or [], samples))
        self.patch = patch
        self.augment = augment
        self.normal = features.slices()["normal"]
        self.rng = np.random.default_rng(seed)

    def plan(self, size: int) -> list[Row]:
        """Draw the patches of one global batch (the random stream is consumed exactly as
        by earlier versions' ``batch``: picks, then per pick its crop and augmentation)."""
        picks = self.rng.integers(0, len(self.catalog), size)
        rows = []
        for g in picks:
            h, w = self.catalog[int(g)]
            p = min(self.patch, h, w)
            y0 = int(self.rng.integers(0, h - p + 1))
            x0 = int(self.rng.integers(0, w - p + 1))
            turns, flip = (int(self.rng.integers(0, 4)), bool(self.rng.integers(0, 2))) if self.augment else (0, False)
            rows.append((int(g), y0, x0, turns, flip, p))
        # mixed image sizes smaller than the patch: every patch is cut to the smallest
        p = min(r[5] for r in rows)
        return [r[:5] + (p,) for r in rows]

    def mine(self, rows: list[Row]) -> list[Row]:
        """The rows whose sample this rank holds, in batch order."""
        return [r for r in rows if r[0] in self.local]

    def _one(self, row: Row) -> tuple[torch.Tensor, ...]:
        g, y0, x0, turns, flip, p = row
        s = self.local[g]
        full = min(self.patch, *s.y.shape[-2:])
        crop = (..., slice(y0, y0 + full), slice(x0, x0 + full))
        images = [s.features[crop], s.y[crop], s.z[crop], s.reference[crop]]
        if s.guide is not None:
            images.append(s.guide[crop])
        if self.augment:
            images = [transform_image(t, turns, flip) for t in images]
            images[0] = images[0].clone()
            images[0][self.normal] = transform_normals(images[0][self.normal], turns, flip)
        return tuple(t[..., :p, :p] for t in images)

    def cut(self, rows: list[Row]) -> tuple[torch.Tensor, ...]:
        """(features (B, C, P, P), y (B, 3, P, P), z (B, 4, 3, P, P), reference (B, 3, P, P))
        of ``rows`` (all held by this rank), and the guide (B, 4, P, P) when the samples
        have one."""
        parts = [self._one(r) for r in rows]
        return tuple(torch.stack(list(x)) for x in zip(*parts))

    def batch(self, size: int) -> tuple[torch.Tensor, ...]:
        """A batch of ``size`` patches (one process holding every sample)."""
        return self.cut(self.plan(size))
