"""Renderer correctness on the project's own small scenes (issue: multi-bandwidth SPPM).

Budgets are stated in each test; all run at 16x16 or 32x32 so the file stays fast.
"""

from __future__ import annotations

import numpy as np
import pytest

from ppmrecon.backend import choose_variant

choose_variant()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.metrics import relmse  # noqa: E402
from ppmrecon.render.integrator import Renderer, RenderSettings  # noqa: E402
from ppmrecon.render.scene import load_scene  # noqa: E402


def render(name, res, **kw):
    loaded = load_scene(name, resolution=res)
    kw.setdefault("max_depth", loaded.depths()[0])
    return loaded, Renderer(loaded.scene, RenderSettings(**kw), scene_name=name)


def path_reference(loaded, spp):
    return np.asarray(mi.render(loaded.scene, spp=spp), np.float32)


def test_converges_to_path_tracer_reference():
    """~z^1 on a diffuse + glossy scene (no caustics) approaches Mitsuba's own `path`
    integrator (1024 spp): relMSE falls as passes grow (2^15 photons per pass)."""
    loaded, r = render("diffuse_glossy", (32, 32), passes=32, photons=1 << 15, seed=3)
    ref = path_reference(loaded, 1024)
    errors = {}

    def on_pass(rr):
        if rr.passes_done in (4, 32):
            errors[rr.passes_done] = relmse(rr.result().estimates[1], ref)

    r.run(on_pass)
    assert errors[32] < 0.5 * errors[4], errors
    assert errors[32] < 0.05, errors


def test_energy_plane_under_point_light():
    """Diffuse plane (rho 0.5) 1 unit under a 10 W/sr point light: every chain's mean
    over the central 8x8 of 16x16 pixels is within 2% of rho/pi * I h / (h^2 + r^2)^1.5
    (2^17 photons x 128 passes)."""
    loaded, r = render("plane_point", (16, 16), passes=128, photons=1 << 17, seed=11, max_depth=2)
    res = r.run()
    half = 4.0 * np.tan(np.radians(10.0))  # camera at height 4, 20 degree horizontal fov
    x = (np.arange(16) + 0.5) / 16 * 2 * half - half
    X, Z = np.meshgrid(x, x)
    analytic = 0.5 / np.pi * 10.0 / (1.0 + X ** 2 + Z ** 2) ** 1.5
    centre = (slice(4, 12), slice(4, 12))
    for k in range(5):
        est = res.estimates[k][centre].mean(-1).mean()
        assert est == pytest.approx(analytic[centre].mean(), rel=0.02), (k, est)


def _relative_residual(est, ref):
    ref_l = ref.mean(-1)
    return ((est.mean(-1) - ref_l) / np.sqrt(ref_l ** 2 + 0.01)).ravel()


def test_two_hit_points_decorrelate_y_and_z():
    """Glossy first surfaces (glossy_spot): the pixel-wise correlation of the relative
    residuals of ~y and ~z^1 (against a 4096-spp path-traced reference) is below 0.1
    with two hit points; with one shared hit point it is high (reported for contrast)."""
    loaded = load_scene("glossy_spot", resolution=(32, 32))
    ref = path_reference(loaded, 4096)
    corr = {}
    for layout in ("multi", "shared"):
        res = Renderer(loaded.scene, RenderSettings(passes=16, photons=1 << 15, seed=1, layout=layout,
                                                    max_depth=loaded.max_depth or 8)).run()
        corr[layout] = np.corrcoef(_relative_residual(res.estimates[0], ref),
                                   _relative_residual(res.estimates[1], ref))[0, 1]
    print(f"residual correlation y/z1: two hit points {corr['multi']:.3f}, shared {corr['shared']:.3f}")
    assert abs(corr["multi"]) < 0.1, corr
    assert corr["shared"] > 0.5, corr


def test_same_seed_same_result_and_different_seed_differs():
    _, a = render("cornell_caustics", (16, 16), passes=3, photons=1 << 12, seed=5)
    _, b = render("cornell_caustics", (16, 16), passes=3, photons=1 << 12, seed=5)
    _, c = render("cornell_caustics", (16, 16), passes=3, photons=1 << 12, seed=6)
    ra, rb, rc = a.run(), b.run(), c.run()
    for name in ("estimates", "variances", "radii", "albedo", "normal", "depth"):
        assert np.array_equal(getattr(ra, name), getattr(rb, name)), name
    assert not np.array_equal(ra.estimates, rc.estimates)


def test_buffer_layers_valid_and_radii_shrink():
    _, r = render("cornell_caustics", (24, 16), passes=4, photons=1 << 12, seed=0)
    res = r.run()
    buf = res.buffer_file()
    assert buf.estimates.shape == (5, 16, 24, 3)
    for arr in (buf.estimates, buf.variances, buf.radii, buf.albedo, buf.depth):
        assert np.isfinite(arr).all() and (arr >= 0).all()
    # chains keep the initial ratios 1/4 : 1/(2 sqrt 2) : 1/2 : 1/sqrt 2 : 1 under SPPM
    ratio = buf.radii / buf.radii[4]
    np.testing.assert_allclose(ratio[:, 0, 0], [0.25, 0.5 ** 1.5, 0.5, 0.5 ** 0.5, 1.0], rtol=1e-5)
    # Knaus-Zwicker: after passes 1..3, r^2 shrank by prod (i + 2/3) / (i + 1)
    _, r1 = render("cornell_caustics", (24, 16), passes=1, photons=1 << 12, seed=0)
    r1_radii = r1.run().radii
    shrink = np.prod([(i + 2 / 3) / (i + 1) for i in (1, 2, 3, 4)]) / ((1 + 2 / 3) / 2)
    np.testing.assert_allclose((buf.radii / r1_radii) ** 2, shrink, rtol=1e-4)
    assert res.header[B.H_PASSES] == 4 and res.header[B.H_METHOD] == "sppm"


def test_interrupt_keeps_completed_passes():
    _, r = render("cornell_caustics", (16, 16), passes=10, photons=1 << 12)

    def on_pass(rr):
        if rr.passes_done == 3:
            raise KeyboardInterrupt

    res = r.run(on_pass)
    assert res.passes == 3 and res.stopped == "interrupted"
    assert res.header["ppmrecon.stopped"] == "interrupted"


def test_time_budget_stops():
    _, r = render("cornell_caustics", (16, 16), passes=None, time_budget=1.0, photons=1 << 12)
    res = r.run()
    assert res.passes >= 1 and res.stopped == "time budget"


def _furnace_sphere(res: int = 16) -> "mi.Scene":
    """Inside a closed sphere (radius 1) whose wall emits L_e = 1 and reflects diffusely
    with albedo rho = 0.8: the radiance is L_e sum_k rho^k over the bounces a path may
    take, 1 / (1 - rho) = 5 unbounded. The constant kernel is exact on a sphere (the
    cap within chord r has area pi r^2), so the estimate is unbiased up to the radius."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60.0,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}}},
        "wall": {"type": "sphere", "radius": 1.0, "flip_normals": True,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}},
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}},
    })


@pytest.mark.parametrize("max_depth, expected, direct", [(-1, 5.0, "none"), (3, 1.0 + 0.8 + 0.64, "none"),
                                                         (-1, 5.0, "all"), (3, 1.0 + 0.8 + 0.64, "all")])
def test_path_depth_follows_mitsuba_closed_form(max_depth, expected, direct):
    """White furnace: max_depth counts segments of the whole camera-to-light path as in
    Mitsuba (1: emitters seen directly, 3: up to two bounces), -1 is unbounded with
    Russian roulette. Every chain's image mean lies within 2% of the closed form
    (16x16, 2^15 photons x 16 passes); depth 8 would give 4.16 instead of 5. With direct
    lighting estimated apart (MIS) and photons for the indirect part only, the same."""
    res = Renderer(_furnace_sphere(), RenderSettings(passes=16, photons=1 << 15, seed=2,
                                                     max_depth=max_depth, direct=direct)).run()
    assert res.header["ppmrecon.max_depth"] == max_depth
    for k in range(5):
        assert res.estimates[k].mean() == pytest.approx(expected, rel=0.02), (k, res.estimates[k].mean())
    assert res.nonfinite == 0


def test_scene_depth_and_cli_override(tmp_path):
    """A scene's max_depth -1 or 65 is kept as it is (no silent cap), --max-depth wins."""
    from ppmrecon.render.cli import main

    scene = tmp_path / "s.xml"
    scene.write_text(
        '<scene version="3.0.0"><integrator type="path"><integer name="max_depth" value="65"/>'
        '<integer name="rr_depth" value="7"/></integrator>'
        '<sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/>'
        '</transform><film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film>'
        '</sensor><shape type="rectangle"><bsdf type="diffuse"/></shape>'
        '<emitter type="point"><point name="position" x="0" y="0" z="1"/></emitter></scene>')
    for extra, depth, rr in (([], 65, 7), (["--max-depth", "-1", "--rr-depth", "3"], -1, 3)):
        out = tmp_path / f"o{depth}.exr"
        assert main([str(scene), "--passes", "1", "--photons", "256", "-q", "-o", str(out)] + extra) == 0
        header = B.read_buffers(out).header
        assert header["ppmrecon.max_depth"] == depth and header["ppmrecon.rr_depth"] == rr


def test_nonfinite_photon_contribution_is_dropped_alone():
    """A photon whose power is NaN or Inf is left out of the gather (and counted); the
    other photons and the emission keep their value: the estimate equals the one of a
    photon map without those photons."""
    import drjit as dr

    from ppmrecon.render.eye import trace_eye
    from ppmrecon.render.gather import gather
    from ppmrecon.render.grid import build_grid
    from ppmrecon.render.photons import trace_photons

    loaded = load_scene("plane_point", resolution=(16, 16))
    pm = trace_photons(loaded.scene, 1 << 12, seed=4, max_depth=2)
    gp = trace_eye(loaded.scene, loaded.scene.sensors()[0], seed=5, max_depth=2)
    power = np.asarray(pm.power).copy()           # (3, n)
    bad = np.zeros(power.shape[1], bool)
    bad[::7] = True
    clean = power.copy()
    clean[:, bad] = 0.0
    power[0, bad[: power.shape[1]]] = np.nan
    power[1, np.flatnonzero(bad)[::2]] = np.inf
    radius = [dr.full(mi.Float, 0.3, 16 * 16)]
    results = {}
    for name, values in (("poisoned", power), ("clean", clean)):
        pm.power = mi.Color3f(values)
        results[name] = gather(gp, radius, build_grid(pm, 0.3), max_depth=2)
    flux = np.asarray(results["poisoned"].flux[0])
    assert np.isfinite(flux).all()
    np.testing.assert_allclose(flux, np.asarray(results["clean"].flux[0]), rtol=1e-5, atol=1e-7)
    assert results["poisoned"].nonfinite > 0 and results["clean"].nonfinite == 0


def test_gather_counts_match_brute_force_and_hash_spreads_cells():
    """The grid's gather counts, at radii that span several cells, equal a brute-force
    count over every photon (same facing, grazing and depth tests), so cells sharing a
    bucket are neither lost nor counted twice; and the block hash leaves fewer than 10%
    of a dense 40^3 lattice's cells sharing a bucket (the plain Teschner hash: 71%)."""
    import drjit as dr

    from ppmrecon.render.eye import trace_eye
    from ppmrecon.render.gather import FACING_COS, gather
    from ppmrecon.render.grid import build_grid, cell_hash
    from ppmrecon.render.photons import REC_D, REC_DEPTH, REC_N, REC_P, RECORD, trace_photons

    loaded = load_scene("cornell_caustics", resolution=(12, 12))
    pm = trace_photons(loaded.scene, 1 << 12, seed=3, max_depth=6)
    gp = trace_eye(loaded.scene, loaded.scene.sensors()[0], seed=9, max_depth=6)
    n = 12 * 12
    r = np.random.default_rng(0).uniform(0.05, 0.3, n).astype(np.float32)
    grid = build_grid(pm, 0.07)
    count = np.asarray(gather(gp, [mi.Float(r)], grid, max_depth=6).count[0])

    rec = np.asarray(pm.record).reshape(-1, RECORD)
    si = gp.si
    x, ng = np.asarray(si.p).T, np.asarray(si.n).T
    n_gp, found, seg = np.asarray(gp.n_oriented).T, np.asarray(gp.found), np.asarray(gp.segments)
    d2 = ((rec[None, :, REC_P:REC_P + 3] - x[:, None]) ** 2).sum(-1)
    facing = (rec[None, :, REC_N:REC_N + 3] * n_gp[:, None]).sum(-1) > FACING_COS
    cos_g = np.abs((rec[None, :, REC_D:REC_D + 3] * ng[:, None]).sum(-1))
    depth_ok = rec[None, :, REC_DEPTH] <= (6 - 1 - seg)[:, None]
    near = np.abs(d2 - (r ** 2)[:, None]) < 1e-5 * (r ** 2)[:, None]  # rounding at the rim
    inside = (d2 < (r ** 2)[:, None]) & facing & (cos_g > 1e-4) & depth_ok & found[:, None]
    # every Cornell-box material is diffuse (no transmission): the facing test applies
    assert count.sum() > 20 * n
    assert (np.abs(count - inside.sum(1)) <= near.sum(1)).all()

    cells = np.stack(np.meshgrid(*[np.arange(-20, 20)] * 3, indexing="ij"), -1).reshape(-1, 3)
    buckets = np.asarray(cell_hash(mi.Vector3i(cells.T.astype(np.int32)), (1 << 20) - 1))
    _, per_bucket = np.unique(buckets, return_counts=True)
    assert per_bucket[per_bucket > 1].sum() / len(cells) < 0.10
    assert dr.width(grid.start) == 2 * (grid.table_mask + 1) + 1


def test_single_baseline_radius_is_its_own_knn():
    """--single starts at the distance to the k-th nearest photon (default k = 10); a
    larger k gives a larger radius, and the header says which k."""
    radii = {}
    for k in (3, 10):
        _, r = render("cornell_caustics", (16, 16), passes=1, photons=1 << 12, seed=0, layout="single",
                      single_knn=k)
        res = r.run()
        radii[k] = res.radii[0]
        assert res.header["ppmrecon.single_knn"] == k
    assert (radii[10] >= radii[3]).all() and (radii[10] > radii[3]).mean() > 0.9


def test_direct_lighting_lowers_error_at_glossy_gather_points():
    """glossy_spot (rough conductor floor under a spot light), 32x32, 2^15 photons x 16
    passes, against Mitsuba's `path` at 1024 spp: with direct lighting by MIS at every
    gather point (photons for the indirect part only) every chain's relMSE is lower than
    with photons alone, and the image mean stays within 3% of the reference."""
    loaded = load_scene("glossy_spot", resolution=(32, 32))
    ref = path_reference(loaded, 1024)
    err = {}
    for direct in ("none", "all"):
        res = Renderer(loaded.scene, RenderSettings(passes=16, photons=1 << 15, seed=1, direct=direct,
                                                    max_depth=loaded.depths()[0])).run()
        err[direct] = [relmse(res.estimates[k], ref) for k in range(5)]
        assert res.estimates[1].mean() == pytest.approx(ref.mean(), rel=0.03)
        assert res.header["ppmrecon.direct"] == direct
    print("relMSE none / all:", err)
    assert all(a < 0.85 * b for a, b in zip(err["all"], err["none"])), err


def test_direct_light_skips_the_bsdf_sample_only_where_no_ray_reaches_an_emitter():
    """With only delta emitters (glossy_spot: a spot light) the BSDF sample of the direct
    light is exactly 0, so leaving it out changes no value; area lights keep it."""
    from ppmrecon.render.direct import direct_light, rays_can_hit_emitters
    from ppmrecon.render.eye import lambertian_table, trace_eye

    assert rays_can_hit_emitters(load_scene("cornell_caustics", resolution=(8, 8)).scene)
    loaded = load_scene("glossy_spot", resolution=(24, 24))
    assert not rays_can_hit_emitters(loaded.scene)
    gp = trace_eye(loaded.scene, loaded.scene.sensors()[0], 5, -1, 5, lambertian_table(loaded.scene))
    full, bad_full = direct_light(loaded.scene, gp, gp.found, 9)
    light, bad = direct_light(loaded.scene, gp, gp.found, 9, bsdf_sampling=False)
    assert float(dr.max(dr.max(full))[0]) > 0 and bad == bad_full == 0
    assert np.array_equal(np.asarray(light), np.asarray(full))
