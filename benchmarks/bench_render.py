"""Renderer benchmark (issues: multi-bandwidth SPPM, 17 renderer speed): speed ratios,
stage split, throughput, memory, and the convergence of ~z^1 to Mitsuba's path tracer.

    .venv/bin/python benchmarks/bench_render.py [--quick] [--out benchmarks/results]
    .venv/bin/python benchmarks/bench_render.py --variant cuda_ad_rgb --resolution 1280x720 --photons 100000

The second line is the GPU benchmark (issue 17: a 1280x720 five-chain pass with 0.1M
photons in <= 20 ms); it writes ``render_cuda_ad_rgb.{json,md}`` and stops with one line
where the variant cannot run. ``--before FILE`` (default: ``render_before17.json``, the
renderer before issue 17) adds that run's figures to the report.

Measured in one run on this machine, as ratios (SPEC section 8):
  * one five-chain pass vs one single-chain pass vs Mitsuba 3's `path` integrator at
    2 spp (same scene, resolution and max depth), with the per-stage split;
  * photons/s of the photon stage and gather points/s of the gather stage;
  * peak resident memory of a 1280x720 five-chain render per method (child processes);
  * relMSE of ~z^1 against a path-traced reference over >= 4 doublings of N (log-log
    plot, PNG) on the built-in `diffuse_glossy` scene (no caustics).
Writes `render.json`, `render.md` and `render_convergence.png` into --out (with a
non-default variant, resolution or photon count: `render_<variant>[_WxH_J].*`).
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
from ppmrecon.errors import BackendError  # noqa: E402


def pass_timings(scene_name: str, res: tuple[int, int], photons: int, passes: int) -> dict:
    import drjit as dr
    import mitsuba as mi

    from ppmrecon.render.integrator import Renderer, RenderSettings
    from ppmrecon.render.scene import load_scene

    loaded = load_scene(scene_name, resolution=res)
    depth = loaded.depths()[0]
    out: dict = {"scene": scene_name, "resolution": f"{res[0]}x{res[1]}", "photons": photons, "max_depth": depth,
                 "passes": passes, "load_before": os.getloadavg()[0]}
    renderers = {layout: Renderer(loaded.scene, RenderSettings(passes=passes + 1, photons=photons, layout=layout,
                                                               max_depth=depth))
                 for layout in ("single", "multi")}
    integrator = mi.load_dict({"type": "path", "max_depth": depth})  # Mitsuba's own, same film and depth

    def path_2spp(seed: int) -> tuple[float, float]:
        t, c = time.perf_counter(), time.process_time()
        dr.eval(mi.render(loaded.scene, integrator=integrator, spp=2, seed=seed))
        dr.sync_thread()
        return time.perf_counter() - t, time.process_time() - c

    first = {}
    for layout, r in renderers.items():
        r.run_pass()  # compiles kernels, builds the k-NN radii: not a steady-state pass
        first[layout] = r.seconds
    path_2spp(0)  # compiles
    # Interleaved, one pass of each and one path-traced frame per round, so that a change
    # of the machine's load hits all three alike; medians over the rounds.
    # CPU seconds (all threads of this process) as well: they move much less with the
    # load of other jobs than wall-clock seconds do.
    seconds: dict = {layout: [] for layout in renderers}
    cpu: dict = {layout: [] for layout in renderers}
    stages: dict = {layout: {k: [] for k in renderers[layout].stage_seconds} for layout in renderers}
    path_times, path_cpu = [], []
    for i in range(passes):
        for layout, r in renderers.items():
            t0, s0, c0 = r.seconds, dict(r.stage_seconds), time.process_time()
            r.run_pass()
            cpu[layout].append(time.process_time() - c0)
            seconds[layout].append(r.seconds - t0)
            for k, v in r.stage_seconds.items():
                stages[layout][k].append(v - s0[k])
        wall, c = path_2spp(i + 1)
        path_times.append(wall)
        path_cpu.append(c)
    for layout, r in renderers.items():
        per_stage = {k: float(np.median(v)) for k, v in stages[layout].items()}
        points = r.n_pixels * len(r._eye_streams())  # gather points per pass
        out[layout] = {"pass_seconds": float(np.median(seconds[layout])), "stages": per_stage,
                       "pass_cpu_seconds": float(np.median(cpu[layout])),
                       "first_pass_seconds": first[layout],
                       "photons_per_s": photons / per_stage["photons"],
                       "gather_points_per_s": points / per_stage["gather"]}
    out["path_2spp_seconds"] = float(np.median(path_times))
    out["path_2spp_cpu_seconds"] = float(np.median(path_cpu))
    out["cpu_ratio_multi_vs_path2spp"] = out["multi"]["pass_cpu_seconds"] / out["path_2spp_cpu_seconds"]
    out["cpu_ratio_multi_vs_single"] = out["multi"]["pass_cpu_seconds"] / out["single"]["pass_cpu_seconds"]
    out["ratio_multi_vs_path2spp"] = out["multi"]["pass_seconds"] / out["path_2spp_seconds"]
    out["ratio_multi_vs_single"] = out["multi"]["pass_seconds"] / out["single"]["pass_seconds"]
    # The same ratios round by round (their spread shows how much the load moved them).
    out["ratio_multi_vs_path2spp_per_round"] = [m / p for m, p in zip(seconds["multi"], path_times)]
    out["ratio_multi_vs_single_per_round"] = [m / s for m, s in zip(seconds["multi"], seconds["single"])]
    out["load_after"] = os.getloadavg()[0]
    return out


def peak_memory(width: int, height: int, passes: int, photons: int, method: str, variant: str) -> dict:
    """Peak RSS of `ppmrecon-render --method METHOD` at WxH in a fresh child process (its
    own measurement: RUSAGE_CHILDREN would report the largest child so far)."""
    out_file = Path("/tmp") / f"ppmrecon_mem_{os.getpid()}_{method}.exr"
    render = [sys.executable, "-m", "ppmrecon.render.cli", "--resolution", f"{width}x{height}",
              "--method", method, "--passes", str(passes), "--photons", str(photons), "--quiet",
              "--variant", variant, "--no-state", "--output", str(out_file)]
    probe = ("import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
    t = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", probe, *render], check=True, cwd=ROOT,
                          capture_output=True, text=True)
    wall = time.perf_counter() - t
    out_file.unlink(missing_ok=True)
    peak_kb = int(done.stdout.split()[-1])
    return {"method": method, "resolution": f"{width}x{height}", "passes": passes, "photons": photons,
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


METHODS = ("sppm", "cppm", "fppm", "appm")
#: Steady-state passes: the integrator's "start" stage (the first pass's k-NN radii) is 0.
STAGES = ("photons", "eye", "grid", "gather", "update")
#: Targets of issue 17 (ratios measured in one run).
TARGET_VS_PATH, TARGET_VS_SINGLE, TARGET_GPU_MS, TARGET_MEMORY_GB = 1.0, 1.3, 20.0, 4.0
DEFAULT_BEFORE = ROOT / "benchmarks" / "results" / "render_before17.json"


def _resolution(text: str) -> tuple[int, int]:
    w, _, h = text.lower().partition("x")
    if not (w.isdigit() and h.isdigit()) or int(w) <= 0 or int(h) <= 0:
        raise argparse.ArgumentTypeError(f"expected WxH, got '{text}'")
    return int(w), int(h)


def stage_rows(label: str, t: dict) -> list[str]:
    """Markdown rows (one per layout) of a pass_timings() result."""
    rows = []
    for layout in ("single", "multi"):
        s = t[layout]["stages"]
        rows.append(f"| {label} {layout} ({'1 chain' if layout == 'single' else '5 chains'}) | "
                    f"{t[layout]['pass_seconds']:.3f} | " + " | ".join(f"{s[k]:.3f}" for k in STAGES) + " |")
    return rows


def report_lines(report: dict, before: dict | None) -> list[str]:
    t, variant, q = report["timings"], report["variant"], report["quick"]
    lines = [f"# Renderer benchmark ({variant}, {report['cpus']} CPUs{', quick' if q else ''})", "",
             f"Scene `{t['scene']}` {t['resolution']}, {t['photons']} photons/pass, max depth {t['max_depth']}, "
             f"median of {t['passes']} rounds (one steady-state pass of each layout and one path-traced frame "
             "per round, interleaved, after the compiling first pass); stage columns: medians per stage; load average "
             f"{t['load_before']:.1f} before, {t['load_after']:.1f} after (other jobs share the machine: "
             "compare ratios, not seconds).", "",
             "| | seconds/pass | photons | eye | grid | gather | update |", "|---|---|---|---|---|---|---|"]
    comparable = before is not None and all(before["timings"].get(k) == t[k] for k in ("scene", "resolution", "photons"))
    if comparable:
        lines += stage_rows("before:", before["timings"])
    lines += stage_rows("now:" if comparable else "", t)
    lines += [f"| Mitsuba `path` 2 spp | {t['path_2spp_seconds']:.3f} | | | | | |", ""]
    if "path_2spp_cpu_seconds" in t:
        lines += [f"CPU seconds per pass (all threads; steadier under load): single {t['single']['pass_cpu_seconds']:.3f}, "
                  f"multi {t['multi']['pass_cpu_seconds']:.3f}, path 2 spp {t['path_2spp_cpu_seconds']:.3f}; "
                  f"ratios multi / single **{t['cpu_ratio_multi_vs_single']:.2f}x**, "
                  f"multi / path 2 spp **{t['cpu_ratio_multi_vs_path2spp']:.2f}x**.", ""]
    if comparable:
        bt = before["timings"]
        lines += [f"Before: the renderer before issue 17 ({DEFAULT_BEFORE.name if before is not None else ''}, "
                  f"measured in its own run: five chains / one chain {bt['ratio_multi_vs_single']:.2f}x, "
                  f"five-chain pass / path 2 spp {bt['ratio_multi_vs_path2spp']:.2f}x).", ""]
    spread = {k: (min(t.get(k + "_per_round", [0])), max(t.get(k + "_per_round", [0])))
              for k in ("ratio_multi_vs_single", "ratio_multi_vs_path2spp")}
    lines += [f"* five chains / one chain: **{t['ratio_multi_vs_single']:.2f}x** (target <= {TARGET_VS_SINGLE:.2f}; "
              "rounds %.2f-%.2f)" % spread["ratio_multi_vs_single"],
              f"* five-chain pass / path 2 spp: **{t['ratio_multi_vs_path2spp']:.2f}x** (target <= {TARGET_VS_PATH:.2f}; "
              "rounds %.2f-%.2f)" % spread["ratio_multi_vs_path2spp"]]
    for layout in ("single", "multi"):
        x = t[layout]
        lines.append(f"* {layout}: {x['photons_per_s'] / 1e6:.2f}M photons/s (photon stage), "
                     f"{x['gather_points_per_s'] / 1e6:.2f}M gather points/s (gather stage)")
    lines.append(f"* first pass (JIT compile + k-NN): single {t['single']['first_pass_seconds']:.2f}s, "
                 f"multi {t['multi']['first_pass_seconds']:.2f}s")
    if variant.startswith("cuda"):
        ms = t["multi"]["pass_seconds"] * 1e3
        lines.append(f"* five-chain pass at {t['resolution']}, {t['photons']} photons: **{ms:.1f} ms** "
                     f"(target <= {TARGET_GPU_MS:.0f} ms at 1280x720, 100000 photons)")
    if report.get("memory"):
        lines += ["", "Peak resident memory, five-chain render (own child process; host memory, also on "
                  "a GPU):", "", "| method | resolution | passes | photons | peak RSS (GB) |", "|---|---|---|---|---|"]
        for m in report["memory"]:
            lines.append(f"| {m['method']} | {m['resolution']} | {m['passes']} | {m['photons']} | {m['peak_rss_gb']:.2f} |")
        worst = max(m["peak_rss_gb"] for m in report["memory"])
        lines += ["", f"* largest: **{worst:.2f} GB** (target < {TARGET_MEMORY_GB:.0f} GB)"]
    lines += ["", "What issue 17 changed (images bit-identical to the renderer before it, every direct-light "
              "mode; the before rows come from that renderer's code run by this same benchmark):", "",
              "* gather: one packet load per photon (16-float records from the photon trace on); direct "
              "photons last in each bucket, skipped unvisited where direct light is estimated apart; "
              "Lambertian BSDFs evaluated once per gather point, and no BSDF call in the loop where every "
              "non-delta BSDF is Lambertian; one loop over photon/cell steps (a SIMD packet runs as long as "
              "its busiest lane, not the sum of each cell's busiest lane); cells stepped without integer "
              "division; cells the search sphere misses skipped; two photons of a cell per loop step "
              "(the cell step and the loop's own work shared: 9% off the gather kernels; 3 or 4 per "
              "step were slower);",
              "* grid: built on the device (stable `dr.argsort`, counting pass and prefix sum), no NumPy "
              "round trip; cells hashed in mixed 4x4x4 blocks, a block's cells in consecutive buckets "
              "(the plain Teschner hash put 16% of the occupied cells in a shared bucket, 7% now, and "
              "scattered neighbouring cells over the table: the gather kernels ~15% faster);",
              "* photons: one packet store per bounce into uninitialised buffers (only the valid flags are "
              "cleared), one packed copy of the segments; with direct light apart at every gather point "
              "the direct photons (d = 0, counted by no gather) are not stored after pass 1 (whose k-NN "
              "radii count them): the grid sorts ~30% fewer records;",
              "* eye: gather points keep the preliminary intersection of the eye walk's own trace (no "
              "second trace of the last ray), each kernel recomputes the surface interaction; the "
              "G-buffer values (albedo, normals, Lambertian flag) come from the walk's own surface "
              "interaction (eye trace ~11% faster);",
              "* update: every accumulator in one kernel, and that kernel is the gather's (the search "
              "loops are evaluated with the Welford updates that consume their sums: no write and re-read "
              "of each chain's flux), so the gather column includes the accumulators and update is the "
              "bandwidth controller alone; the non-finite counts stay on the device and are read once "
              "per pass.",
              "",
              "Not done: the cell size still comes from a host-side quantile of the radii (one read of the "
              "largest radii per pass, ~2 ms) and the photon trace reads its segment sizes (`dr.compress`). "
              "Tried and dropped, no gain in CPU time on this machine: gather points in 8x8 pixel tiles "
              "(coherent packets, but the permutation cost as much); the eye paths and their "
              "direct light fused into one kernel; the direct light computed in the gather kernel "
              "(~9% slower in kernel time); one accumulator kernel per hit point instead of both search "
              "loops in one (no gain, yet the renderer uses it since: with both search loops in one kernel "
              "Dr.Jit 1.5's LLVM backend intermittently emitted the BSDF callable twice and aborted; the "
              "two cost within 2% of each other, and the figures above were measured with one kernel); a symbolic `if` around the photon visit; grid cells 0.5x-1.5x the current "
              "edge (0.5x: the five-chain gather 2.7x slower, the cell steps cost as much as photon "
              "steps; 1.25x-1.5x: flat). Where the five-chain extra goes: the ~z search at hit point B "
              "reaches the largest radius and costs ~2x the ~y search (its four chains' sums cost "
              "almost nothing: one chain at r_z4 measured the same), and B's eye path and direct "
              "light ~2x 22 ms.",
              "",
              "Measured while looking for more (kernel history, 512x512, per pass): the ~z gather at B "
              "visits 41 photons per gather point to find 9.4 inside r_z4, the ~y gather at A 12.5 to find "
              "0.6; a photon step costs ~6 ns per gather point and an empty cell step as much. Sorting "
              "the gather points by their step count (an oracle) made both gathers slower (they are "
              "bound by memory locality, not by idle SIMD lanes), and 4x4 to 32x32 pixel tiles changed "
              "nothing; a finer grid for the ~y search (cell 1-3x its radius) was slower or equal and "
              "costs a second sort; 8-float photon records (half the bytes) gained ~10% in a mock-up, not "
              "worth the rounding of directions and normals; photon segments of 2-5 bounces instead of 8 "
              "were slower or equal; photons grouped by octant of their cell, with a skip to the next "
              "group past the octants a search box misses, was 13% slower (a cell holds ~3 photons, "
              "so a group skip saves no step). The photon trace is one kernel (31 of ~37 ms), the eye walk ~15 ms "
              "and its direct light ~12 ms per hit point: at the throughputs above, a five-chain pass (two eye paths with MIS direct light, 2^17 photon paths, two "
              "searches) costs more than two full path-traced samples per pixel on this CPU, so the "
              "1.0x target is out of reach without a different search (or a GPU)."]
    conv = report.get("convergence")
    if conv:
        lines += ["", f"Convergence of ~z^1 on `diffuse_glossy` {conv['resolution']} against {conv['reference']}:", "",
                  "| N | seconds | relMSE ~y | ~z^1 | ~z^4 |", "|---|---|---|---|---|"]
        for c in conv["curve"]:
            lines.append(f"| {c['passes']} | {c['seconds']:.2f} | {c['relmse']['y']:.4f} | "
                         f"{c['relmse']['z1']:.4f} | {c['relmse']['z4']:.4f} |")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller sizes (a few minutes)")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb if usable, else llvm_ad_rgb)")
    ap.add_argument("--resolution", type=_resolution, default=None, metavar="WxH",
                    help="film of the pass timings (default 512x512, --quick 256x256)")
    ap.add_argument("--photons", type=int, default=1 << 17, help="photons per pass (default 131072)")
    ap.add_argument("--passes", type=int, default=None, help="timed passes (default 8, --quick 4)")
    ap.add_argument("--timings-only", action="store_true", help="skip the memory and convergence runs")
    ap.add_argument("--before", type=Path, default=DEFAULT_BEFORE,
                    help="an earlier render.json whose timings the report shows alongside")
    args = ap.parse_args()
    try:
        variant = choose_variant(args.variant)
    except BackendError as exc:
        raise SystemExit(f"bench_render: {exc}") from None
    q = args.quick
    res = args.resolution or ((256, 256) if q else (512, 512))
    default_run = args.resolution is None and args.photons == 1 << 17 and variant == "llvm_ad_rgb"
    name = "render" if default_run else (
        f"render_{variant}" if (args.resolution is None and args.photons == 1 << 17)
        else f"render_{variant}_{res[0]}x{res[1]}_{args.photons}")
    args.out.mkdir(parents=True, exist_ok=True)
    report: dict = {"variant": variant, "cpus": os.cpu_count(), "quick": q,
                    "timings": pass_timings("cornell_caustics", res, args.photons, args.passes or (4 if q else 8))}
    if not args.timings_only:
        report["memory"] = [peak_memory(1280, 720, 1 if q else 2, 1 << 17, m, variant) for m in METHODS]
        report["convergence"] = convergence(32 if q else 64, 1 << 15, 64 if q else 128, 1024 if q else 4096)
    (args.out / f"{name}.json").write_text(json.dumps(report, indent=2))
    if report.get("convergence"):
        plot(report["convergence"], args.out / f"{name}_convergence.png")
    before = json.loads(args.before.read_text()) if args.before and args.before.exists() else None
    lines = report_lines(report, before)
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
