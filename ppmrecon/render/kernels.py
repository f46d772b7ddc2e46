"""Density-estimation kernels K_r(d) over the disc of radius r, each with unit integral.

Only kernels that keep progressive photon mapping consistent are offered (paper 004,
García Hernández et al.): constant, Epanechnikov, Silverman (biweight) and the cone
with slope 1. The Gaussian is not offered: its usual normalisation over the disc
underestimates by 46.9% (paper 004).

With s = d^2 / r^2 in [0, 1):

    constant      K = 1 / (pi r^2)
    epanechnikov  K = 2 (1 - s) / (pi r^2)
    silverman     K = 3 (1 - s)^2 / (pi r^2)
    cone          K = 3 (1 - sqrt(s)) / (pi r^2)

and K = 0 outside the disc. Each is written once, for Dr.Jit arrays and for numpy.

Two constants of each kernel enter the asymptotic bias and variance of the estimate
(Silverman 1986, Sec. 4.3; paper 001 Eq. 6.2 and 6.4), for the unit disc:

    k_2  = int x_1^2 K(x) dx  (= pi int_0^1 rho^3 K(rho) drho): bias ~ k_2 Laplacian r^2 / 2
    R(K) = int K(x)^2 dx      (= 2 pi int_0^1 rho K(rho)^2 drho): variance ~ R(K) / r^2

                  k_2     R(K)
    constant      1/4     1/pi
    epanechnikov  1/6     4/(3 pi)
    silverman     1/8     9/(5 pi)
    cone          3/20    3/(2 pi)
"""

from __future__ import annotations

import math
from typing import Any

KERNELS: tuple[str, ...] = ("constant", "epanechnikov", "silverman", "cone")

#: (k_2, R(K)) of each kernel on the unit disc (closed forms, see the module docstring).
KERNEL_MOMENTS: dict[str, tuple[float, float]] = {
    "constant": (1.0 / 4.0, 1.0 / math.pi),
    "epanechnikov": (1.0 / 6.0, 4.0 / (3.0 * math.pi)),
    "silverman": (1.0 / 8.0, 9.0 / (5.0 * math.pi)),
    "cone": (3.0 / 20.0, 3.0 / (2.0 * math.pi)),
}


def kernel_moments(name: str) -> tuple[float, float]:
    """(k_2, R(K)) of kernel ``name``: its second moment along one axis and its roughness
    (integral of K^2), both for unit bandwidth."""
    try:
        return KERNEL_MOMENTS[name]
    except KeyError:
        raise ValueError(f"unknown kernel '{name}' (choose {', '.join(KERNELS)})") from None


def kernel_weight(name: str, d2: Any, r2: Any, sqrt=None) -> Any:
    """K_r(d) for squared distance ``d2`` and squared radius ``r2`` (inside the disc).

    Works on Dr.Jit arrays and numpy arrays alike (pass ``sqrt`` for the array type;
    default ``math.sqrt``-free formulas except the cone). The caller masks d2 >= r2.
    """
    inv_area = 1.0 / (math.pi * r2)
    if name == "constant":
        return inv_area
    s = d2 / r2
    if name == "epanechnikov":
        return 2.0 * (1.0 - s) * inv_area
    if name == "silverman":
        return 3.0 * (1.0 - s) * (1.0 - s) * inv_area
    if name == "cone":
        if sqrt is None:
            raise ValueError("the cone kernel needs the array type's sqrt")
        return 3.0 * (1.0 - sqrt(s)) * inv_area
    raise ValueError(f"unknown kernel '{name}' (choose {', '.join(KERNELS)})")
