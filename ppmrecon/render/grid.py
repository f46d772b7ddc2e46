"""Spatial hash grid over one pass's photons (SPEC section 3, step 3).

Photons are bucketed by the hash of their integer cell ``floor(x / cell_size)`` into a
table of T = 2^k >= 2 J slots and sorted by bucket (a stable sort, so the order, and
hence every floating-point sum of the gather, depends on the seed only), all on the
device. With
``split_direct`` each bucket's photons are further split, stably, into those that
bounced before arriving (bounce index d >= 1) and the direct ones (d = 0): gather points
whose direct light is estimated apart (:mod:`.direct`) skip the direct photons without
visiting them. Sorted photon i of bucket h lies in ``start[2h] <= i < start[2h + 2]``,
the indirect ones below ``start[2h + 1]``. Different cells can share a bucket; the
gather compares each photon's own cell with the visited one so a photon is never
counted twice.

Each photon is one record of ``RECORD`` floats (:mod:`.photons`), so the gather reads a
photon with one packet load per lane rather than thirteen scattered gathers.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .photons import RECORD, PhotonMap

# Large primes of the classic spatial hash (Teschner et al. 2003).
_P1, _P2, _P3 = 73856093, 19349663, 83492791
#: Cells are hashed in blocks of 2^BLOCK_BITS cells per axis: a block's cells take
#: consecutive buckets (x fastest), so the cells of one search box share cache lines of
#: the bucket table and their photons lie close in the sorted records (issue 17: the
#: gather ~15% faster than with every cell hashed apart, measured on cornell_caustics).
BLOCK_BITS = 2


def cell_of(p: mi.Point3f, inv_cell: mi.Float) -> mi.Vector3i:
    """Integer cell coordinates of positions ``p``."""
    return mi.Vector3i(dr.floor(p * inv_cell))


def _mix32(x: mi.UInt32) -> mi.UInt32:
    """A 32-bit integer finaliser (xor-shift-multiply; the constants of C. Wellons'
    "lowbias32"): every input bit reaches the low output bits the table mask keeps."""
    x ^= x >> 16
    x *= 0x7FEB352D
    x ^= x >> 15
    x *= 0x846CA68B
    return x ^ (x >> 16)


def cell_hash(c: mi.Vector3i, mask: int) -> mi.UInt32:
    """Bucket of integer cell ``c`` in a table of ``mask + 1`` (a power of two) slots:
    the hash of the cell's block, followed by the cell's index inside its block.

    The Teschner hash alone, ``(x P1) ^ (y P2) ^ (z P3) & mask``, keeps only the low bits
    of the coordinates' products: on cornell_caustics 16% of the occupied cells shared a
    bucket with another (whatever the table size), against 7% with the block hash mixed."""
    ux, uy, uz = (dr.reinterpret_array(mi.UInt32, c.x), dr.reinterpret_array(mi.UInt32, c.y),
                  dr.reinterpret_array(mi.UInt32, c.z))
    b, low = BLOCK_BITS, (1 << BLOCK_BITS) - 1
    local = (ux & low) | ((uy & low) << b) | ((uz & low) << (2 * b))
    block = _mix32(((ux >> b) * _P1) ^ _mix32((uy >> b) * _P2 + _mix32((uz >> b) * _P3)))
    # opaque: the table grows with the photon count, and a literal mask would recompile the gather
    return ((block << (3 * b)) | local) & dr.opaque(mi.UInt32, mask)


@dataclass
class PhotonGrid:
    """Photon records sorted by (bucket, direct), with the ranges ``start`` (2 T + 1
    offsets; see the module docstring)."""

    record: mi.Float
    start: mi.UInt32
    cell_size: float
    table_mask: int
    split_direct: bool = False
    count: int = 0

    def __len__(self) -> int:
        return dr.width(self.record) // RECORD


def build_grid(pm: PhotonMap, cell_size: float, split_direct: bool = False) -> PhotonGrid:
    """Bucket the photons of ``pm`` into cells of edge ``cell_size`` (with
    ``split_direct``, direct photons after the others in every bucket)."""
    n = len(pm)
    table = 1 << max(4, int(np.ceil(np.log2(max(2 * n, 1)))))
    mask = table - 1
    # On the device, no host round trip: a stable radix sort (dr.argsort) and a counting
    # pass whose exclusive prefix sum gives every key's first slot (start[2T] = n).
    counts = dr.zeros(mi.UInt32, 2 * table + 1)
    # Every slot is written; without photons one zero record that no bucket lists (a
    # gather may not read from an empty array, even where no lane is active).
    record = dr.empty(mi.Float, n * RECORD) if n else dr.zeros(mi.Float, RECORD)
    if n:  # (no photon: e.g. only direct ones, left out where direct light is apart)
        inv_cell = dr.opaque(mi.Float, 1.0 / cell_size)
        key = cell_hash(cell_of(pm.p, inv_cell), mask) * 2
        if split_direct:
            key += dr.select(pm.depth == 0, mi.UInt32(1), mi.UInt32(0))
        dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), key)
        order = dr.argsort(key)
        dr.scatter(record, dr.gather(mi.ArrayXf, pm.record, order, shape=(RECORD, n)), dr.arange(mi.UInt32, n))
    start = dr.prefix_sum(counts)
    grid = PhotonGrid(record=record, start=start, cell_size=float(cell_size),
                      table_mask=mask, split_direct=split_direct, count=n)
    dr.eval(grid.record, grid.start)
    return grid
