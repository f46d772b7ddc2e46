"""Per-pixel running estimates over passes (SPEC section 3, step 4).

The pixel value after N passes is the mean of the per-pass estimates E_1..E_N (the
pixel-estimation form of Knaus & Zwicker, paper 002 Eq. 1-2). Welford's recurrence
(Welford 1962) over the same values gives the sample variance, and the variance of
the mean is

    Var[mean] = M2 / ((N - 1) N),   averaged over R, G, B,

reported as 0 after a single pass (unknown).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np


def opaque_count(n: int) -> mi.Float:
    """A pass count as an opaque JIT value: a Python number would be baked into the
    kernel as a literal and recompile it on every pass."""
    return dr.opaque(mi.Float, float(n))


@dataclass
class RunningMean:
    """Welford accumulator of Color3f per pixel."""

    mean: mi.Color3f
    m2: mi.Color3f
    n: int = 0

    @classmethod
    def zeros(cls, size: int) -> "RunningMean":
        return cls(dr.zeros(mi.Color3f, size), dr.zeros(mi.Color3f, size), 0)

    def add(self, value: mi.Color3f, evaluate: bool = True) -> None:
        """Fold in one pass; ``evaluate=False`` leaves the update to the caller's
        ``dr.eval`` (one kernel for several accumulators)."""
        self.n += 1
        delta = value - self.mean
        self.mean = self.mean + delta / opaque_count(self.n)
        self.m2 = self.m2 + delta * (value - self.mean)
        if evaluate:
            dr.eval(self.mean, self.m2)

    def variance_of_mean(self) -> mi.Float:
        if self.n < 2:
            return dr.zeros(mi.Float, dr.width(self.mean))
        var = self.m2 / opaque_count((self.n - 1) * self.n)
        return (var.x + var.y + var.z) / 3.0

    def numpy(self, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """(mean (H, W, 3), variance of the mean (H, W)) as float32."""
        mean = np.asarray(self.mean).reshape(3, height, width).transpose(1, 2, 0)
        var = np.asarray(self.variance_of_mean()).reshape(height, width)
        return np.ascontiguousarray(mean, np.float32), np.ascontiguousarray(var, np.float32)


@dataclass
class PlainMean:
    """Running mean of a per-pixel G-buffer quantity (Float or 3-vector)."""

    mean: object
    n: int = 0

    def add(self, value, evaluate: bool = True) -> None:
        self.n += 1
        self.mean = self.mean + (value - self.mean) / opaque_count(self.n)
        if evaluate:
            dr.eval(self.mean)


def merge_welford(parts: Sequence[tuple[np.ndarray, np.ndarray, int]]) -> tuple[np.ndarray, np.ndarray, int]:
    """Merge Welford states ``(mean, M2, n)`` of disjoint sets of samples into the state
    of their union (Chan, Golub & LeVeque 1979, pairwise update), in float64:

        n = n_a + n_b,  delta = mean_b - mean_a,
        mean = mean_a + delta n_b / n,  M2 = M2_a + M2_b + delta^2 n_a n_b / n.

    The merged mean is the sample-count-weighted mean of the parts and M2 / (n - 1) the
    sample variance of all samples together, as one Welford pass over them would give
    (up to rounding). Parts with n = 0 are skipped; returns zeros with n = 0 if all are."""
    mean = m2 = None
    n = 0
    for mean_b, m2_b, n_b in parts:
        if n_b <= 0:
            continue
        mean_b, m2_b = np.asarray(mean_b, np.float64), np.asarray(m2_b, np.float64)
        if mean is None:
            mean, m2, n = mean_b.copy(), m2_b.copy(), int(n_b)
            continue
        if mean_b.shape != mean.shape or m2_b.shape != mean.shape:
            raise ValueError(f"Welford states of shapes {mean.shape} and {mean_b.shape} do not merge")
        total = n + int(n_b)
        delta = mean_b - mean
        mean = mean + delta * (n_b / total)
        m2 = m2 + m2_b + delta * delta * (n * n_b / total)
        n = total
    if mean is None:
        shape = np.shape(parts[0][0]) if len(parts) else (0,)
        return np.zeros(shape), np.zeros(shape), 0
    return mean, m2, n
