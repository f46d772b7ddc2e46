"""Issue 18: throughput of training-data generation (local pool vs Ray with 1 and 2
workers) and of training (one process vs two DDP/gloo processes) on this machine.

    python benchmarks/bench_distributed.py        # about 5 minutes on 2 cores

Generation: one small data set (``BENCH`` below: 3 scenes at 64x64, 6 items each, the
references in 2 chunks) is generated from scratch by each backend after a warm-up run
(so that every backend finds Dr.Jit's kernel cache filled), each backend ``--repeats``
times in alternation; throughput = items / wall seconds of ``generate`` (Ray's
start-up is timed apart; every worker process's own start-up, imports and scene loads
are inside). Training: ``ppmrecon-train fit``
with the shipped ``cpu`` training config on that data set, one thread per process;
steps/s from the history's ``step_seconds`` (the step loop only; process start-up,
data loading and validation left out). Writes benchmarks/results/distributed.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from ppmrecon.fileio import write_json, write_text  # noqa: E402
from ppmrecon.train.datagen import DataConfig, LocalRunner, generate  # noqa: E402

BENCH = DataConfig(scenes=3, first_seed=1, validation_every=3, resolution=(64, 64), photons=4096,
                   input_passes=(2, 4, 8), seeds=(0, 1), reference_passes=64, reference_photons=4096,
                   max_depth=5, families=("caustics", "glossy", "indirect"), radiance_log10=None,
                   references=2, reference_chunks=2)


def _items(manifest: dict) -> int:
    return sum(len(s["items"]) for s in manifest["scenes"])


def bench_generate(work: Path, repeats: int) -> list[dict]:
    """Every backend ``repeats`` times, alternating (so a change of load hits all alike);
    one Dr.Jit thread per worker everywhere, as a Ray task with one CPU has."""
    import ray

    from ppmrecon.train.raygen import RayRunner

    generate(BENCH, work / "warmup", quiet=True, runner=LocalRunner(2, threads=1))
    runs: dict[str, list[dict]] = {}
    for rep in range(repeats):
        for kind, workers in (("local", 1), ("local", 2), ("ray", 1), ("ray", 2)):
            out = work / f"{kind}{workers}_{rep}"
            startup = 0.0
            if kind == "ray":
                t0 = time.perf_counter()
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
                runner = RayRunner("auto")
                startup = time.perf_counter() - t0
                name = f"Ray, local cluster of {workers} CPU(s)"
            else:
                runner = LocalRunner(workers, threads=1)
                name = f"local pool, {workers} worker(s)"
            t0 = time.perf_counter()
            m = generate(BENCH, out, quiet=True, runner=runner)
            wall = time.perf_counter() - t0
            if kind == "ray":
                ray.shutdown()
            runs.setdefault(name, []).append({"seconds": wall, "items": _items(m), "startup_seconds": startup,
                                              "workers": workers})
    rows = []
    for name, rs in runs.items():
        best = min(rs, key=lambda r: r["seconds"])
        rows.append({"backend": name, "workers": best["workers"], "items": best["items"],
                     "seconds": best["seconds"], "all_seconds": [r["seconds"] for r in rs],
                     "items_per_second": best["items"] / best["seconds"],
                     "startup_seconds": best["startup_seconds"]})
    return rows


def bench_fit(data: Path, work: Path, steps: int) -> list[dict]:
    rows = []
    base = ["fit", str(data), "--config", "cpu", "--epochs", "2", "--steps-per-epoch", str(steps), "--quiet"]
    for procs, threads in ((1, 1), (1, 2), (2, 1)):
        out = work / f"fit_{procs}x{threads}"
        shutil.rmtree(out, ignore_errors=True)
        args = base + ["--out", str(out), "--threads", str(threads)]
        cmd = ([sys.executable, "-m", "ppmrecon.train"] + args if procs == 1 else
               [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={procs}",
                "-m", "ppmrecon.train"] + args + ["--ddp"])
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True, env={**os.environ, "OMP_NUM_THREADS": str(threads)})
        wall = time.perf_counter() - t0
        history = json.loads((out / "history.json").read_text())
        # epoch 1 includes the first steps' warm-up; epoch 2 is the steady state
        steady = history[-1]
        rows.append({"processes": procs, "threads_per_process": threads, "global_batch": 8,
                     "steps": steps, "steps_per_second": steps / steady["step_seconds"],
                     "patches_per_second": 8 * steps / steady["step_seconds"], "wall_seconds": wall,
                     "final_loss": steady["loss"]})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--work", type=Path, default=ROOT / "out" / "bench_distributed")
    p.add_argument("--steps", type=int, default=30, help="training steps per epoch (2 epochs, the 2nd timed)")
    p.add_argument("--repeats", type=int, default=2, help="runs of each generation backend (the fastest is reported)")
    p.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "distributed.json")
    args = p.parse_args()
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    load_before = os.getloadavg()
    gen = bench_generate(args.work, args.repeats)
    fit = bench_fit(args.work / "local2_0", args.work, args.steps)
    result = {"machine": {"cpus": os.cpu_count(), "platform": platform.platform(),
                          "load_average_before": load_before, "load_average_after": os.getloadavg()},
              "data_config": asdict(BENCH), "generate": gen, "fit": fit,
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    write_json(args.out, result)
    g1 = {r["backend"]: r for r in gen}
    lines = [f"# Distributed generation and training (issue 18), {result['date']}", "",
             f"{os.cpu_count()} CPUs, load average {load_before[0]:.1f} before / {os.getloadavg()[0]:.1f} after "
             "(the cores are shared with other jobs: figures are noisy). "
             "Written by `python benchmarks/bench_distributed.py`.", "",
             f"## `ppmrecon-train generate`: {gen[0]['items']} items (3 scenes at 64x64: 2 input seeds + "
             "2 references x 2 chunks each)", "",
             "One Dr.Jit thread per worker. Wall seconds: the fastest of the repeats (all in the JSON).", "",
             "| backend | wall s | items/s | speed-up vs 1 local worker | Ray start-up s |", "|---|---|---|---|---|"]
    base = gen[0]["items_per_second"]
    for r in g1.values():
        lines.append(f"| {r['backend']} | {r['seconds']:.1f} (of {', '.join(f'{x:.1f}' for x in r['all_seconds'])}) | "
                     f"{r['items_per_second']:.2f} | "
                     f"{r['items_per_second'] / base:.2f}x | {r['startup_seconds']:.1f} |")
    lines += ["", f"## `ppmrecon-train fit --config cpu` (tiny preset, global batch 8, 64x64 patches)", "",
              "| processes x threads | steps/s | patches/s | speed-up vs 1x1 | run wall s (incl. start-up) |",
              "|---|---|---|---|---|"]
    b = fit[0]["steps_per_second"]
    for r in fit:
        lines.append(f"| {r['processes']} x {r['threads_per_process']} | {r['steps_per_second']:.2f} | "
                     f"{r['patches_per_second']:.1f} | {r['steps_per_second'] / b:.2f}x | {r['wall_seconds']:.1f} |")
    write_text(args.out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
