"""Spatial hash grid over one pass's photons (SPEC section 3, step 3).

Photons are bucketed by the hash of their integer cell ``floor(x / cell_size)`` into a
table of T = 2^k >= 2 J slots and sorted by bucket (a stable numpy argsort, so the
order, and hence every floating-point sum of the gather, depends on the seed only).
``start[h] .. end[h]`` then index the sorted photons of bucket h. Different cells can
share a bucket; the gather compares each photon's own cell with the visited one so a
photon is never counted twice.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .photons import PhotonMap

# Large primes of the classic spatial hash (Teschner et al. 2003).
_P1, _P2, _P3 = 73856093, 19349663, 83492791


def cell_of(p: mi.Point3f, inv_cell: mi.Float) -> mi.Vector3i:
    """Integer cell coordinates of positions ``p``."""
    return mi.Vector3i(dr.floor(p * inv_cell))


def cell_hash(c: mi.Vector3i, mask: int) -> mi.UInt32:
    """Bucket of integer cell ``c`` in a table of ``mask + 1`` (a power of two) slots."""
    ux, uy, uz = (dr.reinterpret_array(mi.UInt32, c.x), dr.reinterpret_array(mi.UInt32, c.y),
                  dr.reinterpret_array(mi.UInt32, c.z))
    # opaque: the table grows with the photon count, and a literal mask would recompile the gather
    return ((ux * _P1) ^ (uy * _P2) ^ (uz * _P3)) & dr.opaque(mi.UInt32, mask)


@dataclass
class PhotonGrid:
    """Photons sorted by bucket, with per-bucket ranges ``start[h] .. end[h]``."""

    p: mi.Point3f
    d: mi.Vector3f
    n: mi.Normal3f
    power: mi.Color3f
    depth: mi.UInt32
    start: mi.UInt32
    end: mi.UInt32
    cell_size: float
    table_mask: int


def build_grid(pm: PhotonMap, cell_size: float) -> PhotonGrid:
    """Bucket the photons of ``pm`` into cells of edge ``cell_size``."""
    n = len(pm)
    table = 1 << max(4, int(np.ceil(np.log2(max(2 * n, 1)))))
    mask = table - 1
    inv_cell = dr.opaque(mi.Float, 1.0 / cell_size)
    cell = cell_of(pm.p, inv_cell)
    bucket = cell_hash(cell, mask)
    bucket_np = np.asarray(bucket, dtype=np.int64) if n else np.zeros(0, np.int64)
    order_np = np.argsort(bucket_np, kind="stable").astype(np.uint32)
    counts = np.bincount(bucket_np, minlength=table)
    end_np = np.cumsum(counts).astype(np.uint32)
    start_np = (end_np - counts).astype(np.uint32)
    order = mi.UInt32(order_np)
    grid = PhotonGrid(
        p=dr.gather(mi.Point3f, pm.p, order), d=dr.gather(mi.Vector3f, pm.d, order),
        n=dr.gather(mi.Normal3f, pm.n, order), power=dr.gather(mi.Color3f, pm.power, order),
        depth=dr.gather(mi.UInt32, pm.depth, order), start=mi.UInt32(start_np), end=mi.UInt32(end_np),
        cell_size=float(cell_size), table_mask=mask)
    dr.eval(grid.p, grid.d, grid.n, grid.power, grid.depth, grid.start, grid.end)
    return grid
