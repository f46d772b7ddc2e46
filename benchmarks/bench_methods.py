"""Bandwidth-controller study (issues 5, 16): SPPM vs CPPM vs FPPM vs APPM.

    .venv/bin/python benchmarks/bench_methods.py [--quick] [--scenes /work/shared/scenes]
                                                 [--out benchmarks/results]

Measured on this machine in one run (2 shared CPU cores: timings are noisy):
  * relMSE (SPEC section 7) against passes N = 1, 2, 4, ... (log-log) of the
    conventional single-bandwidth layout (one chain at the second-smallest initial
    bandwidth, one eye path per pixel) for each method, on the three literature scenes
    box, cornell-box and cornell-box-spotlight (from --scenes) and the built-in
    water_caustic, each against a reference rendered by our SPPM (same layout, photons
    and depth, another seed) with ``ref_factor`` times more passes;
  * the five-chain layout on the textured spotlight: relMSE of ~y, ~z^1, ~z^4 for SPPM,
    CPPM and FPPM (r_min_frac 0.05, 0.25 = default, 1.0; and per channel), with how
    many radii shrank and how many sit at FPPM's lower bound (the effect of r_min);
  * seconds per pass of each method relative to SPPM in the production five-chain
    layout (steady state, interleaved repetitions, median), and in the single layout;
  * peak resident memory of 1280x720 five-chain renders (FPPM, FPPM per channel, CPPM,
    SPPM), each in its own child process (ru_maxrss).
Writes methods.json, methods.md and methods.png into --out. References are cached in
--out/refs (EXR, ignored by git) and reused when the same settings come again.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon.backend import choose_variant  # noqa: E402

METHODS = ("sppm", "cppm", "fppm", "appm")
LITERATURE = (("box", "box/box.xml"), ("cornell-box", "cornell-box/cbox_SPPM.xml"),
              ("cornell-box-spotlight", "cornell-box-spotlight/cbox_SPPM.xml"))
#: relMSE's +0.01 makes it an absolute MSE on dark images (the spotlight scene's mean is
#: ~0.005): we also report it with estimate and reference scaled to this mean.
EXPOSURE_MEAN = 0.5


def scene_list(scenes_dir: Path) -> list[tuple[str, str]]:
    out = [(name, str(scenes_dir / rel)) for name, rel in LITERATURE]
    missing = [p for _, p in out if not Path(p).exists()]
    if missing:
        raise SystemExit(f"bench_methods: missing scene files: {', '.join(missing)} (see --scenes)")
    return out + [("water_caustic", "water_caustic")]


def load(spec: str, width: int):
    from ppmrecon.render.scene import load_scene

    loaded = load_scene(spec, resolution=width)  # one width keeps the aspect ratio
    depth = loaded.depths()[0]  # the scene's own (issue 20: no silent cap)
    return loaded, depth


def renderer(loaded, depth: int, method: str, layout: str, passes: int, photons: int, seed: int,
             params: dict | None = None):
    from ppmrecon.render.integrator import Renderer, RenderSettings

    return Renderer(loaded.scene, RenderSettings(method=method, layout=layout, passes=passes, photons=photons,
                                                 seed=seed, max_depth=depth, method_params=params or {}),
                    scene_name=loaded.name)


def renderer_code_hash() -> str:
    """Short hash of the renderer package's source files."""
    digest = hashlib.sha1()
    for f in sorted((ROOT / "ppmrecon" / "render").glob("*.py")):
        digest.update(f.read_bytes())
    return digest.hexdigest()[:10]


def reference(name: str, loaded, depth: int, passes: int, photons: int, cache: Path) -> dict:
    """SPPM, single layout, seed 1000: the image, the noise part of its own relMSE
    (mean over pixels of Var[mean] / (mean^2 + 0.01)) and its render time."""
    from ppmrecon import buffers as B

    cache.mkdir(parents=True, exist_ok=True)
    size = f"{loaded.width}x{loaded.height}"
    # The renderer's source is part of the key: a change to it (photon tracing, gather)
    # must not be compared against a reference from the old code.
    path = cache / f"{name}_{size}_{photons}ph_{passes}p_d{depth}_{renderer_code_hash()}.exr"
    if path.exists():
        channels, header = B.read_channels(path)
        rgb = np.stack([channels[c] for c in B.RGB], -1)
        return {"image": rgb, "passes": passes, "seconds": float(header.get("ppmrecon.render_seconds", 0.0)),
                "noise_relmse": float(header.get("bench.noise_relmse", np.nan)), "cached": True}
    r = renderer(loaded, depth, "sppm", "single", passes, photons, seed=1000)
    res = r.run()
    rgb = res.estimates[0]
    noise = float(np.mean(res.variances[0] / (rgb.mean(-1) ** 2 + 0.01)))
    header = dict(res.header)
    header["bench.noise_relmse"] = noise
    B.write_rgb(path, rgb, header=header)
    return {"image": rgb, "passes": passes, "seconds": res.seconds, "noise_relmse": noise, "cached": False}


def convergence(loaded, depth: int, ref: np.ndarray, method: str, max_passes: int, photons: int,
                params: dict | None = None) -> dict:
    """relMSE of the single-layout image at N = 1, 2, 4, ..., max_passes (seed 0)."""
    from ppmrecon.metrics import relmse

    r = renderer(loaded, depth, method, "single", max_passes, photons, seed=0, params=params)
    curve: list[dict] = []
    radius: dict = {}

    scale = EXPOSURE_MEAN / max(float(ref.mean()), 1e-12)

    def on_pass(rr):
        n = rr.passes_done
        if n == 1:
            radius["r1"] = np.asarray(rr.controller.radii()[0]).copy()
        if n & (n - 1) == 0:
            est = rr.result().estimates[0]
            curve.append({"passes": n, "seconds": rr.seconds, "relmse": relmse(est, ref),
                          "relmse_exposed": relmse(est * scale, ref * scale)})

    r.run(on_pass)
    r_end = np.asarray(r.controller.radii()[0])
    ok = radius["r1"] > 0
    return {"curve": curve, "seconds_per_pass": r.seconds / r.passes_done,
            "radius_ratio_median": float(np.median(r_end[ok] / radius["r1"][ok])),
            "radius_unchanged_frac": float(np.mean(r_end[ok] >= radius["r1"][ok] * (1 - 1e-6)))}


def five_chain(loaded, depth: int, ref: np.ndarray, method: str, passes: int, photons: int,
               params: dict | None = None) -> dict:
    """One five-chain (multi layout) render: relMSE of ~y, ~z^1, ~z^4 after ``passes``
    passes, the median r_N / r_1, the share of radii that ever shrank and, for FPPM, the
    share below r_min (where Eq. 21's bound governs)."""
    from ppmrecon.metrics import relmse

    r = renderer(loaded, depth, method, "multi", passes, photons, seed=0, params=params)
    r.run_pass()
    r1 = [np.asarray(x).copy() for x in r.controller.radii()]
    res = r.run()
    row: dict = {"method": method, "params": params or {}, "seconds_per_pass": res.seconds / res.passes}
    scale = EXPOSURE_MEAN / max(float(ref.mean()), 1e-12)
    for k, label in ((0, "y"), (1, "z1"), (4, "z4")):
        ratio = res.radii[k].ravel() / r1[k]
        row[label] = {"relmse": relmse(res.estimates[k], ref),
                      "relmse_exposed": relmse(res.estimates[k] * scale, ref * scale),
                      "radius_ratio_median": float(np.median(ratio)), "shrunk": float(np.mean(ratio < 1 - 1e-6))}
        if method == "fppm":
            # Below r_min the radius is governed by the bound r_min (i + 1)^((alpha - 1) / 2)
            # (Eq. 21): every shrink there was clamped or nearly so.
            row[label]["below_r_min"] = float(np.mean(ratio < r.controller.r_min_frac * (1 - 1e-6)))
    return row


def pass_cost(loaded, depth: int, photons: int, reps: int, passes: int) -> dict:
    """Steady-state seconds per pass of the five-chain (multi) layout, methods
    interleaved, median over ``reps`` repetitions of ``passes`` passes."""
    rs = {m: renderer(loaded, depth, m, "multi", 2 + reps * passes, photons, seed=3) for m in METHODS}
    for r in rs.values():  # compile kernels, k-NN radii
        r.run_pass()
        r.run_pass()
    times: dict[str, list[float]] = {m: [] for m in METHODS}
    gather: dict[str, list[float]] = {m: [] for m in METHODS}
    for _ in range(reps):
        for m, r in rs.items():
            t0, g0 = r.seconds, r.stage_seconds["gather"] + r.stage_seconds["update"]
            for _ in range(passes):
                r.run_pass()
            times[m].append((r.seconds - t0) / passes)
            gather[m].append((r.stage_seconds["gather"] + r.stage_seconds["update"] - g0) / passes)
    out = {m: {"seconds_per_pass": float(np.median(times[m])),
               "gather_update_seconds": float(np.median(gather[m]))} for m in METHODS}
    for m in METHODS:
        out[m]["ratio_vs_sppm"] = out[m]["seconds_per_pass"] / out["sppm"]["seconds_per_pass"]
    return out


def peak_memory(method: str, params: list[str], width: int, height: int, passes: int, photons: int) -> dict:
    """Peak RSS of one `ppmrecon-render` run in a fresh child process: an intermediate
    Python process runs it and reports RUSAGE_CHILDREN (its only child)."""
    out_file = Path("/tmp") / f"ppmrecon_bench_mem_{os.getpid()}.exr"
    cmd = [sys.executable, "-m", "ppmrecon.render.cli", "--method", method, *params, "--resolution",
           f"{width}x{height}", "--passes", str(passes), "--photons", str(photons), "--quiet",
           "--output", str(out_file)]
    probe = ("import resource, subprocess, sys, time; t = time.perf_counter(); "
             "subprocess.run(sys.argv[1:], check=True); "
             "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss, time.perf_counter() - t)")
    res = subprocess.run([sys.executable, "-c", probe, *cmd], check=True, cwd=ROOT, capture_output=True, text=True)
    out_file.unlink(missing_ok=True)
    kb, wall = res.stdout.split()[-2:]
    return {"method": method + (" " + " ".join(params) if params else ""), "resolution": f"{width}x{height}",
            "passes": passes, "photons": photons, "peak_rss_gb": int(kb) / 1024 ** 2, "wall_seconds": float(wall)}


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(report["convergence"])
    fig, axes = plt.subplots(1, len(scenes), figsize=(4.2 * len(scenes), 3.6))
    for ax, name in zip(np.atleast_1d(axes), scenes):
        data = report["convergence"][name]
        for m, style in zip(METHODS, ("o-", "s-", "^-", "d-")):
            c = data["methods"][m]["curve"]
            ax.loglog([p["passes"] for p in c], [p["relmse"] for p in c], style, ms=3, label=m.upper())
        n = [p["passes"] for p in data["methods"]["sppm"]["curve"]]
        e0 = data["methods"]["sppm"]["curve"][0]["relmse"]
        ax.loglog(n, [e0 * (n[0] / k) ** (2 / 3) for k in n], "k:", lw=0.8, label="N^-2/3")
        ax.loglog(n, [e0 * (n[0] / k) for k in n], "k--", lw=0.8, label="N^-1")
        ax.axhline(data["reference"]["noise_relmse"], color="grey", lw=0.8, ls="-.", label="ref. noise")
        ax.set_title(f"{name} {data['resolution']}", fontsize=9)
        ax.set_xlabel("passes N")
    np.atleast_1d(axes)[0].set_ylabel("relMSE vs SPPM reference")
    np.atleast_1d(axes)[0].legend(fontsize=7)
    fig.suptitle(f"single-bandwidth layout, {report['settings']['photons']} photons/pass", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def markdown(report: dict) -> str:
    s = report["settings"]
    lines = [f"# SPPM vs CPPM vs FPPM vs APPM ({report['variant']}, {report['cpus']} CPUs shared with other jobs"
             f"{', quick' if s['quick'] else ''})", "",
             f"Single-bandwidth layout (one chain at the second-smallest initial bandwidth, one eye path), "
             f"{s['photons']} photons/pass, width {s['width']} (aspect kept), the scene's path depth, "
             f"seed 0. Reference: our SPPM, same layout, {s['ref_passes']} passes "
             f"(seed 1000). CPPM: significance 0.05, k 0.8, beta 1.5625, threshold k-NN 20. FPPM: "
             f"significance 0.01, k 0.7, alpha 2/3, r_min = {s['r_min_frac']} r_1, luminance. APPM: "
             f"defaults (r in [0.1, 2] r_1 N^(-1/6), r'_max 2 r_ref, debiased Laplacian z 2, E[psi^2]); "
             f"its 'r_1' columns are the radii after pass 1, on APPM's bound r_max 2^(-1/6) where the "
             f"Laplacian is flat.", "",
             "relMSE against passes N (log-log plot: methods.png); `ref noise` is the noise part of the "
             "reference's own relMSE (its Welford variance), a floor below which differences mean nothing.", ""]
    for name, data in report["convergence"].items():
        ns = [p["passes"] for p in data["methods"]["sppm"]["curve"]]
        lines += [f"## {name} ({data['resolution']}; ref noise {data['reference']['noise_relmse']:.2e}, "
                  f"ref {data['reference']['seconds']:.0f}s)", "",
                  "| method | " + " | ".join(f"N={n}" for n in ns) + " | s/pass | median r_N/r_1 | r kept |",
                  "|---|" + "---|" * (len(ns) + 3)]
        for m in METHODS:
            d = data["methods"][m]
            lines.append(f"| {m.upper()} | " + " | ".join(f"{p['relmse']:.3g}" for p in d["curve"])
                         + f" | {d['seconds_per_pass']:.3f} | {d['radius_ratio_median']:.3f} | "
                         f"{d['radius_unchanged_frac']:.0%} |")
        best = min(METHODS, key=lambda m: data["methods"][m]["curve"][-1]["relmse"])
        exposed = ", ".join(f"{m.upper()} {data['methods'][m]['curve'][-1]['relmse_exposed']:.3g}" for m in METHODS)
        lines += ["", f"Lowest relMSE at N={ns[-1]}: **{best.upper()}**. Exposure-normalised relMSE "
                      f"(images scaled to reference mean {EXPOSURE_MEAN}) at N={ns[-1]}: {exposed}.", ""]
    for fc in report.get("five_chain", []):
        lines += [f"## Five-chain layout ({fc['scene']}, N={fc['passes']}; FPPM's r_min varied)", "",
                  "Same reference as above. `shrunk`: radii that ever shrank; `< r_min`: FPPM radii below "
                  "r_min = r_min_frac r_1, where the bound r_min (i+1)^((alpha-1)/2) of Eq. 21 governs; "
                  f"`exposed`: relMSE with the images scaled to reference mean {EXPOSURE_MEAN}.", "",
                  "| method | relMSE ~y | ~z^1 | ~z^4 | exposed ~z^1 | median r/r_1 ~y | ~z^4 | shrunk ~y | ~z^4 "
                  "| < r_min ~y | ~z^4 |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in fc["rows"]:
            p = row["params"]
            label = row["method"].upper()
            if row["method"] == "appm" and p:
                label += " as printed (Var[psi], E[Lap]^2)"
            if row["method"] == "fppm":
                label += f" r_min_frac {p.get('r_min_frac', report['settings']['r_min_frac'])}"
                label += " per channel" if p.get("per_channel") else ""
            y, z1, z4 = row["y"], row["z1"], row["z4"]
            below = (f"{y['below_r_min']:.0%} | {z4['below_r_min']:.0%}" if "below_r_min" in y else "- | -")
            lines.append(f"| {label} | {y['relmse']:.3g} | {z1['relmse']:.3g} | {z4['relmse']:.3g} | "
                         f"{z1['relmse_exposed']:.3g} | {y['radius_ratio_median']:.3f} | "
                         f"{z4['radius_ratio_median']:.3f} | {y['shrunk']:.0%} | {z4['shrunk']:.0%} | {below} |")
        lines.append("")
    pc = report.get("pass_cost")
    if pc:
        lines += [f"## Seconds per pass, five-chain layout ({pc['scene']} {pc['resolution']}, "
                  f"{pc['photons']} photons, median of {pc['reps']} interleaved runs of {pc['passes']} passes)", "",
                  "| method | s/pass | gather+update s/pass | vs SPPM |", "|---|---|---|---|"]
        for m in METHODS:
            d = pc["methods"][m]
            lines.append(f"| {m.upper()} | {d['seconds_per_pass']:.3f} | {d['gather_update_seconds']:.3f} | "
                         f"{d['ratio_vs_sppm']:.2f}x |")
        lines += ["", "Single layout, from the convergence runs (s/pass relative to SPPM):", "",
                  "| scene | CPPM | FPPM | APPM |", "|---|---|---|---|"]
        for name, data in report["convergence"].items():
            base = data["methods"]["sppm"]["seconds_per_pass"]
            lines.append(f"| {name} | {data['methods']['cppm']['seconds_per_pass'] / base:.2f}x | "
                         f"{data['methods']['fppm']['seconds_per_pass'] / base:.2f}x | "
                         f"{data['methods']['appm']['seconds_per_pass'] / base:.2f}x |")
        lines.append("")
    mem = report.get("memory")
    if mem:
        lines += ["## Peak memory, 1280x720 five-chain renders (child process, ru_maxrss)", "",
                  "| method | passes | photons | peak RSS | wall |", "|---|---|---|---|---|"]
        for row in mem:
            lines.append(f"| {row['method']} | {row['passes']} | {row['photons']} | **{row['peak_rss_gb']:.2f} GB** | "
                         f"{row['wall_seconds']:.0f}s |")
        lines.append("")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="width 128, N <= 64, 1024-pass references (~30 min)")
    ap.add_argument("--scenes", type=Path, default=Path("/work/shared/scenes"),
                    help="folder holding box/, cornell-box/ and cornell-box-spotlight/")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    ap.add_argument("--width", type=int, default=None, help="render width (default 128 quick / 256 full)")
    ap.add_argument("--photons", type=int, default=1 << 16)
    ap.add_argument("--max-passes", type=int, default=None, help="largest N (default 64 quick / 256 full)")
    ap.add_argument("--ref-factor", type=int, default=16, help="reference passes = this x the largest N")
    ap.add_argument("--skip-memory", action="store_true")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    variant = choose_variant()
    q = args.quick
    width = args.width or (128 if q else 256)
    max_passes = args.max_passes or (64 if q else 256)
    ref_passes = args.ref_factor * max_passes
    from ppmrecon.render.controllers import FPPM_R_MIN_FRAC

    report: dict = {"variant": variant, "cpus": os.cpu_count(),
                    "settings": {"quick": q, "width": width, "photons": args.photons, "max_passes": max_passes,
                                 "ref_passes": ref_passes, "r_min_frac": FPPM_R_MIN_FRAC},
                    "convergence": {}}
    t_start = time.perf_counter()

    def save() -> None:
        (args.out / "methods.json").write_text(json.dumps(report, indent=2))
        (args.out / "methods.md").write_text(markdown(report))

    for name, spec in scene_list(args.scenes):
        loaded, depth = load(spec, width)
        ref = reference(name, loaded, depth, ref_passes, args.photons, args.out / "refs")
        took = "cached" if ref["cached"] else f"{ref['seconds']:.0f}s"
        print(f"[{time.perf_counter() - t_start:7.0f}s] {name}: reference {ref_passes} passes ({took}), "
              f"noise {ref['noise_relmse']:.2e}", flush=True)
        entry = {"resolution": f"{loaded.width}x{loaded.height}", "max_depth": depth,
                 "reference": {k: v for k, v in ref.items() if k != "image"}, "methods": {}}
        for m in METHODS:
            entry["methods"][m] = convergence(loaded, depth, ref["image"], m, max_passes, args.photons)
            c = entry["methods"][m]["curve"][-1]
            print(f"[{time.perf_counter() - t_start:7.0f}s]   {m}: relMSE(N={c['passes']}) {c['relmse']:.4f}",
                  flush=True)
        report["convergence"][name] = entry
        save()

    # Five chains on the textured spotlight and the caustic: ~z^4 starts at the k-NN radius
    # (~20 photons a pass), so the tests have power early; FPPM's r_min is varied here.
    runs = [("sppm", None), ("cppm", None), ("fppm", {"r_min_frac": 0.05}), ("fppm", None),
            ("fppm", {"r_min_frac": 1.0}), ("fppm", {"per_channel": True}), ("appm", None),
            ("appm", {"laplacian": "paper", "variance": "paper"})]
    report["five_chain"] = []
    for name, spec in (("cornell-box-spotlight", str(args.scenes / LITERATURE[2][1])),
                       ("water_caustic", "water_caustic")):
        loaded, depth = load(spec, width)
        ref = reference(name, loaded, depth, ref_passes, args.photons, args.out / "refs")
        report["five_chain"].append(
            {"scene": name, "passes": max_passes,
             "rows": [five_chain(loaded, depth, ref["image"], m, max_passes, args.photons, p) for m, p in runs]})
        print(f"[{time.perf_counter() - t_start:7.0f}s] five-chain study on {name} done", flush=True)
        save()
    name, spec = "cornell-box-spotlight", str(args.scenes / LITERATURE[2][1])
    loaded, depth = load(spec, width)

    reps, passes = (3, 3) if q else (3, 6)
    report["pass_cost"] = {"scene": name, "resolution": f"{loaded.width}x{loaded.height}", "photons": args.photons,
                           "reps": reps, "passes": passes,
                           "methods": pass_cost(loaded, depth, args.photons, reps, passes)}
    print(f"[{time.perf_counter() - t_start:7.0f}s] pass cost done", flush=True)
    save()

    if not args.skip_memory:
        mem_passes = 2 if q else 4
        report["memory"] = [peak_memory(m, p, 1280, 720, mem_passes, 1 << 17)
                            for m, p in (("fppm", []), ("fppm", ["--per-channel"]), ("cppm", []), ("sppm", []),
                                         ("appm", []))]
        print(f"[{time.perf_counter() - t_start:7.0f}s] memory done", flush=True)
    save()
    plot(report, args.out / "methods.png")
    print(markdown(report))


if __name__ == "__main__":
    main()
