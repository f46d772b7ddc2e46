"""Training and validation samples from a generated data set, and 64x64 patch batches.

Every input buffer file of a scene is paired with that scene's reference. With the
firefly guard on, each buffer file is guarded first (:func:`..model.guard.guard_buffer`,
the same call inference makes), so ~y, ~z and the features are what the model will see
when it denoises. Network features are computed on the whole image (their per-image
normalisations must not see a crop), then patches are cut and augmented with one of the
eight flips/rotations, identically for every layer (normals turn with the image, see
:mod:`.augment`).

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


def load_split(root: str | os.PathLike, split: str, features: FeatureConfig = FeatureConfig(),
               passes: int | None = None, warn: Warn | None = None,
               guard: GuardConfig = GuardConfig(), max_disagreement: float | None = None) -> list[Sample]:
    """All usable samples of ``split`` ("train" or "val"), optionally of one pass count.

    ``max_disagreement``: skip scenes whose two reference halves disagree by more than
    this trimmed relMSE (manifest ``agreement.relmse_trimmed``): a reference that far from
    converged teaches its own noise.
    """
    root = Path(root)
    warn = warn or (lambda msg: None)
    manifest = load_manifest(root)
    config = manifest.get("config", {})
    samples: list[Sample] = []
    for scene in manifest.get("scenes", []):
        if scene.get("split") != split:
            continue
        folder = root / scene["id"]
        disagreement = (scene.get("agreement") or {}).get("relmse_trimmed")
        if max_disagreement is not None and disagreement is not None and disagreement > max_disagreement:
            warn(f"skipping scene {scene['id']}: its two references disagree by trimmed relMSE "
                 f"{disagreement:.3g} > {max_disagreement:g} (not converged)")
            continue
        try:
            ref_np, _ = B.read_rgb(folder / REFERENCE)
        except PpmreconError as exc:
            warn(f"skipping scene {scene['id']}: reference unusable ({exc})")
            continue
        reference = torch.from_numpy(ref_np).permute(2, 0, 1).contiguous()
        promised = {input_name(n, s) for n in config.get("input_passes", []) for s in config.get("seeds", [])}
        listed = {f["file"]: f for f in scene.get("inputs", [])}
        for name in sorted(promised - set(listed)):
            warn(f"skipping {folder / name}: partial item (not in the manifest; rerun `ppmrecon-train generate`)")
        for name, entry in sorted(listed.items()):
            if passes is not None and entry.get("passes") != passes:
                continue
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
                inputs = from_buffer(guard_buffer(buf, guard), features)
            except PpmreconError as exc:   # e.g. no pass count in the header
                warn(f"skipping {path}: {exc}")
                continue
            samples.append(Sample(str(path), scene["id"], int(entry.get("passes", 0)),
                                  inputs.features[0], inputs.y[0], inputs.z[0], reference))
    return samples


class PatchSampler:
    """Random augmented patches from a list of samples (deterministic given ``seed``)."""

    def __init__(self, samples: list[Sample], patch: int = 64, features: FeatureConfig = FeatureConfig(),
                 augment: bool = True, seed: int = 0):
        if not samples:
            raise UsageError("no usable training samples (see the warnings above)")
        self.samples = samples
        self.patch = patch
        self.augment = augment
        self.normal = features.slices()["normal"]
        self.rng = np.random.default_rng(seed)

    def _one(self, s: Sample) -> tuple[torch.Tensor, ...]:
        _, h, w = s.y.shape
        p = min(self.patch, h, w)
        y0 = int(self.rng.integers(0, h - p + 1))
        x0 = int(self.rng.integers(0, w - p + 1))
        crop = (..., slice(y0, y0 + p), slice(x0, x0 + p))
        feats, y, z, ref = s.features[crop], s.y[crop], s.z[crop], s.reference[crop]
        if self.augment:
            turns, flip = int(self.rng.integers(0, 4)), bool(self.rng.integers(0, 2))
            feats, y, z, ref = (transform_image(t, turns, flip) for t in (feats, y, z, ref))
            feats = feats.clone()
            feats[self.normal] = transform_normals(feats[self.normal], turns, flip)
        return feats, y, z, ref

    def batch(self, size: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(features (B, C, P, P), y (B, 3, P, P), z (B, 4, 3, P, P), reference (B, 3, P, P))."""
        picks = self.rng.integers(0, len(self.samples), size)
        parts = [self._one(self.samples[int(i)]) for i in picks]
        sizes = {t[1].shape[-1] for t in parts} | {t[1].shape[-2] for t in parts}
        if len(sizes) != 1:  # mixed image sizes smaller than the patch: use the smallest
            p = min(sizes)
            parts = [tuple(t[..., :p, :p] for t in part) for part in parts]
        return tuple(torch.stack(list(x)) for x in zip(*parts))  # type: ignore[return-value]
