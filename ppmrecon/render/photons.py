"""Photon pass: emit J photons from the scene's emitters and store them at every
interaction with a non-delta BSDF component (SPEC section 3, step 1).

A photon path starts with ``Scene.sample_emitter_ray``, whose weight is the emitted
power over the sampling density, and continues by BSDF sampling in importance mode
with Russian roulette after ``rr_depth`` bounces (Mitsuba's ``rr_depth``, default 5).
At every surface whose BSDF has a diffuse or glossy component, the photon

    (x_p, w_p, n_p, Phi_p, d)

is stored, Phi_p the path throughput (power / pdf; the gather divides by J) and d the
bounce index (0 at the first surface, i.e. d + 1 light segments).

Path depth follows Mitsuba's ``max_depth`` convention: it bounds the number of segments
of the whole camera-to-light path, -1 meaning unbounded (Russian roulette alone ends the
paths). The eye path takes at least one segment, so a photon is stored only while
d + 1 <= max_depth - 1; the gather then keeps a photon only if the eye path's segments
e satisfy e + d + 1 <= max_depth (see :mod:`.gather`).

Memory is bounded for any depth: paths are traced in *segments* of at most
``SEGMENT_BOUNCES`` bounces into a buffer of ``J_active * bounces`` slots (slot
``(d - d0) * J_active + j``, one record of ``RECORD`` floats, stored with one packet
instruction; only the valid flags are cleared); the paths still alive at the end of a segment are
compacted, their random streams included, and continue in the next one. The photon
map's order therefore depends on the seed only (determinism).

A non-finite throughput (a degenerate BSDF sample) ends that path alone and is counted;
it never reaches the photon map.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .rng import make_rng

#: Bounces traced per segment; deeper paths continue in a compacted next segment.
SEGMENT_BOUNCES = 8
#: Mitsuba's default ``rr_depth`` (its ``path`` integrator starts roulette there too).
RR_DEPTH = 5


#: Floats per photon record (13 used; a power of two, so that the trace stores and the
#: gather reads a photon with one packet instruction per lane).
RECORD = 16
#: Offsets of the record's fields: x_p, w_p (arrival direction), n_p, Phi_p, d.
REC_P, REC_D, REC_N, REC_POWER, REC_DEPTH = 0, 3, 6, 9, 12


def make_record(p: mi.Point3f, d: mi.Vector3f, n: mi.Normal3f, power: mi.Color3f, depth: mi.Float) -> mi.ArrayXf:
    """One photon record per lane (RECORD x lanes), in the REC_* layout."""
    zero = dr.zeros(mi.Float, dr.width(depth))
    return mi.ArrayXf(p.x, p.y, p.z, d.x, d.y, d.z, n.x, n.y, n.z, power.x, power.y, power.z, depth,
                      *([zero] * (RECORD - REC_DEPTH - 1)))


class PhotonMap:
    """Photons of one pass, compacted, one record each (``record``: RECORD floats per
    photon): positions, arrival directions (pointing from the photon's origin to x_p),
    normals oriented towards the side the photon came from, power and bounce index d;
    J (``emitted``, the estimator's normaliser), and how many paths a non-finite
    throughput ended. The fields read (and ``power`` writes) the records."""

    def __init__(self, record: mi.Float, emitted: int, nonfinite: int = 0):
        self.record, self.emitted, self.nonfinite = record, emitted, nonfinite

    def __len__(self) -> int:
        return dr.width(self.record) // RECORD

    def records(self) -> mi.ArrayXf:
        """All records (RECORD x len), lazily."""
        n = len(self)
        return dr.gather(mi.ArrayXf, self.record, dr.arange(mi.UInt32, n), shape=(RECORD, n))

    def _field(self, cls: type, at: int):
        r = self.records()
        return cls(r[at], r[at + 1], r[at + 2])

    p = property(lambda self: self._field(mi.Point3f, REC_P), doc="positions x_p")
    d = property(lambda self: self._field(mi.Vector3f, REC_D), doc="arrival directions")
    n = property(lambda self: self._field(mi.Normal3f, REC_N), doc="oriented normals")

    @property
    def power(self) -> mi.Color3f:
        return self._field(mi.Color3f, REC_POWER)

    @power.setter
    def power(self, value: mi.Color3f) -> None:
        value = mi.Color3f(value)
        self.record = _pack([make_record(self.p, self.d, self.n, value, mi.Float(self.depth))])

    @property
    def depth(self) -> mi.UInt32:
        return mi.UInt32(self.records()[REC_DEPTH])


@dataclass
class _Paths:
    """State of the photon paths still alive between two segments (one lane each)."""

    ray: mi.Ray3f
    beta: mi.Color3f
    inv_power0: mi.Float
    rng: mi.PCG32


def _emit(scene: mi.Scene, rng: mi.PCG32) -> tuple[_Paths, mi.Bool]:
    ray, beta, _ = scene.sample_emitter_ray(
        time=0.0, sample1=rng.next_float32(),
        sample2=mi.Point2f(rng.next_float32(), rng.next_float32()),
        sample3=mi.Point2f(rng.next_float32(), rng.next_float32()),
        active=True)
    beta = mi.Color3f(beta)
    alive = dr.any(beta > 0.0) & dr.all(dr.isfinite(beta))
    # Roulette on the throughput relative to the emitted power, not on the power itself.
    inv_power0 = dr.select(alive, 1.0 / dr.max(beta), 0.0)
    return _Paths(mi.Ray3f(ray), beta, inv_power0, rng), alive


@dr.syntax
def _trace_segment(scene: mi.Scene, paths: _Paths, alive: mi.Bool, depth0: mi.UInt32,
                   bounces: int, last_depth: mi.UInt32, rr_depth: int,
                   buf: mi.Float, buf_valid: mi.Bool, first_depth: mi.UInt32) -> tuple[mi.Bool, mi.Bool]:
    """Trace up to ``bounces`` bounces of every alive path, storing the photon of bounce
    d = depth0 + step (if d >= ``first_depth``) in slot ``step * lanes + lane``. Stops a
    path after bounce index ``last_depth`` (the last one that may be stored). Returns
    (alive, went non-finite)."""
    # Opaque: the number of surviving paths changes every segment and pass, and a
    # literal would compile a new kernel each time.
    lanes = dr.opaque(mi.UInt32, dr.width(alive))
    lane = dr.arange(mi.UInt32, dr.width(alive))
    ray, beta, rng = paths.ray, paths.beta, paths.rng
    step = mi.UInt32(0)
    bad = mi.Bool(False)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)

    while alive & (step < bounces):
        depth = depth0 + step
        si = scene.ray_intersect(ray, alive)
        alive &= si.is_valid()
        bsdf = si.bsdf(ray)

        # Store at every surface with a non-delta (diffuse or glossy) component.
        store = alive & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & (depth >= first_depth)
        n_oriented = dr.select(dr.dot(si.n, ray.d) < 0.0, si.n, -si.n)
        slot = step * lanes + lane
        dr.scatter(buf, make_record(si.p, ray.d, n_oriented, beta, mi.Float(depth)), slot, store)
        dr.scatter(buf_valid, True, slot, store)

        bs, bsdf_weight = bsdf.sample(ctx, si, rng.next_float32(),
                                      mi.Point2f(rng.next_float32(), rng.next_float32()), alive)
        beta *= bsdf_weight
        ray = si.spawn_ray(si.to_world(bs.wo))
        step += 1

        # Russian roulette on the throughput, unbiased by dividing by the survival odds.
        q = dr.minimum(dr.max(beta) * paths.inv_power0, 0.95)
        roulette = depth + 1 >= rr_depth
        survive = rng.next_float32() < q
        beta = dr.select(roulette, beta / dr.maximum(q, 1e-8), beta)
        finite = dr.all(dr.isfinite(beta))
        bad |= alive & ~finite
        alive &= (~roulette | survive) & (depth < last_depth) & dr.any(beta > 0.0) & finite

    paths.ray, paths.beta, paths.rng = ray, beta, rng
    return alive, bad


def _pack(chunks: list[mi.ArrayXf]) -> mi.Float:
    """Records of several chunks, one after the other, as one flat array: scatters at
    opaque offsets, one kernel whatever the number of chunks or their sizes (``dr.concat``
    bakes both into its kernel)."""
    out = dr.empty(mi.Float, sum(dr.width(c) for c in chunks) * RECORD)  # every slot is written
    offset = 0
    for c in chunks:
        n = dr.width(c)
        dr.scatter(out, c, dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, offset))
        offset += n
    dr.eval(out)
    return out


def trace_photons(scene: mi.Scene, n_photons: int, seed: int, max_depth: int,
                  rr_depth: int = RR_DEPTH, first_bounce: int = 0) -> PhotonMap:
    """Emit ``n_photons`` photons with random stream ``seed`` and return the photon map
    of every stored bounce that can still be part of a path of at most ``max_depth``
    segments (-1: unbounded). ``first_bounce`` = 1 leaves out the direct photons (d = 0)
    where no gather point counts them (direct light estimated apart everywhere): the
    paths, and so every other photon, stay the same."""
    max_bounces = None if max_depth < 0 else max_depth - 1   # storable bounce indices
    # Bounce index after which no photon may be stored (the largest UInt32: never).
    last_depth = mi.UInt32(0xFFFFFFFF if max_bounces is None else max(max_bounces - 1, 0))
    chunks: list[mi.ArrayXf] = []
    nonfinite = 0
    rng = make_rng(n_photons, seed)
    paths, alive = _emit(scene, rng)
    depth0 = 0
    while max_bounces is None or depth0 < max_bounces:
        lanes = dr.width(alive)
        bounces = SEGMENT_BOUNCES if max_bounces is None else min(SEGMENT_BOUNCES, max_bounces - depth0)
        size = lanes * bounces
        # Only the valid flags need clearing: compress reads the records nowhere else.
        buf, buf_valid = dr.empty(mi.Float, size * RECORD), dr.zeros(mi.Bool, size)
        alive, bad = _trace_segment(scene, paths, alive, dr.opaque(mi.UInt32, depth0), bounces, last_depth,
                                    rr_depth, buf, buf_valid, dr.opaque(mi.UInt32, first_bounce))
        dr.eval(buf, buf_valid, alive, bad, paths.ray, paths.beta, paths.rng)
        nonfinite += int(dr.count(bad)[0]) if lanes else 0
        index = dr.compress(buf_valid)
        if dr.width(index):
            chunks.append(dr.gather(mi.ArrayXf, buf, index, shape=(RECORD, dr.width(index))))
        depth0 += bounces
        survivors = dr.compress(alive)
        if dr.width(survivors) == 0:
            break
        rng_next = mi.PCG32()
        rng_next.state = dr.gather(type(paths.rng.state), paths.rng.state, survivors)
        rng_next.inc = dr.gather(type(paths.rng.inc), paths.rng.inc, survivors)
        paths = _Paths(dr.gather(mi.Ray3f, paths.ray, survivors), dr.gather(mi.Color3f, paths.beta, survivors),
                       dr.gather(mi.Float, paths.inv_power0, survivors), rng_next)
        alive = dr.full(mi.Bool, True, dr.width(survivors))

    record = _pack(chunks) if chunks else dr.zeros(mi.Float, 0)
    return PhotonMap(record, emitted=n_photons, nonfinite=nonfinite)
