"""Renderer benchmark (issue: multi-bandwidth SPPM): speed ratios, stage split, memory,
and the convergence of ~z^1 to Mitsuba's own path tracer.

    .venv/bin/python benchmarks/bench_render.py [--quick] [--out benchmarks/results]

Measured in one run on this machine, as ratios (SPEC section 8):
  * one five-chain pass vs one single-chain pass vs Mitsuba 3's `path` integrator at
    2 spp (same scene, resolution and max depth), with the per-stage split;
  * peak resident memory of a 1280x720 five-chain render (in a child process);
  * relMSE of ~z^1 against a path-traced reference over >= 4 doublings of N (log-log
    plot, PNG) on the built-in `diffuse_glossy` scene (no caustics).
Writes `render.json`, `render.md` and `render_convergence.png` into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon.backend import choose_variant  # noqa: E402


def pass_timings(scene_name: str, res: int, photons: int, passes: int) -> dict:
    import drjit as dr
    import mitsuba as mi

    from ppmrecon.render.integrator import Renderer, RenderSettings
    from ppmrecon.render.scene import load_scene

    loaded = load_scene(scene_name, resolution=(res, res))
    depth = loaded.depths()[0]
    out: dict = {"scene": scene_name, "resolution": f"{res}x{res}", "photons": photons, "max_depth": depth}
    for layout in ("single", "multi"):
        r = Renderer(loaded.scene, RenderSettings(passes=passes + 1, photons=photons, layout=layout,
                                                  max_depth=depth))
        r.run_pass()  # compiles kernels, builds the k-NN radii: not a steady-state pass
        first = dict(r.stage_seconds)
        t0 = r.seconds
        for _ in range(passes):
            r.run_pass()
        per_stage = {k: (v - first[k]) / passes for k, v in r.stage_seconds.items()}
        out[layout] = {"pass_seconds": (r.seconds - t0) / passes, "stages": per_stage,
                       "first_pass_seconds": t0}
    # Mitsuba's own path tracer, same film and depth, 2 spp (after a compiling call).
    integrator = mi.load_dict({"type": "path", "max_depth": depth})
    img = mi.render(loaded.scene, integrator=integrator, spp=2)
    dr.eval(img)
    dr.sync_thread()
    times = []
    for seed in range(max(3, passes // 2)):
        t = time.perf_counter()
        img = mi.render(loaded.scene, integrator=integrator, spp=2, seed=seed + 1)
        dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    out["path_2spp_seconds"] = float(np.median(times))
    out["ratio_multi_vs_path2spp"] = out["multi"]["pass_seconds"] / out["path_2spp_seconds"]
    out["ratio_multi_vs_single"] = out["multi"]["pass_seconds"] / out["single"]["pass_seconds"]
    return out


def peak_memory(width: int, height: int, passes: int, photons: int) -> dict:
    """Peak RSS of `ppmrecon-render` at WxH in a fresh child process."""
    out_file = Path("/tmp") / f"ppmrecon_mem_{os.getpid()}.exr"
    cmd = [sys.executable, "-m", "ppmrecon.render.cli", "--resolution", f"{width}x{height}",
           "--passes", str(passes), "--photons", str(photons), "--quiet", "--output", str(out_file)]
    t = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT)
    wall = time.perf_counter() - t
    out_file.unlink(missing_ok=True)
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return {"resolution": f"{width}x{height}", "passes": passes, "photons": photons,
            "peak_rss_gb": peak_kb / 1024 ** 2, "wall_seconds": wall}


def convergence(res: int, photons: int, max_passes: int, ref_spp: int) -> dict:
    import mitsuba as mi

    from ppmrecon.metrics import relmse
    from ppmrecon.render.integrator import Renderer, RenderSettings
    from ppmrecon.render.scene import load_scene

    loaded = load_scene("diffuse_glossy", resolution=(res, res))
    t = time.perf_counter()
    ref = np.asarray(mi.render(loaded.scene, spp=ref_spp), np.float32)
    ref_seconds = time.perf_counter() - t
    r = Renderer(loaded.scene, RenderSettings(passes=max_passes, photons=photons, seed=7,
                                              max_depth=loaded.depths()[0]))
    curve: list[dict] = []

    def on_pass(rr):
        n = rr.passes_done
        if n & (n - 1) == 0:
            est = rr.result().estimates
            curve.append({"passes": n, "seconds": rr.seconds,
                          "relmse": {name: relmse(est[k], ref) for k, name in enumerate(("y", "z1", "z2", "z3", "z4"))}})

    r.run(on_pass)
    return {"scene": "diffuse_glossy", "resolution": f"{res}x{res}", "photons": photons,
            "reference": f"Mitsuba path, {ref_spp} spp ({ref_seconds:.1f}s)", "curve": curve}


def plot(conv: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [c["passes"] for c in conv["curve"]]
    fig, ax = plt.subplots(figsize=(5, 3.6))
    for name in ("y", "z1", "z4"):
        ax.loglog(n, [c["relmse"][name] for c in conv["curve"]], "o-", label=f"~{name}")
    ref = conv["curve"][0]["relmse"]["z1"]
    ax.loglog(n, [ref * (n[0] / k) ** (2 / 3) for k in n], "k--", lw=0.8, label="N^-2/3")
    ax.set_xlabel("passes N")
    ax.set_ylabel("relMSE vs path tracer")
    ax.set_title(f"{conv['scene']} {conv['resolution']}, {conv['photons']} photons/pass")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (a few minutes)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    variant = choose_variant()
    q = args.quick
    report = {"variant": variant, "cpus": os.cpu_count(), "quick": q,
              "timings": pass_timings("cornell_caustics", 256 if q else 512, 1 << 17, 4 if q else 8),
              "memory": peak_memory(1280, 720, 2 if q else 4, 1 << 17),
              "convergence": convergence(32 if q else 64, 1 << 15, 64 if q else 128, 1024 if q else 4096)}
    (args.out / "render.json").write_text(json.dumps(report, indent=2))
    plot(report["convergence"], args.out / "render_convergence.png")

    t = report["timings"]
    lines = [f"# Renderer benchmark ({variant}, {os.cpu_count()} CPUs{', quick' if q else ''})", "",
             f"Scene `{t['scene']}` {t['resolution']}, {t['photons']} photons/pass, max depth {t['max_depth']} "
             "(steady-state passes, after the compiling first pass).", "",
             "| | seconds/pass | photons | eye | grid | gather | update |", "|---|---|---|---|---|---|---|"]
    for layout in ("single", "multi"):
        s = t[layout]["stages"]
        lines.append(f"| {layout} ({'1 chain' if layout == 'single' else '5 chains'}) | {t[layout]['pass_seconds']:.3f} | "
                     + " | ".join(f"{s[k]:.3f}" for k in ("photons", "eye", "grid", "gather", "update")) + " |")
    lines += [f"| Mitsuba `path` 2 spp | {t['path_2spp_seconds']:.3f} | | | | | |", "",
              f"* five chains / one chain: **{t['ratio_multi_vs_single']:.2f}x** (target <= 1.20)",
              f"* five-chain pass / path 2 spp: **{t['ratio_multi_vs_path2spp']:.2f}x** (target <= 1.00)",
              f"* first pass (JIT compile + k-NN): single {t['single']['first_pass_seconds']:.2f}s, "
              f"multi {t['multi']['first_pass_seconds']:.2f}s",
              f"* peak RSS, {report['memory']['resolution']} five-chain render ({report['memory']['passes']} passes): "
              f"**{report['memory']['peak_rss_gb']:.2f} GB** (target < 4 GB)", "",
              f"Convergence of ~z^1 on `diffuse_glossy` {report['convergence']['resolution']} "
              f"against {report['convergence']['reference']}:", "",
              "| N | seconds | relMSE ~y | ~z^1 | ~z^4 |", "|---|---|---|---|---|"]
    for c in report["convergence"]["curve"]:
        lines.append(f"| {c['passes']} | {c['seconds']:.2f} | {c['relmse']['y']:.4f} | {c['relmse']['z1']:.4f} | {c['relmse']['z4']:.4f} |")
    (args.out / "render.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
