"""Bandwidth controllers: one object per progressive method (SPEC section 4).

Every chain of every pixel has a radius; the controller owns the radii of all chains
and updates them after each pass from what the gather saw. Only the initial bandwidth
differs between the chains (paper 002 Sec. 4.2), so each chain is exactly as
consistent as the method it runs.

Interface (what the pass loop calls):

    controller.start(r1)                 r1: list of per-pixel initial radii, one per chain
    controller.radii() -> list[Float]    the radii to gather with in the current pass
    controller.update(i, result)         after pass i (1-based), with the gather statistics
    controller.header() -> dict          method name and parameters for the buffer header
    controller.stats                     which extra gather statistics it needs
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import drjit as dr
import mitsuba as mi

#: The five initial bandwidths relative to the k-NN distance, smallest first
#: (paper 002 Sec. 4.1): chain 0 is ~y, chains 1..4 are ~z^1..~z^4.
CHAIN_SCALES: tuple[float, ...] = (0.25, 0.5 ** 1.5, 0.5, 0.5 ** 0.5, 1.0)
#: The conventional single-bandwidth baseline starts at the second-smallest.
SINGLE_SCALE: float = CHAIN_SCALES[1]


class Controller(Protocol):
    name: str
    stats: str

    def start(self, r1: list[mi.Float]) -> None: ...

    def radii(self) -> list[mi.Float]: ...

    def update(self, pass_index: int, result: Any) -> None: ...

    def header(self) -> dict[str, Any]: ...


@dataclass
class SPPMController:
    """Stochastic PPM in the Knaus-Zwicker form (paper 002 Eq. 4):

        r_{i+1}^2 = r_i^2 (i + alpha) / (i + 1),   alpha = 2/3 by default.

    The schedule does not depend on the photons, so every pixel of a chain shrinks by
    the same factor and the gather statistics are not needed.
    """

    alpha: float = 2.0 / 3.0
    name: str = "sppm"
    stats: str = "none"
    _r: list[mi.Float] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must lie in (0, 1), got {self.alpha}")

    def start(self, r1: list[mi.Float]) -> None:
        self._r = [mi.Float(r) for r in r1]

    def radii(self) -> list[mi.Float]:
        return self._r

    def update(self, pass_index: int, result: Any = None) -> None:
        shrink = dr.sqrt((pass_index + self.alpha) / (pass_index + 1.0))
        self._r = [r * shrink for r in self._r]
        dr.eval(self._r)

    def header(self) -> dict[str, Any]:
        return {"ppmrecon.method": self.name, "ppmrecon.alpha": self.alpha}


def make_controller(method: str, **params: Any) -> Controller:
    """The controller for ``method`` (``sppm``; more methods register in CONTROLLERS)."""
    try:
        cls = CONTROLLERS[method]
    except KeyError:
        raise ValueError(f"unknown method '{method}' (choose {', '.join(CONTROLLERS)})") from None
    return cls(**params)


CONTROLLERS: dict[str, type] = {"sppm": SPPMController}
