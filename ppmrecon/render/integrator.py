"""Multi-bandwidth progressive photon mapping: the pass loop (SPEC section 3).

One pass i = 1, 2, ... reads top to bottom:

    photons  = trace_photons(scene, J)                      photon pass
    A, B     = trace_eye(seed_A), trace_eye(seed_B)         two decorrelated eye paths
    D_A, D_B = direct_light(A), direct_light(B)             optional: MIS direct light (.direct)
    r_1      = knn_radius(A) * (1/4, 1/(2 sqrt 2), ..., 1)  initial bandwidths (pass 1)
    grid     = build_grid(photons, cell from the radii)     one photon map for all chains
    S_y      = gather(A, [r_y]);  S_z = gather(B, [r_z1..r_z4])
    E_ik     = L_e + beta * (S_ik / J + D)                  per-pass estimate, chain k (S without
                                                            direct photons where D is used)
    mean_k, M2_k  <- Welford(E_ik)                          pixel value and its variance
    r_{i+1}  = controller.update(i, gather statistics)      bandwidth update

Layouts: ``multi`` (the method's input: ~y on hit point A, ~z^1..~z^4 on hit point B),
``single`` (the conventional baseline: one chain at the second-smallest bandwidth, one
eye path) and ``shared`` (all five chains on one hit point; a diagnostic for the
decorrelation study of paper 002 Fig. 11).
"""

from __future__ import annotations

import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import buffers as B
from .controllers import CHAIN_SCALES, Controller, make_controller
from .direct import check_mode as check_direct_mode
from .direct import direct_light, rays_can_hit_emitters, uses_direct
from .estimates import PlainMean, RunningMean
from .eye import GatherPoints, lambertian_table, trace_eye
from .gather import gather
from .grid import build_grid
from .kernels import KERNELS
from .photons import RR_DEPTH, trace_photons
from .rng import DIRECT_OFFSET, EYE_A, EYE_B, EYE_SINGLE, PHOTONS, stream_seed

LAYOUTS = ("multi", "single", "shared")
#: Timed stages of a pass; ``start`` is the first pass's k-NN initial radii alone (1-2 s at
#: 1280x720, which the per-pass grid figure used to carry).
STAGES = ("photons", "eye", "start", "grid", "gather", "update")
#: Pixels the grid's cell size is estimated from (:meth:`Renderer._cell_size`): a fixed
#: stride, the same pixels every pass, so a render stays deterministic; every pixel of an
#: image up to 256x256, whose cell size is then exactly the full quantile's.
CELL_SAMPLE = 65536


@dataclass
class RenderSettings:
    """What to render and how; defaults follow SPEC section 3."""

    method: str = "sppm"
    passes: int | None = 16
    time_budget: float | None = None
    photons: int = 1 << 17
    seed: int = 0
    kernel: str = "constant"
    #: Segments of the whole camera-to-light path, Mitsuba's convention; -1 = unbounded.
    max_depth: int = -1
    #: Bounces after which Russian roulette may end a path (Mitsuba's default 5).
    rr_depth: int = RR_DEPTH
    alpha: float = 2.0 / 3.0
    knn: int = 20
    #: k of the single-bandwidth baseline's k-NN initial radius (``layout="single"``):
    #: k = 10 is the r_20 / sqrt(2) radius that paper 002 calls "roughly k = 10".
    single_knn: int = 10
    #: Direct lighting by MIS at gather points: "none", "glossy" or "all" (see .direct);
    #: "all" won at equal time on 5 of 6 scenes (benchmarks/results/estimators.md).
    direct: str = "all"
    layout: str = "multi"
    method_params: dict[str, Any] = field(default_factory=dict)
    #: Initial radii are clamped to [min_frac, max_frac] x the scene's bounding radius.
    radius_min_frac: float = 1e-5
    radius_max_frac: float = 0.1

    def validate(self) -> None:
        if self.passes is None and self.time_budget is None:
            raise ValueError("give a pass count or a time budget")
        if self.passes is not None and self.passes <= 0:
            raise ValueError(f"passes must be positive, got {self.passes}")
        if self.time_budget is not None and not self.time_budget > 0:
            raise ValueError(f"time budget must be positive, got {self.time_budget}")
        if self.photons <= 0 or self.knn <= 0 or self.single_knn <= 0 or self.rr_depth <= 0:
            raise ValueError("photons, k and rr_depth must be positive")
        if self.max_depth == 0 or self.max_depth < -1:
            raise ValueError(f"max depth must be positive or -1 (unbounded), got {self.max_depth}")
        if self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel '{self.kernel}' (choose {', '.join(KERNELS)})")
        if self.layout not in LAYOUTS:
            raise ValueError(f"unknown layout '{self.layout}'")
        check_direct_mode(self.direct)


@dataclass
class RenderResult:
    """Accumulated images (H, W, ...) float32 and the bookkeeping of a render."""

    estimates: np.ndarray          # (C, H, W, 3) one per chain
    variances: np.ndarray          # (C, H, W)
    radii: np.ndarray              # (C, H, W)
    albedo: np.ndarray             # (H, W, 3)
    normal: np.ndarray             # (H, W, 3)
    depth: np.ndarray              # (H, W)
    passes: int
    seconds: float
    stage_seconds: dict[str, float]
    stopped: str
    header: dict[str, Any]
    nonfinite: int = 0

    def buffer_file(self) -> B.BufferFile:
        """The five-chain result as a buffer file (``multi`` or ``shared`` layout)."""
        if self.estimates.shape[0] != B.N_ESTIMATES:
            raise ValueError("only five-chain renders make a buffer file")
        return B.BufferFile(self.estimates, self.variances, self.radii, self.albedo,
                            self.normal, self.depth, dict(self.header))


def scene_radius(scene: mi.Scene) -> float:
    """Half the diagonal of the scene's bounding box."""
    bbox = scene.bbox()
    return 0.5 * float(dr.norm(mi.ScalarVector3f(bbox.max) - mi.ScalarVector3f(bbox.min)))


def knn_radius(points: GatherPoints, photon_p: mi.Point3f, k: int, r_lo: float, r_hi: float,
               wanted: np.ndarray | None = None) -> np.ndarray:
    """Distance from each gather point to its k-th nearest photon (paper 002 Sec. 4.1),
    clamped to [r_lo, r_hi]; NaN where the eye path found no surface, or where the boolean
    mask ``wanted`` (one per point) is False: only those are queried."""
    from scipy.spatial import cKDTree

    found = np.asarray(points.found)
    if wanted is not None:
        found = found & wanted
    out = np.full(found.shape, np.nan, np.float64)
    photons = np.asarray(photon_p).T if dr.width(photon_p) else np.zeros((0, 3))
    if photons.shape[0] == 0 or not found.any():
        return out
    query = np.asarray(points.si.p).T[found]
    kk = min(k, photons.shape[0])
    dist, _ = cKDTree(photons).query(query, k=[kk], workers=-1)
    out[found] = np.clip(dist[:, 0], r_lo, r_hi)
    return out


def _narrow(values: np.ndarray) -> np.ndarray:
    """Unsigned counts in the smallest unsigned type that holds them (lossless): CPPM's
    per-cell photon counts are mostly small, and they are most of a state file."""
    if values.dtype.kind != "u" or values.size == 0:
        return values
    top = int(values.max())
    for dtype in (np.uint8, np.uint16):
        if top <= np.iinfo(dtype).max:
            return values.astype(dtype)
    return values


class DeferredInterrupt:
    """Context manager: while active (main thread only, and only where Ctrl-C has its
    default handler), the first SIGINT sets ``requested`` (and calls ``notify(pass)``)
    instead of raising; the second raises KeyboardInterrupt as usual."""

    def __init__(self, notify: Callable[[int], None] | None = None,
                 current_pass: Callable[[], int] | None = None):
        self.notify, self.current_pass = notify, current_pass
        self.requested = False
        self._previous: Any = None

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        if self.notify is not None:
            self.notify(self.current_pass() if self.current_pass else 0)

    def __enter__(self) -> "DeferredInterrupt":
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is signal.default_int_handler):
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
            self._previous = None


class Renderer:
    """Runs passes of the chosen method on a loaded scene and accumulates estimates."""

    def __init__(self, scene: mi.Scene, settings: RenderSettings, scene_name: str = "scene"):
        settings.validate()
        self.scene = scene
        self.settings = settings
        self.scene_name = scene_name
        self.sensor = scene.sensors()[0]
        size = self.sensor.film().crop_size()
        self.width, self.height = int(size[0]), int(size[1])
        self.n_pixels = self.width * self.height
        # Render-wide alpha and k-NN k reach the controllers that take them (SPPM and
        # FPPM's alpha, CPPM's initial photon-count threshold).
        self.controller: Controller = make_controller(
            settings.method,
            defaults={"alpha": settings.alpha, "knn": settings.knn, "photons": settings.photons,
                      "kernel": settings.kernel},
            **settings.method_params)
        # The baseline starts at its own k-NN distance (single_knn), the five chains at
        # CHAIN_SCALES x the k-NN distance (knn).
        self.scales = (1.0,) if settings.layout == "single" else CHAIN_SCALES
        self.n_chains = len(self.scales)
        self.means = [RunningMean.zeros(self.n_pixels) for _ in range(self.n_chains)]
        self.albedo = PlainMean(dr.zeros(mi.Color3f, self.n_pixels))
        self.normal = PlainMean(dr.zeros(mi.Normal3f, self.n_pixels))
        self.depth = PlainMean(dr.zeros(mi.Float, self.n_pixels))
        self.passes_done = 0
        #: Non-finite terms dropped, by where they arose (photon paths, eye paths, photon
        #: contributions in the gather, whole per-pass estimates).
        self.nonfinite = {"photons": 0, "eye": 0, "direct": 0, "gather": 0, "estimate": 0}
        self.stage_seconds = {s: 0.0 for s in STAGES}
        self.seconds = 0.0
        self.radius_scene = scene_radius(scene)
        self.lambertian = lambertian_table(scene)
        #: with only delta emitters the direct light's BSDF sample is exactly 0: skipped
        self.bsdf_direct = rays_can_hit_emitters(scene)
        #: True while a pass has changed some accumulators but not all (see run_pass).
        self.dirty = False

    # -- one pass ----------------------------------------------------------------------
    def _eye_streams(self) -> tuple[int, ...]:
        return (EYE_A, EYE_B) if self.settings.layout == "multi" else (EYE_SINGLE,)

    def _eye_points(self, i: int) -> list[GatherPoints]:
        s = self.settings
        return [trace_eye(self.scene, self.sensor, stream_seed(s.seed, i, stream), s.max_depth, s.rr_depth,
                          self.lambertian, defer_counts=True)
                for stream in self._eye_streams()]

    def _direct(self, i: int, points: list[GatherPoints]) -> tuple[list[tuple[mi.Bool, mi.Color3f] | None], int | mi.UInt32]:
        """Per eye hit point: (where direct light is estimated apart, its estimate); and
        the non-finite samples dropped."""
        s = self.settings
        if s.direct == "none":
            return [None] * len(points), 0
        out, dropped = [], 0
        for stream, p in zip(self._eye_streams(), points):
            use = uses_direct(p, s.direct, s.max_depth)
            light, bad = direct_light(self.scene, p, use, stream_seed(s.seed, i, DIRECT_OFFSET + stream),
                                      defer_counts=True, bsdf_sampling=self.bsdf_direct)
            dropped += bad
            out.append((use, light))
        return out, dropped

    def _chains_of(self, point_index: int) -> list[int]:
        """Which chains gather at eye point ``point_index`` (A = 0, B = 1)."""
        if self.settings.layout == "multi":
            return [0] if point_index == 0 else [1, 2, 3, 4]
        return list(range(self.n_chains))

    def _initial_radii(self, points: list[GatherPoints], photon_p: mi.Point3f) -> list[mi.Float]:
        s = self.settings
        r_lo, r_hi = s.radius_min_frac * self.radius_scene, s.radius_max_frac * self.radius_scene
        k = s.single_knn if s.layout == "single" else s.knn
        r = knn_radius(points[0], photon_p, k, r_lo, r_hi)
        for other in points[1:]:  # where A found no surface, use B's
            missing = np.isnan(r)
            if missing.any():  # the few pixels A missed only (a query of all took as long as A's)
                r[missing] = knn_radius(other, photon_p, k, r_lo, r_hi, wanted=missing)[missing]
        missing = np.isnan(r)
        fallback = float(np.median(r[~missing])) if (~missing).any() else r_hi
        r[missing] = fallback
        return [mi.Float((r * scale).astype(np.float32)) for scale in self.scales]

    def run_pass(self) -> None:
        """Render pass ``passes_done + 1`` and fold it into the estimates.

        Until the gather starts nothing of the renderer changes, so an exception there
        leaves it as it was after the previous pass; from the gather on (the cell
        statistics are updated in place) ``dirty`` is set until the pass is complete."""
        s = self.settings
        i = self.passes_done + 1
        dropped = dict.fromkeys(self.nonfinite, 0)

        def clock() -> float:
            dr.sync_thread()  # kernels run asynchronously: wait so each stage is timed right
            return time.perf_counter()

        t0 = clock()
        # With direct light apart at every gather point no gather counts a direct photon
        # (d = 0): they are not stored, except on pass 1, whose k-NN radii count them.
        first_bounce = 1 if s.direct == "all" and i > 1 else 0
        photon_map = trace_photons(self.scene, s.photons, stream_seed(s.seed, i, PHOTONS), s.max_depth, s.rr_depth,
                                   first_bounce)
        dropped["photons"] += photon_map.nonfinite
        t1 = clock()
        points = self._eye_points(i)
        dropped["eye"] += sum(p.nonfinite for p in points)
        direct, dropped["direct"] = self._direct(i, points)
        t2 = clock()
        self.dirty = True
        if i == 1:
            self.controller.start(self._initial_radii(points, photon_map.p))
        t_start = clock()
        radii = self.controller.radii()
        cell = self._cell_size(radii)
        # Direct photons last in each bucket, skipped unvisited where direct light is apart.
        # Only with direct light everywhere: then every gather point that visits them
        # counts none of them (no room for a segment more), so each sum keeps its order
        # and the image stays bit-identical; with "glossy" the others would sum in a
        # different order (rounding-level changes).
        grid = build_grid(photon_map, cell, split_direct=s.direct == "all")
        t3 = clock()
        results = []
        inv_j = dr.opaque(mi.Float, 1.0 / s.photons)
        n_bad = dr.zeros(mi.UInt32, self.n_pixels)
        n_dropped = dr.zeros(mi.UInt32, self.n_pixels)
        # The search loop of each hit point is not evaluated on its own: the accumulators
        # of its chains consume its sums in the same kernel (no write and re-read of every
        # chain's flux and count). One kernel per hit point, not one for the pass: with
        # both search loops (each with its BSDF call) in one kernel, Dr.Jit 1.5's LLVM
        # backend intermittently emitted the BSDF callable twice ("invalid redefinition
        # of function") and aborted. The gather stage times these kernels.
        for j, p in enumerate(points):
            chains = self._chains_of(j)
            res = gather(p, [radii[c] for c in chains], grid, s.kernel,
                         self.controller.stats_targets(chains), max_depth=s.max_depth,
                         indirect_only=None if direct[j] is None else direct[j][0], evaluate=False)
            results.append((chains, res))
            n_dropped += res.nonfinite
            for slot, c in enumerate(chains):
                reflected = res.flux[slot] * inv_j
                if direct[j] is not None:
                    reflected += direct[j][1]
                estimate = p.emitted + dr.select(p.found, p.beta * reflected, 0.0)
                # Non-finite terms were dropped at their source; this is the last guard
                # (e.g. a finite sum that overflows), counted apart in the header.
                finite = dr.all(dr.isfinite(estimate))
                n_bad += dr.select(finite, mi.UInt32(0), mi.UInt32(1))
                self.means[c].add(dr.select(finite, estimate, 0.0), evaluate=False)
            dr.eval(n_bad, n_dropped, [(self.means[c].mean, self.means[c].m2) for c in chains], res.count, res.pending)
        for p in points:
            self.albedo.add(p.albedo, evaluate=False)
            self.normal.add(p.normal, evaluate=False)
            self.depth.add(p.depth, evaluate=False)
        dr.eval(self.albedo.mean, self.normal.mean, self.depth.mean)
        # The non-finite counts stay on the device until the end of the pass (a host read
        # per chain was a pipeline stall each).
        if self.n_pixels:
            dropped["estimate"] += dr.sum(n_bad)
            dropped["gather"] += dr.sum(n_dropped)
        t4 = clock()
        self.controller.update(i, results)
        t5 = clock()

        for name, dt in zip(STAGES, (t1 - t0, t2 - t1, t_start - t2, t3 - t_start, t4 - t3, t5 - t4)):
            self.stage_seconds[name] += dt
        # The non-finite counts stayed on the device (a host read per stage stalls the
        # pipeline): read once, now that the pass has synced anyway.
        for name, n in dropped.items():
            self.nonfinite[name] += n if isinstance(n, int) else int(n[0])
        self.seconds += t5 - t0
        self.passes_done = i
        self.dirty = False

    def start_at(self, first_pass: int) -> None:
        """Place a fresh renderer just before pass ``first_pass`` of the run it would render
        from pass 1, without rendering passes 1..first_pass-1, so that a range of passes of
        one run can be rendered apart (and the ranges' Welford states merged with
        :func:`.estimates.merge_welford`).

        Pass i's random streams derive from (seed, i) alone, and the radii under a
        schedule-only controller (SPPM) from the initial radii and i alone: the photons
        and eye paths of pass 1 are traced (not gathered) for the initial k-NN radii, the
        schedule is applied for passes 1..first_pass-1, and from here every pass estimate
        is bit for bit the one of the uninterrupted run. The accumulators stay empty: the
        estimates are means over passes first_pass.. only. Controllers that adapt the
        radii to what each pass gathered (CPPM, FPPM, APPM) cannot start mid-run."""
        if self.passes_done:
            raise RuntimeError("start_at needs a renderer that has rendered no pass")
        if first_pass < 1:
            raise ValueError(f"first pass must be >= 1, got {first_pass}")
        if first_pass == 1:
            return
        if not getattr(self.controller, "schedule_only", False):
            raise ValueError(f"method '{self.settings.method}' adapts its radii to what every pass gathered: "
                             "a range of its passes cannot be rendered without the passes before it")
        s = self.settings
        photon_map = trace_photons(self.scene, s.photons, stream_seed(s.seed, 1, PHOTONS), s.max_depth, s.rr_depth)
        self.controller.start(self._initial_radii(self._eye_points(1), photon_map.p))
        for i in range(1, first_pass):
            self.controller.update(i, None)
        self.passes_done = first_pass - 1

    def _cell_size(self, radii: list[mi.Float]) -> float:
        """Grid cell edge: a high quantile of the largest radius in use. Most gather
        points then visit at most 3x3x3 cells (2x2x2 for the smaller chains) while the
        few with larger radii visit more; measured faster than 2x that edge, which makes
        every small-radius point scan photons far outside its disc."""
        r = radii[-1]
        usable = dr.isfinite(r) & (r > 0)
        r_top = float(dr.max(dr.select(usable, r, 0.0))[0]) if dr.width(r) else 0.0
        if r_top <= 0:
            return max(self.radius_scene * 1e-3, 1e-6)
        # The quantile from a fixed stride of pixels: copying every radius to the host and
        # partitioning it took 15-30 ms a pass at 1280x720 (a third of a cuda_ad_rgb pass)
        n = dr.width(r)
        sample = np.asarray(dr.gather(mi.Float, r, dr.arange(mi.UInt32, 0, n, -(-n // CELL_SAMPLE))))
        sample = sample[np.isfinite(sample) & (sample > 0)]
        q = np.quantile(sample, 0.9) if sample.size else 0.0
        return float(max(q, r_top / 16.0, 1e-7))

    # -- the loop ----------------------------------------------------------------------
    def run(self, on_pass: Callable[["Renderer"], None] | None = None,
            on_interrupt: Callable[[int], None] | None = None) -> RenderResult:
        """Render until the pass count (``settings.passes``, counted from pass 1 also when
        the renderer continues a saved state) or the time budget (from this call on) is
        reached.

        Ctrl-C (in the main thread) lets the pass in progress finish, then stops after it
        and ``on_pass``; ``on_interrupt(pass)`` is told at once. A second Ctrl-C, or a
        KeyboardInterrupt raised elsewhere, stops at once: the partial pass is discarded
        if it had not started changing the accumulators, else (``dirty``) the renderer no
        longer holds a consistent state and KeyboardInterrupt propagates, as it does
        before the first pass is complete."""
        s = self.settings
        stopped = "complete"
        start = time.perf_counter()
        with DeferredInterrupt(on_interrupt, lambda: self.passes_done + 1) as ctrl_c:
            try:
                while True:
                    if ctrl_c.requested:
                        stopped = "interrupted"
                        break
                    if s.passes is not None and self.passes_done >= s.passes:
                        break
                    if s.time_budget is not None and self.passes_done > 0:
                        elapsed = time.perf_counter() - start
                        per_pass = self.seconds / self.passes_done
                        if elapsed + per_pass > s.time_budget:
                            stopped = "time budget" if s.passes is None else "time budget before pass count"
                            break
                    self.run_pass()
                    if on_pass is not None:
                        on_pass(self)
            except KeyboardInterrupt:
                stopped = "interrupted"
                if self.passes_done == 0 or self.dirty:
                    raise
        return self.result(stopped)

    # -- state ---------------------------------------------------------------------------
    def export_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """(counters, arrays): everything a later :meth:`import_state` needs to continue
        this render bit for bit; arrays are numpy copies of the accumulators, named
        ``mean.k``, ``m2.k`` (Welford, chain k), ``albedo``/``normal``/``depth`` (G-buffer
        means) and ``ctrl.*`` (the controller's radii and statistics)."""
        if self.dirty:
            raise RuntimeError("the renderer is in the middle of a pass")
        arrays: dict[str, np.ndarray] = {}
        for k, m in enumerate(self.means):
            arrays[f"mean.{k}"], arrays[f"m2.{k}"] = np.array(m.mean), np.array(m.m2)
        for name in ("albedo", "normal", "depth"):
            arrays[name] = np.array(getattr(self, name).mean)
        for key, value in self.controller.state().items():
            arrays[f"ctrl.{key}"] = _narrow(np.array(value))
        counters = {
            "passes": self.passes_done, "seconds": self.seconds, "stage_seconds": dict(self.stage_seconds),
            "nonfinite": dict(self.nonfinite), "mean_counts": [m.n for m in self.means],
            "gbuffer_counts": [getattr(self, n).n for n in ("albedo", "normal", "depth")],
        }
        return counters, arrays

    def import_state(self, counters: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        """Continue from :meth:`export_state`'s output (of a renderer with the same scene,
        film size and settings). Raises ValueError naming what does not fit."""
        n = self.n_pixels
        expect = {"albedo": (3, n), "normal": (3, n), "depth": (n,)}
        for k in range(self.n_chains):
            expect[f"mean.{k}"] = expect[f"m2.{k}"] = (3, n)
        for key, shape in expect.items():
            if key not in arrays:
                raise ValueError(f"lacks the array '{key}'")
            if tuple(arrays[key].shape) != shape:
                raise ValueError(f"array '{key}' has shape {tuple(arrays[key].shape)}, expected {shape}")
        if len(counters["mean_counts"]) != self.n_chains:
            raise ValueError(f"holds {len(counters['mean_counts'])} chains, the render has {self.n_chains}")
        if int(counters["passes"]) <= 0:
            raise ValueError("holds no completed pass")
        self.means = [RunningMean(mi.Color3f(arrays[f"mean.{k}"]), mi.Color3f(arrays[f"m2.{k}"]), int(c))
                      for k, c in enumerate(counters["mean_counts"])]
        kinds = (mi.Color3f, mi.Normal3f, mi.Float)
        for name, kind, c in zip(("albedo", "normal", "depth"), kinds, counters["gbuffer_counts"]):
            setattr(self, name, PlainMean(kind(arrays[name]), int(c)))
        self.controller.load_state({k[len("ctrl."):]: (v.astype(np.uint32) if v.dtype.kind == "u" else v)
                                    for k, v in arrays.items() if k.startswith("ctrl.")})
        if len(self.controller.radii()) != self.n_chains or dr.width(self.controller.radii()[0]) != n:
            raise ValueError("the controller state does not match the film size or chain count")
        self.passes_done = int(counters["passes"])
        self.seconds = float(counters["seconds"])
        self.stage_seconds.update({k: float(v) for k, v in counters["stage_seconds"].items() if k in self.stage_seconds})
        self.nonfinite.update({k: int(v) for k, v in counters["nonfinite"].items() if k in self.nonfinite})

    def result(self, stopped: str = "complete") -> RenderResult:
        """The estimates after the passes completed so far."""
        h, w = self.height, self.width
        means, variances = zip(*(m.numpy(h, w) for m in self.means))
        radii = np.stack([np.asarray(r, np.float32).reshape(h, w) for r in self.controller.radii()])
        albedo = np.asarray(self.albedo.mean).reshape(3, h, w).transpose(1, 2, 0)
        normal = np.asarray(self.normal.mean).reshape(3, h, w).transpose(1, 2, 0)
        depth = np.asarray(self.depth.mean).reshape(h, w)
        s = self.settings
        header = {
            B.H_VERSION: B.SCHEMA_VERSION, B.H_KERNEL: s.kernel, B.H_PASSES: self.passes_done,
            B.H_PHOTONS: s.photons, B.H_ALPHA: s.alpha, B.H_KNN: s.knn, B.H_SEED: s.seed,
            B.H_SCENE: self.scene_name, B.H_SECONDS: self.seconds, B.H_STOPPED: stopped,
            "ppmrecon.layout": s.layout, "ppmrecon.max_depth": s.max_depth, "ppmrecon.rr_depth": s.rr_depth,
            "ppmrecon.nonfinite_samples": self.nonfinite_total,
        }
        for k, v in self.nonfinite.items():
            header[f"ppmrecon.nonfinite.{k}"] = v
        if s.layout == "single":
            header["ppmrecon.single_knn"] = s.single_knn
        header["ppmrecon.direct"] = s.direct
        header.update(self.controller.header())
        for k, v in self.stage_seconds.items():
            header[f"ppmrecon.seconds.{k}"] = v
        return RenderResult(
            estimates=np.stack(means).astype(np.float32), variances=np.stack(variances).astype(np.float32),
            radii=radii.astype(np.float32), albedo=np.ascontiguousarray(albedo, np.float32),
            normal=np.ascontiguousarray(normal, np.float32), depth=np.ascontiguousarray(depth, np.float32),
            passes=self.passes_done, seconds=self.seconds, stage_seconds=dict(self.stage_seconds),
            stopped=stopped, header=header, nonfinite=self.nonfinite_total)

    @property
    def nonfinite_total(self) -> int:
        """Non-finite terms dropped so far, all sources."""
        return sum(self.nonfinite.values())
