"""Network inputs from a buffer file (paper 002 Sec. 4.3; SPEC section 5).

The kernel-predicting network sees 27 channels per pixel, in this order:

    0..14   the five estimates ~y, ~z^1..~z^4 (RGB each), HDR-compressed: log1p(x)
    15..19  their variances of the mean, compressed to match: log1p(V / (1 + xbar)^2)
    20..22  albedo (raw)
    23..25  normal (raw, world space)
    26      depth / max depth of the image

and, behind :class:`FeatureConfig` flags, 5 bandwidth channels (each chain's radius over
the image's largest radius) and 1 pass-count channel (log1p(N) / log1p(1e6)).

The variance transform is the delta method: ``Var[log1p X] ~= Var[X] / (1 + E X)^2``,
averaged over RGB by using the RGB mean ``xbar`` (the file stores V averaged over RGB),
and log1p-compressed again so that fireflies keep a bounded input range.

Only the network sees compressed values; the combiner gets the raw radiance ~y, ~z.
Per-image normalisations (depth, radius) use the whole image, so compute features once
per image and crop them afterwards (tiles, training patches).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping, NamedTuple

import numpy as np
import torch

from ..buffers import H_PASSES, N_ESTIMATES, BufferFile
from ..errors import UsageError

N_BASE_CHANNELS = 3 * N_ESTIMATES + N_ESTIMATES + 3 + 3 + 1   # = 27 (paper 002 Sec. 4.3)
_PASS_SCALE = math.log1p(1e6)


@dataclass(frozen=True)
class FeatureConfig:
    """Which optional channels the network gets on top of the 27 of the paper."""

    radius: bool = False   # + 5 channels: per-chain bandwidth / the image's largest bandwidth
    passes: bool = False   # + 1 channel: log1p(passes) / log1p(1e6), constant over the image

    @property
    def n_channels(self) -> int:
        return N_BASE_CHANNELS + (N_ESTIMATES if self.radius else 0) + (1 if self.passes else 0)

    def slices(self) -> dict[str, slice]:
        """Channel ranges by name (e.g. to transform ``normal`` under augmentation)."""
        names = [("estimates", 3 * N_ESTIMATES), ("variances", N_ESTIMATES), ("albedo", 3),
                 ("normal", 3), ("depth", 1)]
        if self.radius:
            names.append(("radius", N_ESTIMATES))
        if self.passes:
            names.append(("passes", 1))
        out, start = {}, 0
        for name, n in names:
            out[name] = slice(start, start + n)
            start += n
        return out

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "FeatureConfig":
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"unknown feature setting(s) {', '.join(unknown)}")
        for key, value in data.items():
            if not isinstance(value, bool):
                raise ValueError(f"feature setting '{key}' must be true or false, got {value!r}")
        return cls(**dict(data))


class ModelInputs(NamedTuple):
    """Everything the denoiser needs for one image (batch of 1), float32 torch tensors."""

    features: torch.Tensor   # (1, C, H, W) network input
    y: torch.Tensor          # (1, 3, H, W) raw ~y
    z: torch.Tensor          # (1, 4, 3, H, W) raw ~z^1..~z^4


def compress_radiance(x: torch.Tensor) -> torch.Tensor:
    """HDR compression of radiance for the network: log1p (x >= 0)."""
    return torch.log1p(x)


def compress_variance(var: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """Delta-method variance of log1p(X): V / (1 + E X)^2, log1p-compressed again."""
    return torch.log1p(var / (1.0 + mean) ** 2)


class FeatureScales(NamedTuple):
    """Per-image normalisers, from the whole image so that crops agree with it."""

    depth: torch.Tensor    # (B,) largest depth
    radius: torch.Tensor   # (B,) largest bandwidth of the widest chain (ones if unused)


def feature_scales(depth: torch.Tensor, radii: torch.Tensor | None = None) -> FeatureScales:
    """Scales of whole images: depth (B, H, W), radii (B, 5, H, W) or None."""
    peak_r = radii[:, -1].flatten(1).amax(1) if radii is not None else torch.ones(depth.shape[0])
    return FeatureScales(depth.flatten(1).amax(1), peak_r)


def _divide(x: torch.Tensor, peak: torch.Tensor) -> torch.Tensor:
    """x / peak per image of the batch; 0 for an image whose peak is 0 (e.g. all sky)."""
    peak = peak.to(x.dtype).view(-1, *([1] * (x.dim() - 1)))
    safe = torch.where(peak > 0, peak, torch.ones_like(peak))
    return torch.where(peak > 0, x / safe, torch.zeros_like(x))


def build_features(estimates: torch.Tensor, variances: torch.Tensor, albedo: torch.Tensor,
                   normal: torch.Tensor, depth: torch.Tensor, config: FeatureConfig = FeatureConfig(),
                   radii: torch.Tensor | None = None, passes: torch.Tensor | None = None,
                   scales: FeatureScales | None = None) -> torch.Tensor:
    """Assemble the (B, C, H, W) network input.

    estimates (B, 5, 3, H, W), variances (B, 5, H, W), albedo and normal (B, 3, H, W),
    depth (B, H, W); radii (B, 5, H, W) and passes (B,) when the config asks for them.
    Without ``scales`` the inputs are taken to be whole images; for a crop, pass the
    whole image's :func:`feature_scales`.
    """
    b, n, _, h, w = estimates.shape
    if config.radius and radii is None:
        raise ValueError("FeatureConfig(radius=True) needs radii")
    if config.passes and passes is None:
        raise ValueError("FeatureConfig(passes=True) needs the pass count")
    if scales is None:
        scales = feature_scales(depth, radii if config.radius else None)
    mean = estimates.mean(2)                                           # (B, 5, H, W)
    parts = [compress_radiance(estimates).reshape(b, 3 * n, h, w),
             compress_variance(variances, mean), albedo, normal,
             _divide(depth, scales.depth).unsqueeze(1)]
    if config.radius:
        parts.append(_divide(radii, scales.radius))
    if config.passes:
        level = torch.log1p(passes.to(estimates.dtype).clamp(min=0)) / _PASS_SCALE
        parts.append(level.view(b, 1, 1, 1).expand(b, 1, h, w))
    return torch.cat(parts, 1)


def _passes(buf: BufferFile) -> torch.Tensor:
    try:
        return torch.tensor([float(buf.header[H_PASSES])])
    except (KeyError, TypeError, ValueError):
        raise UsageError(f"the model needs the pass count, but the buffer header has no valid '{H_PASSES}'") from None


def buffer_scales(buf: BufferFile) -> FeatureScales:
    """:func:`feature_scales` of a whole buffer file."""
    return FeatureScales(torch.tensor([float(buf.depth.max(initial=0.0))]),
                         torch.tensor([float(buf.radii[-1].max(initial=0.0))]))


def from_buffer(buf: BufferFile, config: FeatureConfig = FeatureConfig(),
                crop: tuple[slice, slice] | None = None, scales: FeatureScales | None = None) -> ModelInputs:
    """Network features and raw ~y, ~z of one buffer file (see module docstring).

    ``crop=(rows, cols)`` gives the inputs of that window only, normalised like the
    whole image (pass ``scales=buffer_scales(buf)`` to compute the scales once).
    """
    rows, cols = crop or (slice(None), slice(None))
    if scales is None:
        scales = buffer_scales(buf)

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).unsqueeze(0)

    est = t(buf.estimates[:, rows, cols]).permute(0, 1, 4, 2, 3)      # (1, 5, 3, h, w)
    feats = build_features(est, t(buf.variances[:, rows, cols]), t(buf.albedo[rows, cols]).permute(0, 3, 1, 2),
                           t(buf.normal[rows, cols]).permute(0, 3, 1, 2), t(buf.depth[rows, cols]), config,
                           radii=t(buf.radii[:, rows, cols]) if config.radius else None,
                           passes=_passes(buf) if config.passes else None, scales=scales)
    return ModelInputs(feats, est[:, 0].contiguous(), est[:, 1:].contiguous())
