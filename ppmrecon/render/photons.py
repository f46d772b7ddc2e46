"""Photon pass: emit J photons from the scene's emitters and store them at every
interaction with a non-delta BSDF component (SPEC section 3, step 1).

A photon path starts with ``Scene.sample_emitter_ray``, whose weight is the emitted
power over the sampling density, and continues by BSDF sampling in importance mode
with Russian roulette after ``rr_depth`` bounces. At every surface whose BSDF has a
diffuse or glossy component, the photon

    (x_p, w_p, n_p, Phi_p, depth)

is written to slot ``depth * J + j`` of a preallocated buffer, so the order of the
photon map depends on the seed only (determinism). Phi_p is the path throughput
(power / pdf); the gather divides by J.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .rng import make_rng


@dataclass
class PhotonMap:
    """Photons of one pass, compacted: positions, arrival directions (pointing from the
    photon's origin to x_p), normals oriented towards the side the photon came from,
    power, bounce depth, and J (photons emitted, the estimator's normaliser)."""

    p: mi.Point3f
    d: mi.Vector3f
    n: mi.Normal3f
    power: mi.Color3f
    depth: mi.UInt32
    emitted: int

    def __len__(self) -> int:
        return dr.width(self.power) if dr.width(self.depth) else 0


@dr.syntax
def _trace(scene: mi.Scene, rng: mi.PCG32, n_photons: int, max_depth: int, rr_depth: int,
           buf_p: mi.Point3f, buf_d: mi.Vector3f, buf_n: mi.Normal3f,
           buf_phi: mi.Color3f, buf_valid: mi.UInt32) -> None:
    """Trace photon paths; scatter each stored photon to slot ``depth * J + j``."""
    j = dr.arange(mi.UInt32, n_photons)
    ray, beta, _ = scene.sample_emitter_ray(
        time=0.0, sample1=rng.next_float32(),
        sample2=mi.Point2f(rng.next_float32(), rng.next_float32()),
        sample3=mi.Point2f(rng.next_float32(), rng.next_float32()),
        active=True)
    ray = mi.Ray3f(ray)
    beta = mi.Color3f(beta)
    depth = mi.UInt32(0)
    active = dr.any(beta > 0.0)
    # Roulette on the throughput relative to the emitted power, not on the power itself.
    inv_power0 = dr.select(active, 1.0 / dr.max(beta), 0.0)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)

    while active:
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        bsdf = si.bsdf(ray)

        # Store at every surface with a non-delta (diffuse or glossy) component.
        store = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        n_oriented = dr.select(dr.dot(si.n, ray.d) < 0.0, si.n, -si.n)
        slot = depth * n_photons + j
        dr.scatter(buf_p, si.p, slot, store)
        dr.scatter(buf_d, ray.d, slot, store)
        dr.scatter(buf_n, n_oriented, slot, store)
        dr.scatter(buf_phi, beta, slot, store)
        dr.scatter(buf_valid, mi.UInt32(1), slot, store)

        bs, bsdf_weight = bsdf.sample(ctx, si, rng.next_float32(),
                                      mi.Point2f(rng.next_float32(), rng.next_float32()), active)
        beta *= bsdf_weight
        ray = si.spawn_ray(si.to_world(bs.wo))
        depth += 1

        # Russian roulette on the throughput, unbiased by dividing by the survival odds.
        q = dr.minimum(dr.max(beta) * inv_power0, 0.95)
        roulette = depth >= rr_depth
        survive = rng.next_float32() < q
        beta = dr.select(roulette, beta / dr.maximum(q, 1e-8), beta)
        active &= (~roulette | survive) & (depth < max_depth) & dr.any(beta > 0.0)


def trace_photons(scene: mi.Scene, n_photons: int, seed: int, max_depth: int,
                  rr_depth: int = 3) -> PhotonMap:
    """Emit ``n_photons`` photons with random stream ``seed`` and return the photon map."""
    size = n_photons * max_depth
    buf_p = dr.zeros(mi.Point3f, size)
    buf_d = dr.zeros(mi.Vector3f, size)
    buf_n = dr.zeros(mi.Normal3f, size)
    buf_phi = dr.zeros(mi.Color3f, size)
    buf_valid = dr.zeros(mi.UInt32, size)
    rng = make_rng(n_photons, seed)
    _trace(scene, rng, n_photons, max_depth, rr_depth, buf_p, buf_d, buf_n, buf_phi, buf_valid)
    dr.eval(buf_p, buf_d, buf_n, buf_phi, buf_valid)
    index = dr.compress(buf_valid > 0)
    slot_depth = index // n_photons
    pm = PhotonMap(
        p=dr.gather(mi.Point3f, buf_p, index), d=dr.gather(mi.Vector3f, buf_d, index),
        n=dr.gather(mi.Normal3f, buf_n, index), power=dr.gather(mi.Color3f, buf_phi, index),
        depth=mi.UInt32(slot_depth), emitted=n_photons)
    dr.eval(pm.p, pm.d, pm.n, pm.power, pm.depth)
    return pm
