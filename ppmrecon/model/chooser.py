"""A learned per-pixel choice among consistent candidates, on top of the envelope (issue 12).

The envelope (:func:`.guide.envelope`) is OIDN's image held inside the range of each pixel's
five estimates. Any image held inside that range converges to the pixel's truth, and so
does any convex combination of such images (paper 002 Appendix A's argument, applied to
the band rather than to Eq. 6's terms). The chooser therefore outputs

    yhat_c = sum_k w_{k,c} C_{k,c},   w_{.,c} = softmax(prior + f_theta(features)_c),

over the candidates C_k (:data:`CANDIDATES`), each clamped per channel into
``[min_j X_{j,c}, max_j X_{j,c}]`` (X = ~y, ~z^1..~z^4): the envelope, the guide without the
anchor, OIDN's images of ~z^4 and of ~y, and ~z^1..~z^4 themselves. The weights may be any
function of anything without costing consistency, so f_theta sees scale-free features of
every candidate and of the inputs' noise. Its head starts at zero and the prior puts
logit :attr:`ChooserConfig.prior` on the envelope, so an untrained chooser is mostly the
envelope.

Measured held out (``benchmarks/bench_refine.py --steps 3000``: 4-fold by scene over the 288
images of 36 scenes of ``data/v3_cpu``, each fold scored by a chooser trained on the other
three with the shipped config), geometric means over each image's best single input: 0.497
against the envelope's 0.535, 7 images worse than their best input against 15, 8x8-block
ratio 0.92 against 0.94. On the literature scenes (``benchmarks/results/chooser``) it is
worse than the envelope (0.474 against 0.436; at N = 1024, beyond the training data's 256,
box 1.33x its best input), so the shipped model carries it opt-in (``--guide-mode chooser``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import torch
import torch.nn as nn

from ..fileio import unknown_keys

#: The candidates, in the order of the chooser's weights.
CANDIDATES = ("envelope", "guide", "oidn(z4)", "oidn(y)", "z1", "z2", "z3", "z4")
N_CANDIDATES = len(CANDIDATES)
#: Feature channels: log1p of every candidate and of ~y (27), the five estimates' standard
#: deviations of the mean (5), albedo (3), normal (3), the band's width (3), log2 N / 10 (1).
N_FEATURES = 3 * N_CANDIDATES + 3 + 5 + 3 + 3 + 3 + 1
#: The channel of the normal's x among the features (a mirror image negates it).
FEATURE_NORMAL_X = 3 * N_CANDIDATES + 3 + 5 + 3


@dataclass(frozen=True)
class ChooserConfig:
    """The chooser's architecture; travels inside the checkpoint (``"chooser"``)."""

    width: int = 12        # channels of each hidden 3 x 3 convolution
    layers: int = 2        # hidden convolutions
    prior: float = 3.0     # logit of the envelope before the network's correction

    def __post_init__(self) -> None:
        for key in ("width", "layers"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"chooser setting '{key}' must be a positive integer, got {value!r}")
        if isinstance(self.prior, bool) or not isinstance(self.prior, (int, float)) or not math.isfinite(self.prior):
            raise ValueError(f"chooser setting 'prior' must be a finite number, got {self.prior!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "ChooserConfig":
        unknown = unknown_keys(cls, data)
        if unknown:
            raise ValueError(f"unknown chooser setting(s) {', '.join(unknown)}")
        return cls(**dict(data))


def band(y: torch.Tensor, z: torch.Tensor, y_out: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-channel range of one image's five estimates, ``(lo, hi)``, each like ``y``
    ((H, W, 3) or (3, H, W)); z holds the four ~z^j along a leading axis ((4, *y.shape));
    ``y_out`` (y's shape with one channel) the pixels whose range is the ~z^j's alone (the
    envelope's lone ~y spikes, :func:`.guide.y_spike_mask`)."""
    from .guard import band_bounds

    lo, hi = band_bounds(y[None], z[None], 1.0, None if y_out is None else y_out[None])
    return lo[0], hi[0]


def candidates(envelope: torch.Tensor, guide: torch.Tensor, oidn_source: torch.Tensor, oidn_y: torch.Tensor,
               z: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """The candidates of one image in :data:`CANDIDATES`' order, (H, W, K, 3), each held in
    the band ``[lo, hi]`` (H, W, 3) of its five estimates (:func:`band`); the first four
    arguments are (H, W, 3) images (any strides), z (4, H, W, 3) the ~z^j, which are in
    their band already. Pixel-major, as the chooser reads them (channels-last)."""
    out = torch.empty(*lo.shape[:2], N_CANDIDATES, 3, dtype=lo.dtype, device=lo.device)
    for k, c in enumerate((envelope, guide, oidn_source, oidn_y)):
        torch.clamp(c, lo, hi, out=out[:, :, k])
    out[:, :, 4:] = z.permute(1, 2, 0, 3)
    return out


def features(cands: torch.Tensor, y: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor, variances: torch.Tensor,
             albedo: torch.Tensor, normal: torch.Tensor, scale: float, passes: float) -> torch.Tensor:
    """The chooser's input, (H, W, :data:`N_FEATURES`) (pixel-major: a channels-last image):
    radiance as log1p(x / s) with s the image's radiance scale (:func:`.guard.image_scale`),
    so the features do not change when all radiance is scaled. ``cands`` (H, W, K, 3) from
    :func:`candidates`, y (H, W, 3) (nonnegative, as every estimate), ``[lo, hi]`` the band,
    ``variances`` (5, H, W) of the mean (as standard deviations), albedo and normal (H, W, 3).
    Each transform runs on contiguous memory before its copy into the interleaved output
    (a transcendental on a strided view is several times slower)."""
    s = float(scale) if scale > 0 else 1.0
    h, w = y.shape[:2]
    k = 3 * N_CANDIDATES
    out = torch.empty(h, w, N_FEATURES, dtype=y.dtype, device=y.device)
    out[..., :k] = cands.reshape(h, w, k).div(s).log1p_()
    out[..., k:k + 3] = y.div(s).log1p_()
    out[..., k + 3:k + 8] = variances.clamp(min=0).sqrt_().div_(s).log1p_().permute(1, 2, 0)
    out[..., k + 8:k + 11] = albedo
    out[..., k + 11:k + 14] = normal
    out[..., k + 14:k + 17] = (hi - lo).div_(s).log1p_()
    out[..., k + 17] = math.log2(max(float(passes), 1.0)) / 10
    return out


class Chooser(nn.Module):
    """Features (B, :data:`N_FEATURES`, H, W) and candidates (B, K, 3, H, W) -> their convex
    combination (B, 3, H, W): ``layers`` 3 x 3 convolutions with ReLU, a 1 x 1 head that
    starts at zero, a softmax over the candidates with the envelope's prior logit."""

    def __init__(self, cfg: ChooserConfig = ChooserConfig()):
        super().__init__()
        self.cfg = cfg
        body: list[nn.Module] = []
        channels = N_FEATURES
        for _ in range(cfg.layers):
            body += [nn.Conv2d(channels, cfg.width, 3, padding=1), nn.ReLU(inplace=True)]
            channels = cfg.width
        self.body = nn.Sequential(*body)
        self.head = nn.Conv2d(channels, N_CANDIDATES, 1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        prior = torch.zeros(1, N_CANDIDATES, 1, 1)
        prior[0, 0] = cfg.prior
        self.register_buffer("prior", prior)

    def weights(self, feats: torch.Tensor) -> torch.Tensor:
        """The softmax weights (B, K, H, W)."""
        return torch.softmax(self.head(self.body(feats)) + self.prior, 1)

    def forward(self, feats: torch.Tensor, cands: torch.Tensor) -> torch.Tensor:
        return (self.weights(feats).unsqueeze(2) * cands).sum(1)

    @torch.no_grad()
    def predict(self, feats: torch.Tensor, cands: torch.Tensor) -> torch.Tensor:
        """Inference, channels-last (weights and features; about 2.5x faster on a CPU at
        1280x720, and free when ``feats`` is the pixel-major view :func:`features` makes);
        the mix as one contraction over the candidates of each pixel."""
        self.to(memory_format=torch.channels_last)
        w = self.weights(feats.contiguous(memory_format=torch.channels_last))
        return torch.einsum("bkhw,bkchw->bhwc", w, cands).permute(0, 3, 1, 2)   # pixel-major, like the input
