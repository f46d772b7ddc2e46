"""Bandwidth controllers: one object per progressive method (SPEC section 4).

Every chain of every pixel has a radius; the controller owns the radii of all chains
and updates them after each pass from what the gather saw. Only the initial bandwidth
differs between the chains (paper 002 Sec. 4.2), so each chain is exactly as
consistent as the method it runs.

Interface (what the pass loop calls):

    controller.start(r1)                 r1: list of per-pixel initial radii, one per chain
    controller.radii() -> list[Float]    the radii to gather with in the current pass
    controller.stats_targets(chains)     per-chain cell statistics the gather accumulates
                                         into (None: the gather's fast path, no statistics)
    controller.update(i, results)        after pass i (1-based); results: one
                                         (chains, GatherResult) per eye hit point
    controller.header() -> dict          method name and parameters for the buffer header
    controller.stats                     which extra gather statistics it needs:
                                         "none", "counts" (CPPM), "moments" (FPPM) or
                                         "appm" (per-pass sums, :class:`APPMStatistics`)
    controller.state() -> dict           every per-pixel array it holds, by name (for
                                         a render's state file; empty before start)
    controller.load_state(arrays)        the inverse: continue from those arrays

The radii and statistics are per *pixel* chain state: the eye path's gather point moves
every pass (new random position in the pixel), and the statistics pool the photons seen
around all of a pixel's gather points since the radius last changed, in each point's own
tangent frame (the unified space of paper 000 Eq. 2), just as SPPM pools its per-pixel
photon statistics. The hypothesis tests themselves live in :mod:`.hypothesis`.
"""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, Sequence

import drjit as dr
import mitsuba as mi

from . import appm as A
from . import hypothesis as H
from .kernels import kernel_moments

#: The five initial bandwidths relative to the k-NN distance, smallest first
#: (paper 002 Sec. 4.1): chain 0 is ~y, chains 1..4 are ~z^1..~z^4.
CHAIN_SCALES: tuple[float, ...] = (0.25, 0.5 ** 1.5, 0.5, 0.5 ** 0.5, 1.0)

#: Dr.Jit's spelling of the element-wise operations of :mod:`.hypothesis`.
DRJIT_OPS = H.ArrayOps(floor=dr.floor, select=dr.select, minimum=dr.minimum,
                       maximum=dr.maximum)


def _float64(x: Any) -> Any:
    """Statistics are tested in double precision (the accumulators are float32/uint32)."""
    return dr.float64_array_t(mi.Float)(x)


class Controller(Protocol):
    name: str
    stats: str

    def start(self, r1: list[mi.Float]) -> None: ...

    def radii(self) -> list[mi.Float]: ...

    def stats_targets(self, chains: Sequence[int]) -> list["CellStatistics"] | None: ...

    def update(self, pass_index: int, result: Any) -> None: ...

    def header(self) -> dict[str, Any]: ...

    def state(self) -> dict[str, Any]: ...

    def load_state(self, arrays: dict[str, Any]) -> None: ...


class ChainState:
    """State export for the controllers: ``STATE`` lists the per-chain attributes (each
    a list with one Dr.Jit array per chain) and their Dr.Jit type names; the cell
    statistics (``_stats``, if the method has them) travel as their raw data. A resumed
    render must continue bit for bit, so nothing is recomputed from other fields."""

    STATE: tuple[tuple[str, str], ...] = (("_r", "Float"),)

    def state(self) -> dict[str, Any]:
        """Name -> Dr.Jit array of everything the controller carries between passes."""
        out: dict[str, Any] = {}
        for attr, _ in self.STATE:
            for c, arr in enumerate(getattr(self, attr, [])):
                out[f"{attr.lstrip('_')}.{c}"] = arr
        for c, st in enumerate(getattr(self, "_stats", [])):
            out[f"stats.{c}"] = st.data
        return out

    def load_state(self, arrays: dict[str, Any]) -> None:
        """Continue from ``state()``'s arrays (Dr.Jit or numpy); raises ValueError (with
        the array's name) if one is missing or the chains disagree in size."""
        n_chains = sum(1 for k in arrays if k.startswith("r."))
        if n_chains == 0:
            raise ValueError("no radii (r.0 ...) in the controller state")
        n = None
        for attr, type_name in self.STATE:
            cls = getattr(mi, type_name)
            values = []
            for c in range(n_chains):
                key = f"{attr.lstrip('_')}.{c}"
                if key not in arrays:
                    raise ValueError(f"{self.name} state lacks '{key}'")
                values.append(cls(arrays[key]))
                n = dr.width(values[-1]) if n is None else n
                if dr.width(values[-1]) != n:
                    raise ValueError(f"{self.name} state '{key}' has {dr.width(values[-1])} pixels, not {n}")
            setattr(self, attr, values)
        if self.stats in ("counts", "moments"):  # APPM's per-pass sums are empty between passes
            stats = []
            for c in range(n_chains):
                st = self._new_statistics(n)
                key = f"stats.{c}"
                if key not in arrays:
                    raise ValueError(f"{self.name} state lacks '{key}'")
                data = type(st.data)(arrays[key])
                if dr.width(data) != dr.width(st.data):
                    raise ValueError(f"{self.name} state '{key}' holds {dr.width(data)} values, "
                                     f"not {dr.width(st.data)}")
                st.data = data
                stats.append(st)
            self._stats = stats

    def _new_statistics(self, n_pixels: int) -> "CellStatistics":
        raise NotImplementedError


class CellStatistics:
    """Per-pixel accumulators over the 12 cells of one chain since its radius last changed.

    ``kind`` "counts": photon count per cell (uint32), for CPPM. ``kind`` "moments": sum
    and sum of squares of the photon contribution per cell (float32; ``channels`` 1 for
    luminance, 3 for RGB), for FPPM. Layout [pixel][cell][channel][sum, sum of squares]:
    one photon is one scatter of 2 x channels adjacent values, and one pixel's cells
    share cache lines while the gather visits its photons (measured ~1.3x faster than
    separate sum and square arrays at 256x256).
    """

    def __init__(self, n_pixels: int, kind: str, channels: int = 1):
        if kind not in ("counts", "moments"):
            raise ValueError(f"unknown statistics kind '{kind}'")
        if channels not in (1, 3) or (kind == "counts" and channels != 1):
            raise ValueError("channels must be 1 (luminance) or 3 (RGB, moments only)")
        self.n_pixels, self.kind, self.channels = n_pixels, kind, channels
        self.stride = 1 if kind == "counts" else 2 * channels  # values per (pixel, cell)
        size = n_pixels * H.N_CELLS * self.stride
        self.data = dr.zeros(mi.UInt32 if kind == "counts" else mi.Float, size)

    def add(self, pixel: mi.UInt32, cell: mi.UInt32, contrib: mi.Color3f, active: mi.Bool) -> None:
        """Accumulate one photon per lane (its cell and contribution f * Phi) into pixel
        ``pixel``'s statistics where ``active``. Called inside the gather's loop; each
        lane owns its pixel, so the scatters never conflict."""
        index = pixel * H.N_CELLS + cell
        if self.kind == "counts":
            value: Any = mi.UInt32(1)
        else:
            parts = [mi.luminance(contrib)] if self.channels == 1 else [contrib.x, contrib.y, contrib.z]
            value = mi.ArrayXf(*(x for v in parts for x in (v, v * v)))
        dr.scatter_reduce(dr.ReduceOp.Add, self.data, value, index, active,
                          mode=dr.ReduceMode.NoConflicts)

    def _cell(self, cell: int, offset: int) -> Any:
        index = dr.arange(mi.UInt32, self.n_pixels) * (H.N_CELLS * self.stride) + (cell * self.stride + offset)
        return _float64(dr.gather(type(self.data), self.data, index))

    def cell_counts(self) -> list[Any]:
        """Per-cell photon counts (float64), one array of pixels per cell."""
        if self.kind != "counts":
            raise ValueError("these statistics hold moments, not counts")
        return [self._cell(c, 0) for c in range(H.N_CELLS)]

    def cell_moments(self, channel: int) -> tuple[list[Any], list[Any]]:
        """Per-cell sums and sums of squares (float64) of one channel."""
        if self.kind != "moments":
            raise ValueError("these statistics hold counts, not moments")
        sums = [self._cell(c, 2 * channel) for c in range(H.N_CELLS)]
        sumsqs = [self._cell(c, 2 * channel + 1) for c in range(H.N_CELLS)]
        return sums, sumsqs

    def reset(self, mask: mi.Bool) -> None:
        """Zero the statistics of the pixels in ``mask`` (their radius changed)."""
        per_pixel = H.N_CELLS * self.stride
        index = dr.arange(mi.UInt32, self.n_pixels * per_pixel)
        dr.scatter(self.data, type(self.data)(0), index, dr.repeat(mask, per_pixel))
        dr.eval(self.data)


class APPMStatistics:
    """Per-pixel sums of one pass for APPM (one chain): sum K_r, sum K_r c, sum K_r c^2
    over the photons inside the chain's radius r and, with ``laplacian``, sum c w_lap
    over those within 2 r' (see :mod:`.appm`; c = luminance(beta f Phi)). Layout
    [pixel][4]: one photon is one scatter of 4 adjacent values (a 4-vector at index
    ``pixel``). ``rp`` is the Laplacian bandwidth r' of each pixel, ``reach`` = 2 r' the
    distance the gather must search for it (None without ``laplacian``: the chains of
    one hit point share r' and so the Laplacian, which only the first computes)."""

    kind = "appm"
    N_SUMS = 4

    def __init__(self, rp: mi.Float, laplacian: bool = True):
        self.rp = rp
        self.laplacian = laplacian
        self.reach = 2.0 * rp if laplacian else None
        self.n_pixels = dr.width(rp)
        self.data = dr.zeros(mi.Float, self.n_pixels * self.N_SUMS)

    def add_photon(self, pixel: mi.UInt32, u: mi.Float, v: mi.Float, weight: mi.Float, c: mi.Float,
                   inside: mi.Bool, active: mi.Bool) -> None:
        """One photon per lane: tangent offset (u, v), kernel weight K_r (valid where
        ``inside`` the radius), contribution c; ``active``: it passed the gather's checks.
        Each lane owns its pixel, so the scatters never conflict."""
        k = dr.select(inside, weight, 0.0)
        if self.laplacian:
            w_lap = A.laplacian_weight(u, v, self.rp, DRJIT_OPS)
            near = active & (u * u + v * v < self.reach * self.reach)
            lap, where = dr.select(near, c * w_lap, 0.0), inside | near
        else:
            lap, where = mi.Float(0.0), inside
        value = mi.ArrayXf(k, k * c, k * c * c, lap)
        dr.scatter_reduce(dr.ReduceOp.Add, self.data, value, pixel, where, mode=dr.ReduceMode.NoConflicts)

    def sums(self) -> list[Any]:
        """The four per-pixel sums (float64): sum K, sum K c, sum K c^2, sum c w_lap."""
        base = dr.arange(mi.UInt32, self.n_pixels) * self.N_SUMS
        return [_float64(dr.gather(mi.Float, self.data, base + k)) for k in range(self.N_SUMS)]


def _per_chain_counts(results: Any) -> list[tuple[int, mi.UInt32]]:
    """(chain, photons inside its radius this pass) for every chain in ``results``."""
    return [(c, res.count[slot]) for chains, res in results for slot, c in enumerate(chains)]


@dataclass
class SPPMController(ChainState):
    """Stochastic PPM in the Knaus-Zwicker form (paper 002 Eq. 4):

        r_{i+1}^2 = r_i^2 (i + alpha) / (i + 1),   alpha = 2/3 by default.

    The schedule does not depend on the photons, so every pixel of a chain shrinks by
    the same factor and the gather statistics are not needed.
    """

    alpha: float = 2.0 / 3.0
    name: str = "sppm"
    stats: str = "none"
    _r: list[mi.Float] = field(default_factory=list)
    #: The radii of pass i depend on the initial radii and i alone (not on what was
    #: gathered), so any range of passes can be rendered apart (Renderer.start_at).
    schedule_only: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must lie in (0, 1), got {self.alpha}")

    def start(self, r1: list[mi.Float]) -> None:
        self._r = [mi.Float(r) for r in r1]

    def radii(self) -> list[mi.Float]:
        return self._r

    def stats_targets(self, chains: Sequence[int]) -> None:
        return None

    def update(self, pass_index: int, result: Any = None) -> None:
        # Opaque: a per-pass literal would compile a new kernel every pass.
        shrink = dr.opaque(mi.Float, math.sqrt((pass_index + self.alpha) / (pass_index + 1.0)))
        self._r = [r * shrink for r in self._r]
        dr.eval(self._r)

    def header(self) -> dict[str, Any]:
        return {"ppmrecon.method": self.name, "ppmrecon.alpha": self.alpha}


@dataclass
class CPPMController(ChainState):
    """Chi-squared PPM (Lin et al. 2020), as the authors' public Mitsuba 0.6 code does it.

    Per pixel and chain: photon counts O_c of the 12 cells since the radius last changed,
    their total N and a threshold T (starts at the k-NN k). Once N >= T, Pearson's test
    of uniformity runs cumulatively (inner annulus, then the whole disc; see
    :func:`.hypothesis.cppm_test`). If the whole disc passes, r is kept (and the counts
    keep growing); if not, the counts reset, T *= beta and r shrinks to the outer radius
    of the largest inner annulus that passed, r sqrt(1/2), or else to r sqrt(k).
    """

    significance: float = 0.05
    k: float = 0.8
    beta: float = 1.5625
    knn: int = 20
    name: str = "cppm"
    stats: str = "counts"
    _r: list[mi.Float] = field(default_factory=list)

    def __post_init__(self) -> None:
        _check_open_unit("significance", self.significance)
        _check_open_unit("k", self.k)
        if not self.beta >= 1.0:
            raise ValueError(f"beta must be >= 1, got {self.beta}")
        if self.knn <= 0:
            raise ValueError(f"knn must be positive, got {self.knn}")
        # Critical values once per controller (df 5 and 11), never per pixel or pass.
        self.critical = H.chi2_critical(self.significance)

    STATE = (("_r", "Float"), ("_total", "UInt32"), ("_threshold", "Float"))

    def _new_statistics(self, n_pixels: int) -> CellStatistics:
        return CellStatistics(n_pixels, "counts")

    def start(self, r1: list[mi.Float]) -> None:
        n = dr.width(r1[0])
        self._r = [mi.Float(r) for r in r1]
        self._stats = [self._new_statistics(n) for _ in r1]
        self._total = [dr.zeros(mi.UInt32, n) for _ in r1]
        self._threshold = [dr.full(mi.Float, float(self.knn), n) for _ in r1]

    def radii(self) -> list[mi.Float]:
        return self._r

    def stats_targets(self, chains: Sequence[int]) -> list[CellStatistics]:
        return [self._stats[c] for c in chains]

    def update(self, pass_index: int, results: Any) -> None:
        for c, count in _per_chain_counts(results):
            total = self._total[c] + count
            ready = mi.Float(total) >= self._threshold[c]
            passed = H.cppm_test(self._stats[c].cell_counts(), self.critical, DRJIT_OPS)
            shrink = ready & ~passed[-1]
            r_new = mi.Float(H.cppm_radius(_float64(self._r[c]), passed, self.k, DRJIT_OPS))
            self._r[c] = dr.select(shrink, r_new, self._r[c])
            self._threshold[c] = dr.select(shrink, self._threshold[c] * self.beta, self._threshold[c])
            self._total[c] = dr.select(shrink, 0, total)
            dr.eval(self._r[c], self._threshold[c], self._total[c], shrink)
            self._stats[c].reset(shrink)

    def header(self) -> dict[str, Any]:
        return {"ppmrecon.method": self.name, "ppmrecon.cppm.significance": self.significance,
                "ppmrecon.cppm.k": self.k, "ppmrecon.cppm.beta": self.beta,
                "ppmrecon.cppm.threshold0": self.knn,
                "ppmrecon.cppm.cells": f"{H.N_ANNULI}x{H.N_SECTORS}"}


#: Default r_min of FPPM relative to each chain's (per-pixel) initial radius.
FPPM_R_MIN_FRAC = 0.25


@dataclass
class FPPMController(ChainState):
    """F-test PPM (paper 000 Sec. 3.2 and 5.1).

    Per pixel and chain: per-cell sums S_c and sums of squares Q_c of the photon
    contributions psi = luminance(f * Phi) (or each of R, G, B with ``per_channel``)
    since the radius last changed, the number of passes t since then, and the photons N
    filed in the cells. As in the paper, every light path of those passes is one sample
    of each cell (zero where its photon fell elsewhere or missed the disc), so the common
    sample count of Eq. 7 is m = t J, J = ``photons`` emitted per pass (Sec. 5.1; see
    :func:`.hypothesis.fppm_samples`). After every pass, F of Eq. 7 is compared with F_c,
    the (1 - significance) quantile of F(11, 12 (m - 1)) from a table built once; Eq. 21
    then keeps r if F <= F_c, else sets r = max(k r, r_min (i + 1)^((alpha - 1) / 2)) and
    resets the statistics.

    ``significance`` bounds the chance that a pixel of a uniform region shrinks after one
    test. With ``per_channel`` a pixel shrinks if any channel rejects, so each channel is
    tested at significance / 3 (Bonferroni, :func:`.hypothesis.fppm_test_significance`):
    the per-pixel rate is ~significance for independent channels and significance / 3
    for a white light (paper 000 tests each channel at alpha_F, up to 3 alpha_F per pixel).

    r_min is ``r_min_frac`` times the chain's initial radius at that pixel (the paper
    leaves it open; its VCM+ experiments use 0.1% of r_1). It only binds where the test
    keeps rejecting; then the radius follows SPPM's (i + 1)^((alpha - 1) / 2) decay,
    which keeps the method consistent (paper 000 Sec. 5.2). Measured over 256 passes
    (benchmarks/results/full/methods.md, five chains): with 0.25 the bound governs at
    most ~5% of the ~z^4 pixels and the results equal those of 0.05; with 1.0 (never
    below SPPM's schedule) the small bandwidths gain ~5% relMSE but ~z^4 loses 10-25%
    at light and caustic edges, where it can no longer shrink.
    """

    significance: float = 0.01
    k: float = 0.7
    alpha: float = 2.0 / 3.0
    r_min_frac: float = FPPM_R_MIN_FRAC
    per_channel: bool = False
    photons: int = 1 << 17
    name: str = "fppm"
    stats: str = "moments"
    _r: list[mi.Float] = field(default_factory=list)

    def __post_init__(self) -> None:
        _check_open_unit("significance", self.significance)
        _check_open_unit("k", self.k)
        _check_open_unit("alpha", self.alpha)
        if not 0.0 < self.r_min_frac <= 1.0:
            raise ValueError(f"r_min_frac must lie in (0, 1], got {self.r_min_frac}")
        if int(self.photons) != self.photons or self.photons <= 0:
            raise ValueError(f"photons must be a positive integer, got {self.photons}")
        self.channels = 3 if self.per_channel else 1
        self.test_significance = H.fppm_test_significance(self.significance, self.channels)
        self._f_table = mi.Float(H.f_critical_table(self.test_significance).astype("float32"))

    STATE = (("_r", "Float"), ("_r_min", "Float"), ("_passes", "UInt32"), ("_in_disc", "UInt32"))

    def _new_statistics(self, n_pixels: int) -> CellStatistics:
        return CellStatistics(n_pixels, "moments", self.channels)

    def start(self, r1: list[mi.Float]) -> None:
        n = dr.width(r1[0])
        self._r = [mi.Float(r) for r in r1]
        self._r_min = [mi.Float(r) * self.r_min_frac for r in r1]
        self._stats = [self._new_statistics(n) for _ in r1]
        self._passes = [dr.zeros(mi.UInt32, n) for _ in r1]  # t, passes since the reset
        self._in_disc = [dr.zeros(mi.UInt32, n) for _ in r1]  # N, photons filed since then
        dr.eval(self._r_min)

    def radii(self) -> list[mi.Float]:
        return self._r

    def stats_targets(self, chains: Sequence[int]) -> list[CellStatistics]:
        return [self._stats[c] for c in chains]

    def samples(self, chain: int) -> Any:
        """m of Eq. 7 per pixel (float64): t J, the light paths since the reset."""
        return H.fppm_samples(_float64(self._passes[chain]), self.photons,
                              _float64(self._in_disc[chain]), DRJIT_OPS)

    def critical_value(self, m: Any) -> mi.Float:
        """F_c for sample count m (UInt32 or float64), looked up in the table (inf for
        m < 2; the last entry beyond the table, where F_c has converged)."""
        return dr.gather(mi.Float, self._f_table, mi.UInt32(dr.minimum(m, H.F_TABLE_SIZE)))

    def reject(self, chain: int) -> mi.Bool:
        """Where chain ``chain``'s F-test rejects the null hypothesis (Eq. 7 > F_c)."""
        m = self.samples(chain)
        f_c = _float64(self.critical_value(m))
        reject = dr.zeros(mi.Bool, dr.width(m))
        for ch in range(self.channels):
            sums, sumsqs = self._stats[chain].cell_moments(ch)
            reject |= H.anova_f(sums, sumsqs, m, DRJIT_OPS) > f_c
        # No photon since the reset: F = 0 already; spelled out, it needs no statistics.
        return reject & (self._in_disc[chain] > 0)

    def update(self, pass_index: int, results: Any) -> None:
        floor_factor = dr.opaque(mi.Float, H.fppm_floor_factor(pass_index, self.alpha))
        # Gather points per chain this pass (one per pixel today; each brings J samples).
        seen: dict[int, list[Any]] = {}
        for c, count in _per_chain_counts(results):
            gathers, photons = seen.get(c, [0, 0])
            seen[c] = [gathers + 1, photons + count]
        for c, (gathers, photons) in seen.items():
            self._passes[c] = self._passes[c] + gathers
            self._in_disc[c] = self._in_disc[c] + photons
            reject = self.reject(c)
            self._r[c] = H.fppm_radius(self._r[c], reject, self.k, self._r_min[c] * floor_factor, DRJIT_OPS)
            self._passes[c] = dr.select(reject, 0, self._passes[c])
            self._in_disc[c] = dr.select(reject, 0, self._in_disc[c])
            dr.eval(self._r[c], self._passes[c], self._in_disc[c], reject)
            self._stats[c].reset(reject)

    def header(self) -> dict[str, Any]:
        return {"ppmrecon.method": self.name, "ppmrecon.fppm.significance": self.significance,
                "ppmrecon.fppm.test_significance": self.test_significance,
                "ppmrecon.fppm.k": self.k, "ppmrecon.fppm.alpha": self.alpha,
                "ppmrecon.fppm.r_min_frac": self.r_min_frac,
                "ppmrecon.fppm.per_channel": bool(self.per_channel),
                "ppmrecon.fppm.samples": f"t*{int(self.photons)}",
                "ppmrecon.fppm.cells": f"{H.N_ANNULI}x{H.N_SECTORS}"}


#: APPM defaults: bounds of r relative to each chain's initial radius r_1, and r'_max / r_1.
APPM_R_MIN_FRAC = 0.1
APPM_R_MAX_FRAC = 2.0
APPM_RP_MAX_FRAC = 2.0


@dataclass
class APPMController(ChainState):
    """Adaptive PPM (Kaplanyan and Dachsbacher 2013, paper 001 Sec. 6-7; formulas in
    :mod:`.appm`): after every pass each chain of each pixel gets the plug-in bandwidth
    of Eq. 6.4 from recursive estimates of E[psi^2] (or Var[psi] with ``variance=
    "paper"``), the light-path density p_l and the Laplacian Delta I (its square without
    the noise of its mean unless ``laplacian="paper"``; see :mod:`.appm`) (Eq. 6.5-6.6, with its own bandwidth r' from
    Silverman's rule, Eq. 6.7), all from the sums the one shared gather files per chain.

    Per pixel and chain the state is that of Sec. 7: E[psi] (``_psi``), p_l E[c^2]
    (``_psi2``; E[psi^2] = p_l times it), the recursive Laplacian estimate Delta I_N =
    E[Lap] (``_lap``; Eq. 6.5 is itself a running mean, so it and its first moment are one
    value) and E[Lap^2] (``_lap2``), the density p_l (``_density``), plus r, r' and the
    chain's initial radius r_1 that scales its bounds.

    The five chains keep their roles (paper 002 Sec. 4.1): chain c's bandwidth is
    ``scale_c`` times its own plug-in optimum, with scale_c = CHAIN_SCALES[c] /
    CHAIN_SCALES[1] (~z^1, the conventional single-bandwidth scale, sits at the optimum;
    ~y 1/sqrt(2) below it, ~z^2..~z^4 at sqrt(2), 2, 2 sqrt(2)), so the ladder of
    bandwidths that the reconstruction relies on survives; a single chain uses scale 1.
    Chain c starts at its k-NN radius r_1 (the paper starts at r_max; ours keeps the
    roles and the cost of the first pass) and r'_1 = r'_max.

    Bounds (Sec. 6.4), per chain: r_{N} in [r_min_frac, r_max_frac] r_1 N^(-1/6) and
    r'_N in [r_min_frac, 1] r'_max N^(-1/8), r'_max = rp_max_frac r_ref, r_ref = r_1 /
    scale_c the reference chain's initial radius (the same for all chains of a hit
    point). The paper bounds r by 1e-6 and 0.1 scene radii and starts r' at 0.1 scene
    radii; relative to r_1 the upper bound of r keeps the gather cost near that of the
    other methods on flat walls, where the Laplacian is ~0 and r sits at r_max. r' must be
    much larger than r: the Laplacian's noise grows as r'^-3 (measured on
    ``cornell_caustics``/``water_caustic`` at 32x32: with r'_max = 0.5 r_ref the
    Laplacian was indistinguishable from noise at caustic edges and on walls alike; with
    4 r_ref, the default, caustic edges stand out), at the price of a gather that
    searches 2 r' (8 r_ref at pass 1). Consistency by construction (Eq. 4.2, d = 2): for the value
    (lambda = 0), (1/N^2) sum r_i^-2 <= (r_min_frac r_1)^-2 N^(-2/3) -> 0 and
    (1/N) sum r_i^2 <= (r_max_frac r_1)^2 N^(-1/3) -> 0; for the Laplacian (lambda = 4,
    Sec. 6.3), (1/N^2) sum r'_i^-6 -> 0 as N^(-1/4) and (1/N) sum r'_i^2 -> 0 as
    N^(-1/4). Scaling a chain by a constant keeps both.
    """

    r_min_frac: float = APPM_R_MIN_FRAC
    r_max_frac: float = APPM_R_MAX_FRAC
    rp_max_frac: float = APPM_RP_MAX_FRAC
    variance: str = "full"
    laplacian: str = "debiased"
    laplacian_z: float = 2.0
    photons: int = 1 << 17
    kernel: str = "constant"
    name: str = "appm"
    stats: str = "appm"
    _r: list[mi.Float] = field(default_factory=list)

    STATE = (("_r", "Float"), ("_r1", "Float"), ("_rp", "Float"), ("_psi", "Float"),
             ("_psi2", "Float"), ("_density", "Float"), ("_lap", "Float"), ("_lap2", "Float"))

    def __post_init__(self) -> None:
        if not 0.0 < self.r_min_frac <= 1.0:
            raise ValueError(f"r_min_frac must lie in (0, 1], got {self.r_min_frac}")
        if not 1.0 <= self.r_max_frac < math.inf:
            raise ValueError(f"r_max_frac must be at least 1, got {self.r_max_frac}")
        if not 0.0 < self.rp_max_frac < math.inf:
            raise ValueError(f"rp_max_frac must be positive, got {self.rp_max_frac}")
        if self.variance not in A.VARIANCES:
            raise ValueError(f"variance must be one of {', '.join(A.VARIANCES)}, got '{self.variance}'")
        if not 0.0 <= self.laplacian_z < math.inf:
            raise ValueError(f"laplacian_z must be >= 0, got {self.laplacian_z}")
        if self.laplacian not in A.LAPLACIANS:
            raise ValueError(f"laplacian must be one of {', '.join(A.LAPLACIANS)}, got '{self.laplacian}'")
        if int(self.photons) != self.photons or self.photons <= 0:
            raise ValueError(f"photons must be a positive integer, got {self.photons}")
        self.k2, self.roughness = kernel_moments(self.kernel)

    def _scales(self, n_chains: int) -> list[float]:
        if n_chains == len(CHAIN_SCALES):
            return [s / CHAIN_SCALES[1] for s in CHAIN_SCALES]
        return [1.0] * n_chains

    def start(self, r1: list[mi.Float]) -> None:
        n = dr.width(r1[0])
        self._r = [mi.Float(r) for r in r1]
        self._r1 = [mi.Float(r) for r in r1]
        # r'_max from the reference chain's radius r_1 / scale_c: every chain at a hit point
        # shares the Laplacian's bounds (the Laplacian is the pixel's, not the chain's).
        scales = self._scales(len(r1))
        self._rp = [mi.Float(r) * (self.rp_max_frac / s) for r, s in zip(r1, scales)]
        for attr in ("_psi", "_psi2", "_density", "_lap", "_lap2"):
            setattr(self, attr, [dr.zeros(mi.Float, n) for _ in r1])
        dr.eval(self._rp)

    def radii(self) -> list[mi.Float]:
        return self._r

    def stats_targets(self, chains: Sequence[int]) -> list[APPMStatistics]:
        """This pass's sums for the chains of one hit point: the first (the group's lead)
        also estimates the Laplacian, with its r', for all of them."""
        if not hasattr(self, "_pass"):
            self._pass = {}
        for k, c in enumerate(chains):
            self._pass[c] = APPMStatistics(self._rp[chains[0]], laplacian=k == 0)
        return [self._pass[c] for c in chains]

    def update(self, pass_index: int, results: Any) -> None:
        # Per-pass literals enter as opaque values: one compiled kernel for every pass.
        n_done = dr.opaque(mi.Float64, float(pass_index))
        inv_i = dr.opaque(mi.Float64, 1.0 / pass_index)
        n_next = dr.opaque(mi.Float64, pass_index + 1.0)
        value_rate = dr.opaque(mi.Float64, (pass_index + 1.0) ** A.RATE_VALUE)
        lap_rate = dr.opaque(mi.Float64, (pass_index + 1.0) ** A.RATE_LAPLACIAN)
        inv_j = 1.0 / self.photons
        scales = self._scales(len(self._r))
        for chains, _ in results:
            lap = self._pass[chains[0]].sums()[3] * inv_j  # the group's shared Laplacian
            for c in chains:
                self._update_chain(c, chains[0], lap, inv_i, n_done, n_next, value_rate, lap_rate, scales[c])
        self._pass = {}

    def _update_chain(self, c: int, lead: int, lap: Any, inv_i: Any, n_done: Any, n_next: Any,
                      value_rate: Any, lap_rate: Any, scale: float) -> None:
        """Fold pass sums into chain c's running means, then its r' (the lead's, Eq. 6.7)
        and r (Eq. 6.4), both bounded (Sec. 6.4)."""
        inv_j = 1.0 / self.photons
        d, a, q, _ = (x * inv_j for x in self._pass[c].sums())
        # Running means over the passes (the recursive estimators of Eq. 4.1 / 6.5).
        means = {}
        for attr, x in (("_psi", a), ("_psi2", q), ("_density", d), ("_lap", lap), ("_lap2", lap * lap)):
            m = _float64(getattr(self, attr)[c])
            means[attr] = m + (x - m) * inv_i
        r1 = _float64(self._r1[c])
        if c == lead:
            unit = r1 * (1.0 / scale)  # the reference chain's initial radius
            rp_max = unit * self.rp_max_frac
            rp = A.silverman_radius(means["_lap"], means["_lap2"], unit, n_done, n_next, DRJIT_OPS)
            self._rp[c] = mi.Float(A.bounded(rp, rp_max * self.r_min_frac * lap_rate, rp_max * lap_rate, DRJIT_OPS))
        else:  # computed from the same moments: the lead's, exactly
            self._rp[c] = self._rp[lead]
        moment = A.psi_moment(means["_psi"], means["_psi2"], means["_density"], self.variance, DRJIT_OPS)
        lap2 = A.laplacian_square(means["_lap"], means["_lap2"], n_done, self.laplacian,
                                  self.laplacian_z, DRJIT_OPS)
        r = A.plugin_radius(moment, lap2, n_next, self.photons, self.k2, self.roughness, DRJIT_OPS)
        r = A.bounded(r * scale, r1 * self.r_min_frac * value_rate, r1 * self.r_max_frac * value_rate, DRJIT_OPS)
        for attr, m in means.items():
            getattr(self, attr)[c] = mi.Float(m)
        self._r[c] = mi.Float(r)
        dr.eval(self._r[c], self._rp[c], *(getattr(self, attr)[c] for attr in means))

    def header(self) -> dict[str, Any]:
        return {"ppmrecon.method": self.name, "ppmrecon.appm.r_min_frac": self.r_min_frac,
                "ppmrecon.appm.r_max_frac": self.r_max_frac, "ppmrecon.appm.rp_max_frac": self.rp_max_frac,
                "ppmrecon.appm.variance": self.variance, "ppmrecon.appm.laplacian": self.laplacian,
                "ppmrecon.appm.laplacian_z": self.laplacian_z,
                "ppmrecon.appm.laplacian_kernel": "perlin",
                "ppmrecon.appm.silverman": A.SILVERMAN_PERLIN}


def _check_open_unit(name: str, value: float) -> None:
    if not 0.0 < value < 1.0:
        raise ValueError(f"{name} must lie in (0, 1), got {value}")


def make_controller(method: str, defaults: dict[str, Any] | None = None, **params: Any) -> Controller:
    """The controller for ``method``. ``params`` are its options; ``defaults`` are
    render-wide settings (alpha, knn, photons, kernel) passed on to the controllers that take
    them."""
    try:
        cls = CONTROLLERS[method]
    except KeyError:
        raise ValueError(f"unknown method '{method}' (choose {', '.join(CONTROLLERS)})") from None
    accepted = inspect.signature(cls).parameters
    unknown = [k for k in params if k not in accepted or k.startswith("_") or k in ("name", "stats")]
    if unknown:
        raise ValueError(f"method '{method}' takes no option {', '.join(unknown)}")
    for key, value in (defaults or {}).items():
        if key in accepted:
            params.setdefault(key, value)
    return cls(**params)


CONTROLLERS: dict[str, type] = {"sppm": SPPMController, "cppm": CPPMController, "fppm": FPPMController,
                                 "appm": APPMController}
