"""Network inputs from a buffer file (paper 002 Sec. 4.3; SPEC section 5).

The kernel-predicting network sees 27 channels per pixel, in this order:

    0..14   the five estimates ~y, ~z^1..~z^4 (RGB each), HDR-compressed: log1p(x)
    15..19  their variances of the mean, compressed to match: log1p(V / (1 + xbar)^2)
    20..22  albedo (raw)
    23..25  normal (raw, world space)
    26      depth / max depth of the image

and, behind :class:`FeatureConfig` flags, 5 bandwidth channels (each chain's radius over
the image's largest radius), 1 pass-count channel (log1p(N) / log1p(1e6)) and 3 outlier
channels (below).

The variance transform is the delta method: ``Var[log1p X] ~= Var[X] / (1 + E X)^2``,
averaged over RGB by using the RGB mean ``xbar`` (the file stores V averaged over RGB),
and log1p-compressed again so that fireflies keep a bounded input range.

``scale_free`` (issue 12): log1p of raw radiance depends on the units of the scene (a
scene at 1e-4 looks all black to the network, one at 1e4 saturates it). With the flag,
the estimates are divided by the image's radiance scale ``s`` (:func:`.guard.image_scale`)
before log1p, and the variances become relative: ``log1p(V / (xbar^2 + (f s)^2))``, the
squared relative standard error (f = :data:`.guard.RELATIVE_FLOOR`). Every channel is
then unchanged when all radiance is multiplied by a constant.

``outliers`` adds 3 scale-free channels that say how the estimates disagree, which is
what a firefly looks like: for ~y and for ~z^1 (the sharpest of the correlated four,
which share hit point B and mostly their spikes), ``log((xbar_k + f s) / (M_k + f s))``
with M_k a robust level of its 3 x 3 window (:func:`.guard.local_floor`; a lone bright
pixel stands out of it), and ``log((max_k xbar_k + f s) / (median_k xbar_k + f s))``
over the five (one or two estimates far from the others). Not one contrast per
estimate: per-tile work and the first layer's width are what inference time is made of.

``guide`` adds the denoiser guide (:mod:`.guide`; OIDN's image of ~z^4) as 3 channels,
``log1p(g / s)``: the network then sees what the prior of the weights pulls towards, and
can learn where to trust it (with the guide's ``temperature``).

Only the network sees compressed values; the combiner gets the raw radiance ~y, ~z.
Per-image normalisations (depth, radius, radiance) use the whole image, so compute
features once per image and crop them afterwards (tiles, training patches);
:func:`from_buffer` crops exactly (the 3 x 3 levels see one pixel beyond the crop).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping, NamedTuple

import numpy as np
import torch

from ..buffers import N_ESTIMATES, BufferFile
from ..fileio import unknown_keys
from .guard import RELATIVE_FLOOR, image_scale, local_floor, median_of_estimates, passes_of
from .guide import guide_channels

N_BASE_CHANNELS = 3 * N_ESTIMATES + N_ESTIMATES + 3 + 3 + 1   # = 27 (paper 002 Sec. 4.3)
N_OUTLIER_CHANNELS = 3   # contrast of ~y, contrast of ~z^1, spread of the five
N_GUIDE_CHANNELS = 3     # the denoiser guide's RGB
_PASS_SCALE = math.log1p(1e6)


@dataclass(frozen=True)
class FeatureConfig:
    """Which optional channels the network gets on top of the 27 of the paper."""

    radius: bool = False       # + 5 channels: per-chain bandwidth / the image's largest bandwidth
    passes: bool = False       # + 1 channel: log1p(passes) / log1p(1e6), constant over the image
    scale_free: bool = False   # radiance / image scale before log1p; relative variances
    outliers: bool = False     # + 3 channels: ~y, ~z^1 over their 3x3 level; max/median of the five
    guide: bool = False        # + 3 channels: the denoiser guide, log1p(g / s) (needs the guide on)

    @property
    def n_channels(self) -> int:
        return (N_BASE_CHANNELS + (N_ESTIMATES if self.radius else 0) + (1 if self.passes else 0)
                + (N_OUTLIER_CHANNELS if self.outliers else 0) + (N_GUIDE_CHANNELS if self.guide else 0))

    def slices(self) -> dict[str, slice]:
        """Channel ranges by name (e.g. to transform ``normal`` under augmentation)."""
        names = [("estimates", 3 * N_ESTIMATES), ("variances", N_ESTIMATES), ("albedo", 3),
                 ("normal", 3), ("depth", 1)]
        if self.radius:
            names.append(("radius", N_ESTIMATES))
        if self.passes:
            names.append(("passes", 1))
        if self.outliers:
            names.append(("outliers", N_OUTLIER_CHANNELS))
        if self.guide:
            names.append(("guide", N_GUIDE_CHANNELS))
        out, start = {}, 0
        for name, n in names:
            out[name] = slice(start, start + n)
            start += n
        return out

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "FeatureConfig":
        unknown = unknown_keys(cls, data)
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
    #: (1, 4, H, W) the denoiser guide and its tolerance (:mod:`.guide`); None without a guide
    guide: torch.Tensor | None = None


def compress_radiance(x: torch.Tensor) -> torch.Tensor:
    """HDR compression of radiance for the network: log1p (x >= 0)."""
    return torch.log1p(x)


def compress_variance(var: torch.Tensor, mean: torch.Tensor) -> torch.Tensor:
    """Delta-method variance of log1p(X): V / (1 + E X)^2, log1p-compressed again."""
    return torch.log1p(var / (1.0 + mean) ** 2)


class FeatureScales(NamedTuple):
    """Per-image normalisers, from the whole image so that crops agree with it."""

    depth: torch.Tensor      # (B,) largest depth
    radius: torch.Tensor     # (B,) largest bandwidth of the widest chain (ones if unused)
    radiance: torch.Tensor | None = None   # (B,) :func:`.guard.image_scale`; None if unused


def _needs_radiance(config: FeatureConfig) -> bool:
    return config.scale_free or config.outliers or config.guide


def feature_scales(depth: torch.Tensor, radii: torch.Tensor | None = None,
                   estimates: torch.Tensor | None = None) -> FeatureScales:
    """Scales of whole images: depth (B, H, W), radii (B, 5, H, W) or None,
    estimates (B, 5, 3, H, W) or None (no radiance scale)."""
    peak_r = radii[:, -1].flatten(1).amax(1) if radii is not None else torch.ones(depth.shape[0])
    radiance = image_scale(estimates) if estimates is not None else None
    return FeatureScales(depth.flatten(1).amax(1), peak_r, radiance)


def _per_image(v: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    return v.to(like.dtype).view(-1, *([1] * (like.dim() - 1)))


def _divide(x: torch.Tensor, peak: torch.Tensor) -> torch.Tensor:
    """x / peak per image of the batch; 0 for an image whose peak is 0 (e.g. all sky)."""
    peak = _per_image(peak, x)
    safe = torch.where(peak > 0, peak, torch.ones_like(peak))
    return torch.where(peak > 0, x / safe, torch.zeros_like(x))


def outlier_channels(mean: torch.Tensor, floor: torch.Tensor) -> torch.Tensor:
    """The 3 ``outliers`` channels from RGB means (B, 5, H, W) and the floor f s (B,)."""
    f = _per_image(floor, mean)
    sharp = mean[:, :2]                                                        # ~y, ~z^1
    contrast = (sharp + f).div_(local_floor(sharp).add_(f)).log_()
    spread = (mean.amax(1, keepdim=True) + f).div_(median_of_estimates(mean).unsqueeze(1).add_(f)).log_()
    return torch.cat([contrast, spread], 1)


def build_features(estimates: torch.Tensor, variances: torch.Tensor, albedo: torch.Tensor,
                   normal: torch.Tensor, depth: torch.Tensor, config: FeatureConfig = FeatureConfig(),
                   radii: torch.Tensor | None = None, passes: torch.Tensor | None = None,
                   scales: FeatureScales | None = None, guide: torch.Tensor | None = None) -> torch.Tensor:
    """Assemble the (B, C, H, W) network input.

    estimates (B, 5, 3, H, W), variances (B, 5, H, W), albedo and normal (B, 3, H, W),
    depth (B, H, W); radii (B, 5, H, W), passes (B,) and the guide planes (B, 4, H, W,
    :func:`.guide.guide_planes`) when the config asks for them.
    Without ``scales`` the inputs are taken to be whole images; for a crop, pass the
    whole image's :func:`feature_scales`.
    """
    b, n, _, h, w = estimates.shape
    if config.radius and radii is None:
        raise ValueError("FeatureConfig(radius=True) needs radii")
    if config.passes and passes is None:
        raise ValueError("FeatureConfig(passes=True) needs the pass count")
    if config.guide and guide is None:
        raise ValueError("FeatureConfig(guide=True) needs the denoiser guide's planes (the guide on)")
    if scales is None:
        scales = feature_scales(depth, radii if config.radius else None,
                                estimates if _needs_radiance(config) else None)
    if _needs_radiance(config) and scales.radiance is None:
        raise ValueError("scale-free/outlier features need the image's radiance scale: "
                         "buffer_scales(buf, config) or feature_scales(..., estimates)")
    mean = estimates.mean(2)                                           # (B, 5, H, W)
    floor = RELATIVE_FLOOR * scales.radiance if scales.radiance is not None else None
    if config.scale_free:
        s = _per_image(scales.radiance, mean)
        radiance = compress_radiance(estimates * (1.0 / s).unsqueeze(-1))
        # squared relative standard error: scale-free, ~1 for a one-pass firefly
        variance = torch.log1p(variances / (mean.square() + _per_image(floor, mean).square()))
    else:
        radiance, variance = compress_radiance(estimates), compress_variance(variances, mean)
    parts = [radiance.reshape(b, 3 * n, h, w), variance, albedo, normal,
             _divide(depth, scales.depth).unsqueeze(1)]
    if config.radius:
        parts.append(_divide(radii, scales.radius))
    if config.passes:
        level = torch.log1p(passes.to(estimates.dtype).clamp(min=0)) / _PASS_SCALE
        parts.append(level.view(b, 1, 1, 1).expand(b, 1, h, w))
    if config.outliers:
        parts.append(outlier_channels(mean, floor))
    if config.guide:
        parts.append(guide_channels(guide, scales.radiance))
    return torch.cat(parts, 1)


def buffer_scales(buf: BufferFile, config: FeatureConfig = FeatureConfig()) -> FeatureScales:
    """:func:`feature_scales` of a whole buffer file (the radiance scale only if ``config``
    uses it: it costs a pass over the image)."""
    radiance = None
    if _needs_radiance(config):
        est = torch.from_numpy(np.ascontiguousarray(buf.estimates, dtype=np.float32)).permute(0, 3, 1, 2)[None]
        radiance = image_scale(est)
    return FeatureScales(torch.tensor([float(buf.depth.max(initial=0.0))]),
                         torch.tensor([float(buf.radii[-1].max(initial=0.0))]), radiance)


def _widen(s: slice, size: int, by: int) -> tuple[slice, slice]:
    """``s`` widened by ``by`` pixels each side (clipped), and where ``s`` lies in it."""
    start, stop, _ = s.indices(size)
    lo, hi = max(start - by, 0), min(stop + by, size)
    return slice(lo, hi), slice(start - lo, start - lo + max(stop - start, 0))


def from_buffer(buf: BufferFile, config: FeatureConfig = FeatureConfig(),
                crop: tuple[slice, slice] | None = None, scales: FeatureScales | None = None,
                guide: torch.Tensor | None = None) -> ModelInputs:
    """Network features and raw ~y, ~z of one buffer file (see module docstring).

    ``crop=(rows, cols)`` gives the inputs of that window only, normalised like the
    whole image (pass ``scales=buffer_scales(buf, config)`` to compute the scales once).
    ``guide``: the whole image's (1, 4, H, W) :func:`.guide.guide_planes`, cropped alike.
    """
    rows, cols = crop or (slice(None), slice(None))
    if scales is None:
        scales = buffer_scales(buf, config)
    height, width = buf.shape
    # the 3x3 levels of the outlier channels need one pixel beyond the crop to equal
    # the whole image's; the others are per pixel
    by = 1 if config.outliers else 0
    (rows, keep_r), (cols, keep_c) = _widen(rows, height, by), _widen(cols, width, by)

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).unsqueeze(0)

    est = t(buf.estimates[:, rows, cols]).permute(0, 1, 4, 2, 3)      # (1, 5, 3, h, w)
    feats = build_features(est, t(buf.variances[:, rows, cols]), t(buf.albedo[rows, cols]).permute(0, 3, 1, 2),
                           t(buf.normal[rows, cols]).permute(0, 3, 1, 2), t(buf.depth[rows, cols]), config,
                           radii=t(buf.radii[:, rows, cols]) if config.radius else None,
                           passes=torch.tensor([passes_of(buf)]) if config.passes else None, scales=scales,
                           guide=guide[..., rows, cols] if config.guide and guide is not None else None)
    est = est[..., keep_r, keep_c]
    if guide is not None:
        guide = guide[..., crop[0], crop[1]].contiguous() if crop else guide
    return ModelInputs(feats[..., keep_r, keep_c].contiguous(), est[:, 0].contiguous(), est[:, 1:].contiguous(),
                       guide)
