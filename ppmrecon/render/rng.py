"""Random streams: one PCG32 per lane, decorrelated by a TEA hash of (seed, lane).

Every random number of a render derives from the user's seed, the pass index and a
purpose tag, so the same seed gives the same file.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

# Purpose tags keep the photon, eye-A and eye-B streams of one pass independent.
PHOTONS, EYE_A, EYE_B, EYE_SINGLE = 1, 2, 3, 4
#: Direct-lighting samples at the gather points of eye stream EYE_x: DIRECT_OFFSET + x.
DIRECT_OFFSET = 16


def stream_seed(seed: int, pass_index: int, purpose: int) -> int:
    """A 32-bit seed for one purpose of one pass."""
    x = (seed * 0x9E3779B1 + pass_index * 0x85EBCA77 + purpose * 0xC2B2AE3D) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    return x


def make_rng(size: int, seed: int) -> mi.PCG32:
    """``size`` independent PCG32 streams (one sequence per lane)."""
    lane = dr.arange(mi.UInt32, size)
    # Opaque, so a new seed each pass does not bake a new literal into the kernel.
    v0, v1 = mi.sample_tea_32(dr.opaque(mi.UInt32, seed), lane)
    initstate = (mi.UInt64(v0) << 32) | mi.UInt64(v1)
    return mi.PCG32(size, initstate=initstate, initseq=mi.UInt64(lane))
