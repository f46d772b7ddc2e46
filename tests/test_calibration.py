"""Calibration of the bandwidth controllers' hypothesis tests (issue 20).

Under the null hypothesis -- uniform photon density over the disc, contributions that
do not depend on where a photon fell -- a test at level alpha must reject in a fraction
alpha of the trials. Each simulation below is vectorised over trials and runs the
statistics through the very functions of :mod:`ppmrecon.render.hypothesis` that the
controllers call: J light paths per pass over ``PASSES`` passes since the radius last
changed, each landing in the disc with probability p and then uniformly in one of the 12
equal-area cells, with a constant or a random positive contribution.

FPPM (alpha_F = 0.01, m = t J samples as in paper 000 Sec. 5.1): the rejection rate lies
in a binomial interval around alpha from 20 expected photons on. Below, the statistic is
discrete (Pearson's X^2 / 11 for equal contributions) and its exact level wanders around
alpha with the photon count: ~0.4 alpha for 2 photons, up to ~1.3 alpha near 7 (for
exactly 4 photons it is 2.6 alpha: three in one cell of 12). There the assertion is the
upper bound of that band. Heavy-tailed contributions (lognormal) make the F-test
conservative (~0.8 alpha): upper bound and a floor only.

CPPM (Pearson's chi-squared test at 0.05, counts from its initial threshold 20 on): the
exact level of the discrete test lies between ~3.9% (20 photons) and ~5.3% (31 photons)
and converges to 5% (two-sided from 100 photons on).

Every bound is the central 1 - 2e-5 range of Binomial(trials, rate) (about 4.3 sigma).
Power checks (so that a test that never rejects cannot pass): a 3:1 density gradient
across the disc, and for FPPM contributions 3x larger on one half.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import pytest
from scipy import stats

from ppmrecon.render import hypothesis as H

ALPHA_F = 0.01  # FPPM's default significance (paper 000 Sec. 6)
ALPHA_CHI = 0.05  # CPPM's default significance
J = 1 << 17  # light paths per pass (the renderer's default)
PASSES = 8  # passes since the radius last changed: m = t J = 2^20
TAIL = 1e-5  # one-sided tail of each binomial bound
#: Band of the exact level of the discrete statistics at small counts (module docstring).
SMALL_COUNT_BAND = 1.3
UNIFORM = np.full(H.N_CELLS, 1.0 / H.N_CELLS)
#: 3x the photon density on the upper half (sectors 0-2 of both annuli).
UPPER_HALF = np.tile(np.repeat([True, False], H.N_SECTORS // 2), H.N_ANNULI)
GRADIENT = np.where(UPPER_HALF, 3.0, 1.0) / np.where(UPPER_HALF, 3.0, 1.0).sum()
LUMINANCE = np.array([0.212671, 0.715160, 0.072169])

Draw = Callable[[np.random.Generator, np.ndarray], np.ndarray]


def binomial_bounds(trials: int, rate: float) -> tuple[float, float]:
    """Rejection-rate bounds: the central 1 - 2 TAIL range of Binomial(trials, rate) / trials."""
    lo = stats.binom.ppf(TAIL, trials, rate)
    hi = stats.binom.isf(TAIL, trials, rate)
    return lo / trials, hi / trials


def in_disc_counts(rng: np.random.Generator, expected: float, trials: int) -> np.ndarray:
    """Photons in the disc: each of the m = PASSES J paths lands there with probability p."""
    m = PASSES * J
    return rng.binomial(m, expected / m, trials)


def cell_counts(rng: np.random.Generator, n: np.ndarray, probs: np.ndarray = UNIFORM) -> np.ndarray:
    """(12, trials) photon counts of the cells for ``n`` photons per trial."""
    return rng.multinomial(n, probs).T.astype(np.float64)


def cell_moments(rng: np.random.Generator, n: np.ndarray, draw: Draw,
                 probs: np.ndarray = UNIFORM) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel, per-cell sums and sums of squares, each (channels, 12, trials), of
    explicit photons: ``n`` per trial, cells drawn from ``probs``, contributions
    ``draw(rng, cells)`` of shape (channels, photons). Chunks of trials bound memory."""
    sums, sumsqs = [], []
    for part in np.array_split(np.arange(n.size), max(1, int(n.sum()) // 2_000_000)):
        k = n[part]
        trial = np.repeat(np.arange(part.size), k)
        cells = rng.choice(H.N_CELLS, size=trial.size, p=probs)
        psi = draw(rng, cells)
        index = trial * H.N_CELLS + cells
        size, shape = part.size * H.N_CELLS, (part.size, H.N_CELLS)
        sums.append(np.stack([np.bincount(index, p, size).reshape(shape).T for p in psi]))
        sumsqs.append(np.stack([np.bincount(index, p * p, size).reshape(shape).T for p in psi]))
    return np.concatenate(sums, axis=2), np.concatenate(sumsqs, axis=2)


def fppm_rejects(sums: np.ndarray, sumsqs: np.ndarray, n: np.ndarray,
                 significance: float = ALPHA_F) -> np.ndarray:
    """FPPM's decision per trial, as FPPMController.reject takes it: m = t J (Eq. 7 and
    Sec. 5.1), F_c from the table at the per-channel level, any channel rejects."""
    channels = sums.shape[0]
    m = H.fppm_samples(np.full(n.shape, float(PASSES)), J, n.astype(np.float64))
    table = H.f_critical_table(H.fppm_test_significance(significance, channels))
    f_c = table[np.minimum(m, H.F_TABLE_SIZE).astype(int)]
    reject = np.zeros(n.shape, bool)
    for ch in range(channels):
        reject |= H.anova_f(list(sums[ch]), list(sumsqs[ch]), m) > f_c
    return reject & (n > 0)


def exponential(rng: np.random.Generator, cells: np.ndarray) -> np.ndarray:
    return rng.exponential(1.0, (1, cells.size))


def lognormal(rng: np.random.Generator, cells: np.ndarray) -> np.ndarray:
    return rng.lognormal(0.0, 1.0, (1, cells.size))


def rgb_independent(rng: np.random.Generator, cells: np.ndarray) -> np.ndarray:
    return rng.exponential(1.0, (3, cells.size))


def rgb_white(rng: np.random.Generator, cells: np.ndarray) -> np.ndarray:
    """A white light: the channels are proportional, so F is the same in each."""
    return np.array([1.0, 0.8, 0.6])[:, None] * rng.exponential(1.0, (1, cells.size))


def textured(rng: np.random.Generator, cells: np.ndarray) -> np.ndarray:
    """Paper 000 Fig. 4: uniform photons, contributions 3x larger on the upper half."""
    return np.where(UPPER_HALF[cells], 3.0, 1.0)[None] * rng.exponential(1.0, (1, cells.size))


def chromatic(rng: np.random.Generator, cells: np.ndarray) -> np.ndarray:
    """Red above, blue below, of equal luminance: only a per-channel test can see it."""
    red, blue = np.array([1.0, 0, 0]), np.array([0, 0, LUMINANCE[0] / LUMINANCE[2]])
    return np.where(UPPER_HALF[cells], red[:, None], blue[:, None]) * rng.exponential(1.0, cells.size)


def luminance(draw: Draw) -> Draw:
    return lambda rng, cells: (LUMINANCE @ draw(rng, cells))[None]


def assert_calibrated(rate: float, trials: int, alpha: float, expected: float,
                      two_sided_from: float = 20.0) -> None:
    """The rate lies in the binomial interval around alpha from ``two_sided_from``
    photons on; below, at most the upper bound of the small-count band."""
    lo, hi = binomial_bounds(trials, alpha)
    if expected >= two_sided_from:
        assert lo <= rate <= hi, (expected, rate, (lo, hi))
    else:
        assert rate <= binomial_bounds(trials, SMALL_COUNT_BAND * alpha)[1], (expected, rate)


# ------------------------------------------------------------------------------ FPPM

@pytest.mark.parametrize("expected", [2, 5, 10, 20, 50, 200, 1000, 10_000])
def test_fppm_null_rate_equal_contributions(expected):
    """Equal contributions (S_c = Q_c = the cell counts): the F-test's level, 40000 trials."""
    rng = np.random.default_rng(100 + expected)
    trials = 40_000
    n = in_disc_counts(rng, expected, trials)
    counts = cell_counts(rng, n)[None]
    rate = fppm_rejects(counts, counts, n).mean()
    assert_calibrated(rate, trials, ALPHA_F, expected)


@pytest.mark.parametrize("expected", [2, 5, 10, 20, 50, 200, 1000, 10_000])
def test_fppm_null_rate_exponential_contributions(expected):
    rng = np.random.default_rng(200 + expected)
    trials = min(20_000, 10_000_000 // expected)
    n = in_disc_counts(rng, expected, trials)
    rate = fppm_rejects(*cell_moments(rng, n, exponential), n).mean()
    assert_calibrated(rate, trials, ALPHA_F, expected)


@pytest.mark.parametrize("expected", [5, 50, 1000])
def test_fppm_null_rate_heavy_tailed_contributions_is_conservative(expected):
    """Lognormal(0, 1) contributions: at most alpha (the F-test turns conservative,
    ~0.8 alpha measured), and not a dead test."""
    rng = np.random.default_rng(300 + expected)
    trials = min(20_000, 5_000_000 // expected)
    n = in_disc_counts(rng, expected, trials)
    rate = fppm_rejects(*cell_moments(rng, n, lognormal), n).mean()
    assert rate <= binomial_bounds(trials, ALPHA_F)[1], rate
    if expected >= 20:
        assert rate >= binomial_bounds(trials, 0.5 * ALPHA_F)[0], rate


@pytest.mark.parametrize("draw, expected", [(rgb_independent, 5), (rgb_independent, 50),
                                            (rgb_independent, 1000), (rgb_white, 50),
                                            (rgb_white, 1000)])
def test_fppm_per_channel_null_rate(draw, expected):
    """The per-channel option tests R, G, B at alpha / 3 each (Bonferroni), so a pixel
    shrinks with probability ~alpha for independent channels, alpha / 3 for a white light
    (identical F in each channel), never above alpha."""
    rng = np.random.default_rng(400 + expected + (draw is rgb_white))
    trials = min(20_000, 6_000_000 // expected)
    n = in_disc_counts(rng, expected, trials)
    rate = fppm_rejects(*cell_moments(rng, n, draw), n).mean()
    if draw is rgb_white:
        lo, hi = binomial_bounds(trials, ALPHA_F / 3)
        assert (lo if expected >= 20 else 0.0) <= rate <= hi, (rate, (lo, hi))
    else:
        family = 1 - (1 - ALPHA_F / 3) ** 3  # independent channels: 0.99 alpha
        assert_calibrated(rate, trials, family, expected)


def test_fppm_in_disc_count_would_fail_calibration():
    """The calibration sees the old counting (m = photons inside the disc, issue 20):
    F is then ~12/11 too large and the rate doubles at large counts, and with two
    photons in one cell F is infinite."""
    rng = np.random.default_rng(500)
    trials = 40_000
    n = in_disc_counts(rng, 1000, trials)
    counts = cell_counts(rng, n)
    table = H.f_critical_table(ALPHA_F)
    m_old = n.astype(np.float64)
    rate = np.mean(H.anova_f(list(counts), list(counts), m_old) > table[np.minimum(n, H.F_TABLE_SIZE)])
    assert rate > binomial_bounds(trials, ALPHA_F)[1], rate
    two = np.zeros((H.N_CELLS, 1))
    two[3] = 2.0
    assert np.isinf(H.anova_f(list(two), list(two), np.array([2.0])))
    assert not fppm_rejects(two[None], two[None], np.array([2]))[0]


@pytest.mark.parametrize("case", ["gradient", "textured", "chromatic"])
def test_fppm_power(case):
    """Real differences are found: a 3:1 density gradient, 3x contributions on one half
    (paper 000 Fig. 4) and, per channel, red above / blue below at equal luminance."""
    rng = np.random.default_rng(600)
    trials = 2000
    n = in_disc_counts(rng, 1000, trials)
    if case == "gradient":
        sums, sumsqs = cell_moments(rng, n, exponential, GRADIENT)
    else:
        sums, sumsqs = cell_moments(rng, n, textured if case == "textured" else chromatic)
    assert fppm_rejects(sums, sumsqs, n).mean() > 0.99
    if case == "chromatic":  # luminance alone cannot tell (rate ~alpha)
        lum_sums, lum_sumsqs = cell_moments(rng, n, luminance(chromatic))
        assert fppm_rejects(lum_sums, lum_sumsqs, n).mean() < 0.05
    # Fewer photons, less power, but the test is alive.
    n = in_disc_counts(rng, 200, trials)
    assert fppm_rejects(*cell_moments(rng, n, exponential, GRADIENT), n).mean() > 0.5


# ------------------------------------------------------------------------------ CPPM

@pytest.mark.parametrize("photons", [20, 30, 50, 100, 1000, 10_000])
def test_cppm_null_rate(photons):
    """Pearson's cumulative test at 0.05 from the initial threshold (20 photons) on: the
    whole-disc test (which decides the shrink) at most ~alpha, two-sided from 100 photons
    (measured 3.9% at 20, 5.3% at 31, 4.7% at 50); the inner-annulus test never above."""
    rng = np.random.default_rng(700 + photons)
    trials = 40_000
    counts = cell_counts(rng, np.full(trials, photons))
    passed = H.cppm_test(list(counts), H.chi2_critical(ALPHA_CHI))
    whole, inner = np.mean(~passed[-1]), np.mean(~passed[0])
    lo, hi = binomial_bounds(trials, ALPHA_CHI)
    if photons >= 100:
        assert lo <= whole <= hi, (whole, (lo, hi))
    else:
        assert binomial_bounds(trials, 0.75 * ALPHA_CHI)[0] <= whole
        assert whole <= binomial_bounds(trials, 1.1 * ALPHA_CHI)[1], whole
    assert inner <= hi, inner


def test_cppm_power():
    rng = np.random.default_rng(800)
    trials = 4000
    crit = H.chi2_critical(ALPHA_CHI)
    gradient = H.cppm_test(list(cell_counts(rng, np.full(trials, 200), GRADIENT)), crit)
    assert np.mean(~gradient[-1]) > 0.99
    gradient = H.cppm_test(list(cell_counts(rng, np.full(trials, 50), GRADIENT)), crit)
    assert np.mean(~gradient[-1]) > 0.5
