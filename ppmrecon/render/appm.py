"""The formulas of adaptive progressive photon mapping (APPM; Kaplanyan and Dachsbacher
2013, paper 001) as pure functions: the plug-in bandwidth (Eq. 6.4), the per-photon
weight of the recursive Laplacian estimate (Eq. 6.5-6.6) and Silverman's rule for its
own bandwidth r' (Eq. 6.7), with the bounds of Section 6.4. The controller that keeps
the per-pixel state and calls them is :class:`.controllers.APPMController`; the gather
supplies the per-pass sums (:class:`.controllers.APPMStatistics`).

Per pass i and pixel, over the photons j of that pass's gather (contribution
c_j = luminance(beta * f * Phi_j), in pixel units; K_r the render's kernel; J photons
emitted; (u_j, v_j) the photon's offset in the gather point's tangent frame):

    D_i   = (1/J) sum_{|x_j - e| < r}  K_r(x_j - e)           light-path density p_l
                                                              (Algorithm 1, "Eq. 5.4 w/o psi")
    A_i   = (1/J) sum_{|x_j - e| < r}  K_r(x_j - e) c_j       E[psi]   (Eq. 5.4)
    Q_i   = (1/J) sum_{|x_j - e| < r}  K_r(x_j - e) c_j^2     p_l E[c^2] (Eq. 5.4 with psi^2)
    Lap_i = (1/J) sum_j c_j w_lap(u_j, v_j; r')               Eq. 6.5 + 6.6

(the photons the gather counts: where direct light is estimated apart by MIS, the
indirect ones only, so the bandwidth trades the bias and variance of the photon part,
the only part it affects), and the state holds their running means over the passes (D, A, Q, Lap; the recursive
estimators of Eq. 4.1 / 6.5 are such means) and E[Lap^2] for the variance of the
Laplacian estimate.

Variance. The paper's psi is the per-path sample whose mean over the S ~ pi r^2 J p_l
paths in the disc is the measurement, psi = p_l c, so E[psi^2] = p_l Q and
Var[psi] = p_l Q - A^2 (Sec. 7: variances as differences of moments). Eq. 6.1 takes
S as fixed and keeps Var[psi]; the photon count in the disc is Poisson, though, and
its fluctuation adds E[psi]^2 (Appendix D's aleph term, which the paper drops): the
exact leading-order variance of one pass's kernel estimate is R(K) p_l E[c^2] / (J r^2)
= R(K) E[psi^2] / (J p_l r^2). With ``variance="full"`` (the default) Eq. 6.4 uses
E[psi^2]; with ``"paper"`` it uses Var[psi] as printed. "paper" collapses the bandwidth
wherever the photons carry equal power (Var[psi] = 0: every photon of a diffuse wall lit
directly by a uniform area light), which is why it is not the default.

Plug-in bandwidth (Eq. 6.4; 1/pi there is R(K) of the constant kernel, written R(K)
here so that every offered kernel gets its own constant; k_2 from :mod:`.kernels`):

    r_N^6 = 2 R(K) V / (J p_l k_2^2 (Delta I)^2 N),   V = E[psi^2] or Var[psi].

Laplacian (Eq. 6.5-6.6): second differences of kernel estimates at e +- u r' and
e +- v r' with the normalised 2D Perlin kernel K'_{r'} (the paper's kernel; the
constant 1.9635 of Eq. 6.7 is for it):

    w_lap(u, v; r') = [K'(u - r', v) + K'(u + r', v) + K'(u, v - r') + K'(u, v + r')
                       - 4 K'(u, v)] / r'^2,
    K'_{r'}(q) = 7 / (2 pi r'^2) * (1 - 10 t^3 + 15 t^4 - 6 t^5),  t = |q| / r' <= 1.

For a radiance that is quadratic around e its expectation is exactly Delta I.

The square of the Laplacian. E[Lap]^2 overestimates (Delta I)^2 by the variance of that
mean, Var[Lap] / N, and on a flat wall (Delta I = 0) that noise alone sets the bandwidth:
r^6 ~ Q / (E[Lap]^2 N) then stops depending on N and r stays a fixed multiple of r',
well below r_max where the paper expects the widest bandwidth. With
``laplacian="debiased"`` (the default) Eq. 6.4 uses E[Lap]^2 - z^2 Var[Lap] / N (floored
at 0: no curvature distinguishable from noise, r = r_max), from the same two moments the
state holds for Eq. 6.7; ``"paper"`` uses E[Lap]^2 as printed. z = 1 would be the
plain unbiased estimate of (Delta I)^2, positive by chance on about a third of a flat
wall (measured: 30-40% of the pixels of flat walls then shrank at 16 passes); z = 2
(the default) counts a curvature only ~2 standard errors away from 0 (E[Lap]^2 N /
Var[Lap] ~ chi^2_1 on a flat wall: 4.6% pass).

Laplacian bandwidth (Eq. 6.7): r'_N = 1.9635 sigma_N N^(-1/8). As printed, sigma_N =
sqrt(Var[Delta I_N]) has the units of the Laplacian, not of a length; we measure the
spread of the per-pass Laplacian estimates relative to their root mean square and in
units of the chain's initial bandwidth r_1 (sigma_N = r_1 where the Laplacian is pure
noise, -> 0 where it is estimated without noise):

    sigma_N = r_1 sqrt(Var[Lap] / E[Lap^2])   (Var the sample variance; sigma = r_1 at N = 1).

Bounds (Sec. 6.4): r_N in [r_min N^(-1/6), r_max N^(-1/6)] and r'_N in
[r'_min N^(-1/8), r'_max N^(-1/8)]; see the controller for their defaults. These bounds
are what makes the method consistent whatever the estimates do (Eq. 4.2, d = 2):
lambda = 0 for the value, (1/N^2) sum r_i^-2 <= r_min^-2 N^(-2/3) -> 0 and
(1/N) sum r_i^2 <= r_max^2 N^(-1/3) -> 0; lambda = 2s = 4 for the second derivative
(Hall and Patil 1994, Sec. 6.3), (1/N^2) sum r'_i^-6 <= r'_min^-6 N^(-1/4) -> 0 and
(1/N) sum r'_i^2 <= r'_max^2 N^(-1/4) -> 0.

Every function takes numpy or Dr.Jit arrays and an ``ops`` bundle for the element-wise
operations whose names differ (:class:`.hypothesis.ArrayOps`).
"""

from __future__ import annotations

import math
from typing import Any

from .hypothesis import NUMPY_OPS, ArrayOps

#: Silverman's rule-of-thumb constant of Eq. 6.7 (second derivative, 2D Perlin kernel).
SILVERMAN_PERLIN = 1.9635
#: Normalisation of the 2D Perlin kernel: int_disc k(|x|) dx = 2 pi / 7.
_PERLIN_NORM = 7.0 / (2.0 * math.pi)
#: Rates of Sec. 6.3-6.4: r ~ N^(-1/6) (value), r' ~ N^(-1/8) (second derivative).
RATE_VALUE = -1.0 / 6.0
RATE_LAPLACIAN = -1.0 / 8.0
VARIANCES = ("full", "paper")
LAPLACIANS = ("debiased", "paper")


def perlin_weight(q2: Any, rp2: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """K'_{r'}(q) of the normalised 2D Perlin kernel (paper 001 Sec. 4) for squared
    distance ``q2`` and squared bandwidth ``rp2``; 0 from |q| = r' on (k(1) = 0)."""
    t = ops.minimum(q2 / rp2, 1.0) ** 0.5
    return (1.0 + t * t * t * (t * (15.0 - 6.0 * t) - 10.0)) * (_PERLIN_NORM / rp2)


def laplacian_weight(u: Any, v: Any, rp: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """w_lap of Eq. 6.5-6.6 for a photon at tangent offset (u, v) from the gather point,
    Laplacian bandwidth ``rp``: nonzero for |(u, v)| < 2 r'."""
    rp2 = rp * rp
    u2, v2 = u * u, v * v
    side = (perlin_weight((u - rp) ** 2 + v2, rp2, ops) + perlin_weight((u + rp) ** 2 + v2, rp2, ops)
            + perlin_weight(u2 + (v - rp) ** 2, rp2, ops) + perlin_weight(u2 + (v + rp) ** 2, rp2, ops))
    return (side - 4.0 * perlin_weight(u2 + v2, rp2, ops)) / rp2


def psi_moment(psi: Any, psi2_density: Any, density: Any, variance: str, ops: ArrayOps = NUMPY_OPS) -> Any:
    """V / p_l of Eq. 6.4: E[psi^2] / p_l = Q ("full") or Var[psi] / p_l = Q - A^2 / p_l
    ("paper"), from the running means A = E[psi], Q = p_l E[c^2] and p_l (see the module
    docstring). 0 where no photon was seen."""
    if variance == "full":
        return psi2_density
    if variance != "paper":
        raise ValueError(f"unknown APPM variance '{variance}' (choose {', '.join(VARIANCES)})")
    seen = density > 0.0
    var = psi2_density - psi * psi / ops.select(seen, density, 1.0)
    return ops.select(seen, ops.maximum(var, 0.0), 0.0)


def laplacian_variance(lap_mean: Any, lap_sq: Any, n_passes: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """Sample variance of the per-pass Laplacian estimates from their running moments,
    (E[Lap^2] - E[Lap]^2) n / (n - 1); NaN for n < 2 (one pass says nothing about it)."""
    biased = ops.maximum(lap_sq - lap_mean * lap_mean, 0.0)
    return ops.select(n_passes >= 2.0, biased * n_passes / ops.maximum(n_passes - 1.0, 1.0), math.nan)


def laplacian_square(lap_mean: Any, lap_sq: Any, n_passes: Any, laplacian: str, z: float = 2.0,
                     ops: ArrayOps = NUMPY_OPS) -> Any:
    """(Delta I)^2 for Eq. 6.4 from the running moments of the per-pass Laplacian
    estimates over ``n_passes``: E[Lap]^2 as printed ("paper"), or ("debiased") with
    z^2 times the noise of that mean taken out, E[Lap]^2 - z^2 Var[Lap] / n, floored at 0
    (0 after one pass, when Var[Lap] is unknown)."""
    if laplacian == "paper":
        return lap_mean * lap_mean
    if laplacian != "debiased":
        raise ValueError(f"unknown APPM Laplacian '{laplacian}' (choose {', '.join(LAPLACIANS)})")
    var = laplacian_variance(lap_mean, lap_sq, n_passes, ops)
    lap2 = ops.maximum(lap_mean * lap_mean - (z * z) * var / n_passes, 0.0)
    return ops.select(var == var, lap2, 0.0)


def plugin_radius(moment: Any, lap2: Any, n: Any, photons: int, k2: float, roughness: float,
                  ops: ArrayOps = NUMPY_OPS) -> Any:
    """Unbounded plug-in bandwidth of Eq. 6.4 for pass ``n``:
    (2 R(K) (V / p_l) / (J k_2^2 (Delta I)^2 n))^(1/6); ``moment`` is V / p_l from
    :func:`psi_moment`, ``lap2`` (Delta I)^2 from :func:`laplacian_square`. inf where
    it is 0 (no curvature seen: no bias to trade against), 0 where V is 0; the caller
    clamps to the bounds."""
    flat = lap2 <= 0.0
    r6 = 2.0 * roughness * moment / (photons * k2 * k2 * ops.select(flat, 1.0, lap2) * n)
    return ops.select(flat, math.inf, r6 ** (1.0 / 6.0))


def silverman_radius(lap_mean: Any, lap_sq: Any, unit: Any, n_passes: Any, n: Any,
                     ops: ArrayOps = NUMPY_OPS) -> Any:
    """Unbounded r'_n of Eq. 6.7: 1.9635 sigma n^(-1/8), sigma = unit sqrt(Var[Lap] / E[Lap^2])
    over the ``n_passes`` per-pass estimates so far (``unit``: the chain's initial
    bandwidth; sigma = unit where nothing was seen or after a single pass)."""
    var = laplacian_variance(lap_mean, lap_sq, n_passes, ops)
    known = (lap_sq > 0.0) & (var == var)
    rel = ops.select(known, ops.minimum(var / ops.select(known, lap_sq, 1.0), 1.0), 1.0)
    return SILVERMAN_PERLIN * unit * rel ** 0.5 * n ** RATE_LAPLACIAN


def bounded(r: Any, lo: Any, hi: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """r clamped to [lo, hi] (Sec. 6.4); NaN (from empty statistics) goes to ``hi``."""
    return ops.select(r == r, ops.minimum(ops.maximum(r, lo), hi), hi)
