"""Eye pass: one eye path per lane to its first non-delta hit, the gather point
(SPEC section 3, step 2).

Each lane samples a uniform position inside its pixel (box filter) and follows delta
interactions (mirror, glass, and the null transmission of a partly opaque ``mask``,
taken with its probability) by BSDF sampling in radiance mode, accumulating

    L_e += beta * L_emitted            (emitters seen directly or through specular chains)

until the first surface whose BSDF has a diffuse or glossy component: that surface is
the gather point, carrying the throughput beta to the camera and its segment count e
(the gather keeps photons of d + 1 light segments only while e + d + 1 <= max_depth,
Mitsuba's convention). Paths that escape (the environment, if any, is added to L_e) or
exceed ``max_depth`` segments keep only L_e; with ``max_depth`` = -1 (unbounded) a delta
chain ends by Russian roulette after ``rr_depth`` segments, as in Mitsuba's ``path``.
A non-finite throughput or emitted term (a degenerate BSDF sample) is dropped alone and
counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from .rng import make_rng


@dataclass
class GatherPoints:
    """Gather points of one wavefront (one per lane) and their G-buffer values."""

    hit: mi.PreliminaryIntersection3f  # of ``ray``: the gather point where ``found``
    ray: mi.Ray3f                  # the eye path's last ray
    found: mi.Bool                 # the path reached a non-delta surface
    beta: mi.Color3f               # throughput camera -> gather point
    emitted: mi.Color3f            # L_e collected on the way
    albedo: mi.Color3f             # diffuse reflectance at the gather point
    normal: mi.Normal3f            # world-space shading normal at the gather point
    depth: mi.Float                # distance along the eye path to the gather point
    n_oriented: mi.Normal3f        # geometric normal facing the eye
    segments: mi.UInt32            # eye-path segments to the gather point (e)
    nonfinite: int | mi.UInt32 = 0 # non-finite terms dropped on the way (a device count: see trace_eye)
    #: Where the gather point's BSDF is Lambertian (None: unknown, evaluate per photon).
    lambertian: mi.Bool | None = None
    #: Every non-delta BSDF of the scene is Lambertian: the gather needs no BSDF call.
    only_lambertian: bool = False

    def __len__(self) -> int:
        return dr.width(self.found)

    @property
    def si(self) -> mi.SurfaceInteraction3f:
        """The gather point's full surface interaction (valid where ``found``), computed
        inside each kernel that reads it: what ``scene.ray_intersect`` returns, bit for
        bit, without writing its ~40 values per lane to memory and reading them back."""
        return self.hit.compute_surface_interaction(self.ray, mi.RayFlags.All, self.found)


def _has_null_bsdf(scene: mi.Scene) -> bool:
    """Whether a shape's BSDF lets light through unchanged (a Mitsuba 3 ``mask``): only
    then do eye paths draw the extra random number that decides to pass, so scenes
    without one keep their random streams (same seed, same image)."""
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null):
            return True
    return False


def _is_lambertian(bsdf: mi.BSDF) -> bool:
    """Mitsuba's `diffuse`, alone or as both sides of a `twosided`: f = rho / pi."""
    if bsdf.class_name() == "SmoothDiffuse":
        return True
    # A twosided's sides show only in its description (a texture below them is fine).
    nested = [ln.strip() for ln in str(bsdf).splitlines() if ln.strip().startswith("brdf[")]
    return (bsdf.class_name() == "TwoSidedBRDF" and len(nested) == 2
            and all(ln.endswith("= SmoothDiffuse[") for ln in nested))


@dataclass(frozen=True)
class LambertianTable:
    """Per BSDF registry id (``dr.reinterpret_array(mi.UInt32, bsdf_ptr)``): whether that
    BSDF is Lambertian (so the gather evaluates it once per gather point); ``only``: every
    BSDF with a diffuse or glossy component is."""

    by_id: mi.Bool
    only: bool


def lambertian_table(scene: mi.Scene) -> LambertianTable:
    """The :class:`LambertianTable` of ``scene``'s BSDFs."""
    ids: dict[int, bool] = {}
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None:
            ids[int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0])] = (
                _is_lambertian(bsdf) or not mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth))
    table = [False] * (max(ids, default=0) + 1)
    for i, v in ids.items():
        table[i] = v
    return LambertianTable(mi.Bool(table), all(ids.values()))


@dr.syntax
def _walk(scene: mi.Scene, ray: mi.Ray3f, rng: mi.PCG32, max_depth: mi.UInt32, rr_depth: int,
          lambertian_ids: mi.Bool, null_bsdfs: bool = False):
    """Follow delta bounces; returns the last ray, its preliminary intersection (the
    gather point where found), throughput, L_e, path length, segments, found, which
    lanes dropped a non-finite term, and the gather point's G-buffer values (albedo,
    shading normal, geometric normal facing the eye, Lambertian flag), taken from the
    surface interaction the walk computes there anyway."""
    n = dr.width(ray)
    last = dr.zeros(mi.PreliminaryIntersection3f, n)
    albedo = dr.zeros(mi.Color3f, n)
    normal = dr.zeros(mi.Normal3f, n)
    n_oriented = dr.zeros(mi.Normal3f, n)
    lambert = dr.zeros(mi.Bool, n)
    beta = mi.Color3f(1.0)
    emitted = mi.Color3f(0.0)
    length = mi.Float(0.0)
    depth = mi.UInt32(0)
    found = mi.Bool(False)
    bad = mi.Bool(False)
    active = mi.Bool(True)
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)

    while active:
        # What ray_intersect does, kept in two steps so that the gather point's
        # preliminary intersection leaves the loop (no second trace of the last ray).
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, active)
        depth += 1
        # The environment (invalid si) or an area light: what the eye sees directly.
        emitter = si.emitter(scene, active)
        le = beta * emitter.eval(si, active)
        le_ok = dr.all(dr.isfinite(le))
        bad |= active & ~le_ok
        emitted += dr.select(active & le_ok, le, 0.0)

        hit = active & si.is_valid()
        bsdf = si.bsdf(ray)
        smooth = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        # A surface that also lets light through unchanged (a Mitsuba 3 `mask` with
        # opacity < 1): pass through with the probability of its null transmission,
        # else gather here, each branch divided by its probability.
        passes = mi.Bool(False)
        if dr.hint(null_bsdfs, mode="scalar"):
            through = hit & smooth & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null)
            t_null = dr.select(through, mi.Color3f(bsdf.eval_null_transmission(si, through)), 0.0)
            p_null = dr.clip((t_null.x + t_null.y + t_null.z) / 3.0, 0.0, 1.0)
            passes = through & (rng.next_float32() < p_null)
            beta *= dr.select(passes, t_null / dr.maximum(p_null, 1e-8),
                              dr.select(through, 1.0 / dr.maximum(1.0 - p_null, 1e-8), 1.0))
            smooth &= ~passes
        stop_here = hit & smooth
        found |= stop_here
        last[stop_here] = pi
        albedo[stop_here] = bsdf.eval_diffuse_reflectance(si, stop_here)
        normal[stop_here] = si.sh_frame.n
        n_oriented[stop_here] = dr.select(dr.dot(si.n, ray.d) < 0.0, si.n, -si.n)
        # A delta-only BSDF counts as Lambertian in the table (it is never a gather point).
        lambert[stop_here] = dr.gather(mi.Bool, lambertian_ids, dr.reinterpret_array(mi.UInt32, bsdf), stop_here)
        length += dr.select(hit, si.t, 0.0)
        active = hit & ~smooth & (depth < max_depth)

        delta = active & ~passes
        bs, bsdf_weight = bsdf.sample(ctx, si, rng.next_float32(),
                                      mi.Point2f(rng.next_float32(), rng.next_float32()), delta)
        beta[delta] *= bsdf_weight
        ray[delta] = si.spawn_ray(si.to_world(bs.wo))
        ray[active & passes] = si.spawn_ray(ray.d)
        # Roulette on delta chains (only unbounded depth needs it to end mirror halls).
        q = dr.minimum(dr.max(beta), 0.95)
        roulette = active & (depth >= rr_depth)
        survive = rng.next_float32() < q
        beta[roulette] = beta / dr.maximum(q, 1e-8)
        finite = dr.all(dr.isfinite(beta))
        bad |= active & ~finite
        active &= (~roulette | survive) & dr.any(beta > 0.0) & finite

    return ray, last, beta, emitted, length, depth, found, bad, albedo, normal, n_oriented, lambert


def trace_eye(scene: mi.Scene, sensor: mi.Sensor, seed: int, max_depth: int,
              rr_depth: int = 5, lambertian: LambertianTable | None = None,
              defer_counts: bool = False) -> GatherPoints:
    """One eye path per pixel (row-major, top row first) with random stream ``seed``;
    ``max_depth`` in segments, -1 for unbounded; ``lambertian``: :func:`lambertian_table`
    of the scene (computed here if not given). ``defer_counts``: ``nonfinite`` stays a
    device value (one element), read by the caller when it syncs anyway."""
    film_size = sensor.film().crop_size()
    width, height = int(film_size[0]), int(film_size[1])
    n = width * height
    rng = make_rng(n, seed)
    idx = dr.arange(mi.UInt32, n)
    pixel = mi.Point2f(mi.Float(idx % width), mi.Float(idx // width))
    jitter = mi.Point2f(rng.next_float32(), rng.next_float32())
    film_pos = (pixel + jitter) / mi.ScalarPoint2f(width, height)
    ray, ray_weight = sensor.sample_ray(time=0.0, sample1=0.5, sample2=film_pos,
                                        sample3=mi.Point2f(rng.next_float32(), rng.next_float32()))
    ray = mi.Ray3f(ray)

    depth_cap = mi.UInt32(0xFFFFFFFF if max_depth < 0 else max_depth)
    table = lambertian_table(scene) if lambertian is None else lambertian
    last_ray, hit, beta, emitted, length, segments, found, bad, albedo, normal, n_oriented, lambert = _walk(
        scene, ray, rng, depth_cap, rr_depth, table.by_id, _has_null_bsdf(scene))
    beta *= ray_weight
    emitted *= ray_weight
    gp = GatherPoints(hit=hit, ray=last_ray, found=found, beta=beta, emitted=emitted, albedo=albedo,
                      normal=normal, depth=dr.select(found, length, 0.0), n_oriented=n_oriented,
                      segments=segments, lambertian=lambert, only_lambertian=table.only)
    dr.eval(gp.hit, gp.ray, gp.found, gp.beta, gp.emitted, gp.albedo, gp.normal, gp.depth, gp.n_oriented,
            gp.segments, gp.lambertian, bad)
    gp.nonfinite = (dr.count(bad) if defer_counts else int(dr.count(bad)[0])) if n else 0
    return gp
