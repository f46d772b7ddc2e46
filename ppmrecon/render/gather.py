"""Gather: one neighbour search per gather point serves all of its bandwidth chains
(SPEC section 3, step 3; paper 002 Sec. 4.1, Fig. 3).

For gather point x with throughput-free BSDF f and chain radii r_1..r_C, the photons
within the largest radius R = max_s r_s are visited once and

    S_s = sum_p K_{r_s}(|x_p - x|) * f(x, w_o, w_p) * Phi_p * |w_p . n_s| / |w_p . n_g|

is accumulated for every chain s with |x_p - x| < r_s; the last factor is the
shading-normal correction of adjoint transport (Veach 1997, Sec. 5.3), which turns
Mitsuba's cosine-weighted ``bsdf.eval`` into f / |w_p . n_g|. Photons whose oriented
normal faces away from the gather point's are rejected (the back side of a thin wall
must neither light nor shrink the estimate), unless the BSDF transmits. With a finite
``max_depth`` (Mitsuba's convention: segments of the whole path), a photon of bounce
index d counts only if e + d + 1 <= max_depth, e the eye path's segments. A non-finite
contribution (a degenerate BSDF evaluation) is dropped alone and counted. The pass
estimate is then ``L_e + beta * S_s / J`` (see :mod:`ppmrecon.render.integrator`).

With ``stats`` (CPPM, FPPM), the same visit also files every photon inside a chain's
radius into that chain's per-pixel cell statistics (2 equal-area annuli x 6 sectors of
a tangent frame that depends on the shading normal alone, ``mi.coordinate_system(n)``,
so that successive gather points of a pixel on the same or a gently curved surface pool
their photons into the same sectors whatever the mesh's UV parameterisation; see
:mod:`ppmrecon.render.hypothesis`): a
count per cell, or the sum and sum of squares of its contribution f * Phi (without the
kernel weight: a sample of the integral of Psi* over the cell, paper 000 Eq. 5-6). The
photon's sector is computed once and shared by the chains; its annulus depends on each
chain's radius. Without ``stats`` none of this enters the kernel (SPPM's fast path).

APPM's targets (:class:`.controllers.APPMStatistics`) take each photon instead with its
tangent-plane offset, kernel weight and luminance contribution c = luminance(beta f Phi)
(in pixel units, beta = the eye path's throughput): the sums of K, K c and K c^2 inside
the chain's radius and of c w_lap within 2 r' (paper 001 Eq. 5.4, 6.5; see
:mod:`ppmrecon.render.appm`; only the first chain of a hit point estimates the
Laplacian, the others share it). Its ``reach`` 2 r' widens the search where it exceeds
the chain's radius.

Cost (issue 17): a photon is one packet load of its record (:mod:`.grid`); at
Lambertian gather points (Mitsuba's ``diffuse``, f cos = rho / pi max(0, cos_o)) the BSDF
is evaluated once, towards the normal, and scaled by each photon's cos_o, which is what
``bsdf.eval`` computes, bit for bit; gather points with direct light apart skip the
bucket's direct photons without visiting them (the grid keeps them last). Where every
non-delta BSDF of the scene is Lambertian, the loop holds no BSDF call at all.

The search is one Dr.Jit symbolic loop whose every step visits up to two photons of one
cell and/or moves to the next cell of the search box (cells the search sphere misses are empty steps): one
kernel over all gather points, compiled on the first pass and reused afterwards (every
per-pass number enters as an opaque array). Each gather point visits its photons in
the order of the sorted grid, cell by cell, so every sum is bit for bit that of a
nested cell-then-photon loop.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import drjit as dr
import mitsuba as mi

from .controllers import DRJIT_OPS
from .eye import GatherPoints
from .grid import PhotonGrid, cell_hash, cell_of
from .hypothesis import cell_index, sector_index
from .kernels import kernel_weight
from .photons import REC_D, REC_DEPTH, REC_N, REC_P, REC_POWER, RECORD

if TYPE_CHECKING:
    from .controllers import CellStatistics

#: A photon counts only if its oriented normal and the gather point's agree this much.
FACING_COS = 1e-3
#: Slack, in cell edges, of the test that skips the cells the search sphere misses.
CELL_MARGIN = 1e-3


@dataclass
class GatherResult:
    """Per chain slot s: kernel-weighted sum S_s (RGB) and the photon count M_s; and
    how many non-finite photon contributions were dropped."""

    flux: list[mi.Color3f]
    count: list[mi.UInt32]
    nonfinite: int | mi.UInt32 = 0
    #: With ``evaluate=False``: the statistics arrays the loop scatters into, for the
    #: caller's ``dr.eval`` (``nonfinite`` is then the per-lane count, unevaluated).
    pending: list = field(default_factory=list)


def gather(gp: GatherPoints, radii: list[mi.Float], grid: PhotonGrid, kernel: str = "constant",
           stats: list["CellStatistics"] | None = None, max_depth: int = -1,
           indirect_only: mi.Bool | None = None, evaluate: bool = True) -> GatherResult:
    """Sum photon contributions within each radius of ``radii`` (one array per chain slot,
    0 for unused slots) around every gather point of ``gp``; with ``stats`` (one per
    slot) also accumulate the per-cell statistics of the photons inside each radius.
    ``max_depth``: segments of the whole path (-1: unbounded). ``indirect_only``: gather
    points whose direct light is estimated apart (:mod:`.direct`); they skip the photons
    that arrive straight from an emitter (bounce index 0). ``evaluate=False``:
    nothing is evaluated here, so that the caller's ``dr.eval`` runs the search loop in the
    kernel that also consumes its sums (see the result's ``pending``)."""
    if stats is not None and len(stats) != len(radii):
        raise ValueError("gather: one statistics target per chain slot")
    n_slots = len(radii)
    si = gp.si
    r_search = radii[0]
    for r in radii[1:]:
        r_search = dr.maximum(r_search, r)
    appm = [st is not None and getattr(st, "kind", None) == "appm" for st in (stats or [])]
    for st, is_appm in zip(stats or [], appm):
        if is_appm and st.reach is not None:  # the Laplacian's stencil reaches 2 r' (paper 001 Eq. 6.5)
            r_search = dr.maximum(r_search, st.reach)
    r_search = dr.select(gp.found, r_search, 0.0)
    r2 = [r * r for r in radii]
    r_search2 = r_search * r_search

    inv_cell = dr.opaque(mi.Float, 1.0 / grid.cell_size)
    cell_size = dr.opaque(mi.Float, grid.cell_size)
    lo = cell_of(si.p - r_search, inv_cell)
    hi = cell_of(si.p + r_search, inv_cell)
    extent = dr.select(gp.found, hi - lo + 1, 0)
    n_cells = mi.UInt32(extent.x) * mi.UInt32(extent.y) * mi.UInt32(extent.z)

    bsdf = si.bsdf()
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)
    check_facing = ~mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
    # Lambertian gather points: f cos = (rho / pi) max(0, cos_o) (Mitsuba's `diffuse`),
    # so one BSDF evaluation per gather point, towards the normal on the eye's side,
    # serves every photon; the others evaluate per photon (a virtual call in the loop).
    lambert = gp.found & (mi.Bool(False) if gp.lambertian is None else gp.lambertian)
    side = dr.select(mi.Frame3f.cos_theta(si.wi) < 0.0, -1.0, 1.0)
    f_normal = bsdf.eval(ctx, si, mi.Vector3f(0.0, 0.0, side), lambert)
    n_gp = gp.n_oriented
    mask = grid.table_mask
    lane = dr.arange(mi.UInt32, dr.width(gp.found))
    # Largest photon bounce index that keeps the path within max_depth segments.
    bounded = max_depth >= 0
    if bounded:
        last_bounce = dr.opaque(mi.Int32, max_depth - 1) - mi.Int32(gp.segments)
    if indirect_only is not None:
        first_bounce = dr.select(indirect_only, mi.Int32(1), mi.Int32(0))
    end_offset = mi.UInt32(2) if indirect_only is None or not grid.split_direct else \
        dr.select(indirect_only, mi.UInt32(1), mi.UInt32(2))
    if stats is not None:
        frame_s, frame_t = mi.coordinate_system(si.sh_frame.n)

    def visit(k, cell, flux, count, dropped, active):
        """Photon k (where ``active``) into every chain's sums."""
        rec = dr.gather(mi.ArrayXf, grid.record, k, active, shape=(RECORD, dr.width(k)))
        xp = mi.Point3f(rec[REC_P], rec[REC_P + 1], rec[REC_P + 2])
        # Buckets can hold other cells (hash collisions): count a photon only from its own cell.
        same_cell = dr.all(cell_of(xp, inv_cell) == cell)
        d2 = dr.squared_norm(xp - si.p)
        ok = active & same_cell & (d2 < r_search2)
        n_p = mi.Normal3f(rec[REC_N], rec[REC_N + 1], rec[REC_N + 2])
        ok &= ~check_facing | (dr.dot(n_p, n_gp) > FACING_COS)
        w_p = -mi.Vector3f(rec[REC_D], rec[REC_D + 1], rec[REC_D + 2])
        cos_g = dr.abs(dr.dot(w_p, si.n))
        ok &= cos_g > 1e-4
        if bounded or indirect_only is not None:
            bounce = mi.Int32(rec[REC_DEPTH])
            if bounded:
                ok &= bounce <= last_bounce
            if indirect_only is not None:
                ok &= bounce >= first_bounce
        wo = si.to_local(w_p)
        cos_o = wo.z * side
        f_cos = dr.select(cos_o > 0.0, f_normal * cos_o, 0.0)
        if not gp.only_lambertian:  # the virtual call costs ~15% even where no lane makes it
            f_cos = dr.select(lambert, f_cos, bsdf.eval(ctx, si, wo, ok & ~lambert))
        contrib = f_cos / cos_g * mi.Color3f(rec[REC_POWER], rec[REC_POWER + 1], rec[REC_POWER + 2])
        finite = dr.all(dr.isfinite(contrib))
        dropped = dr.select(ok & ~finite, dropped + 1, dropped)
        ok &= finite
        flux = list(flux)
        count = list(count)
        if stats is not None:
            # Tangent-plane offset (paper 000 Eq. 2); the sector is the same for every
            # chain, only the annulus depends on r_s.
            offset = xp - si.p
            off_s, off_t = dr.dot(offset, frame_s), dr.dot(offset, frame_t)
            if not all(appm):
                sector = sector_index(off_s, off_t, DRJIT_OPS)
            if any(appm):
                lum = mi.luminance(gp.beta * contrib)
        for s in range(n_slots):
            inside = ok & (d2 < r2[s])
            weight = kernel_weight(kernel, d2, r2[s], sqrt=dr.sqrt)
            flux[s] = dr.select(inside, flux[s] + weight * contrib, flux[s])
            count[s] = dr.select(inside, count[s] + 1, count[s])
            if stats is not None and appm[s]:
                stats[s].add_photon(lane, off_s, off_t, weight, lum, inside, ok)
            elif stats is not None:
                cell_s = mi.UInt32(cell_index(sector, d2, r2[s], DRJIT_OPS))
                stats[s].add(lane, cell_s, contrib, inside)
        return tuple(flux), tuple(count), dropped

    def cell_range(cell, active):
        """Photons [k, end) of ``cell``'s bucket that a gather point may visit; empty where
        the search sphere misses the cell (a corner cell of the bounding box, or a layer
        off a wall: none of its photons can lie within r_search; the margin keeps any cell
        a photon's rounded floor() may have put it in)."""
        corner = mi.Vector3f(cell) * cell_size
        gap = dr.maximum(dr.maximum(corner - si.p, si.p - (corner + cell_size)), 0.0)
        gap = dr.maximum(gap - cell_size * CELL_MARGIN, 0.0)
        active = active & (dr.squared_norm(gap) < r_search2)
        bucket = cell_hash(cell, mask) * 2
        k = dr.gather(mi.UInt32, grid.start, bucket, active)
        # Gather points with direct light apart stop before the bucket's direct photons.
        end = dr.gather(mi.UInt32, grid.start, bucket + end_offset, active)
        return k, end

    def body(c, cell, k, end, flux, count, dropped):
        # One loop over steps of photons and/or one cell rather than a photon loop
        # nested in a cell loop: a SIMD packet then runs as long as its busiest lane's
        # total, not the sum over cells of each cell's busiest lane. A lane's photon
        # order is unchanged.
        # Two photons per step (the second where the cell has one more): the cell step
        # and the loop's own work are shared by both (9% faster; 3 or 4 were slower).
        for _ in range(2):
            has = k < end
            flux, count, dropped = visit(k, cell, flux, count, dropped, has)
            k = dr.select(has, k + 1, k)
        # Next cell as soon as this one is done, in the same step as its last photon.
        # Stepped x fastest, then y, then z, not by c % ex, c // ex ... (integer division
        # has no vector instruction: it cost more than the photons on the CPU).
        step = k >= end
        x = cell.x + 1
        wrap_x = x > hi.x
        y = dr.select(wrap_x, cell.y + 1, cell.y)
        wrap_y = y > hi.y
        cell = dr.select(step, mi.Vector3i(dr.select(wrap_x, lo.x, x), dr.select(wrap_y, lo.y, y),
                                           dr.select(wrap_y, cell.z + 1, cell.z)), cell)
        c = dr.select(step, c + 1, c)
        step &= c < n_cells
        k_next, end_next = cell_range(cell, step)
        k, end = dr.select(step, k_next, k), dr.select(step, end_next, end)
        return c, cell, k, end, flux, count, dropped

    width = dr.width(gp.found)
    flux0 = tuple(dr.zeros(mi.Color3f, width) for _ in range(n_slots))
    count0 = tuple(dr.zeros(mi.UInt32, width) for _ in range(n_slots))
    k0, end0 = cell_range(lo, n_cells > 0)
    _, _, _, _, flux, count, dropped = dr.while_loop(
        state=(mi.UInt32(0), mi.Vector3i(lo), k0, end0, flux0, count0, dr.zeros(mi.UInt32, width)),
        cond=lambda c, cell, k, end, flux, count, dropped: c < n_cells,
        body=body,
        labels=("c", "cell", "k", "end", "flux", "count", "dropped"),
        label="ppmrecon_gather")
    flux, count = list(flux), list(count)
    if not evaluate:
        return GatherResult(flux=flux, count=count, nonfinite=dropped,
                            pending=[st.data for st in stats] if stats is not None else [])
    dr.eval(flux, count, dropped)
    if stats is not None:  # the scatters ran in the loop kernel; make them visible
        dr.eval(*(st.data for st in stats))
    nonfinite = int(dr.sum(dropped)[0]) if dr.width(dropped) else 0
    return GatherResult(flux=flux, count=count, nonfinite=nonfinite)
