"""Where do a render's fireflies come from? (issue 12: find the source before hiding it.)

Renders a scene with the multi-bandwidth renderer, records every per-pass pixel estimate
E_i that exceeds ``--factor`` times the image's mean per-pass estimate (chains ~y and
~z^4), then replays the worst pass (every random number derives from seed and pass
index, so pass i can be rebuilt exactly) and lists, for the worst pixel, the photons
inside its radius with the factors of their contribution

    f_cos / cos_g * Phi_p = f(x, w_o, w_p) * (|w_p . n_s| / |w_p . n_g|) * Phi_p

(BSDF, shading-normal correction of adjoint transport, photon power relative to the
mean emitted power), the photon's bounce index and the eye path's throughput.

    python benchmarks/firefly_probe.py ../shared/scenes/box/box.xml --resolution 200 --passes 64
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("scene")
    p.add_argument("--resolution", type=int, default=200)
    p.add_argument("--passes", type=int, default=64)
    p.add_argument("--photons", type=int, default=1 << 17)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--factor", type=float, default=100.0, help="firefly: E_i > factor x the image's mean E_i")
    p.add_argument("--top", type=int, default=8, help="photons listed for the worst pixel")
    p.add_argument("--json", default=None, help="also write the findings here")
    args = p.parse_args(argv)

    from ppmrecon.backend import choose_variant

    choose_variant()
    import drjit as dr
    import mitsuba as mi

    from ppmrecon.render.integrator import Renderer, RenderSettings
    from ppmrecon.render.photons import trace_photons
    from ppmrecon.render.rng import EYE_A, EYE_B, PHOTONS, stream_seed
    from ppmrecon.render.eye import trace_eye
    from ppmrecon.render.scene import load_scene

    loaded = load_scene(args.scene, resolution=args.resolution)
    max_depth, rr_depth = loaded.depths()
    settings = RenderSettings(passes=args.passes, photons=args.photons, seed=args.seed,
                              max_depth=max_depth, rr_depth=rr_depth)
    r = Renderer(loaded.scene, settings, scene_name=loaded.name)
    h, w = r.height, r.width
    prev = {c: np.zeros((h, w, 3)) for c in (0, 4)}
    radii_before: dict[int, list[np.ndarray]] = {1: []}
    events: list[dict] = []

    def on_pass(rr: Renderer) -> None:
        i = rr.passes_done
        res = rr.result()
        for c in (0, 4):
            mean = res.estimates[c].astype(np.float64)
            e_i = mean * i - prev[c] * (i - 1)          # this pass's estimate
            prev[c] = mean
            lum = e_i.mean(-1)
            med = max(float(lum.mean()), 1e-12)
            for flat in np.flatnonzero(lum > args.factor * med):
                events.append({"pass": i, "chain": "y" if c == 0 else "z4", "pixel": [int(flat // w), int(flat % w)],
                               "E": float(lum.flat[flat]), "image_mean": med})
        radii_before[i + 1] = [np.asarray(x) for x in rr.controller.radii()]

    radii_before[1] = None  # filled after pass 1 starts (k-NN radii); recomputed below
    r.run(on_pass)
    print(f"{len(events)} per-pass firefly pixel estimates (> {args.factor:g} x median) in "
          f"{args.passes} passes; nonfinite dropped: {r.nonfinite}")
    if not events:
        return 0
    worst = max(events, key=lambda e: e["E"] / e["image_mean"])
    by_pass = {}
    for e in events:
        by_pass.setdefault(e["chain"], 0)
        by_pass[e["chain"]] += 1
    print("events by chain:", by_pass, " worst:", worst)

    i, (row, col) = worst["pass"], worst["pixel"]
    chain = 0 if worst["chain"] == "y" else 4
    pm = trace_photons(loaded.scene, args.photons, stream_seed(args.seed, i, PHOTONS), max_depth, rr_depth)
    gp = trace_eye(loaded.scene, r.sensor, stream_seed(args.seed, i, EYE_A if chain == 0 else EYE_B),
                   max_depth, rr_depth)
    radii = radii_before.get(i)
    if radii is None:
        print("worst event is in pass 1: radii of pass 1 are not replayed; rerun with more passes")
        return 0
    lane = row * w + col
    radius = float(radii[chain][lane])
    x = np.asarray(gp.si.p)[:, lane]
    ps = np.asarray(pm.p)
    d2 = ((ps - x[:, None]) ** 2).sum(0)
    inside = np.flatnonzero(d2 < radius ** 2)
    idx = mi.UInt32(np.full(len(inside), lane, np.uint32))
    si = dr.gather(type(gp.si), gp.si, idx)
    wp = -mi.Vector3f(np.asarray(pm.d)[:, inside])
    bsdf = si.bsdf()
    f_cos = np.asarray(bsdf.eval(mi.BSDFContext(), si, si.to_local(wp)))
    cos_g = np.abs(np.asarray(dr.dot(wp, si.n)))
    cos_s = np.abs(np.asarray(dr.dot(wp, si.sh_frame.n)))
    power = np.asarray(pm.power)[:, inside]
    mean_power = float(np.asarray(pm.power).mean()) * len(pm) / args.photons
    contrib = (f_cos / np.maximum(cos_g, 1e-4) * power).mean(0)
    emitted = float(np.asarray(gp.emitted)[:, lane].mean())
    photon_part = float(np.asarray(gp.beta)[:, lane].mean()) * contrib.sum() / (np.pi * radius ** 2) / args.photons
    print(f"decomposition of E = {worst['E']:.4g}: emission seen along the eye path {emitted:.4g}, "
          f"photon part ~{photon_part:.4g} (constant kernel)")
    order = np.argsort(-contrib)[: args.top]
    beta = np.asarray(gp.beta)[:, lane]
    print(f"pass {i} pixel ({row},{col}) chain {worst['chain']}: radius {radius:.3g}, {len(inside)} photons inside, "
          f"eye throughput {beta.round(3).tolist()}, eye segments {int(np.asarray(gp.segments)[lane])}, "
          f"gather BSDF flags {int(np.asarray(bsdf.flags())[0]) if dr.width(bsdf.flags()) > 1 else 'n/a'}")
    print(f"{'photon':>8} {'contrib':>10} {'power/mean':>10} {'f/pi?':>8} {'cos_s':>8} {'cos_g':>8} {'cos_s/g':>8} {'depth':>5}")
    rows = []
    for o in order:
        k = inside[o]
        f = f_cos[:, o].mean() / max(cos_s[o], 1e-8)
        rows.append({"contrib": float(contrib[o]), "power_rel": float(power[:, o].mean() / mean_power),
                     "f": float(f), "cos_s": float(cos_s[o]), "cos_g": float(cos_g[o]),
                     "depth": int(np.asarray(pm.depth)[k])})
        print(f"{k:>8} {contrib[o]:>10.3g} {rows[-1]['power_rel']:>10.3g} {f:>8.3g} {cos_s[o]:>8.3g} "
              f"{cos_g[o]:>8.3g} {cos_s[o] / max(cos_g[o], 1e-8):>8.3g} {rows[-1]['depth']:>5}")
    share = contrib[order[0]] / max(contrib.sum(), 1e-30)
    print(f"the top photon is {share:.1%} of the pixel's pass sum")
    if args.json:
        from ppmrecon.fileio import write_json

        write_json(args.json, {"events": len(events), "worst": worst, "photons": rows, "top_share": float(share)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
