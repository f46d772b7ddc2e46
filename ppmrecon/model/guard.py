"""A consistent firefly guard around the combiner of paper 002 (Eq. 6; issue 12).

Two failure modes of Eq. 6, ``yhat_c = sum_{j,i} w^j_{c,i} (~y_i + ~z^j_c - ~z^j_i)``:

* a firefly at pixel c present in ~y_c and in every ~z^j_c (a hit point that saw the light
  through a rare specular chain, a photon shared by both gathers) is in *every* term at c
  (the i = c term is ~y_c, the others carry ~z^j_c), so no weights can remove it;
* a firefly at a neighbour's ~z^j_i drives the terms ``... - ~z^j_i`` of pixel c far below 0
  ("black dots" once the output is clamped at 0); one in ~y_i pushes them far above.

What the guard does
-------------------
1. **Input guard** (a switching median filter, per estimate X in {~y, ~z^1..~z^4}): with
   ``Xbar`` the RGB mean, ``M`` the median of ``Xbar`` over the 3 x 3 window of the same
   estimate, ``V`` its Welford variance of the mean (buffer layer ``*.V``) and N passes,
   pixel c of X is an outlier when

       Xbar_c > g(N) (M_c + eps)    and    sqrt(V_c) >= r0 Xbar_c,
       g(N) = g0 N^p,   eps = floor * s   (s: the image's radiance scale, :func:`image_scale`)

   and its R,G,B (and V, which only the network sees) are replaced by their 3 x 3
   medians in that estimate. The variance test keeps genuinely bright, steady pixels
   (a small light seen directly): a mean made by one pass has sqrt(V)/Xbar ~ 1, one made
   by k comparable passes ~ 1/sqrt(k), a steady pixel after N passes ~ 1/sqrt(N).
   With ``confirm`` c > 1 a pixel of ~y is also kept where a ~z^j of the same pixel
   (the independent hit point B) is settled, ``sqrt(V)/Xbar < r0``, and ``>= ~y / c``
   (:func:`confirmed`): a small light both hit points see. With ``peers`` m > 0 a pixel
   is also kept where m unsettled pixels of its 5 x 5 window in the same estimate are
   within 4x of it (:func:`speckled`): one speckle of a sparse field, not a lone firefly.
   With ``edge`` e > 0 a pixel is also kept where a settled pixel of its 3 x 3 window in
   the same estimate is at least e x its value (:func:`beside_a_light`): the edge of a
   small light, which some passes see and some do not. With ``mutual`` r1 (both hit points
   below sqrt(V)/Xbar = r1) or ``events`` K (both saw it, and their events Xbar^2 / V add up
   to K) no estimate of a pixel is an outlier where ~y and a ~z^j within ``confirm`` of each
   other confirm it (:func:`mutually_confirmed`, :func:`events_confirmed`): a rare light
   the two independent eye paths both see, where a photon both gathers shared in one pass
   leaves one event in each.
2. **Low-frequency anchor**: Eq. 6 takes its low frequencies from ~y. Every term is
   ``~y_i + (~z^j_c - ~z^j_i)``; the bracket is a high-pass of ~z^j over the K x K window,
   so below the window's frequency (K = 5 in the tiny preset) the output is a weighted
   mean of ~y, the noisiest of the five inputs (smallest bandwidth, its own hit point A).
   That is the "smooth error" of issue 12: on a glossy Cornell box the 8x8-block relMSE
   of the output was 7x that of ~z^4. The anchor keeps the high frequencies of the
   combination and takes the low ones from ~z^4, the widest (lowest-variance) chain:

       yhat'_c = yhat_c + (G_sigma * (~z^4 - yhat))_c,

   G_sigma a normalised Gaussian (``anchor`` = sigma in pixels). The bandwidth bias of
   ~z^4 is a blur of the radiance at the scale of its radius, which G_sigma blurs
   further anyway; the weights' noise-dependent bias (a log-L1-trained network leans to
   the median of right-skewed photon noise, i.e. darker) is removed at the scales G_sigma
   passes.
3. **Output band**: the combined value is clamped, per channel, into
   ``[min_k Xhat_{k,c} / h, max_k Xhat_{k,c} * h]`` over the five guarded inputs at c
   (h >= 1); this replaces the old clamp at 0 (the band's floor is >= 0) and removes
   black dots: no pixel can fall below all five of its own estimates.

Why the result stays consistent (paper 002 Eq. 7, Appendix A)
---------------------------------------------------------------
Let the inputs converge, X_{k,c}(N) -> x_c (finite) for every k and c, as N -> inf.

* Input guard: ``g(N) -> inf`` and ``eps(N) -> floor * s(x) > 0`` whenever the truth is
  not all black (s is a mean of the five estimates' per-pixel median, which converges
  to that of x). Then ``g(N)(M_c + eps) -> inf`` while ``Xbar_c -> x_c`` stays finite,
  so after some N_c the outlier test is false at c and ``Xhat_c = X_c`` exactly: the
  guard is eventually the identity, pixel by pixel (an all-black truth is converged
  to by any replacement too: medians of values that -> 0 go to 0). The variance test
  can only switch replacements off, so it cannot break this. The replacement value
  does not matter for the limit, which is why it can be the local median (a value
  that removes the firefly) instead of the threshold.
* Combiner: Eq. 6 on the guarded inputs is a convex combination of terms
  ``Xhat-y_i + Xhat-z^j_c - Xhat-z^j_i`` that each converge to x_c, so it converges to
  x_c whatever the weights (Appendix A).
* Anchor: G_sigma is a fixed linear filter with unit sum, and ``~z^4 - yhat -> 0`` at
  every pixel, so the correction goes to 0 and ``yhat' -> x_c``. The anchored value may
  leave Appendix A's interval of terms; the band below brings it back to within the five
  estimates at c, which converge to x_c themselves (for h = 1 that alone is a proof).
* Band: the term with i = c is ``~y_c`` itself, and ``min_k Xhat_{k,c} / h <= ~y_c <=
  max_k Xhat_{k,c} * h`` (radiance >= 0, h >= 1), so the band always overlaps the
  interval [smallest term, largest term] of Appendix A; clamping a point of that interval
  into the band keeps it inside the interval (up to float rounding). The banded output
  is therefore still between the smallest and largest term and converges to x_c by
  Eq. 10-12. (The band's ends also converge, to x_c / h and x_c h.) No growth of h is
  needed; h = 1 confines the output to the range of its own five estimates.

Constants (the ``GuardConfig`` defaults), measured with the shipped model on the built-in
``water_caustic`` and ``cornell_caustics`` at 128 px, 65536 photons, N = 16, 64, 256
(and a second seed at 64), against 1024-pass single-bandwidth references:

* ``g(N) = 16 sqrt(N)`` (g = 64, 128, 256 at N = 16, 64, 256). Those renders have
  no catastrophic outliers; their largest are water sparkles (the light seen through
  the surface in one pass: 55 at N = 16, 14 at N = 64, 78-180 and 25-50 x the local
  median) whose truth is 1-16 x that median. g0 = 16 replaces the 13 worst (N = 16):
  plain and trimmed relMSE -3%, 8x8-block relMSE +0.5%; g0 = 8 also touches
  ``cornell_caustics`` N = 16 (trimmed +1.4%) and water N = 64; g0 = 2-4 removes the
  N = 64 sparkles and real energy with them (block relMSE +50%). So 16 is the most
  aggressive power of two that costs no metric more than 1% on those renders, while
  issue 12's example (1750 x the truth at N = 64) and the synthetic 1e3..1e5 x of
  ``tests/test_fireflies.py`` are far above it. ``sqrt(N)``: one pass of value E adds
  E / N to the mean, so caught events need E > g0 N^1.5 x the local median: the guard
  fades out as more passes average such events in.
* ``r0 = 0.5`` (a mean made by at most ~4 comparable passes): with an aggressive g,
  ``r0 = 0`` tripled the block error of ``cornell_caustics`` N = 16 (steady caustic
  peaks replaced), 0.5 kept it; 0.7 misses two-pass events (sqrt(V)/Xbar = 0.71).
* ``h = 1``: lower trimmed and block relMSE on all seven renders than h = 1.25, 2 or no
  band, lower plain relMSE on six (the seventh, water at N = 256, loses one pixel
  where all five inputs carry a sparkle and the unbanded output happened to be 0).
* ``floor = 1e-3``: radiance below 0.1% of the image's scale counts as black.
* ``anchor = 1.5`` (sigma in pixels), additive: measured with ``benchmarks/bench_anchor.py``
  on the first seven complete scenes of ``data/v2_cpu`` (all four N, seed 0; the model
  shipped before issue 12's retraining). Against the best single input, relMSE / 8x8-block
  relMSE geomean 0.66 / 1.20 without the anchor, 0.80 / 0.93 at sigma 1, 0.76 / 0.90 at
  1.5, 0.71 / 0.88 at 3; worse than the best input in relMSE on 10 / 3 / 4 / 8 of 28
  inputs. The anchor costs plain relMSE where ~z^4 is far off at high contrast (a small
  light seen directly: its edge spreads) and gains most where Eq. 6 leans on ~y. An
  energy-ratio form ``yhat (G ~z^4 + eps) / (G yhat + eps)`` was worse in block relMSE
  (geomean 0.97, max 2.2).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import Any, Mapping, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from ..buffers import H_PASSES, BufferFile
from ..errors import UsageError
from ..fileio import unknown_keys

#: eps = RELATIVE_FLOOR x the image's radiance scale: the smallest radiance the guard and
#: the scale-free features tell apart from black (a relative, not absolute, floor).
RELATIVE_FLOOR = 1e-3
#: :func:`speckled`: a peer is within this factor of the candidate (photons of one kind of
#: path carry comparable power, a firefly is orders of magnitude above its neighbours).
PEER_RATIO = 4.0
#: :func:`speckled`'s window (pixels, odd).
PEER_WINDOW = 5
#: Winsorising quantile of :func:`image_scale` (a 0.1% tail of fireflies cannot set it).
SCALE_QUANTILE = 0.999


# ------------------------------------------------------------------ robust statistics

def _sort(p: list[torch.Tensor], network: tuple[tuple[int, int], ...]) -> None:
    for i, j in network:
        p[i], p[j] = torch.minimum(p[i], p[j]), torch.maximum(p[i], p[j])


# Median selection networks (Paeth; Devillard's opt_med5 / opt_med9): 7 and 19 exchanges.
_MED5 = ((0, 1), (3, 4), (0, 3), (1, 4), (1, 2), (2, 3), (1, 2))
_MED9 = ((1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 3), (5, 8),
         (4, 7), (3, 6), (1, 4), (2, 5), (4, 7), (4, 2), (6, 4), (4, 2))


def _shifted(x: torch.Tensor) -> list[torch.Tensor]:
    """The 9 views x[r + dr, c + dc] (replicate padding) of (..., H, W), row-major."""
    h, w = x.shape[-2:]
    pad = F.pad(x.reshape(-1, 1, h, w), (1, 1, 1, 1), mode="replicate").reshape(*x.shape[:-2], h + 2, w + 2)
    return [pad[..., r:r + h, c:c + w] for r in range(3) for c in range(3)]


def median3x3(x: torch.Tensor) -> torch.Tensor:
    """Median over the 3 x 3 window of each pixel (replicate padding), any leading dims.

    A selection network on 9 shifted views: O(H W) temporaries, no 9-fold copy.
    """
    p = _shifted(x)
    _sort(p, _MED9)
    return p[4].contiguous()


def median3x3_at(x: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
    """:func:`median3x3` of x (C, H, W) at the pixels (rows, cols) only, (C, n): the 5th of
    the 9 window values, replicate padding, equal to the whole image's at those pixels."""
    h, w = x.shape[-2:]
    offsets = torch.arange(-1, 2, device=x.device)
    r = (rows[:, None, None] + offsets[None, :, None]).clamp(0, h - 1).expand(-1, 3, 3)
    c = (cols[:, None, None] + offsets[None, None, :]).clamp(0, w - 1).expand(-1, 3, 3)
    return x[:, r, c].reshape(x.shape[0], -1, 9).median(-1).values


def floor_of(cfg: "GuardConfig") -> float:
    """The relative floor eps / scale in force: the guard's ``floor``, or
    :data:`RELATIVE_FLOOR` with the guard off (the guide's rules use it either way)."""
    return cfg.floor if cfg.enabled else RELATIVE_FLOOR


def local_floor(x: torch.Tensor) -> torch.Tensor:
    """A robust local level in 6 operations instead of the median's 38: the smallest of
    the three row medians of the 3 x 3 window (replicate padding). A lone spike moves no
    row median; it is a lower bound of :func:`median3x3` (each row has at most one value
    below its median, so at most three of the nine lie below the smallest row median)."""
    p = _shifted(x)
    rows = [torch.maximum(torch.minimum(a, b), torch.minimum(torch.maximum(a, b), c))
            for a, b, c in (p[0:3], p[3:6], p[6:9])]
    return torch.minimum(torch.minimum(rows[0], rows[1]), rows[2])


def rgb_mean(x: torch.Tensor, dim: int, keepdim: bool = False) -> torch.Tensor:
    """``x.mean(dim)`` over a dimension of 3 (R, G, B) as ``(R + G + B) / 3``: the same float32
    sum in the same order, so bit-identical, and 2.5x faster on the buffer's pixel-major
    memory (a strided reduction: 6 against 16 ms for 5 x 3 x 1280 x 720)."""
    if x.shape[dim] != 3:
        raise ValueError(f"rgb_mean: dimension {dim} has {x.shape[dim]} channels, not 3")
    r, g, b = x.unbind(dim)
    out = torch.add(r, g).add_(b).div_(3)        # in place: one image-sized allocation, not three
    return out.unsqueeze(dim) if keepdim else out


def median_of_estimates(lum: torch.Tensor) -> torch.Tensor:
    """Per-pixel median of the five estimates, (B, 5, H, W) -> (B, H, W)."""
    p = list(lum.unbind(1))
    _sort(p, _MED5)
    return p[2]


def image_scale(estimates: torch.Tensor) -> torch.Tensor:
    """Radiance scale of whole images, (B,), from estimates (B, 5, 3, H, W).

    The mean over pixels of the median of the five estimates' RGB means, winsorised at
    its :data:`SCALE_QUANTILE` quantile: a firefly in up to two estimates does not enter
    the per-pixel median, one in all five is cut by the winsorising. Falls back to the
    plain mean where that is 0 (a few bright pixels on black), and to 1 for an all-black
    image. Converges to the same statistic of the truth as the inputs converge.
    """
    return _scale_of(rgb_mean(estimates, 2))


def _scale_of(lum: torch.Tensor) -> torch.Tensor:
    med = median_of_estimates(lum).flatten(1)                          # (B, H W)
    n = med.shape[1]
    top = n - min(n, max(1, math.ceil(SCALE_QUANTILE * n))) + 1        # values at or above the quantile
    q = med.topk(top, dim=1, sorted=False).values.amin(1, keepdim=True)
    wins = torch.minimum(med, q).mean(1)
    plain = med.mean(1)
    return torch.where(wins > 0, wins, torch.where(plain > 0, plain, torch.ones_like(plain)))


# ---------------------------------------------------------------------------- config

@dataclass(frozen=True)
class GuardConfig:
    """Firefly guard settings; travel inside the checkpoint (``"guard"``)."""

    enabled: bool = False
    threshold: float = 16.0       # g0 in g(N) = g0 N^growth: outlier = g(N) x local median
    growth: float = 0.5           # p: g(N) -> inf, so the guard is eventually the identity
    min_rel_error: float = 0.5    # r0: only pixels with sqrt(V)/Xbar >= r0 can be outliers
    band: float = 1.0             # h >= 1: output within [min_k Xhat / h, max_k Xhat * h]; 0 = no band
    floor: float = RELATIVE_FLOOR  # eps = floor x image_scale
    anchor: float = 1.5           # sigma (px) of the low-frequency anchor to ~z^4; 0 = off
    #: c > 1: a ~y pixel is no outlier where a ~z^j of the same pixel is settled (its
    #: sqrt(V)/Xbar below r0: many passes saw it) and at least 1/c of ~y (:func:`confirmed`);
    #: 0 = off (checkpoints without the setting read as 0)
    confirm: float = 0.0
    #: m > 0: a candidate is no outlier where at least m other pixels of its 5 x 5 window in
    #: the same estimate are unsettled and within :data:`PEER_RATIO` of it (:func:`speckled`:
    #: a sparse photon speckle field, not a lone firefly); 0 = off (checkpoints without it read as 0)
    peers: float = 0.0
    #: r1 > 0: no estimate of a pixel is an outlier where ~y and a ~z^j of it (the two
    #: independent hit points A and B) are each below sqrt(V)/Xbar = r1 (more than one pass
    #: behind each: r1 < 1) and within ``confirm`` (else 4) of each other
    #: (:func:`mutually_confirmed`: a small light both see, not a one-pass event); 0 = off
    #: (checkpoints without it read as 0)
    mutual: float = 0.0
    #: e > 0: a candidate is no outlier where a pixel of its 3 x 3 window in the same
    #: estimate is settled (sqrt(V)/Xbar < r0) and at least e x its value
    #: (:func:`beside_a_light`: the unsettled edge of a small light, not a firefly); 0 = off
    #: (checkpoints without it read as 0)
    edge: float = 0.0
    #: K > 0: no estimate of a pixel is an outlier where ~y and a ~z^j of it (hit points A and
    #: B) each saw the light at least once, lie within ``confirm`` (else 4) of each other, and
    #: together rest on at least K passes' events, counted as Xbar^2 / V per estimate
    #: (:func:`events_confirmed`: one chain's lone event beside several of the other's is a
    #: rare light both see, not a shared photon); 0 = off (checkpoints without it read as 0)
    events: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"guard setting 'enabled' must be true or false, got {self.enabled!r}")
        for key in ("threshold", "growth", "min_rel_error", "band", "floor", "anchor", "confirm", "peers", "mutual",
                    "edge", "events"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"guard setting '{key}' must be a finite number, got {value!r}")
        if self.threshold <= 0 or self.growth <= 0 or self.floor <= 0 or self.min_rel_error < 0:
            raise ValueError("guard settings threshold, growth and floor must be > 0, min_rel_error >= 0 "
                             "(growth > 0 is what makes the guard consistent)")
        if self.band != 0 and self.band < 1:
            raise ValueError(f"guard setting 'band' must be 0 (off) or >= 1, got {self.band}")
        if self.anchor < 0:
            raise ValueError(f"guard setting 'anchor' must be 0 (off) or a blur width > 0 in pixels, got {self.anchor}")
        if self.confirm != 0 and self.confirm <= 1:
            raise ValueError(f"guard setting 'confirm' must be 0 (off) or a factor > 1, got {self.confirm}")
        if self.mutual < 0 or self.mutual >= 1:
            raise ValueError(f"guard setting 'mutual' must be 0 (off) or a ratio in (0, 1), got {self.mutual}")
        if self.events != 0 and self.events <= 2:
            raise ValueError(f"guard setting 'events' must be 0 (off) or a count > 2 (one event in each chain "
                             f"is what a photon both gathers shared leaves), got {self.events}")
        if self.edge < 0:
            raise ValueError(f"guard setting 'edge' must be 0 (off) or a ratio > 0, got {self.edge}")
        if self.peers < 0 or self.peers != int(self.peers) or self.peers > PEER_WINDOW ** 2 - 1:
            raise ValueError(f"guard setting 'peers' must be 0 (off) or a whole count of "
                             f"1..{PEER_WINDOW ** 2 - 1} neighbours, got {self.peers}")

    def factor(self, passes: torch.Tensor) -> torch.Tensor:
        """g(N) = threshold * N^growth for pass counts (B,)."""
        return self.threshold * passes.to(torch.float64).clamp(min=1.0) ** self.growth

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "GuardConfig":
        unknown = unknown_keys(cls, data)
        if unknown:
            raise ValueError(f"unknown guard setting(s) {', '.join(unknown)}")
        return cls(**dict(data))


#: The guard on, with the measured defaults (see the module docstring).
DEFAULT_ON = GuardConfig(enabled=True)


# ------------------------------------------------------------------------ input guard

class Guarded(NamedTuple):
    estimates: torch.Tensor   # (B, 5, 3, H, W) Xhat
    variances: torch.Tensor   # (B, 5, H, W) V with outliers replaced (network input only)
    outliers: torch.Tensor    # (B, 5, H, W) bool: where X was replaced


#: Above this fraction of candidate pixels, :func:`find_outliers` bounds the medians with
#: :func:`local_floor` first instead of gathering every candidate's window.
_GATHER_FRACTION = 1 / 8


def find_outliers(estimates: torch.Tensor, variances: torch.Tensor, passes: torch.Tensor,
                  cfg: GuardConfig) -> torch.Tensor:
    """The outlier test of the module docstring, (B, 5, H, W) bool."""
    b = estimates.shape[0]
    lum = rgb_mean(estimates, 2)
    eps = (cfg.floor * _scale_of(lum)).view(b, 1, 1, 1)
    g = cfg.factor(passes).to(lum.dtype).view(b, 1, 1, 1)
    # Per-pixel necessary conditions first (M >= 0); the 3x3 median only where they hold.
    mask = (variances.clamp(min=0).sqrt() >= cfg.min_rel_error * lum) & (lum > g * eps)   # sqrt(V)/Xbar >= r0
    if mask.sum() > _GATHER_FRACTION * mask.numel():
        mask &= lum > g * (local_floor(lum) + eps)                   # median >= floor: a cheap bound
    idx = mask.nonzero(as_tuple=True)
    if idx[0].numel():
        med = window_median(lum.unsqueeze(2), idx).squeeze(1)
        mask[idx] = lum[idx] > g.view(b)[idx[0]] * (med + eps.view(b)[idx[0]])
    if cfg.confirm:
        mask[:, 0] &= ~confirmed(lum, variances, cfg)
    if cfg.mutual:
        mask &= ~mutually_confirmed(lum, variances, cfg)[:, None]
    if cfg.events:
        b, r, c = mask.any(1).nonzero(as_tuple=True)            # only where some estimate is a candidate
        if b.numel():
            kept = events_confirmed(lum[b, :, r, c][..., None, None], variances[b, :, r, c][..., None, None], cfg)
            mask[b, :, r, c] &= ~kept.view(-1, 1)
    if cfg.peers:
        idx = mask.nonzero(as_tuple=True)
        if idx[0].numel():
            mask[idx] = ~speckled(lum, variances, idx, cfg)
    if cfg.edge:
        idx = mask.nonzero(as_tuple=True)
        if idx[0].numel():
            mask[idx] = ~beside_a_light(lum, variances, idx, cfg)
    return mask


def beside_a_light(lum: torch.Tensor, variances: torch.Tensor, idx: tuple[torch.Tensor, ...],
                   cfg: GuardConfig) -> torch.Tensor:
    """Which candidate pixels ``idx`` (b, k, row, col) of ``lum`` (B, 5, H, W), the
    estimates' RGB means, lie beside a light, (n,) bool: some other pixel of the 3 x 3
    window in the same estimate is settled (sqrt(V) < r0 Xbar, :func:`settled_mask`) and at
    least ``cfg.edge`` times the candidate's value.

    A pixel on the edge of a small emitter sees it in some passes only, so its mean rests
    on a few events and is far above the 3 x 3 median of a window that is mostly dark
    (``0108_bright_emitters`` N = 64: all five estimates 0.17 at sqrt(V)/Xbar 1.0 beside an
    emitter pixel of 4.1 at 0.16, reference 0.53) and every estimate was replaced by that
    median (0.0005): a black dot where every input is well above it. A firefly is an event
    far above its whole window, settled bright neighbours included (the issue's box
    firefly, 489 beside 0.28, is still caught). Keeping a pixel costs no consistency.
    """
    win, var, inside = _neighbours(lum, variances, idx, 3)
    light = inside & settled_mask(win, var, cfg.min_rel_error) & (win >= cfg.edge * lum[idx][:, None])
    return light.any(1)


def speckled(lum: torch.Tensor, variances: torch.Tensor, idx: tuple[torch.Tensor, ...],
             cfg: GuardConfig) -> torch.Tensor:
    """Which candidate pixels ``idx`` (b, k, row, col) of ``lum`` (B, 5, H, W), the
    estimates' RGB means, sit in a sparse *speckle field*, (n,) bool: at least ``cfg.peers``
    other pixels of the :data:`PEER_WINDOW` window of the same estimate are unsettled
    (sqrt(V) >= r0 Xbar, :func:`settled_mask`) and within :data:`PEER_RATIO` of the candidate.

    A small-bandwidth estimate on a surface that photons reach rarely (the literature
    ``cornell-box``'s glossy floor) is a field of one-photon speckles of comparable value
    whose 3 x 3 median is 0, so the median test takes every speckle for a firefly and the
    region loses most of its energy (docs/RECONSTRUCTION_LOG.md). A firefly is a lone
    event far above every neighbour; steady bright neighbours (a light seen directly) are
    settled and are no peers. Keeping a pixel costs no consistency (module docstring).
    """
    win, var, inside = _neighbours(lum, variances, idx, PEER_WINDOW)
    peer = inside & (win > 0) & (PEER_RATIO * win >= lum[idx][:, None]) & ~settled_mask(win, var, cfg.min_rel_error)
    return peer.sum(1) >= cfg.peers


def confirmed(lum: torch.Tensor, variances: torch.Tensor, cfg: GuardConfig) -> torch.Tensor:
    """Where hit point B confirms ~y, (B, H, W) bool: some ~z^j of the same pixel is settled,
    sqrt(V)/Xbar < r0 (a mean made by many comparable passes, not one lucky one), and at
    least 1/``cfg.confirm`` of ~y's value. ``lum`` (B, 5, H, W) the estimates' RGB means.

    ~y and the ~z^j are gathered at independent eye hit points A and B; a small emitter or
    a one-pixel caustic that both see over many passes is light, not a firefly, even when
    ~y's own mean still rests on a few passes (``0021_caustic_paths``, N = 16: an emitter
    pixel with ~y 32 and every ~z^j 75, reference 53, went to 0.04, and the guide's B-only
    spike rule then took ~z^4's value out of the guide too). A photon that both gathers
    shared in one pass (the issue's box firefly) leaves every estimate unsettled and is
    still caught. Not replacing a pixel costs no consistency.
    """
    z = lum[:, 1:]
    return (settled_mask(z, variances[:, 1:], cfg.min_rel_error) & (cfg.confirm * z >= lum[:, :1])).any(1)


def mutually_confirmed(lum: torch.Tensor, variances: torch.Tensor, cfg: GuardConfig) -> torch.Tensor:
    """Where the two hit points confirm each other, (B, H, W) bool: ~y (hit point A) and some
    ~z^j (hit point B) each have sqrt(V)/Xbar < ``cfg.mutual`` and lie within ``cfg.confirm``
    (4 when that is off) of each other. ``lum`` (B, 5, H, W) the estimates' RGB means.

    A small emitter seen directly, partly covering the pixel, flickers from pass to pass at
    both hit points, so neither is settled at a few passes (``0069_caustic_paths`` N = 16:
    ~y 0.75 and every ~z^j 1.12 at sqrt(V)/Xbar 0.69 and 0.54, reference 1.12) and every
    estimate was replaced by its 3 x 3 median (0.001): the pixel went black. A one-pass
    event, also one photon both gathers shared, has sqrt(V)/Xbar ~ 1 at both and is still
    caught; two independent eye paths each seeing the same light over several passes is
    light. Not replacing a pixel costs no consistency.
    """
    y, z = lum[:, :1], lum[:, 1:]
    a = settled_mask(y, variances[:, :1], cfg.mutual)
    b = settled_mask(z, variances[:, 1:], cfg.mutual) & _agree(y, z, cfg)
    return a[:, 0] & b.any(1)


def _agree(y: torch.Tensor, z: torch.Tensor, cfg: GuardConfig) -> torch.Tensor:
    """Where ~y and each ~z^j lie within the confirmation factor (``cfg.confirm``, 4 when
    that is off) of each other, both ways; broadcasts y (.., 1, ..) against z (.., 4, ..)."""
    c = cfg.confirm or 4.0
    return (c * z >= y) & (c * y >= z)


def event_count(mean: torch.Tensor, variance: torch.Tensor) -> torch.Tensor:
    """How many passes' events a mean rests on, ``Xbar^2 / V`` (0 where Xbar = 0): k equal
    events in N passes give sqrt(V)/Xbar = sqrt(1/k - 1/N), so 1/r^2 ~ k for k << N; a
    mean of N steady passes gives ~N; V = 0 with Xbar > 0 (every pass equal) counts as inf."""
    var = variance.clamp(min=0)
    k = mean.square() / var.clamp(min=torch.finfo(var.dtype).tiny)
    return torch.where(mean > 0, torch.where(var > 0, k, torch.full_like(k, math.inf)), torch.zeros_like(k))


def events_confirmed(lum: torch.Tensor, variances: torch.Tensor, cfg: GuardConfig) -> torch.Tensor:
    """Where the two hit points confirm each other by their events together, (B, H, W) bool:
    ~y (hit point A) and some ~z^j (hit point B) are both > 0, lie within ``cfg.confirm``
    (4 when that is off) of each other, and ``k_y + k_z >= cfg.events`` with k
    :func:`event_count`. ``lum`` (B, 5, H, W) the estimates' RGB means.

    :func:`mutually_confirmed` asks more than one event of *each* chain. A rare light (a
    glint of a small emitter that a pixel sees in 0.2% of its passes) gives one chain one
    event and the other several: the literature ``box`` at N = 1024, pixel (60, 63): ~y 30.8
    from one event, every ~z^j 91.8 from three, reference 53.7; the guard replaced the
    ~z^j by their 3 x 3 median (0.17), the envelope then left ~y out as a lone spike, and
    the output was 0.17, which alone made that image's 8x8-block relMSE 6.4x its best
    input's. A photon both gathers shared in one pass leaves one event in each (k_y + k_z
    ~ 2) and is still caught. Not replacing a pixel costs no consistency.
    """
    y, z = lum[:, :1], lum[:, 1:]
    k = event_count(lum, variances)
    both = (y > 0) & (z > 0) & _agree(y, z, cfg) & (k[:, :1] + k[:, 1:] >= cfg.events)
    return both.any(1)


def settled_mask(mean: torch.Tensor, variance: torch.Tensor, r0: float) -> torch.Tensor:
    """Where an estimate's mean is *settled*, ``sqrt(V) < r0 Xbar``: made by many comparable
    passes. A mean resting on one pass has sqrt(V)/Xbar ~ 1 (two: 0.71), so r0 = 0.5 (the
    guard's ``min_rel_error``) leaves out one- and two-pass events; a pixel no photon
    reached (0 / 0) is not settled. ``mean`` and ``variance`` of the same shape."""
    return variance.clamp(min=0).sqrt() < r0 * mean


def _window_pixels(idx: tuple[torch.Tensor, ...], size: int, h: int, w: int
                   ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``size`` x ``size`` windows (row-major) around the pixels ``idx`` (b, k, row, col
    index tensors) of an H x W image: rows and cols (n, size^2) clamped to the image
    (replicate padding), and which of them lie inside it."""
    offs = torch.arange(size, device=idx[2].device) - size // 2
    rows = idx[2][:, None] + offs.repeat_interleave(size)[None]
    cols = idx[3][:, None] + offs.repeat(size)[None]
    inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
    return rows.clamp(0, h - 1), cols.clamp(0, w - 1), inside


def _neighbours(lum: torch.Tensor, variances: torch.Tensor, idx: tuple[torch.Tensor, ...], size: int
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``size`` x ``size`` windows around the pixels ``idx`` (b, k, row, col) in the same
    estimate: values of ``lum`` and ``variances`` (B, 5, H, W), each (n, size^2), and which
    entries are neighbours (inside the image and not the centre: a clamped border pixel
    would count twice)."""
    rows, cols, inside = _window_pixels(idx, size, *lum.shape[-2:])
    inside[:, size * size // 2] = False
    b, k = idx[0][:, None], idx[1][:, None]
    return lum[b, k, rows, cols], variances[b, k, rows, cols], inside


def window_median(x: torch.Tensor, idx: tuple[torch.Tensor, ...], size: int = 3) -> torch.Tensor:
    """``size`` x ``size`` medians (replicate padding; size odd) of x (B, K, C, H, W) at the
    pixels ``idx`` (b, k, row, col index tensors), (n, C); only those windows are gathered."""
    rows, cols, _ = _window_pixels(idx, size, *x.shape[-2:])
    win = x[idx[0][:, None], idx[1][:, None], :, rows, cols]           # (n, size^2, C)
    return win.median(dim=1).values


def _replace_outliers(est: torch.Tensor, var: torch.Tensor, mask: torch.Tensor) -> None:
    """Write the 3 x 3 medians into ``est`` (B, 5, 3, H, W) and ``var`` (B, 5, H, W) at
    ``mask``, in place (all medians are taken before anything is written)."""
    idx = mask.nonzero(as_tuple=True)
    med, vmed = window_median(est, idx), window_median(var.unsqueeze(2), idx)
    est[idx[0], idx[1], :, idx[2], idx[3]] = med
    var[idx] = vmed.squeeze(1)


def guard_estimates(estimates: torch.Tensor, variances: torch.Tensor, passes: torch.Tensor,
                    cfg: GuardConfig) -> Guarded:
    """Replace the outliers of each estimate by their 3 x 3 median (whole images).

    estimates (B, 5, 3, H, W) raw radiance, variances (B, 5, H, W), passes (B,).
    Returns the inputs themselves where nothing is an outlier, else new tensors.
    """
    mask = find_outliers(estimates, variances, passes, cfg)
    if not bool(mask.any()):
        return Guarded(estimates, variances, mask)
    est, var = estimates.clone(), variances.clone()
    _replace_outliers(est, var, mask)
    return Guarded(est, var, mask)


def passes_of(buf: BufferFile) -> float:
    """The pass count N of a buffer file (header ``ppmrecon.passes``)."""
    try:
        n = float(buf.header[H_PASSES])
    except (KeyError, TypeError, ValueError):
        n = float("nan")
    if not math.isfinite(n) or n < 0:
        raise UsageError(f"the model needs the pass count, but the buffer header has no valid '{H_PASSES}'")
    return n


def guard_buffer(buf: BufferFile, cfg: GuardConfig) -> BufferFile:
    """A copy of ``buf`` with guarded estimates and variances (``buf`` itself when the
    guard is off or finds nothing)."""
    if not cfg.enabled:
        return buf
    est = torch.from_numpy(np.ascontiguousarray(buf.estimates, np.float32)).permute(0, 3, 1, 2)[None]
    var = torch.from_numpy(np.ascontiguousarray(buf.variances, np.float32))[None]
    mask = find_outliers(est, var, torch.tensor([passes_of(buf)]), cfg)
    if not bool(mask.any()):
        return buf
    estimates, variances = buf.estimates.astype(np.float32, copy=True), buf.variances.astype(np.float32, copy=True)
    # views of the copies in the (B, 5, 3, H, W) layout: written in place, no relayout
    _replace_outliers(torch.from_numpy(estimates).permute(0, 3, 1, 2)[None], torch.from_numpy(variances)[None], mask)
    return replace(buf, estimates=estimates, variances=variances)


# ------------------------------------------------------------------------ output band

def output_band(image: torch.Tensor, y: torch.Tensor, z: torch.Tensor, band: float) -> torch.Tensor:
    """Clamp a combined image (B, 3, H, W) into ``[min_k X_k / band, max_k X_k * band]``
    of its five inputs y (B, 3, H, W), z (B, 4, 3, H, W) at each pixel and channel.

    See the module docstring for why the output stays within Appendix A's bounds.
    ``band = 0`` only clamps at 0 (radiance is nonnegative). Differentiable (a clamp).
    """
    if band == 0:
        return image.clamp(min=0.0)
    lo, hi = band_bounds(y, z, band)
    return torch.minimum(torch.maximum(image, lo), hi)


def band_bounds(y: torch.Tensor, z: torch.Tensor, band: float,
                y_out: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The ends ``(min_k X_k / band, max_k X_k * band)`` of :func:`output_band` (band >= 1),
    each (B, 3, H, W), for callers that clamp more than one image into them; ``y_out``
    (B, 1, H, W) bool: pixels whose range is that of the four ~z^j alone (still
    consistent: they converge to the truth without ~y)."""
    zmin, zmax = torch.aminmax(z, dim=1)                  # one pass over the four ~z^j
    lo = torch.minimum(y, zmin).clamp_(min=0.0)
    hi = torch.maximum(y, zmax)
    if y_out is not None:
        lo = torch.where(y_out, zmin.clamp(min=0.0), lo)
        hi = torch.where(y_out, zmax, hi)
    if band != 1:
        lo, hi = lo / band, hi * band
    return lo, hi


# ------------------------------------------------------------- low-frequency anchor

def _gaussian_taps(sigma: float, like: torch.Tensor) -> torch.Tensor:
    """Normalised Gaussian taps of standard deviation ``sigma`` px, truncated at 3 sigma."""
    radius = max(1, math.ceil(3.0 * sigma))
    t = torch.arange(-radius, radius + 1, dtype=like.dtype, device=like.device)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    return g / g.sum()


#: Bytes of padded input per band of rows in :func:`_separable`: a band and its row pass stay
#: in a core's L2 cache (2 MiB here) through all the taps.
SEPARABLE_BAND_BYTES = 1 << 20


def _separable(x: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """``x`` (B, C, H, W) filtered by ``taps`` along rows and columns, replicate padding.

    As sums of shifted copies: a depthwise convolution (one channel per group) of an
    11-13 tap kernel runs about 5x slower on a CPU (100 ms against 18 ms for 3 x 1280 x 720);
    the two agree to float rounding. In bands of output rows, each with the 2r rows of
    input around it (:data:`SEPARABLE_BAND_BYTES`, at least 8r rows): a band's taps then run
    in cache, not through memory, about twice as fast for 1280 x 720 (5.6 against 13 ms for
    3 channels and 11 taps), and every output value is the same sum in the same order as
    without bands. Differentiable."""
    radius = len(taps) // 2
    h, w = x.shape[-2:]
    weights = [float(t) for t in taps]
    x = F.pad(x, (radius, radius, radius, radius), mode="replicate")
    band = max(8 * radius, SEPARABLE_BAND_BYTES // max(1, x[..., :1, :].numel() * x.element_size()))
    parts = []
    for r0 in range(0, h, band):
        n = min(band, h - r0)
        src = x[..., r0:r0 + n + 2 * radius, :]
        rows = src[..., :, 0:w] * weights[0]
        for k in range(1, len(weights)):
            rows = rows.add_(src[..., :, k:k + w], alpha=weights[k])
        out = rows[..., 0:n, :] * weights[0]
        for k in range(1, len(weights)):
            out = out.add_(rows[..., k:k + n, :], alpha=weights[k])
        parts.append(out)
    return parts[0] if len(parts) == 1 else torch.cat(parts, -2)


def gaussian_lowpass(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of x (B, C, H, W), standard deviation ``sigma`` pixels,
    truncated at 3 sigma and renormalised, replicate padding (a linear, mean-preserving
    low-pass whose weights do not depend on the image). Differentiable."""
    return _separable(x, _gaussian_taps(sigma, x))


def anchor_low_frequencies(image: torch.Tensor, anchor: torch.Tensor, sigma: float) -> torch.Tensor:
    """``image + G_sigma * (anchor - image)``: the high frequencies of ``image`` over the low
    frequencies of ``anchor`` (both (B, 3, H, W))."""
    return image + gaussian_lowpass(anchor - image, sigma)


def lowpass_variance(variance: torch.Tensor, sigma: float) -> torch.Tensor:
    """Variance of ``G_sigma * X`` for pixels with independent errors of variance
    ``variance`` (B, C, H, W): ``sum_m a_{c,m}^2 V_m`` with a_{c,m} the blur's weight on pixel m,
    the same separable Gaussian as :func:`gaussian_lowpass` (a lower bound where neighbours
    share photons). Inside the image a_{c,m} is the tap g_{m-c}; within the blur's radius of an
    edge the replicate padding gives the edge pixel the sum of every tap that falls outside, and
    its share of the variance is that sum squared, not the sum of the squares: at an edge the
    independent-pixel variance is about 2.5x the latter for sigma 1.5 px, at a corner about 6x
    (``sum_k g_k^2 V_{c-k}`` everywhere was the form before 2026-12-06).
    Separable, so the exact 2-D weights are products of exact 1-D ones: the replicate pass with
    squared taps plus, near each edge, the excess ``(sum g)^2 - sum g^2`` of the edge pixel
    (:func:`_edge_excess`) times the blurred edge line."""
    taps = _gaussian_taps(sigma, variance)
    out = _separable(variance, taps.square())
    h, w = variance.shape[-2:]
    radius = len(taps) // 2
    ex_w, ex_h = _edge_excess(taps, w), _edge_excess(taps, h)
    sq = taps.square()
    # the excess is 0 beyond the radius: only the strips within it are touched
    cols = [slice(0, min(w, radius)), slice(max(0, w - radius), w)]
    rows = [slice(0, min(h, radius)), slice(max(0, h - radius), h)]
    # rows first: the row pass's excess lives in the edge columns, then goes through the column blur
    for ex, col, strip in zip(ex_w, (0, w - 1), cols):
        out[..., :, strip] += _blur_line(variance[..., :, col:col + 1], sq, -2) * ex[strip]
    # then the column pass's excess at the edge rows, of the exact row pass of those rows
    for ex, row, strip in zip(ex_h, (0, h - 1), rows):
        line = _blur_line(variance[..., row:row + 1, :], sq, -1)
        for ex_c, col in zip(ex_w, (0, w - 1)):
            line = line + variance[..., row:row + 1, col:col + 1] * ex_c
        out[..., strip, :] += line * ex[strip, None]
    return out


def _edge_excess(taps: torch.Tensor, n: int) -> list[torch.Tensor]:
    """Per output position c of a line of n pixels, ``a_{c,e}^2 - b_{c,e}`` for its edge pixels
    e = 0 and e = n - 1 (one entry where n = 1): a the replicate-padded blur's weight on e (the
    sum of the taps that land on it), b the same sum of squared taps. (n,) each."""
    radius = len(taps) // 2
    k = torch.arange(-radius, radius + 1, device=taps.device)
    lands = (torch.arange(n, device=taps.device)[:, None] + k).clamp(0, n - 1)       # (n, K): the pixel each tap reads
    out = []
    for e in ((0, n - 1) if n > 1 else (0,)):
        on = (lands == e).to(taps.dtype)
        out.append((on * taps).sum(1).square() - (on * taps.square()).sum(1))
    return out


def _blur_line(x: torch.Tensor, taps: torch.Tensor, axis: int) -> torch.Tensor:
    """``x`` (..., H, W) blurred along ``axis`` (-1 or -2) only by ``taps``, replicate padding:
    for a line of pixels (one row or column), where the banded 2-D blur would be all overhead."""
    radius = len(taps) // 2
    n = x.shape[axis]
    idx = (torch.arange(n, device=x.device)[:, None] + torch.arange(-radius, radius + 1, device=x.device)).clamp(0, n - 1)
    gathered = x.movedim(axis, -1)[..., idx]                  # (..., n, K)
    return (gathered * taps).sum(-1).movedim(-1, axis)


def noise_correlation(x: torch.Tensor, variance: torch.Tensor, window: float) -> torch.Tensor:
    """The correlation rho of neighbouring pixels' noise in ``x`` (B, C, H, W), (B, 1, H, W):

        E |x_c - x_{c+1}|^2 = 2 V (1 - rho) + |signal step|^2   =>   rho ~ 1 - G_w * D / (2 G_w * V)

    with D the squared step to the right and down neighbour (mean over C and the two
    directions), V the per-pixel variance of the mean (B, 1, H, W) and G_w a Gaussian of
    ``window`` px, clamped to [0, 0.999]. A photon-map estimate's noise is correlated because
    one photon lands in the kernels of every pixel within its radius (a single photon in a
    dark region paints a plateau); signal steps only lower rho, towards independent pixels.
    """
    right = F.pad(_squared_step(x[..., :, 1:], x[..., :, :-1]), (0, 1, 0, 0), mode="replicate")
    down = F.pad(_squared_step(x[..., 1:, :], x[..., :-1, :]), (0, 0, 0, 1), mode="replicate")
    d2 = gaussian_lowpass(0.5 * (right + down), window)
    vbar = gaussian_lowpass(variance, window)
    rho = 1.0 - d2 / (2.0 * vbar).clamp(min=torch.finfo(vbar.dtype).tiny)
    return torch.where(vbar > 0, rho, torch.zeros_like(rho)).clamp_(0.0, 0.999)


def _squared_step(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|a - b|^2, the mean over channels, (B, 1, H, W)."""
    return (a - b).square().mean(1, keepdim=True)


def correlated_lowpass_variance(variance: torch.Tensor, rho: torch.Tensor, sigma: float) -> torch.Tensor:
    """Variance of ``G_sigma * X`` for noise of local variance V (``variance``, (B, 1, H, W))
    whose autocorrelation is Gaussian, c(d) = exp(-d^2 / (4 s^2)) with s fitted to the
    neighbour correlation ``rho`` = c(1) (:func:`noise_correlation`):

        Var = max(s^2 / (s^2 + sigma^2) G_sigma * V,  sum_k g_k^2 V_{c-k})

    (the first term is the integral of G * G, a Gaussian of variance 2 sigma^2, against c;
    the second, :func:`lowpass_variance`, the independent-pixel limit s -> 0 on the pixel
    grid). s -> infinity (fully correlated) gives the local V itself: the low-pass then
    removes none of the noise."""
    s2 = -0.25 / torch.log(rho.clamp(min=1e-30))          # rho = 0: s^2 = 0, independent pixels
    shared = s2 / (s2 + sigma * sigma) * gaussian_lowpass(variance, sigma)
    return torch.maximum(shared, lowpass_variance(variance, sigma))


def estimated_lowpass_variance(x: torch.Tensor, variance: torch.Tensor, window: float, sigma: float) -> torch.Tensor:
    """:func:`correlated_lowpass_variance` of ``x``'s noise (variance (B, 1, H, W)), its
    neighbour correlation estimated from ``x`` over a Gaussian of ``window`` px
    (:func:`noise_correlation`)."""
    return correlated_lowpass_variance(variance, noise_correlation(x, variance, window), sigma)


def anchor_where_biased(image: torch.Tensor, anchor: torch.Tensor, anchor_variance: torch.Tensor,
                        sigma: float, k: float, window: float = 0.0, settled: float = 0.0) -> torch.Tensor:
    """The low-frequency anchor applied as far as the gap is larger than the anchor's noise:

        yhat' = yhat + a D,   D = G_sigma * (anchor - yhat),   a = |D|^2 / (|D|^2 + k Var(G_sigma * anchor))

    with |D|^2 the mean over R, G, B and Var from :func:`lowpass_variance` of the anchor's
    per-pixel variance of the mean (buffer layer ``V``, (B, 1, H, W)), or with ``window``
    > 0 from :func:`correlated_lowpass_variance`, the anchor's neighbour correlation
    estimated over a Gaussian window of that width (:func:`noise_correlation`). Where
    ``yhat``'s low frequencies differ from the anchor's by more than the anchor's own noise
    (a smooth bias of ``yhat``, e.g. a denoiser darkening a glossy wall) a -> 1, the plain
    anchor; where the gap is within that noise a -> 0 and ``yhat`` keeps its
    (lower-variance) low frequencies. a lies in [0, 1] and D -> 0 as the inputs converge,
    so the correction vanishes whatever the noise estimate.

    With ``settled`` r0 > 0 the anchor acts only where its own low-pass is *settled*,
    ``sqrt(Var) < r0 G_sigma * anchor`` (:func:`settled_mask` of the low-pass, RGB mean):
    a low-pass that rests on one photon event (a wide kernel's plateau, whose neighbours
    share the same photon, so the correlated variance stays ~ V) is no low-frequency
    reference, yet the noise test above lets half of a one-sigma gap through
    (``0000_bright_emitters`` of this session's targeted data, scene seed 20028, N = 16:
    relMSE 0.10 of the best input with the anchor, 0.002 without it). Not shipped: it also
    removes the anchor from the sparse glossy floor of the literature ``cornell-box``, where
    OIDN crushes the speckles and the plain anchor restores part of the mean
    (docs/RECONSTRUCTION_LOG.md).
    """
    variance = anchor_variance.clamp(min=0.0)
    gap = gaussian_lowpass(anchor - image, sigma)
    gap2 = gap.square().mean(1, keepdim=True)
    if window > 0:
        var = estimated_lowpass_variance(anchor, variance, window, sigma)
    else:
        var = lowpass_variance(variance, sigma)
    noise = k * var
    a = torch.where(gap2 > 0, gap2 / (gap2 + noise).clamp(min=torch.finfo(gap2.dtype).tiny), torch.zeros_like(gap2))
    if settled > 0:
        a = a * settled_mask(gaussian_lowpass(anchor, sigma).mean(1, keepdim=True), var, settled).to(a.dtype)
    return image + a * gap


def finish(image: torch.Tensor, y: torch.Tensor, z: torch.Tensor, cfg: GuardConfig) -> torch.Tensor:
    """What follows Eq. 6 for a combined image (B, 3, H, W) of the (guarded) inputs y
    (B, 3, H, W), z (B, 4, 3, H, W): with the guard on, the low-frequency anchor to ~z^4
    (when ``cfg.anchor > 0``), then the output band; with it off, only the clamp at 0.

    Whole images (or whole training patches): the anchor's blur has no tile halo.
    Differentiable, so training sees exactly what inference produces.
    """
    if not cfg.enabled:
        # Terms y_i + z_c - z_i can be negative, so can their convex combination; radiance
        # is not, and projecting onto [0, inf) never moves the estimate away from the truth.
        return image.clamp(min=0.0)
    if cfg.anchor > 0:
        image = anchor_low_frequencies(image, z[:, -1], cfg.anchor)
    return output_band(image, y, z, cfg.band)
