"""Direct lighting at gather points (issue 20, item 5; paper 002 Sec. 5: its authors
"use direct lighting when primary rays hit glossy surfaces", for SPPM and CPPM alike;
pbrt's SPPM does it at every visible point).

At a gather point x with BSDF f, the radiance towards the eye splits into light that
arrives straight from an emitter and everything else:

    L_o(x, w_o) = L_direct(x, w_o) + L_indirect(x, w_o)

L_direct is estimated per pass by next-event estimation combined with BSDF sampling
under multiple importance sampling (power heuristic, Veach 1997 Sec. 9.2), as the first
vertex of Mitsuba 3's ``path`` integrator does:

    L_direct ~= w_em f(w_o, w_e) L_e / p_em(w_e)  +  w_bsdf f(w_o, w_b) L_e(w_b) / p_bsdf(w_b),
    w_a = p_a^2 / (p_em^2 + p_bsdf^2)

and L_indirect by the photon gather restricted to photons that bounced at least once
before arriving (bounce index d >= 1; the photons with d = 0 carry exactly the direct
light). Both parts are consistent estimators, so is their sum; the five chains keep one
photon map. On a peaked BSDF the density estimate of direct light multiplies a narrow
lobe by a sparse photon density, the noisiest pixels of every glossy scene, while the
MIS estimate samples that lobe directly.

``mode``: "none" (photons carry all light), "glossy" (direct lighting at gather points
whose BSDF has a glossy component) or "all" (at every gather point).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .eye import GatherPoints
from .rng import make_rng

DIRECT_MODES = ("none", "glossy", "all")


def check_mode(mode: str) -> None:
    if mode not in DIRECT_MODES:
        raise ValueError(f"unknown direct-lighting mode '{mode}' (choose {', '.join(DIRECT_MODES)})")


def uses_direct(gp: GatherPoints, mode: str, max_depth: int) -> mi.Bool:
    """Gather points whose direct light comes from :func:`direct_light` (and whose gather
    must then skip photons with d = 0): found, of the chosen kind, and with room for one
    more segment under ``max_depth`` (-1: unbounded)."""
    check_mode(mode)
    if mode == "none":
        return dr.zeros(mi.Bool, dr.width(gp.found))
    use = mi.Bool(gp.found)
    if mode == "glossy":
        use &= mi.has_flag(gp.si.bsdf().flags(), mi.BSDFFlags.Glossy)
    if max_depth >= 0:
        use &= gp.segments + 1 <= dr.opaque(mi.UInt32, max_depth)
    return use


def _mis(pdf_a: mi.Float, pdf_b: mi.Float) -> mi.Float:
    """Power heuristic weight of technique a (0 where both densities vanish)."""
    a2 = dr.square(pdf_a)
    return dr.detach(dr.select(a2 > 0.0, a2 / (a2 + dr.square(pdf_b)), 0.0))


def rays_can_hit_emitters(scene: mi.Scene) -> bool:
    """Whether a ray can reach an emitter of ``scene`` (an area light, an environment):
    False when every emitter is a point, spot, projector or directional light."""
    delta = mi.EmitterFlags.DeltaPosition | mi.EmitterFlags.DeltaDirection
    return any(not mi.has_flag(e.flags(), delta) for e in scene.emitters())


def direct_light(scene: mi.Scene, gp: GatherPoints, active: mi.Bool, seed: int,
                 defer_counts: bool = False, bsdf_sampling: bool = True) -> tuple[mi.Color3f, int | mi.UInt32]:
    """L_direct at every gather point in ``active`` (0 elsewhere), one emitter sample and
    one BSDF sample each, random stream ``seed``; and how many non-finite samples were
    dropped (``defer_counts``: as a one-element device value, no host read here).

    ``bsdf_sampling=False`` leaves the BSDF sample out, which is exact where no ray can
    reach an emitter (:func:`rays_can_hit_emitters`): every emitter sample is then a delta
    one (MIS weight 1) and the BSDF sample's term is 0, yet it costs a ray per gather point.
    """
    n = dr.width(gp.found)
    rng = make_rng(n, seed)
    si = gp.si
    bsdf = si.bsdf()
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)

    # Emitter sampling (next-event estimation with a shadow ray).
    ds, em_weight = scene.sample_emitter_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()),
                                                   True, active)
    active_em = active & (ds.pdf != 0.0)
    f_em, pdf_bsdf_em = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_em)
    w_em = dr.select(ds.delta, 1.0, _mis(ds.pdf, pdf_bsdf_em))
    l_em = dr.select(active_em, w_em * f_em * em_weight, 0.0)

    if not bsdf_sampling:
        return _finite(l_em, active, n, defer_counts)

    # BSDF sampling: what the sampled ray hits, if it is an emitter (or the environment).
    bs, bsdf_weight = bsdf.sample(ctx, si, rng.next_float32(), mi.Point2f(rng.next_float32(), rng.next_float32()),
                                  active)
    # A delta lobe (a smooth coating) is left out, as the photon gather's bsdf.eval
    # leaves it out: the split into direct + photons stays exact for the same BSDF.
    active_b = active & dr.any(bsdf_weight > 0.0) & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    ray = si.spawn_ray(si.to_world(bs.wo))
    si_b = scene.ray_intersect(ray, active_b)
    ds_b = mi.DirectionSample3f(scene, si=si_b, ref=si)
    pdf_em_b = scene.pdf_emitter_direction(si, ds_b, active_b)
    w_b = _mis(bs.pdf, pdf_em_b)
    emitter_b = si_b.emitter(scene, active_b)
    l_b = dr.select(active_b, w_b * bsdf_weight * emitter_b.eval(si_b, active_b), 0.0)

    return _finite(l_em + l_b, active, n, defer_counts)


def _finite(total: mi.Color3f, active: mi.Bool, n: int, defer_counts: bool) -> tuple[mi.Color3f, int | mi.UInt32]:
    """``total`` with its non-finite samples set to 0, and how many there were."""
    finite = dr.all(dr.isfinite(total))
    dr.eval(total, finite)
    bad = dr.count(active & ~finite) if n else 0
    bad = int(bad[0]) if n and not defer_counts else bad
    return dr.select(finite, total, 0.0), bad
