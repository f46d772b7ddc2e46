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

from bench_denoise import _cpu_name  # noqa: E402
from bench_quality import LITERATURE, oidn  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.backend import choose_variant  # noqa: E402
from ppmrecon.fileio import atomic_write, write_json  # noqa: E402
from ppmrecon.metrics import relmse, relmse_map, relmse_trimmed  # noqa: E402

METHODS = ("sppm", "cppm", "fppm", "appm")
BUILTIN = ("cornell_caustics", "water_caustic")
#: Fraction of worst pixels left out of the trimmed relMSE (fireflies).
TRIM = 1e-3
#: relMSE ratios within this of 1 are called a tie (one seed per entry).
TIE = 0.05
#: Seeds of the consistency curves (--curve-seeds): one seed's plain relMSE is decided by a
#: few glints (a rare caustic path seen in every estimate at once), so the curve that asks
#: whether more passes keep converging is the mean over several renders.
CURVE_SEEDS = 4
#: The figures of a consistency curve: plain and trimmed relMSE of each method.
CURVE_KEYS = ("sppm", "oidn", "ours")
#: The equal-time entries, in table order.
NAMES = [*METHODS, "oidn+sppm", *(f"ours+{m}" for m in METHODS)]


def names_of(report: dict) -> list[str]:
    """The entries a results.json holds, in table order (files from before APPM joined the
    study, issue 16, have no appm entries)."""
    row = next(iter(report["scenes"].values()))["equal_time"][0]
    return [n for n in NAMES if n in row]


#: The single-bandwidth baselines of the equal-time comparison are rendered at each of
#: these k-NN radii and the best is kept (issue 20: compare with the best single radius,
#: not the noisiest).
SINGLE_KNNS = (10, 20)


def renderer(loaded, name, layout, method, photons, seed, passes=None, budget=None, single_knn=None, **settings):
    """A renderer for a loaded scene with its own path depth (issue 20); the single layout
    starts at the ``single_knn`` k-NN radius (default RenderSettings.single_knn = 10).
    ``settings``: other RenderSettings fields, overriding these (e.g. ``max_depth``, ``kernel``)."""
    from ppmrecon.render.integrator import Renderer, RenderSettings

    max_depth, rr_depth = loaded.depths()
    fields = {"max_depth": max_depth, "rr_depth": rr_depth, **({} if single_knn is None else {"single_knn": single_knn})}
    fields.update(settings)
    return Renderer(loaded.scene, RenderSettings(method=method, passes=passes, time_budget=budget, photons=photons,
                                                 seed=seed, layout=layout, **fields),
                    scene_name=name)


#: How the single-bandwidth baselines of a results.json were rendered; files from before
#: issue 20 carry no such entry.
LEGACY_BASELINE = ("b = 0.354 r_20 (the second-smallest of the five initial radii, about 2.5 photons: the "
                   "noisiest single radius), path depth capped at 8")


def baseline_text() -> str:
    from ppmrecon.render.integrator import RenderSettings

    return (f"the best at equal time of the k = {' and k = '.join(map(str, SINGLE_KNNS))} k-NN radii "
            f"(k = {RenderSettings.single_knn} is r_20 / sqrt 2, what paper 002 calls roughly k = 10; each "
            "entry names the k it used), the scene's own path depth")


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


def comparison_figure(images: list[np.ndarray], ref: np.ndarray, zoom: int = 3) -> np.ndarray:
    """Full images and the reference in a row; below, the same crop of each (a third of the
    image, where SPPM's error is largest) magnified ``zoom`` times (paper 002 Fig. 7 style)."""
    from scipy.ndimage import uniform_filter

    from ppmrecon.preview import side_by_side

    h, w = ref.shape[:2]
    ch, cw = max(h // 3, 8), max(w // 3, 8)
    err = uniform_filter(relmse_map(images[0], ref), size=(ch, cw), mode="constant")
    cy, cx = np.unravel_index(np.argmax(err), err.shape)
    y0, x0 = int(np.clip(cy - ch // 2, 0, h - ch)), int(np.clip(cx - cw // 2, 0, w - cw))
    all_images = [*images, ref]
    exposure = max(1.0, 0.18 / max(float(ref.mean()), 1e-6))     # brightens dark scenes (the spotlight)
    top = side_by_side(all_images, exposure=exposure)
    crops = [np.repeat(np.repeat(im[y0:y0 + ch, x0:x0 + cw], zoom, 0), zoom, 1) for im in all_images]
    bottom = side_by_side(crops, gap=4 + max(w - cw * zoom, 0), exposure=exposure)
    width = max(top.shape[1], bottom.shape[1])
    pad = lambda a: np.pad(a, ((0, 0), (0, width - a.shape[1]), (0, 0)), constant_values=255)  # noqa: E731
    return np.concatenate([pad(top), np.full((6, width, 3), 255, np.uint8), pad(bottom)], 0)


def score(img: np.ndarray, ref: np.ndarray) -> dict:
    return {"relmse": relmse(img, ref), "relmse_trim": relmse_trimmed(img, ref, TRIM)}


REF_SEEDS = (1001, 1002)


def ref_path(cache: Path, key: str, width: int, passes: int, photons: int, seed: int) -> Path:
    return cache / f"{key}_{width}_{passes}x{photons}_s{seed}.exr"


def agreement(refs: list[np.ndarray]) -> dict:
    """relMSE between the two references, both ways round (a firefly in one of them makes
    it asymmetric), and the symmetric trimmed figure, which fireflies do not decide."""
    return {"reference_agreement_relmse": relmse(refs[0], refs[1]),
            "reference_agreement_relmse_reverse": relmse(refs[1], refs[0]),
            "reference_agreement_relmse_trim": 0.5 * (relmse_trimmed(refs[0], refs[1], TRIM)
                                                      + relmse_trimmed(refs[1], refs[0], TRIM))}


def references(scenes: dict, width: int, photons: int, passes: int, cache: Path, seeds: tuple = REF_SEEDS,
               **settings) -> dict:
    """Two independent single-bandwidth SPPM references per scene (cached as EXR), rendered
    with random streams ``seeds`` and the RenderSettings fields ``settings`` (e.g. a path
    depth other than the scene's; the cache key should then say so)."""
    from ppmrecon.render.scene import load_scene

    out = {}
    for key, spec in scenes.items():
        loaded = load_scene(spec, resolution=width)
        refs = []
        for seed in seeds:
            path = ref_path(cache, key, width, passes, photons, seed)
            if not path.exists():
                t = time.perf_counter()
                res = renderer(loaded, key, "single", "sppm", photons, seed, passes=passes, **settings).run()
                B.write_rgb(path, res.estimates[0], header=res.header)
                print(f"{key}: reference seed {seed} in {time.perf_counter() - t:.0f}s", flush=True)
            refs.append(B.read_rgb(path)[0])
        out[key] = (loaded, refs)
    return out


def preset_trade(models: dict, buffers: dict, singles: dict, refs: dict) -> list[dict]:
    """Inference time at 1280x720 against relMSE on the study's five-chain SPPM buffers,
    per trained model (one per preset), with OIDN on the single-chain SPPM image beside."""
    from bench_denoise import synthetic_buffer

    from ppmrecon.model.checkpoint import load_checkpoint

    big = synthetic_buffer(1280, 720)
    rows = []
    for name, path in models.items():
        ckpt = load_checkpoint(path)
        times = [timed_denoise(big, ckpt.model)[1]]
        if times[0] < 20:                        # a second run for the cheap ones: the first pays warm-up
            times.append(timed_denoise(big, ckpt.model)[1])
        per_scene = {k: score(timed_denoise(buf, ckpt.model)[0], refs[k]) for k, buf in buffers.items()}
        rows.append({"name": name, "path": str(path), "preset": ckpt.meta.get("preset", "?"),
                     "parameters": sum(p.numel() for p in ckpt.model.parameters()),
                     "epochs": ckpt.meta.get("epochs"), "train_seconds": ckpt.meta.get("train_seconds"),
                     "seconds_720p": min(times), "scenes": per_scene})
        print(f"preset {name}: {min(times):.2f}s at 1280x720", flush=True)
    t_oidn = min(timed_oidn(big, 1)[1] for _ in range(2))
    rows.append({"name": "OIDN (SPPM image)", "path": "", "preset": "oidn", "parameters": None, "epochs": None,
                 "train_seconds": None, "seconds_720p": t_oidn,
                 "scenes": {k: score(timed_oidn(single_as_buffer(res), 0)[0], refs[k]) for k, res in singles.items()}})
    return rows


def parse_models(items: list[str]) -> dict[str, Path]:
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not Path(path).is_file():
            sys.exit(f"study.py: --preset-model {item!r}: expected NAME=PATH to an existing checkpoint")
        out[name] = Path(path)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=Path, required=True, help="folder of the literature scenes")
    ap.add_argument("--model", type=Path, default=ROOT / "ppmrecon" / "data" / "models" / "default.pt")
    ap.add_argument("--preset-model", action="append", default=[], metavar="NAME=PATH",
                    help="a trained checkpoint for the preset trade (repeat; default: only --model)")
    ap.add_argument("--quick", action="store_true", help="small sizes and budgets (< 15 min on 2 cores)")
    ap.add_argument("--refs-only", action="store_true", help="render (and cache) the references, then stop")
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite RESULTS.md and the plots from the last run's results.json (no rendering)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs")
    ap.add_argument("--curve-seeds", type=int, default=CURVE_SEEDS, metavar="K",
                    help=f"independent renders per consistency curve, averaged (default {CURVE_SEEDS}; the first "
                         "uses the seeds of single-seed runs)")
    ap.add_argument("--budgets", type=str, default=None, metavar="S,S",
                    help="equal-time budgets in seconds (default 15,60; --quick 3,9)")
    args = ap.parse_args()
    if args.report_only:
        report_only(args.out)
        return
    q = args.quick
    fig_dir = args.out / "figures"
    cache = args.out / "cache"
    fig_dir.mkdir(parents=True, exist_ok=True)
    cache.mkdir(parents=True, exist_ok=True)
    choose_variant()
    import mitsuba as mi  # noqa: F401

    from ppmrecon.model.checkpoint import load_checkpoint
    from ppmrecon.preview import write_png

    model = load_checkpoint(args.model).model
    preset_models = parse_models(args.preset_model) or {"default": args.model}
    width = 64 if q else 128
    photons = 1 << (14 if q else 16)
    budgets = (3.0, 9.0) if q else (15.0, 60.0)
    if args.curve_seeds < 1:
        sys.exit(f"study.py: --curve-seeds {args.curve_seeds}: expected at least 1")
    if args.budgets:
        try:
            budgets = tuple(float(x) for x in args.budgets.split(","))
        except ValueError:
            sys.exit(f"study.py: --budgets {args.budgets!r}: expected seconds separated by commas, e.g. 15,60")
    ref_passes = 256 if q else 1024
    doublings = [2, 4, 8, 16, 32, 64] if q else [4, 8, 16, 32, 64, 128]
    preset_passes = 32
    scenes = {k: args.scenes / v for k, v in LITERATURE.items()}
    scenes.update({k: k for k in BUILTIN})
    t_all = time.perf_counter()
    reference_sets = references(scenes, width, photons, ref_passes, cache)
    if args.refs_only:
        return
    report: dict = {"quick": q, "single_baseline": baseline_text(), "width": width, "photons": photons,
                    "budgets": budgets, "reference_passes": ref_passes,
                    "cpus": os.cpu_count(), "cpu": _cpu_name(), "load_start": os.getloadavg()[1], "model": str(args.model), "trim": TRIM,
                    "curve_seeds": args.curve_seeds, "scenes": {},
                    "command": " ".join(["benchmarks/study.py", *sys.argv[1:]])}
    t_all = time.perf_counter()
    preset_buffers, preset_singles, ref_of = {}, {}, {}
    for key, (loaded, refs) in reference_sets.items():
        sc = loaded
        ref = ref_of[key] = 0.5 * (refs[0] + refs[1])
        entry: dict = {"resolution": f"{loaded.width}x{loaded.height}", **agreement(refs)}

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
        images: dict[str, np.ndarray] = {}          # the largest budget's images are kept for the figure
        for budget in budgets:
            row: dict = {"budget": budget}
            for method in METHODS:
                runs = {k: renderer(sc, key, "single", method, photons, 11, budget=budget, single_knn=k).run()
                        for k in SINGLE_KNNS}
                k_best = min(runs, key=lambda k: score(runs[k].estimates[0], ref)["relmse"])
                res = runs[k_best]
                row[method] = {"passes": res.passes, "single_knn": k_best, **score(res.estimates[0], ref)}
                images[method] = res.estimates[0]
                if method == "sppm":
                    t_oidn = timed_oidn(single_as_buffer(res), 0)[1]
                    res_o = renderer(sc, key, "single", method, photons, 12, budget=max(budget - t_oidn, 0.1)).run()
                    img_o, t_oidn = timed_oidn(single_as_buffer(res_o), 0)
                    row["oidn+sppm"] = {"passes": res_o.passes, "inference": t_oidn, **score(img_o, ref)}
                    images["oidn+sppm"] = img_o
                t_inf = overhead[method]["inference"]
                res_m = renderer(sc, key, "multi", method, photons, 13, budget=max(budget - t_inf, 0.1)).run()
                img_m, t_inf = timed_denoise(res_m.buffer_file(), model)
                row[f"ours+{method}"] = {"passes": res_m.passes, "inference": t_inf, **score(img_m, ref)}
                images[f"ours+{method}"] = img_m
            equal.append(row)
        entry["equal_time"] = equal
        write_png(fig_dir / f"equal_time_{key}.png", comparison_figure([images[n] for n in NAMES], ref))

        # consistency curves (SPPM, ours + SPPM, OIDN + SPPM), the mean over --curve-seeds renders
        ns = set(doublings)
        runs = []
        for i in range(args.curve_seeds):
            curve = {n: {} for n in doublings}

            def on_multi(rr, curve=curve, first=i == 0):
                if rr.passes_done in ns:
                    buf = rr.result().buffer_file()
                    img = timed_denoise(buf, model)[0]
                    curve[rr.passes_done].update(ours=relmse(img, ref), ours_trim=relmse_trimmed(img, ref, TRIM))
                    if first and rr.passes_done == preset_passes:
                        preset_buffers[key] = buf

            def on_single(rr, curve=curve, first=i == 0):
                if rr.passes_done in ns:
                    res = rr.result()
                    img = timed_oidn(single_as_buffer(res), 0)[0]
                    curve[rr.passes_done].update(sppm=relmse(res.estimates[0], ref),
                                                 sppm_trim=relmse_trimmed(res.estimates[0], ref, TRIM),
                                                 oidn=relmse(img, ref), oidn_trim=relmse_trimmed(img, ref, TRIM))
                    if first and rr.passes_done == preset_passes:
                        preset_singles[key] = res

            renderer(sc, key, "multi", "sppm", photons, 21 + 10 * i, passes=max(doublings)).run(on_multi)
            renderer(sc, key, "single", "sppm", photons, 22 + 10 * i, passes=max(doublings)).run(on_single)
            runs.append(curve)
        entry["consistency"] = [mean_point(n, [c[n] for c in runs]) for n in doublings]
        report["scenes"][key] = entry
        print(f"{key}: done ({time.perf_counter() - t_all:.0f}s so far)", flush=True)

    report["preset_passes"] = preset_passes
    report["presets"] = preset_trade(preset_models, preset_buffers, preset_singles, ref_of)
    report["seconds"] = time.perf_counter() - t_all
    report["load_end"] = os.getloadavg()[1]
    write_report(report, args.out)
    print(markdown(report))


def report_only(out: Path) -> None:
    """Rewrite the Markdown and plots from ``results.json``; reference agreements missing
    from an older file are computed from the cached references when they are there."""
    from ppmrecon import buffers as B

    path = out / "results.json"
    if not path.is_file():
        sys.exit(f"study.py: {path}: no results to report (run the study first)")
    report = json.loads(path.read_text())
    for key, e in report["scenes"].items():
        paths = [ref_path(out / "cache", key, report["width"], report["reference_passes"], report["photons"], s)
                 for s in REF_SEEDS]
        if "reference_agreement_relmse_trim" not in e and all(p.is_file() for p in paths):
            e.update(agreement([B.read_rgb(p)[0] for p in paths]))
    write_report(report, out)


def write_report(report: dict, out: Path) -> None:
    """results.json, the plots and RESULTS.md, each written atomically."""
    write_json(out / "results.json", report)
    plots(report, out / "figures")
    text = markdown(report)
    atomic_write(out / "RESULTS.md", lambda tmp: Path(tmp).write_text(text))


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
    names = names_of(report)
    colours = {n: "#3a7" if n.startswith("ours") else "#c84" if n.startswith("oidn") else "#999" for n in names}
    for ax, key in zip(axes[0], keys):
        row = report["scenes"][key]["equal_time"][-1]
        ax.bar(range(len(names)), [row[n]["relmse"] for n in names], color=[colours[n] for n in names])
        ax.set_xticks(range(len(names)), names, rotation=60, fontsize=7)
        ax.set_yscale("log")
        ax.set_title(f"{key}, {row['budget']:.0f}s", fontsize=9)
    axes[0][0].set_ylabel("relMSE (equal time)")
    fig.tight_layout()
    fig.savefig(fig_dir / "equal_time.png", dpi=110)

    fig, ax = plt.subplots(figsize=(4.2, 3.2))
    for p in report["presets"]:
        ax.loglog(p["seconds_720p"], preset_mean(p), "s" if p["preset"] == "oidn" else "o")
        ax.annotate(p["name"], (p["seconds_720p"], preset_mean(p)), fontsize=8, xytext=(4, 4),
                    textcoords="offset points")
    ax.set_xlabel("seconds per 1280x720 image")
    ax.set_ylabel(f"mean relMSE, N={report['preset_passes']}")
    fig.tight_layout()
    fig.savefig(fig_dir / "presets.png", dpi=110)


def best(row: dict, ours: bool, metric: str) -> str:
    """The entry of ``row`` with the lowest ``metric`` among ours (or among the others)."""
    return min((n for n in NAMES if n in row and n.startswith("ours") == ours), key=lambda n: row[n][metric])


def verdict(ratio: float) -> str:
    return "tie" if abs(ratio - 1) < TIE else ("win" if ratio < 1 else "loss")


def summary_rows(r: dict) -> tuple[list[str], str]:
    """Per scene and budget: our best entry against the best of the others; and a line
    counting wins, ties and losses for plain and trimmed relMSE."""
    lines, counts = [], {"plain": [], "trimmed": []}
    for key, e in r["scenes"].items():
        for row in e["equal_time"]:
            ours, other = best(row, True, "relmse"), best(row, False, "relmse")
            ratio = row[ours]["relmse"] / row[other]["relmse"]
            ours_t, other_t = best(row, True, "relmse_trim"), best(row, False, "relmse_trim")
            ratio_t = row[ours_t]["relmse_trim"] / row[other_t]["relmse_trim"]
            counts["plain"].append(verdict(ratio))
            counts["trimmed"].append(verdict(ratio_t))
            v = verdict(ratio)
            lines.append(f"| {key} | {row['budget']:.0f}s | {ours} {row[ours]['relmse']:.3g} | "
                         f"{other} {row[other]['relmse']:.3g} | {ratio:.2f}x | {ratio_t:.2f}x ({other_t}) | "
                         f"{'**win**' if v == 'win' else v} |")
    tally = "; ".join(f"{kind}: {c.count('win')} wins, {c.count('tie')} ties, {c.count('loss')} losses of {len(c)}"
                      for kind, c in counts.items())
    return lines, f"Tally (relMSE {tally})."


def consistency_verdicts(r: dict) -> list[str]:
    """The claim of issue/paper 002 Fig. 8: ours keeps falling where a plain denoiser flattens;
    and issue 12's: ours still falls at each of the last three doublings (plain and trimmed)."""
    lines = []
    for key, e in r["scenes"].items():
        c = e["consistency"]
        s = {k: tail_slope(c, k) for k in CURVE_KEYS}
        last = c[-1]
        steeper = "falls faster than" if s["ours"] < s["oidn"] else "falls no faster than"
        lower = "below" if last["ours"] < last["oidn"] else "above"
        line = (f"- {key}: ours {steeper} OIDN + SPPM over the last three doublings (slope {s['ours']:+.2f} vs "
                f"{s['oidn']:+.2f}, SPPM {s['sppm']:+.2f}) and ends {lower} it at N={last['passes']} "
                f"({last['ours']:.3g} vs {last['oidn']:.3g})")
        for label, k in (("plain", "ours"), ("trimmed", "ours_trim")):
            if k in last:
                steps = [b[k] < a[k] for a, b in zip(c[-4:-1], c[-3:])]
                line += (f"; {label}, ours falls at {sum(steps)} of the last {len(steps)} doublings"
                         + ("" if all(steps) else " (not at N = " + ", ".join(
                             str(b["passes"]) for b, ok in zip(c[-3:], steps) if not ok) + ")"))
        lines.append(line + ".")
    return lines


def markdown(r: dict) -> str:
    names = names_of(r)
    methods = [n for n in names if "+" not in n]
    upper = "/".join(m.upper() for m in methods)
    trim = f"{100 * r['trim']:g}%"
    rows, tally = summary_rows(r)
    lines = ["# Results: speed and accuracy", "",
             f"Generated by `benchmarks/study.py{' --quick' if r['quick'] else ''}` on {r['cpus']} CPU cores"
             f"{' (' + r['cpu'] + ')' if r.get('cpu') else ''} in "
             f"{r['seconds'] / 60:.1f} min (references not counted{load_text(r)}); model `{Path(r['model']).name}`. Scenes at "
             f"width {r['width']} (aspect kept), {r['photons']} photons per pass. References: single-bandwidth SPPM, "
             f"{r['reference_passes']} passes, mean of two independent renders; their *agreement* is the relMSE "
             "between the two (trimmed, both ways round: a firefly in one reference otherwise decides it), and "
             "the mean's own noise is about a quarter of it. Every entry's relMSE includes that noise, so where "
             "it is close to the entries' figures the ratios between entries are compressed towards 1.", "",
             f"Command: `{r.get('command', 'benchmarks/study.py')}`", "",
             f"{', '.join(m.upper() for m in methods)} (without *ours*) are single-bandwidth renders (`--single`) whose initial "
             f"radius is {r.get('single_baseline', LEGACY_BASELINE)}.", "",
             "relMSE as SPEC section 7 (eps 0.01); *trimmed* leaves out the "
             f"{trim} of pixels with the largest error, so that a few fireflies do not decide the figure.", "",
             "## Where we win and where we lose", "",
             "Equal wall-clock time, multi-bandwidth overhead and inference included. *ours* is the best of "
             f"ours+{upper}; *other* the best of {', '.join(m.upper() for m in methods)} and OIDN+SPPM. Ratio < 1: ours is better; "
             f"within {100 * TIE:g}% of 1 is called a tie (each entry is one seed).", "",
             "| scene | budget | best ours | best other | relMSE ratio | trimmed ratio (best other, trimmed) | |",
             "|---|---|---|---|---|---|---|", *rows, "", tally, "",
             "## Equal-time comparison (relMSE, passes reached)", ""]
    for key, e in r["scenes"].items():
        agree = e.get("reference_agreement_relmse_trim", e["reference_agreement_relmse"])
        plain = e["reference_agreement_relmse"], e.get("reference_agreement_relmse_reverse", e["reference_agreement_relmse"])
        lines += [f"### {key} ({e['resolution']}; reference agreement relMSE {agree:.2e} trimmed, "
                  f"{plain[0]:.2e} / {plain[1]:.2e} plain both ways; the reference's noise is ~{agree / 4:.1e})", "",
                  "| budget | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        for row in e["equal_time"]:
            best = min(row[n]["relmse"] for n in names)
            cells = [(f"**{row[n]['relmse']:.3g}**" if row[n]["relmse"] == best else f"{row[n]['relmse']:.3g}")
                     + f" ({row[n]['passes']})" for n in names]
            lines.append(f"| {row['budget']:.0f}s | " + " | ".join(cells) + " |")
        lines += ["", f"![{key}](figures/equal_time_{key}.png)  ",
                  " | ".join(names) + " | reference, at the largest budget; below: the crop where SPPM's error "
                  "is largest, magnified.", ""]
    lines += ["![equal time](figures/equal_time.png)", "",
              f"### Trimmed relMSE ({trim} worst pixels left out), largest budget", "",
              "| scene | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for key, e in r["scenes"].items():
        row = e["equal_time"][-1]
        best = min(row[n]["relmse_trim"] for n in names)
        lines.append(f"| {key} | " + " | ".join(f"**{row[n]['relmse_trim']:.3g}**" if row[n]["relmse_trim"] == best
                                                 else f"{row[n]['relmse_trim']:.3g}" for n in names) + " |")
    lines += ["", "## Consistency (relMSE against passes)", "",
              "![consistency](figures/consistency.png)", "",
              "Slope: least-squares slope of log relMSE against log N over the last three points "
              "(0 = flat; SPPM's variance alone would give about -1 at best)."
              + (f" Each entry is the mean over {r['curve_seeds']} independent renders (seeds 21, 31, ... for ours, "
                 "22, 32, ... for SPPM and OIDN; per-seed values in results.json): one render's plain relMSE is "
                 f"decided by a few glints. Trimmed: the {trim} worst pixels left out."
                 if r.get("curve_seeds", 1) > 1 else " One render per curve."), ""]
    trimmed = all("ours_trim" in x for e in r["scenes"].values() for x in e["consistency"])
    head = "| scene | N | SPPM | OIDN + SPPM | ours + SPPM |" + (
        " SPPM trimmed | OIDN + SPPM trimmed | ours + SPPM trimmed |" if trimmed else "")
    lines += [head, "|---" * (head.count("|") - 1) + "|"]
    keys = CURVE_KEYS + (tuple(f"{k}_trim" for k in CURVE_KEYS) if trimmed else ())
    for key, e in r["scenes"].items():
        for x in e["consistency"]:
            lines.append(f"| {key} | {x['passes']} | " + " | ".join(f"{x[k]:.3g}" for k in keys) + " |")
        slopes = [f"{tail_slope(e['consistency'], k):+.2f}" for k in keys]
        lines.append(f"| {key} | slope | " + " | ".join(slopes) + " |")
    lines += ["", *consistency_verdicts(r)]
    lines += ["", "## Overheads (after paper 002 Table 2)", "",
              "| scene | method | s/pass, 1 chain | s/pass, 5 chains | pass overhead | inference |", "|---|---|---|---|---|---|"]
    for key, e in r["scenes"].items():
        for m, o in e["overhead"].items():
            lines.append(f"| {key} | {m} | {o['single_pass']:.3f} | {o['multi_pass']:.3f} | "
                         f"{o['pass_overhead_pct']:+.0f}% | {o['inference']:.3f}s |")
    keys = list(r["scenes"])
    lines += ["", "## Speed trade: model presets", "",
              f"Inference at 1280x720 (synthetic buffer, best of two runs when under 20 s) against relMSE on the "
              f"study scenes' five-chain SPPM buffers at N={r['preset_passes']}; OIDN is applied to the "
              "single-chain SPPM image at the same N. Each preset was trained on the same data for the stated time "
              "on this CPU, so larger presets are further from converged.", "",
              "![presets](figures/presets.png)", "",
              "| model | preset | parameters | trained | s at 1280x720 | mean relMSE | " + " | ".join(keys) + " |",
              "|---" * (6 + len(keys)) + "|"]
    for p in r["presets"]:
        trained = (f"{p['epochs']} ep, {p['train_seconds'] / 60:.0f} min" if p.get("train_seconds") else "-")
        params = f"{p['parameters']:,}" if p["parameters"] else "-"
        lines.append(f"| {p['name']} | {p['preset']} | {params} | {trained} | {p['seconds_720p']:.2f} | "
                     f"{preset_mean(p):.4g} | " + " | ".join(f"{p['scenes'][k]['relmse']:.3g}" for k in keys) + " |")
    return "\n".join(lines) + "\n"


def load_text(r: dict) -> str:
    """The machine's 5-minute load average at the start and end of the run: equal-time
    entries share the cores with whatever else ran, so a loaded machine makes them noisy."""
    if "load_start" not in r:
        return ""
    return f"; load average {r['load_start']:.1f} at the start, {r['load_end']:.1f} at the end"


def preset_mean(p: dict) -> float:
    return float(np.mean([v["relmse"] for v in p["scenes"].values()]))


def mean_point(passes: int, seeds: list[dict]) -> dict:
    """One N of a consistency curve: each figure's mean over the seeds' renders, and the
    per-seed values under ``"seeds"``."""
    keys = [k for k in seeds[0] if isinstance(seeds[0][k], float)]
    return {"passes": passes, **{k: float(np.mean([x[k] for x in seeds])) for k in keys},
            "seeds": {k: [x[k] for x in seeds] for k in keys}}


def tail_slope(curve: list[dict], key: str, points: int = 3) -> float:
    n = np.log([x["passes"] for x in curve[-points:]])
    e = np.log([x[key] for x in curve[-points:]])
    return float(np.polyfit(n, e, 1)[0])


if __name__ == "__main__":
    main()
