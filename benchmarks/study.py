"""The speed/accuracy study (equal-time comparisons, consistency curves, overheads),
after paper 002 Fig. 7, Fig. 8 and Table 2. Writes ``docs/RESULTS.md`` and its plots;
nothing in that file is typed by hand.

    .venv/bin/python benchmarks/study.py --scenes ../shared/scenes [--quick] \
        [--model ppmrecon/data/models/default.pt] [--out docs]

Scenes: the three literature scenes (reduced resolution, aspect kept) and two built-in
scenes. References: single-bandwidth SPPM with many passes, rendered twice with
independent seeds; the relMSE between the two shows how converged they are.

Equal time: every method gets the same wall-clock budget, including the multi-bandwidth
overhead and the inference time (the budget of a denoised run is shortened by the
measured inference time). Kernels are compiled once per configuration before timing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_quality import LITERATURE, oidn  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.backend import choose_variant  # noqa: E402
from ppmrecon.metrics import relmse  # noqa: E402

METHODS = ("sppm", "cppm", "fppm")
BUILTIN = ("cornell_caustics", "water_caustic")


def renderer(scene, name, layout, method, photons, seed, passes=None, budget=None):
    from ppmrecon.render.integrator import Renderer, RenderSettings

    return Renderer(scene, RenderSettings(method=method, passes=passes, time_budget=budget, photons=photons,
                                          seed=seed, layout=layout), scene_name=name)


def timed_denoise(buf: B.BufferFile, model) -> tuple[np.ndarray, float]:
    from ppmrecon.model.infer import denoise

    t = time.perf_counter()
    rgb = denoise(buf, model).rgb
    return rgb, time.perf_counter() - t


def timed_oidn(buf: B.BufferFile, layer: int) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    rgb = oidn(buf, layer)
    return rgb, time.perf_counter() - t


def single_as_buffer(res) -> B.BufferFile:
    """A single-chain result dressed as a buffer file so OIDN can read albedo/normal."""
    est = np.repeat(res.estimates[:1], 5, 0)
    var = np.repeat(res.variances[:1], 5, 0)
    rad = np.repeat(res.radii[:1], 5, 0)
    return B.BufferFile(est, var, rad, res.albedo, res.normal, res.depth, dict(res.header))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=Path, required=True, help="folder of the literature scenes")
    ap.add_argument("--model", type=Path, default=ROOT / "ppmrecon" / "data" / "models" / "default.pt")
    ap.add_argument("--quick", action="store_true", help="small sizes and budgets (< 15 min on 2 cores)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    args = ap.parse_args()
    q = args.quick
    fig_dir = args.out / "figures"
    cache = args.out / "cache"
    fig_dir.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    choose_variant()
    import mitsuba as mi  # noqa: F401

    from ppmrecon.model.checkpoint import load_checkpoint
    from ppmrecon.preview import side_by_side, write_png
    from ppmrecon.render.scene import load_scene

    model = load_checkpoint(args.model).model
    width = 64 if q else 128
    photons = 1 << (14 if q else 16)
    budgets = (3.0, 9.0) if q else (15.0, 60.0)
    ref_passes = 256 if q else 1024
    doublings = [2, 4, 8, 16, 32, 64] if q else [4, 8, 16, 32, 64, 128]
    scenes = {k: args.scenes / v for k, v in LITERATURE.items()}
    scenes.update({k: k for k in BUILTIN})
    report: dict = {"quick": q, "width": width, "photons": photons, "budgets": budgets, "reference_passes": ref_passes,
                    "cpus": os.cpu_count(), "model": str(args.model), "scenes": {}}
    t_all = time.perf_counter()
    for key, spec in scenes.items():
        loaded = load_scene(spec, resolution=width)
        sc = loaded.scene
        entry: dict = {"resolution": f"{loaded.width}x{loaded.height}"}
        # references: two independent single-bandwidth SPPM renders
        refs = []
        for seed in (1001, 1002):
            path = cache / f"{key}_{width}_{ref_passes}x{photons}_s{seed}.exr"
            if not path.exists():
                res = renderer(sc, key, "single", "sppm", photons, seed, passes=ref_passes).run()
                B.write_rgb(path, res.estimates[0], header=res.header)
            refs.append(B.read_rgb(path)[0])
        ref = 0.5 * (refs[0] + refs[1])
        entry["reference_agreement_relmse"] = relmse(refs[0], refs[1])

        # warm-up: compile every configuration once, measure per-pass costs
        overhead = {}
        for method in METHODS:
            per = {}
            for layout in ("single", "multi"):
                r = renderer(sc, key, layout, method, photons, 7, passes=4)
                r.run_pass()
                t0 = r.seconds
                for _ in range(3):
                    r.run_pass()
                per[layout] = (r.seconds - t0) / 3
            res = r.result()
            _, t_inf = timed_denoise(res.buffer_file(), model)
            overhead[method] = {"single_pass": per["single"], "multi_pass": per["multi"], "inference": t_inf,
                                "pass_overhead_pct": 100 * (per["multi"] / per["single"] - 1)}
        entry["overhead"] = overhead

        # equal-time comparisons
        equal = []
        crops = []
        for budget in budgets:
            row: dict = {"budget": budget}
            for method in METHODS:
                res = renderer(sc, key, "single", method, photons, 11, budget=budget).run()
                row[f"{method}"] = {"passes": res.passes, "relmse": relmse(res.estimates[0], ref)}
                if method == "sppm":
                    sppm_img = res.estimates[0]
                    t_oidn = timed_oidn(single_as_buffer(res), 0)[1]
                    res_o = renderer(sc, key, "single", method, photons, 12, budget=max(budget - t_oidn, 0.1)).run()
                    img_o, t_oidn = timed_oidn(single_as_buffer(res_o), 0)
                    row["oidn+sppm"] = {"passes": res_o.passes, "relmse": relmse(img_o, ref), "inference": t_oidn}
                t_inf = overhead[method]["inference"]
                res_m = renderer(sc, key, "multi", method, photons, 13, budget=max(budget - t_inf, 0.1)).run()
                img_m, t_inf = timed_denoise(res_m.buffer_file(), model)
                row[f"ours+{method}"] = {"passes": res_m.passes, "relmse": relmse(img_m, ref), "inference": t_inf}
                if method == "sppm" and budget == budgets[-1]:
                    crops = [sppm_img, img_o, img_m, ref]
            equal.append(row)
        entry["equal_time"] = equal
        write_png(fig_dir / f"equal_time_{key}.png", side_by_side(crops))

        # consistency curves (SPPM, ours + SPPM, OIDN + SPPM)
        ns = set(doublings)
        curve = {n: {} for n in doublings}
        r_multi = renderer(sc, key, "multi", "sppm", photons, 21, passes=max(doublings))
        r_multi.run(lambda rr: curve[rr.passes_done].update(
            ours=relmse(timed_denoise(rr.result().buffer_file(), model)[0], ref)) if rr.passes_done in ns else None)
        r_single = renderer(sc, key, "single", "sppm", photons, 22, passes=max(doublings))

        def on_single(rr):
            if rr.passes_done in ns:
                res = rr.result()
                curve[rr.passes_done].update(sppm=relmse(res.estimates[0], ref),
                                             oidn=relmse(timed_oidn(single_as_buffer(res), 0)[0], ref))

        r_single.run(on_single)
        entry["consistency"] = [{"passes": n, **curve[n]} for n in doublings]
        report["scenes"][key] = entry
        print(f"{key}: done ({time.perf_counter() - t_all:.0f}s so far)", flush=True)

    report["seconds"] = time.perf_counter() - t_all
    (args.out / "results.json").write_text(json.dumps(report, indent=1))
    plots(report, fig_dir)
    (args.out / "RESULTS.md").write_text(markdown(report))
    print(markdown(report))


def plots(report: dict, fig_dir: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(report["scenes"])
    fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 3.0), squeeze=False)
    for ax, key in zip(axes[0], keys):
        c = report["scenes"][key]["consistency"]
        n = [x["passes"] for x in c]
        for name, label in (("sppm", "SPPM"), ("oidn", "OIDN + SPPM"), ("ours", "ours + SPPM")):
            ax.loglog(n, [x[name] for x in c], "o-", ms=3, label=label)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("passes")
        ax.minorticks_off()
        ax.set_xticks(n, [str(k) for k in n], fontsize=7)
    axes[0][0].set_ylabel("relMSE")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(fig_dir / "consistency.png", dpi=110)

    fig, axes = plt.subplots(1, len(keys), figsize=(3.2 * len(keys), 3.0), squeeze=False)
    names = ["sppm", "cppm", "fppm", "oidn+sppm", "ours+sppm", "ours+cppm", "ours+fppm"]
    for ax, key in zip(axes[0], keys):
        row = report["scenes"][key]["equal_time"][-1]
        ax.bar(range(len(names)), [row[n]["relmse"] for n in names],
               color=["#999"] * 3 + ["#c84"] + ["#3a7"] * 3)
        ax.set_xticks(range(len(names)), names, rotation=60, fontsize=7)
        ax.set_yscale("log")
        ax.set_title(f"{key}, {row['budget']:.0f}s", fontsize=9)
    axes[0][0].set_ylabel("relMSE (equal time)")
    fig.tight_layout()
    fig.savefig(fig_dir / "equal_time.png", dpi=110)


def markdown(r: dict) -> str:
    names = ["sppm", "cppm", "fppm", "oidn+sppm", "ours+sppm", "ours+cppm", "ours+fppm"]
    lines = ["# Results: speed and accuracy", "",
             f"Generated by `benchmarks/study.py{' --quick' if r['quick'] else ''}` on {r['cpus']} CPU cores in "
             f"{r['seconds'] / 60:.1f} min; model `{Path(r['model']).name}`. Scenes at width {r['width']} "
             f"(aspect kept), {r['photons']} photons per pass. References: single-bandwidth SPPM, "
             f"{r['reference_passes']} passes, mean of two independent renders.", "",
             "## Equal-time comparison (relMSE, passes reached)", ""]
    for key, e in r["scenes"].items():
        lines += [f"### {key} ({e['resolution']}; reference agreement relMSE {e['reference_agreement_relmse']:.2e})", "",
                  "| budget | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        for row in e["equal_time"]:
            best = min(row[n]["relmse"] for n in names)
            cells = [(f"**{row[n]['relmse']:.4f}**" if row[n]["relmse"] == best else f"{row[n]['relmse']:.4f}")
                     + f" ({row[n]['passes']})" for n in names]
            lines.append(f"| {row['budget']:.0f}s | " + " | ".join(cells) + " |")
        lines += ["", f"![{key}](figures/equal_time_{key}.png)  ", "SPPM | OIDN + SPPM | ours + SPPM | reference "
                  f"(largest budget)", ""]
    lines += ["![equal time](figures/equal_time.png)", "", "## Consistency (relMSE against passes)", "",
              "![consistency](figures/consistency.png)", "", "| scene | N | SPPM | OIDN + SPPM | ours + SPPM |",
              "|---|---|---|---|---|"]
    for key, e in r["scenes"].items():
        for x in e["consistency"]:
            lines.append(f"| {key} | {x['passes']} | {x['sppm']:.5f} | {x['oidn']:.5f} | {x['ours']:.5f} |")
    lines += ["", "## Overheads (after paper 002 Table 2)", "",
              "| scene | method | s/pass, 1 chain | s/pass, 5 chains | pass overhead | inference |", "|---|---|---|---|---|---|"]
    for key, e in r["scenes"].items():
        for m, o in e["overhead"].items():
            lines.append(f"| {key} | {m} | {o['single_pass']:.3f} | {o['multi_pass']:.3f} | "
                         f"{o['pass_overhead_pct']:+.0f}% | {o['inference']:.3f}s |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
