"""Denoiser benchmark (issue 4; SPEC section 8): time per preset vs OIDN, peak memory.

    .venv/bin/python benchmarks/bench_denoise.py [--presets shipped,tiny,small,paper] [--repeats 3] [--rounds 3]
                                                 [--threads 2] [--input BUFFER.exr] [--out DIR]

Measured in one run on this machine, each measurement in its own child process (so
one's memory and thread pools cannot affect another):
  * seconds to denoise 1280x720 (network features + network + consistent combiner,
    in memory, no EXR I/O) for each preset, and for OIDN (`pyoidn`, colour + albedo +
    normal, HDR) on the ~z^1 image of the same buffer; median of --repeats runs after
    one warm-up run (which pays one-time costs: allocator, oneDNN kernel selection), in
    --rounds rounds of OIDN and every preset side by side; the ratio to OIDN is taken
    within each round and its median reported (this machine drifts within minutes);
  * peak resident memory (ru_maxrss of the child, imports included) for 1920x1080 with
    the default preset.
The input is a synthetic buffer (seeded: shapes and gradients, gamma noise on ~y,
blurred weaker noise on ~z^j) unless --input gives a rendered one. Weights are
untrained (timing and memory do not depend on their values), except ``shipped``: the
default checkpoint with its firefly guard and denoiser guide (OIDN inside), as
``ppmrecon-denoise`` runs it (in the guide's envelope mode that is no network at all; in
its chooser mode the envelope and the chooser), and ``shipped:MODE``, the same in another
guide mode (``shipped:envelope``: the envelope alone) or with another guide denoiser
(``shipped:nlm_source``: NL-means for the guide's source) or with guide settings changed
(``shipped:nlm_albedo=2``, several joined by ``+``).
Writes `denoise.md`, `denoise.json` and `denoise.png` into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


# ------------------------------------------------------------------------------ input

def synthetic_buffer(width: int, height: int, seed: int = 0):
    """A buffer file with plausible structure and noise; deterministic in ``seed``."""
    from scipy.ndimage import gaussian_filter

    from ppmrecon import buffers as B

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
    yy /= height
    xx /= width
    clean = np.stack([0.3 + 0.5 * xx, 0.2 + 0.4 * yy, 0.25 + 0.2 * np.sin(6 * xx) ** 2], -1)
    albedo = np.full((height, width, 3), 0.6, np.float32)
    for _ in range(40):
        cx, cy, r = rng.random(3)
        mask = (xx - cx) ** 2 * (width / height) ** 2 + (yy - cy) ** 2 < (0.02 + 0.1 * r) ** 2
        colour = rng.random(3).astype(np.float32)
        clean[mask] = colour * (1 + 20 * (r > 0.9))          # a few bright caustic-like blobs
        albedo[mask] = colour
    clean = clean.astype(np.float32)
    y = clean * rng.gamma(2.0, 0.5, clean.shape).astype(np.float32)
    noisy_b = clean * rng.gamma(8.0, 0.125, clean.shape).astype(np.float32)
    zs = [gaussian_filter(noisy_b, sigma=(s, s, 0)) for s in (0.8, 1.5, 2.5, 4.0)]
    est = np.stack([y] + zs).astype(np.float32)
    normal = np.zeros((height, width, 3), np.float32)
    normal[..., 2] = 1.0
    header = {B.H_VERSION: B.SCHEMA_VERSION, B.H_METHOD: "sppm", B.H_KERNEL: "constant", B.H_PASSES: 100,
              B.H_PHOTONS: 131072, B.H_ALPHA: 2 / 3, B.H_KNN: 20, B.H_SEED: seed, B.H_SCENE: "synthetic",
              B.H_SECONDS: 0.0}
    return B.BufferFile(est, (est.mean(-1) * 0.1) ** 2, np.ones((5, height, width), np.float32) * 0.01,
                        albedo, normal, np.ones((height, width), np.float32), header)


def load_input(args_input: str | None, width: int, height: int):
    if args_input:
        from ppmrecon.buffers import read_buffers

        return read_buffers(args_input)
    return synthetic_buffer(width, height)


# ----------------------------------------------------------------------------- worker

def worker(spec: dict) -> dict:
    """Runs in a child process: time one method, report its own peak RSS."""
    import torch

    torch.set_num_threads(spec["threads"])
    buf = load_input(spec.get("input"), spec["width"], spec["height"])
    h, w = buf.shape
    rss_input = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if spec["method"] == "oidn":
        import pyoidn

        colour = np.ascontiguousarray(buf.estimates[1])
        albedo = np.ascontiguousarray(np.clip(buf.albedo, 0, 1))
        normal = np.ascontiguousarray(buf.normal)

        def run() -> None:
            out = pyoidn.denoise(colour, albedo, normal, hdr=True)
            assert np.isfinite(out).all()
        extra = {"precision": "oidn default (native)"}
    else:
        from ppmrecon.model.infer import denoise, resolve_precision
        from ppmrecon.model.kpn import build, parameter_count

        torch.manual_seed(0)
        if spec["method"].split(":")[0] == "shipped":   # the default model as ppmrecon-denoise runs it
            from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint

            model = load_checkpoint(DEFAULT_MODEL).model
            if ":" in spec["method"]:                   # shipped:MODE, another guide mode or denoiser of it
                from dataclasses import replace

                from ppmrecon.model.guide import DENOISERS
                how = spec["method"].split(":", 1)[1]
                if "=" in how:                          # shipped:KEY=VALUE[+KEY=VALUE]: guide settings
                    from bench_guide import _setting   # text read as the setting's type

                    pairs = dict(p.split("=", 1) for p in how.split("+"))
                    model.guide = replace(model.guide, **{k: _setting(getattr(model.guide, k), v)
                                                          for k, v in pairs.items()})
                else:
                    model.guide = (replace(model.guide, denoiser=how) if how in DENOISERS
                                   else model.guide.in_mode(how))
        else:
            model = build(spec["method"]).eval()
        precision = resolve_precision(spec["precision"], torch.device("cpu"))

        def run() -> None:
            out = denoise(buf, model, precision=precision)
            assert np.isfinite(out.rgb).all()
        if model.guide.enabled and model.guide.mode == "envelope":   # the guide's envelope runs no network
            extra = {"precision": "guide envelope (no network)"}
        elif model.guide.enabled and model.guide.mode == "chooser":
            extra = {"precision": f"guide envelope + chooser (float32, {model.chooser.cfg.width} channels)",
                     "parameters": parameter_count(model.chooser)}
        else:
            extra = {"precision": precision, "parameters": parameter_count(model), "window": model.window}
    times = []
    for i in range(spec["repeats"] + 1):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
        if i == 0 and times[0] > spec["slow_after"]:
            break                                  # very slow presets: one timed run is enough
    timed = times[1:] or times
    return {"method": spec["method"], "size": f"{w}x{h}", "threads": spec["threads"],
            "seconds_median": float(np.median(timed)), "seconds_min": float(min(timed)),
            "warmup_seconds": times[0], "runs": len(timed),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "input_rss_mb": rss_input / 1024, **extra}


def measure(spec: dict) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(spec)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        raise SystemExit(f"worker {spec['method']} failed:\n{proc.stderr[-2000:]}")
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # cross-check: the largest child so far, as the kernel accounts it
    result["children_max_rss_mb"] = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    print(f"  {result['method']:>6} {result['size']}: {result['seconds_median']:.3f} s "
          f"(min {result['seconds_min']:.3f}, warm-up {result['warmup_seconds']:.3f}), "
          f"peak RSS {result['peak_rss_mb']:.0f} MB", flush=True)
    return result


def combine_rounds(runs: list[dict], oidn: list[dict]) -> dict:
    """One method's result over the rounds: the median of its per-round medians, the
    fastest run, the largest peak RSS, and its per-round ratios to that round's OIDN."""
    ratios = [r["seconds_median"] / o["seconds_median"] for r, o in zip(runs, oidn)]
    return {**runs[0], "seconds_median": float(np.median([r["seconds_median"] for r in runs])),
            "seconds_min": min(r["seconds_min"] for r in runs),
            "peak_rss_mb": max(r["peak_rss_mb"] for r in runs),
            "round_medians": [r["seconds_median"] for r in runs],
            "ratio_median": float(np.median(ratios)), "ratios": ratios}


# ----------------------------------------------------------------------------- report

def table(results: list[dict], memory: dict, default: str, meta: dict) -> str:
    oidn = next(r for r in results if r["method"] == "oidn")
    lines = [
        f"# Denoising benchmark ({meta['date']})",
        "",
        f"Machine: {meta['cpu']}, {meta['cores']} cores, torch {meta['torch']}, pyoidn {meta['pyoidn']}; "
        f"load average {meta['load_before']} before, {meta['load_after']} after (other jobs share this machine: "
        "timings are noisy). Threads per measurement: "
        f"{results[0]['threads']}. Input: {meta['input']}.",
        "",
        "| method | size | precision | params | K | median s | min s | x OIDN (median of rounds) | "
        "x OIDN per round | peak RSS MB |",
        "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in results:
        name = r["method"] + (" (default)" if r["method"] == default else "")
        per_round = " / ".join(f"{x:.2f}" for x in r["ratios"])
        lines.append(f"| {name} | {r['size']} | {r['precision']} | {r.get('parameters', '-')} | "
                     f"{r.get('window', '-')} | {r['seconds_median']:.3f} | {r['seconds_min']:.3f} | "
                     f"{r['ratio_median']:.2f} | {per_round} | {r['peak_rss_mb']:.0f} |")
    lines += [
        "",
        f"Peak memory, {memory['size']}, default preset `{default}` ({memory['precision']}): "
        f"**{memory['peak_rss_mb']:.0f} MB** resident (target < 4096 MB; the process after reading the input "
        f"held {memory['input_rss_mb']:.0f} MB), {memory['seconds_median']:.2f} s.",
        "",
        "Times cover the whole in-memory denoise (guard, guide, features, network, combiner, as the model's "
        "settings ask), not EXR I/O; OIDN gets the "
        "~z^1 estimate with albedo and normal. Per method and round: the median of the timed runs after one "
        f"warm-up run, each method in its own child process; {len(oidn['ratios'])} rounds of OIDN and every "
        "preset side by side, the ratio taken within each round.",
    ]
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.2))
    names = [r["method"] for r in results]
    ax.barh(names, [r["seconds_median"] for r in results], color=["#888" if n == "oidn" else "#3a7" for n in names])
    ax.set_xscale("log")
    ax.set_xlabel(f"seconds to denoise {results[0]['size']} (log)")
    for i, r in enumerate(results):
        ax.text(r["seconds_median"], i, f" {r['seconds_median']:.2f}s", va="center")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--presets", default="tiny,small,paper")
    ap.add_argument("--default", default=None, help="preset for the memory run (default: the CLI's)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=3,
                    help="rounds of OIDN and every preset side by side (ratios are taken within a round)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--precision", default="auto", choices=("auto", "float32", "bfloat16"))
    ap.add_argument("--slow-after", type=float, default=20.0,
                    help="a preset whose warm-up run takes longer than this many seconds is timed once")
    ap.add_argument("--input", help="a rendered buffer file instead of the synthetic 1280x720 one")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = ap.parse_args()
    if args.worker:
        print(json.dumps(worker(json.loads(args.worker))))
        return

    import torch

    from ppmrecon.model.kpn import DEFAULT_PRESET

    default = args.default or DEFAULT_PRESET
    base = {"threads": args.threads, "precision": args.precision, "repeats": args.repeats,
            "slow_after": args.slow_after, "input": args.input, "width": 1280, "height": 720}
    load_before = " ".join(f"{x:.2f}" for x in os.getloadavg())
    methods = ["oidn"] + args.presets.split(",")
    rounds = []
    for r in range(args.rounds):
        # OIDN and every preset side by side in each round: this machine's speed drifts by
        # more than 10% within minutes, so a ratio is only fair between neighbouring runs
        print(f"timing at 1280x720, round {r + 1}/{args.rounds}:", flush=True)
        rounds.append({m: measure({**base, "method": m}) for m in methods})
    print("memory at 1920x1080:", flush=True)
    memory = measure({**base, "method": default, "input": None, "width": 1920, "height": 1080, "repeats": 1})

    import pyoidn

    results = [combine_rounds([rd[m] for rd in rounds], [rd["oidn"] for rd in rounds]) for m in methods]
    meta = {"date": time.strftime("%Y-%m-%d %H:%M"), "cpu": _cpu_name(), "cores": os.cpu_count(),
            "torch": torch.__version__, "pyoidn": getattr(pyoidn, "__version__", _dist_version("pyoidn")),
            "python": platform.python_version(), "load_before": load_before,
            "load_after": " ".join(f"{x:.2f}" for x in os.getloadavg()),
            "input": args.input or "synthetic 1280x720 buffer (seed 0)"}
    args.out.mkdir(parents=True, exist_ok=True)
    md = table(results, memory, default, meta)
    (args.out / "denoise.md").write_text(md)
    (args.out / "denoise.json").write_text(json.dumps({"meta": meta, "timings": results, "memory": memory}, indent=2))
    plot(results, args.out / "denoise.png")
    print()
    print(md)


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _dist_version(name: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(name)
    except PackageNotFoundError:
        return "?"


if __name__ == "__main__":
    main()
