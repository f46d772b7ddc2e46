"""Issue 12, part 5, on renders no model was trained on: per-N curves of the shipped
reconstruction against its five inputs, and equal time against OIDN on SPPM.

    python benchmarks/bench_curves.py --scenes ../shared/scenes [--model M] [--passes 16,64,256]

Scenes and references are those of ``bench_estimators.py`` (the three literature scenes
of ``--scenes`` and three built-in scenes, width 128, the references cached in
``out/bench_estimators/refs``: Mitsuba 3 ``path`` at 4096 spp where it converges, else
two 512-pass single-bandwidth renders of 65536 photons; rendered when missing).

1. **Curves**: one five-chain FPPM render per scene with the renderer's defaults (direct
   lighting ``all``, the scene's own path depth), 65536 photons per pass, with buffer
   snapshots at each N of ``--passes`` (cached in ``out/bench_curves``). Per snapshot:
   relMSE and 8x8-block relMSE of each input, of the best one, of ours (default guard:
   outlier guard, low-frequency anchor, band) and of ours without the anchor.
2. **Equal time**: bench_estimators' 20 s renders: ours on the five-chain FPPM file
   against OIDN (``pyoidn``, HDR, albedo + normal) on the single-bandwidth SPPM file of
   the same budget (the SPPM file has no G-buffer; the FPPM file's albedo and normal,
   the same camera's first non-specular hits, stand in for it) and on ~y of the FPPM file.
   Our denoising time (< 0.1 s at this size) is not added to the 20 s.

Writes ``benchmarks/results/curves.{json,md,png}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_estimators import SCENES, path_reference, ppm_reference  # noqa: E402

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.metrics import relmse, relmse_blocks, relmse_trimmed  # noqa: E402

WIDTH, PHOTONS, REF_SPP, REF_PASSES = 128, 1 << 16, 4096, 512


def oidn(colour: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    import pyoidn

    return np.asarray(pyoidn.denoise(np.ascontiguousarray(colour, np.float32), np.ascontiguousarray(albedo, np.float32),
                                     np.ascontiguousarray(normal, np.float32), hdr=True), np.float64)


def score(img: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    img = img.astype(np.float64)
    return {"relmse": relmse(img, ref), "blocks": relmse_blocks(img, ref), "trimmed": relmse_trimmed(img, ref)}


def snapshots(name: str, spec: str, passes: list[int], work: Path, method: str = "fppm") -> dict[int, Path]:
    """Buffer files of one five-chain render at each N (rendered once, then cached)."""
    files = {n: work / f"{name}_{method}_n{n:04d}.exr" for n in passes}
    if all(f.exists() for f in files.values()):
        return files
    from ppmrecon.backend import choose_variant

    choose_variant()
    from ppmrecon.render.integrator import Renderer, RenderSettings
    from ppmrecon.render.scene import load_scene

    loaded = load_scene(spec, resolution=WIDTH)
    max_depth, rr_depth = loaded.depths()
    settings = RenderSettings(method=method, passes=max(passes), photons=PHOTONS, seed=7, max_depth=max_depth,
                              rr_depth=rr_depth)
    renderer = Renderer(loaded.scene, settings, scene_name=name)
    t0 = time.perf_counter()

    def on_pass(r) -> None:
        if r.passes_done in files:
            B.write_buffers(files[r.passes_done], r.result().buffer_file())
            print(f"{name}: N = {r.passes_done} after {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)

    renderer.run(on_pass)
    return files


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", type=Path, default=None, help="folder of the literature scenes (../shared/scenes)")
    p.add_argument("--model", default=None, help="checkpoint (default: the shipped model)")
    p.add_argument("--passes", default="16,64,256", help="snapshot pass counts (comma-separated)")
    p.add_argument("--method", default="fppm", help="bandwidth controller of the curve renders (default fppm)")
    p.add_argument("--no-equal-time", action="store_true", help="skip part 2")
    p.add_argument("--estimators", type=Path, default=ROOT / "out" / "bench_estimators",
                   help="bench_estimators' work folder (references and the equal-time renders)")
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench_curves")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = p.parse_args()
    passes = sorted({int(x) for x in args.passes.split(",")})
    args.work.mkdir(parents=True, exist_ok=True)
    refs = args.estimators / "refs"
    refs.mkdir(parents=True, exist_ok=True)

    import torch

    from ppmrecon.model import checkpoint
    from ppmrecon.model.guard import DEFAULT_ON
    from ppmrecon.model.infer import denoise

    torch.set_num_threads(1)
    model, _ = checkpoint.load_checkpoint(args.model or checkpoint.DEFAULT_MODEL)
    guard = model.guard if model.guard.enabled else DEFAULT_ON
    report = {"model": str(args.model or "default.pt"), "method": args.method, "width": WIDTH, "photons": PHOTONS,
              "curves": [],
              "equal_time": []}
    for name, spec, kind in SCENES:
        if "/" in spec:
            if args.scenes is None:
                continue
            spec = str(args.scenes / spec)
        if kind == "path":
            ref, _ = path_reference(name, spec, WIDTH, REF_SPP, refs)
        else:
            ref, _ = ppm_reference(ROOT, name, spec, WIDTH, REF_PASSES, PHOTONS, refs)
        for n, path in snapshots(name, spec, passes, args.work, args.method).items():
            buf = B.read_buffers(path)
            inputs = [score(x, ref) for x in buf.estimates]
            row = {"scene": name, "passes": n,
                   "best_input": {k: min(s[k] for s in inputs) for k in inputs[0]},
                   "inputs": dict(zip(B.ESTIMATES, inputs)),
                   "ours": score(denoise(buf, model, guard=guard).rgb, ref),
                   "ours_no_anchor": score(denoise(buf, model, guard=replace(guard, anchor=0.0)).rgb, ref),
                   "oidn_y": score(oidn(buf.estimates[0], buf.albedo, buf.normal), ref)}
            report["curves"].append(row)
            print(json.dumps({k: row[k] for k in ("scene", "passes", "best_input", "ours")}), flush=True)
        fppm = args.estimators / f"{name}_after+direct=all_fppm.exr"
        single = args.estimators / f"{name}_after+direct=all_single.exr"
        if fppm.exists() and single.exists() and not args.no_equal_time:
            buf = B.read_buffers(fppm)
            sppm, header = B.read_rgb(single)
            t0 = time.perf_counter()
            mine = denoise(buf, model, guard=guard).rgb
            seconds = time.perf_counter() - t0
            inputs = [score(x, ref) for x in buf.estimates]
            report["equal_time"].append({
                "scene": name, "budget_s": float(buf.header.get("ppmrecon.render_seconds", float("nan"))),
                "fppm_passes": int(buf.header[B.H_PASSES]), "sppm_passes": int(header.get(B.H_PASSES, 0)),
                "ours": score(mine, ref), "denoise_seconds": seconds,
                "best_input": {k: min(s[k] for s in inputs) for k in inputs[0]},
                "sppm": score(sppm, ref), "oidn_sppm": score(oidn(sppm, buf.albedo, buf.normal), ref),
                "oidn_y": score(oidn(buf.estimates[0], buf.albedo, buf.normal), ref)})
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "curves" if args.method == "fppm" else f"curves_{args.method}"
    write_json(args.out / f"{stem}.json", report)
    write_text(args.out / f"{stem}.md", markdown(report))
    plot(report, args.out / f"{stem}.png")


def markdown(r: dict) -> str:
    f = lambda s: f"{s['relmse']:.3g} / {s['blocks']:.3g}"   # noqa: E731
    lines = ["# Reconstruction on renders no model was trained on (issue 12)", "",
             f"Generated by `benchmarks/bench_curves.py` with model `{r['model']}`; width {r['width']}, "
             f"{r['photons']} photons per pass, five-chain {r.get('method', 'fppm').upper()} with the renderer's defaults. Each cell: relMSE / "
             "8x8-block relMSE; ratios are ours / best single input (targets: <= 0.5 and <= 1).", "",
             "| scene | N | best input | ours | ratio | block ratio | ours, no anchor | OIDN(~y) |",
             "| --- | ---: | --- | --- | ---: | ---: | --- | --- |"]
    for x in r["curves"]:
        b, o = x["best_input"], x["ours"]
        lines.append(f"| {x['scene']} | {x['passes']} | {f(b)} | {f(o)} | {o['relmse'] / b['relmse']:.2f} | "
                     f"{o['blocks'] / b['blocks']:.2f} | {f(x['ours_no_anchor'])} | {f(x['oidn_y'])} |")
    if r["equal_time"]:
        lines += ["", "Equal time (bench_estimators' renders, about 20 s each): ours on five-chain FPPM against OIDN "
                  "on single-bandwidth SPPM of the same budget (and on ~y of the FPPM file). Ratio: ours / OIDN(SPPM).",
                  "", "| scene | FPPM N | SPPM N | ours | best input | SPPM | OIDN(SPPM) | OIDN(~y) | ours / OIDN(SPPM) |",
                  "| --- | ---: | ---: | --- | --- | --- | --- | --- | ---: |"]
        for x in r["equal_time"]:
            lines.append(f"| {x['scene']} | {x['fppm_passes']} | {x['sppm_passes']} | {f(x['ours'])} | "
                         f"{f(x['best_input'])} | {f(x['sppm'])} | {f(x['oidn_sppm'])} | {f(x['oidn_y'])} | "
                         f"{x['ours']['relmse'] / x['oidn_sppm']['relmse']:.2f} |")
    return "\n".join(lines) + "\n"


def plot(r: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scenes = list(dict.fromkeys(x["scene"] for x in r["curves"]))
    if not scenes:
        return
    fig, axes = plt.subplots(1, len(scenes), figsize=(3.2 * len(scenes), 3.2), squeeze=False)
    for ax, name in zip(axes[0], scenes):
        rows = [x for x in r["curves"] if x["scene"] == name]
        n = [x["passes"] for x in rows]
        for key, label in (("best_input", "best input"), ("ours", "ours"), ("oidn_y", "OIDN(~y)")):
            ax.loglog(n, [x[key]["relmse"] for x in rows], "o-", label=label)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("passes N")
    axes[0][0].set_ylabel("relMSE")
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
