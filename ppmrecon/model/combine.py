"""The consistent multi-buffer combiner (Choi & Moon 2021, paper 002, Eq. 6 / Eq. 9).

For pixel c, window Omega_c (K x K, K odd) and the four correlated estimates ~z^j:

    yhat_c = sum_{j=1..4} sum_{i in Omega_c} w^j_{c,i} * ( ~y_i + ~z^j_c - ~z^j_i )

with ``w = softmax`` over the 4 K^2 logits the network predicts for pixel c, so every
``w >= 0`` and they sum to 1 (the 1/W_c of Eq. 6). yhat_c is a convex combination of
the *terms* ``t^j_{c,i} = ~y_i + ~z^j_c - ~z^j_i``, each of which converges to y_c when
the inputs are consistent; hence yhat_c is consistent whatever the weights are
(paper 002 Appendix A, Eq. 10-12).

Numerical contract (what the tests check)
-----------------------------------------
* Terms are evaluated as ``t = (y_i - z^j_i) + z^j_c`` in the working precision
  (float32 for the denoiser). Pixels outside the image take the value of the nearest
  border pixel (replicate padding of both ~y and ~z), so every term is a valid one.
* The output is **exactly** inside ``[min_{i,j} t, max_{i,j} t]`` of those evaluated
  terms, for any finite logits, any image size (1 x 1 included) and radiance from 0
  to 1e8 (anything whose terms stay within float32 range). A weighted mean of floats can leave the interval of its operands by a few
  ulps of rounding, so the result is clamped into the bounds, which are computed in
  the same call with exact operations (min/max pooling of ``y - z^j``, then ``+ z^j_c``,
  which is monotone and therefore commutes with min/max). The clamp is a no-op up to
  rounding (tested against a float64 evaluation of Eq. 6); it makes the guarantee
  exact instead of "up to a few ulps" and makes ``y = z^j = t`` return exactly ``t``.
* The weights are a numerically stable softmax (the per-pixel maximum logit is
  subtracted before ``exp``), so logits of any magnitude neither overflow nor divide
  by zero: the largest weight numerator is exactly 1. Logits more than 87 below the
  pixel's largest (float32's underflow) weigh exp(-87) ~ 1.6e-38 of it (see
  :func:`_stable_exp`).

Logit layout (offset-major): channel ``4 * (a * K + b) + j`` of ``logits`` is the weight
of ~z^(j+1) (j = 0..3) at window offset (a - K//2, b - K//2) (row, column), so the four
weights of one offset are adjacent planes.

Two evaluation paths with the same numerics (they differ only in summation order):
``"unfold"`` materialises the K^2 neighbourhood of ``y - z^j`` (fast, differentiable,
for 64 x 64 training patches) and ``"loop"`` accumulates over the K^2 offsets with
O(H W) temporaries (inference on large images; no K^2-fold copy is ever built).
"""

from __future__ import annotations

import math
from typing import Callable, Literal, NamedTuple

import torch
import torch.nn.functional as F

N_CORRELATED = 4          # ~z^1..~z^4 (SPEC section 2: m = 5 inputs)
N_RGB = 3

#: ``method="auto"`` unfolds when the unfolded neighbourhood stays below this size.
UNFOLD_BUDGET_BYTES = 256 * 1024 ** 2

Method = Literal["auto", "loop", "unfold"]


class NonFiniteLogitsError(ValueError):
    """The weights cannot be formed: a NaN/+Inf logit, or all logits of a pixel -Inf."""


class Combined(NamedTuple):
    """Result of :func:`combine_with_weights`."""

    image: torch.Tensor          # (B, 3, H, W) yhat of Eq. 6
    weights_per_z: torch.Tensor  # (B, 4, H, W) sum_i w^j_{c,i}: the share of ~z^j (paper 002 Fig. 6)


def window_size(logits_channels: int) -> int:
    """The window width K (odd) implied by ``4 K^2`` logit channels."""
    kk, rest = divmod(int(logits_channels), N_CORRELATED)
    k = math.isqrt(kk) if kk > 0 else 0
    if rest or k * k != kk or k % 2 == 0:
        raise ValueError(f"logits must have 4*K*K channels with K odd, got {logits_channels}")
    return k


def logit_channels(k: int) -> int:
    """Number of logit channels for a K x K window: 4 K^2."""
    if k < 1 or k % 2 == 0:
        raise ValueError(f"window size K must be odd and positive, got {k}")
    return N_CORRELATED * k * k


def _check(y: torch.Tensor, z: torch.Tensor, logits: torch.Tensor) -> int:
    if y.dim() != 4 or y.shape[1] != N_RGB:
        raise ValueError(f"y must be (B, 3, H, W), got {tuple(y.shape)}")
    b, _, h, w = y.shape
    if tuple(z.shape) != (b, N_CORRELATED, N_RGB, h, w):
        raise ValueError(f"z must be (B, 4, 3, H, W) = {(b, N_CORRELATED, N_RGB, h, w)}, got {tuple(z.shape)}")
    if logits.dim() != 4 or logits.shape[0] != b or tuple(logits.shape[2:]) != (h, w):
        raise ValueError(f"logits must be (B, 4*K*K, {h}, {w}), got {tuple(logits.shape)}")
    return window_size(logits.shape[1])


def _padded_differences(y: torch.Tensor, z: torch.Tensor, r: int) -> torch.Tensor:
    """``y_i - z^j_i`` as (B, 12, H + 2r, W + 2r), replicate-padded by r on each side.

    Padding the difference equals taking the difference of replicate-padded y and z
    (both copy the same border pixel), so every out-of-image term is a valid term.
    """
    b, _, h, w = y.shape
    d = (y.unsqueeze(1) - z).reshape(b, N_CORRELATED * N_RGB, h, w)
    return F.pad(d, (r, r, r, r), mode="replicate") if r else d


def _sliding(x: torch.Tensor, k: int, dim: int,
             op: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """``op``-reduce (torch.minimum/maximum) over windows of k along ``dim`` (valid part).

    Doubling (van Herk / sparse table): windows of 1, 2, 4, ... p <= k, then two
    overlapping windows of p cover k. O(log k) passes; exact, since min/max never round.
    """
    n = x.shape[dim]
    acc, width = x, 1
    while 2 * width <= k:
        acc = op(acc.narrow(dim, 0, acc.shape[dim] - width), acc.narrow(dim, width, acc.shape[dim] - width))
        width *= 2
    out = n - k + 1
    return op(acc.narrow(dim, 0, out), acc.narrow(dim, k - width, out)) if width < k else acc


def _window_extremes(dpad: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact min and max of ``y_i - z^j_i`` over each K x K window, (B, 12, H, W) each."""
    return tuple(_sliding(_sliding(dpad, k, -1, op), k, -2, op) for op in (torch.minimum, torch.maximum))


def term_bounds(y: torch.Tensor, z: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(min, max)`` over j and the K x K window of the Eq. 6 terms, each (B, 3, H, W).

    ``fl(d + z_c)`` is monotone in d, so the min of the evaluated terms equals
    ``min_j (min_i d^j_i + z^j_c)`` evaluated the same way: exact, not a bound on a bound.
    """
    dpad = _padded_differences(y, z, k // 2)
    return _bounds_from(dpad, z, k)


def _bounds_from(dpad: torch.Tensor, z: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    b, nz, nc, h, w = z.shape
    dmin, dmax = _window_extremes(dpad, k)
    lo = (dmin.view(b, nz, nc, h, w) + z).amin(1)
    hi = (dmax.view(b, nz, nc, h, w) + z).amax(1)
    return lo, hi


def _numerator_unfold(dpad: torch.Tensor, e: torch.Tensor, k: int) -> torch.Tensor:
    """sum_{j,i} e^j_i d^j_i via one K^2-fold unfold of d (for training patches)."""
    b, _, h, w = e.shape
    kk = k * k
    cols = F.unfold(dpad, k).view(b, N_CORRELATED, N_RGB, kk, h, w)
    e6 = e.view(b, kk, N_CORRELATED, h, w).transpose(1, 2).unsqueeze(2)   # (B, 4, 1, K^2, H, W)
    return (e6 * cols).sum(dim=(1, 3))


def _numerator_loop(dpad: torch.Tensor, e: torch.Tensor, k: int) -> torch.Tensor:
    """Same sum as :func:`_numerator_unfold`, accumulated over the K^2 window offsets."""
    b, _, h, w = e.shape
    d6 = dpad.view(b, N_CORRELATED, N_RGB, h + k - 1, w + k - 1)
    num = e.new_zeros(b, N_RGB, h, w)
    for row in range(k):
        for col in range(k):
            base = N_CORRELATED * (row * k + col)
            for j in range(N_CORRELATED):
                # d^j at pixel c + offset (a view) times its weight plane, accumulated in place
                num.addcmul_(d6[:, j, :, row:row + h, col:col + w], e[:, base + j:base + j + 1])
    return num


#: Logit gaps below this are evaluated at it: exp(-87) ~ 1.6e-38, float32's smallest normal.
EXP_FLOOR = -87.0


def _stable_exp(x: torch.Tensor) -> torch.Tensor:
    """``exp(max(x, EXP_FLOOR))`` for x <= 0; without autograd ``x`` (the caller's
    temporary) is overwritten.

    torch's vectorised exp takes a slow path for arguments below float32's underflow
    threshold (-87.3): 7x slower measured, and guided logits (:mod:`.guide`) put most of
    the 4 K^2 logits of a pixel there. A weight that was below 1.2e-38 of the largest
    (subnormal, or 0 for a -inf logit) becomes 1.6e-38 of it: still a valid term's weight,
    so the combination stays a convex combination of terms (and is clamped into their
    bounds anyway); masking those back to 0 cost another 60% of the exp.
    """
    if x.requires_grad:
        return x.clamp(min=EXP_FLOOR).exp()
    return x.clamp_(min=EXP_FLOOR).exp_()


def _choose(method: Method, y: torch.Tensor, k: int) -> str:
    if method not in ("auto", "loop", "unfold"):
        raise ValueError(f"method must be 'auto', 'loop' or 'unfold', got {method!r}")
    if method != "auto":
        return method
    b, _, h, w = y.shape
    unfolded = b * N_CORRELATED * N_RGB * k * k * h * w * y.element_size()
    return "unfold" if unfolded <= UNFOLD_BUDGET_BYTES else "loop"


def combine_with_weights(y: torch.Tensor, z: torch.Tensor, logits: torch.Tensor,
                         method: Method = "auto", consume: bool = False) -> Combined:
    """Eq. 6 of paper 002 and the summed weight of each ~z^j.

    y: (B, 3, H, W) ~y; z: (B, 4, 3, H, W) ~z^1..~z^4; logits: (B, 4 K^2, H, W) with K
    odd (inferred). Raw (uncompressed) radiance in, raw radiance out. Differentiable
    in the logits (and in y, z). See the module docstring for the numerical contract.
    ``consume``: the logits are the caller's temporary and may be overwritten (without
    autograd): the weights are formed in their memory, not in a new 4 K^2-plane tensor.
    """
    k = _check(y, z, logits)
    dpad = _padded_differences(y, z, k // 2)
    # Stable softmax: exp(l - max l) <= 1 and the largest equals 1, so the total >= 1.
    peak = logits.amax(dim=1, keepdim=True)
    # max propagates NaN and +Inf, so one check on the (B, 1, H, W) maxima covers every
    # logit; a -Inf logit is legitimate (the least weight, exp(EXP_FLOOR)).
    if not bool(torch.isfinite(peak).all()):
        raise NonFiniteLogitsError("logits contain NaN/+Inf, or a pixel whose logits are all -Inf")
    e = _stable_exp(logits.sub_(peak) if consume and not logits.requires_grad else logits - peak)
    path = _choose(method, y, k)
    num = (_numerator_unfold if path == "unfold" else _numerator_loop)(dpad, e, k)
    b, _, h, w = e.shape
    den = e.view(b, k * k, N_CORRELATED, h, w).sum(1)                  # sum_i e^j_i, (B, 4, H, W)
    total = den.sum(1, keepdim=True)
    weights = den / total                                              # sum_i w^j_{c,i}
    # sum_{j,i} w (y_i - z^j_i) + sum_j (sum_i w^j_i) z^j_c  ==  Eq. 6 regrouped.
    image = num / total + (weights.unsqueeze(2) * z).sum(1)
    lo, hi = _bounds_from(dpad, z, k)
    image = torch.minimum(torch.maximum(image, lo), hi)                # no-op up to rounding
    return Combined(image, weights)


def combine(y: torch.Tensor, z: torch.Tensor, logits: torch.Tensor,
            method: Method = "auto") -> torch.Tensor:
    """Eq. 6 of paper 002: the consistent combination ``yhat`` (B, 3, H, W).

    ``yhat_c = sum_j sum_{i in Omega_c} softmax(logits_c)^j_i (~y_i + ~z^j_c - ~z^j_i)``.
    """
    return combine_with_weights(y, z, logits, method).image
