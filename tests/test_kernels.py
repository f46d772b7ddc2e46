"""Each offered kernel integrates to 1 over the disc; the Gaussian is not offered."""

from __future__ import annotations

import numpy as np
import pytest

from ppmrecon.render.kernels import KERNELS, kernel_moments, kernel_weight


@pytest.mark.parametrize("name", KERNELS)
@pytest.mark.parametrize("radius", [0.01, 1.0, 7.5])
def test_unit_integral_over_disc(name, radius):
    # midpoint rule in polar coordinates: integral of K(d) 2 pi d dd over [0, r]
    n = 200_000
    d = (np.arange(n) + 0.5) / n * radius
    w = kernel_weight(name, d * d, radius * radius, sqrt=np.sqrt)
    integral = float(np.sum(w * 2 * np.pi * d) * radius / n)
    assert integral == pytest.approx(1.0, rel=1e-6)


def test_gaussian_not_offered():
    assert "gaussian" not in KERNELS
    with pytest.raises(ValueError, match="unknown kernel"):
        kernel_weight("gaussian", 0.1, 1.0)


@pytest.mark.parametrize("name", KERNELS)
def test_moments_match_quadrature(name):
    """k_2 and R(K) of kernel_moments equal their integrals (midpoint rule, polar)."""
    n = 400_000
    rho = (np.arange(n) + 0.5) / n
    w = kernel_weight(name, rho * rho, 1.0, sqrt=np.sqrt)
    k2 = float(np.sum(np.pi * rho ** 3 * w) / n)
    rough = float(np.sum(2 * np.pi * rho * w * w) / n)
    assert kernel_moments(name) == pytest.approx((k2, rough), rel=1e-6)
