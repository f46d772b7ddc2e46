"""Each offered kernel integrates to 1 over the disc; the Gaussian is not offered."""

from __future__ import annotations

import numpy as np
import pytest

from ppmrecon.render.kernels import KERNELS, kernel_weight


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
