"""The hypothesis tests behind the CPPM and FPPM bandwidth controllers, as pure functions
(SPEC section 4; paper 000 Sec. 3.2 and 5.1; Lin et al. 2020, CPPM).

The disc of radius r around a gather point x is split into ``N_ANNULI`` = 2 equal-area
annuli times ``N_SECTORS`` = 6 equal-angle sectors: 12 cells of equal area (paper 000
Sec. 3.2.1 and 6.1.1, n_a = 2, n_s = 6). A photon at x_p falls in

    annulus a = min(floor(n_a |x_p - x|^2 / r^2), n_a - 1)
    sector  s = floor(n_s * phi / (2 pi)),  phi = atan2(<x_p - x, t>, <x_p - x, s>) in [0, 2 pi)
    cell      = a * n_s + s

where (s, t) is the gather point's tangent frame (the map f_map of paper 000 Eq. 2; we
use the shading frame ``si.sh_frame`` as the authors' CPPM code does with ``its.toLocal``;
the distance is the 3D distance, as in the gather).

CPPM (Pearson's chi-squared test of uniformity, cumulative over annuli):

    X^2 = sum_c (O_c - E)^2 / E = C * sum_c O_c^2 / N - N,   E = N / C,
    C = 6 (inner annulus) or 12 (whole disc), N = sum_c O_c, df = C - 1.

FPPM (one-way ANOVA F-test over the 12 cells, paper 000 Eq. 7): every light path
emitted since the radius last changed is one sample for each of the n = 12 groups (its
contribution psi in the cell where its photon fell, 0 in the others, and 0 in every
cell if it missed the disc; Sec. 3.2.4), so all groups share the sample count

    m = t J   (Sec. 5.1: t passes since the radius last changed, J paths per pass),

and, with S_c = sum psi and Q_c = sum psi^2 per cell (the zeros add nothing),

    SS_between = sum_c S_c^2 / m - (sum_c S_c)^2 / (n m)
    SS_within  = sum_c Q_c - sum_c S_c^2 / m
    F = (SS_between / (n - 1)) / (SS_within / (n (m - 1))),   d1 = n - 1, d2 = n (m - 1).

We file each photon as one sample (the paper sums a path's photons per cell); a path
rarely leaves two photons in one disc, and m = max(t J, N) with N the photons in the
disc keeps the formulas valid if it does. Since N << m in a render, F tends to
(n / (n - 1)) sum_c (S_c - S)^2 / sum_c Q_c (S = the mean S_c); for equal contributions
that is X^2 / (n - 1), Pearson's statistic over the 12 cells, and F_c tends to
chi^2_{n-1} quantile / (n - 1): Pearson's whole-disc test (CPPM's) at level alpha_F.
Calibration under uniform photon density (tests/test_calibration.py): the rejection
rate matches alpha_F from ~20 photons on; below, the statistic is discrete and its
level wanders around alpha_F (at most ~1.3 alpha_F for a Poisson photon count, 2.6
alpha_F for exactly 4 photons: three in one cell); heavy-tailed contributions make it
conservative. The groups share light paths (a path is nonzero in one cell at most),
which raises E[F] under the null by at most 1 / (1 - p / n), p = a path's chance to hit
the disc (~1e-4 in a render; with m = N it would be 12/11, doubling the rate).

Every function takes an ``ops`` bundle (numpy by default; the renderer passes Dr.Jit's),
so the same formulas serve the vectorised controllers and the tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

N_ANNULI = 2
N_SECTORS = 6
N_CELLS = N_ANNULI * N_SECTORS

#: The FPPM critical-value table is exact for m <= F_TABLE_SIZE; beyond, the last entry
#: (d2 = 12 * 4095) is used, within 0.02% of the d2 -> infinity limit and on the
#: conservative side (F_c falls with d2). With m = t J that is every test once J >= 4096.
F_TABLE_SIZE = 4096
_SQRT3 = math.sqrt(3.0)


@dataclass(frozen=True)
class ArrayOps:
    """The few element-wise operations whose names differ between numpy and Dr.Jit."""

    floor: Callable[[Any], Any]
    select: Callable[[Any, Any, Any], Any]
    minimum: Callable[[Any, Any], Any]
    maximum: Callable[[Any, Any], Any]


NUMPY_OPS = ArrayOps(floor=np.floor, select=np.where, minimum=np.minimum,
                     maximum=np.maximum)


# ------------------------------------------------------------------------ cell layout

def sector_index(u: Any, v: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """Sector (0..5, float) of tangent-plane offsets (u, v): 60 degrees each,
    counter-clockwise from the frame's first tangent, i.e. floor(6 phi / (2 pi)) with
    phi = atan2(v, u) in [0, 2 pi). Half-plane tests instead of atan2 (cheaper in the
    gather loop): rotate the lower half by 180 degrees, then split the upper half at
    60 and 120 degrees (v < sqrt(3) u, v < -sqrt(3) u)."""
    flip = v < 0.0
    uu = ops.select(flip, -u, u)
    vv = ops.select(flip, -v, v)
    upper = ops.select(vv < _SQRT3 * uu, 0.0, ops.select(vv < -_SQRT3 * uu, 2.0, 1.0))
    return upper + ops.select(flip, N_SECTORS / 2.0, 0.0)


def cell_index(sector: Any, d2: Any, r2: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """Cell (0..11, float) of photons in sector ``sector`` at squared distance ``d2``
    from the gather point, for squared radius ``r2``: equal-area annuli, the inner one
    ends at r / sqrt(2)."""
    annulus = ops.minimum(ops.floor(d2 * N_ANNULI / r2), N_ANNULI - 1.0)
    return annulus * N_SECTORS + sector


def annulus_radius_factor(annuli: int) -> float:
    """Outer radius of the innermost ``annuli`` equal-area annuli relative to r:
    sqrt(a / n_a) (CPPM's shrink to the largest passing annulus)."""
    return math.sqrt(annuli / N_ANNULI)


# ------------------------------------------------------------------------------ CPPM

def pearson_chi2(counts: Sequence[Any], ops: ArrayOps = NUMPY_OPS) -> Any:
    """Pearson's X^2 of the cell counts ``counts`` (one array per cell) against the
    uniform distribution over those cells: C sum O^2 / N - N (0 where N = 0)."""
    total = counts[0]
    square = counts[0] * counts[0]
    for o in counts[1:]:
        total = total + o
        square = square + o * o
    return len(counts) * square / ops.maximum(total, 1.0) - total


def chi2_critical(significance: float, cells: Sequence[int] = (N_SECTORS, N_CELLS)) -> tuple[float, ...]:
    """The (1 - significance) quantiles of chi^2 with C - 1 degrees of freedom for each
    cumulative test (inner annulus, whole disc); computed once per controller."""
    from scipy.stats import chi2

    return tuple(float(chi2.isf(significance, c - 1)) for c in cells)


def cppm_test(counts: Sequence[Any], critical: Sequence[float],
              ops: ArrayOps = NUMPY_OPS) -> list[Any]:
    """CPPM's cumulative chi-squared test (as in the authors' Mitsuba 0.6 code): entry a
    says whether the innermost a + 1 annuli (their 6 (a + 1) cells) look uniform, i.e.
    X^2 < critical[a]; an empty set of cells passes."""
    passed = []
    for a in range(N_ANNULI):
        cells = counts[: (a + 1) * N_SECTORS]
        passed.append(pearson_chi2(cells, ops) < critical[a])
    return passed


def cppm_radius(r: Any, passed: Sequence[Any], k: float, ops: ArrayOps = NUMPY_OPS) -> Any:
    """The radius after a failed whole-disc test: the outer radius of the largest inner
    annulus group that passed, r sqrt(a / n_a), else r sqrt(k)."""
    factor = ops.select(passed[0], annulus_radius_factor(1), math.sqrt(k))
    for a in range(1, N_ANNULI - 1):  # more than two annuli: prefer the largest passing
        factor = ops.select(passed[a], annulus_radius_factor(a + 1), factor)
    return r * factor


# ------------------------------------------------------------------------------ FPPM

def anova_f(sums: Sequence[Any], sumsqs: Sequence[Any], m: Any,
            ops: ArrayOps = NUMPY_OPS) -> Any:
    """One-way ANOVA F statistic of paper 000 Eq. 7 from per-group sums S_c and sums of
    squares Q_c of m samples each (float64: m = t J reaches 1e9 and more, where the
    between-group term is a difference of O(1/m) values). F = 0 where m < 2 or all
    samples are equal (no evidence); F = inf where the within-group variation is zero but
    the between-group one is not (all samples of each group equal, groups different).
    With m = t J that branch cannot fire by chance: Cauchy-Schwarz gives
    sum_c S_c^2 <= N sum_c Q_c, so SS_within >= (1 - N / m) sum_c Q_c > 1e-6 sum_c Q_c
    wherever a photon was seen (N photons, N << m)."""
    n = len(sums)
    total = sums[0]
    s2 = sums[0] * sums[0]
    q = sumsqs[0]
    for s, qq in zip(sums[1:], sumsqs[1:]):
        total = total + s
        s2 = s2 + s * s
        q = q + qq
    mm = ops.maximum(m, 2.0)
    ss_between = ops.maximum(s2 / mm - total * total / (n * mm), 0.0)
    ss_within = ops.maximum(q - s2 / mm, 0.0)
    # Relative floor: Q and S^2/m carry float32 rounding from the accumulation.
    tiny = 1e-6 * q
    f = (ss_between / (n - 1.0)) / ops.maximum(ss_within / (n * (mm - 1.0)), 1e-300)
    f = ops.select(ss_within > tiny, f, ops.select(ss_between > tiny, math.inf, 0.0))
    return ops.select(m >= 2.0, f, 0.0)


def fppm_samples(passes: Any, photons: int, in_disc: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """The ANOVA sample count m of Eq. 7: every light path emitted since the radius last
    changed, m = t J (paper 000 Sec. 5.1; ``passes`` = t, ``photons`` = J per pass),
    zeros included. At least ``in_disc`` (the photons filed in the cells), so that
    SS_within stays >= 0 should a path leave several photons in one disc.
    Pass float64 arrays: t J exceeds 2^32 in long renders."""
    return ops.maximum(passes * float(photons), in_disc)


def fppm_test_significance(significance: float, channels: int) -> float:
    """The level of each channel's F-test so that a pixel, which shrinks if any of its
    ``channels`` tests rejects, does so with probability at most ``significance`` under
    the null (Bonferroni): significance / channels. Luminance: the level itself. With
    RGB the per-pixel rate lies between significance / 3 (white light: the channels are
    proportional and F is the same in each) and ~significance (independent channels)."""
    return significance / channels


def f_critical_table(significance: float, n_groups: int = N_CELLS,
                     size: int = F_TABLE_SIZE) -> np.ndarray:
    """F_c[m] = (1 - significance) quantile of F(n - 1, n (m - 1)) for m = 0..size
    (inf for m < 2: no test), from ``scipy.stats.f`` once per controller."""
    from scipy.stats import f

    table = np.full(size + 1, np.inf)
    m = np.arange(2, size + 1)
    table[2:] = f.isf(significance, n_groups - 1, n_groups * (m - 1))
    return table


def fppm_radius(r: Any, reject: Any, k: float, floor: Any, ops: ArrayOps = NUMPY_OPS) -> Any:
    """Paper 000 Eq. 21: keep r where the F-test passed, else max(k r, floor) with
    floor = r_min (i + 1)^((alpha - 1) / 2)."""
    return ops.select(reject, ops.maximum(k * r, floor), r)


def fppm_floor_factor(pass_index: int, alpha: float) -> float:
    """(i + 1)^((alpha - 1) / 2): the lower bound's decay after pass i (Eq. 21)."""
    return float((pass_index + 1.0) ** ((alpha - 1.0) / 2.0))
