"""``ppmrecon-train``: generate training data, then train the kernel-predicting network.

    ppmrecon-train generate --config v2_cpu --out data/v2_cpu [--workers 2]
    ppmrecon-train generate --config v2 --out data/v2 --ray auto [--reference-chunks 8]
    ppmrecon-train generate --config v2 --estimate [--out data/v2]   (what it would take here)
    ppmrecon-train fit data/cpu --out runs/cpu [--config cpu] [--resume]
    torchrun --nproc-per-node 2 -m ppmrecon.train fit data/cpu --out runs/cpu [--ddp]
    ppmrecon-train fit data/cpu --out runs/cpu --ddp --nproc-per-node 2   (torchrun --standalone for you)
    ppmrecon-train chooser data/v3_cpu --out runs/chooser [--config cpu] [--resume]

``--config`` takes a JSON file or the name of one that ships with the package
(``ppmrecon/data/configs/data/*.json`` for ``generate``, ``.../train/*.json`` for ``fit``).

``generate`` renders randomised scenes (never the literature scenes) into buffer files
and references with a manifest; it is resumable. ``fit`` trains on 64x64 augmented
patches with the loss of paper 002 Eq. 8 and writes a checkpoint every epoch.
``chooser`` trains the learned choice on top of the shipped envelope
(:mod:`ppmrecon.model.chooser`) and writes ``chooser.pt``; resumable.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from ..cli_common import ArgumentParser, nonnegative_int, positive_float, positive_int, run_main
from ..data import CONFIGS
from ..errors import UsageError

PROG = "ppmrecon-train"


def builtin_configs(kind: str) -> dict[str, Path]:
    """Config names -> files shipped in ``ppmrecon/data/configs/<kind>/`` (kind: data, train)."""
    return {p.stem: p for p in sorted((CONFIGS / kind).glob("*.json"))}


def config_file(kind: str):
    """argparse type: a JSON path, or the name of a shipped ``kind`` config."""
    def parse(text: str) -> Path:
        shipped = builtin_configs(kind)
        if text in shipped:
            return shipped[text]
        path = Path(text)
        if not path.is_file():
            raise argparse.ArgumentTypeError(f"'{text}' is neither a file nor a shipped {kind} config "
                                             f"({', '.join(shipped) or 'none found'})")
        return path
    return parse


def build_parser() -> ArgumentParser:
    p = ArgumentParser(prog=PROG, description="Generate training data and train the ppmrecon denoiser.")
    sub = p.add_subparsers(dest="command", metavar="{generate,fit,chooser}", parser_class=ArgumentParser)
    g = sub.add_parser("generate", help="render a training data set (resumable)",
                       description="Render randomised training scenes into buffer files + references.")
    g.add_argument("--config", type=config_file("data"), default=builtin_configs("data").get("cpu"),
                   metavar="NAME|FILE.json",
                   help=f"data-set budgets: a JSON file or a shipped set ({', '.join(builtin_configs('data'))}; "
                        "default: cpu; the issue-12 sets are v2 and v2_cpu, holdout the scenes no rule was tuned "
                        "on, and holdout_n1024 such scenes up to N = 1024)")
    g.add_argument("--out", type=Path, default=None,
                   help="output folder (manifest.json + one folder per scene); required unless --estimate")
    g.add_argument("--workers", type=positive_int, default=2, help="parallel worker processes (default: 2; not used with --ray)")
    g.add_argument("--ray", metavar="auto|local|ADDRESS", default=None,
                   help="run the work items as Ray tasks instead of local processes: 'auto' joins the "
                        "cluster this machine belongs to (or $RAY_ADDRESS), 'local' starts one here, or a "
                        "head address such as ray://host:10001 (needs ppmrecon[distributed])")
    g.add_argument("--ray-cpus-per-task", type=positive_int, default=1,
                   help="CPUs (and Dr.Jit threads) per CPU task (default: 1)")
    g.add_argument("--ray-gpus", default="auto", type=_gpus,
                   help="GPU tasks at a time: 'auto' (one per GPU of the cluster) or a number (0: CPU only)")
    g.add_argument("--ray-retries", type=nonnegative_int, default=2,
                   help="retries of a failed Ray task before it is recorded as failed (default: 2)")
    g.add_argument("--reference-chunks", type=positive_int, default=None,
                   help="split every reference render into this many ranges of passes, rendered as separate "
                        "items and merged exactly (overrides the config's reference_chunks)")
    g.add_argument("--scenes", type=positive_int, default=None,
                   help="override the number of scenes (more than an existing data set has grows it: "
                        "its scenes are kept)")
    g.add_argument("--families", default=None,
                   help="comma-separated scene families, overriding the config's (default: the config's; "
                        "see ppmrecon.train.scenegen)")
    g.add_argument("--estimate", action="store_true",
                   help="render nothing into --out: time a few passes of one input seed and one reference half "
                        "of the first scene of each family, --workers processes at once, and print what the "
                        "whole data set (and, with an existing --out, what is left of it) would take on this machine")
    g.add_argument("--estimate-seconds", type=positive_float, default=5.0,
                   help="seconds of passes timed per item after its first (default: 5)")
    g.add_argument("--quiet", "-q", action="store_true", help="no progress bar")

    f = sub.add_parser("fit", help="train a model on a generated data set",
                       description="Train the kernel-predicting network (paper 002 Sec. 4.3).")
    f.add_argument("data", type=Path, help="data-set folder made by `ppmrecon-train generate`")
    f.add_argument("--out", type=Path, required=True, help="run folder (model.pt, best.pt, history.json)")
    f.add_argument("--config", type=config_file("train"), default=None, metavar="NAME|FILE.json",
                   help=f"training settings: a JSON file or a shipped config "
                        f"({', '.join(builtin_configs('train'))}; default: built-in defaults)")
    f.add_argument("--preset", default=None, help="model preset name or JSON path (overrides the config)")
    f.add_argument("--epochs", type=positive_int, default=None)
    f.add_argument("--steps-per-epoch", type=positive_int, default=None)
    f.add_argument("--batch", type=positive_int, default=None)
    f.add_argument("--lr", type=positive_float, default=None, help="Adam learning rate (default 1e-4, as the paper)")
    f.add_argument("--seed", type=int, default=None)
    f.add_argument("--resume", action="store_true", help="continue from the run folder's last epoch")
    f.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads")
    f.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    f.add_argument("--max-seconds", type=positive_float, default=None, help="stop after the epoch that passes this")
    f.add_argument("--ddp", action="store_true",
                   help="train data-parallel in the process group torchrun set up (gloo on CPU, nccl with "
                        "--device cuda); implied when torchrun starts more than one process. "
                        "--batch is the global batch, shared out between the ranks")
    f.add_argument("--nproc-per-node", type=positive_int, default=None, metavar="N",
                   help="with --ddp outside torchrun: start N processes on this machine through "
                        "`torchrun --standalone` (under torchrun: not allowed, torchrun's own option sets it)")
    f.add_argument("--quiet", "-q", action="store_true", help="no progress bar")

    c = sub.add_parser("chooser", help="train the learned choice on top of the envelope (resumable)",
                       description="Train the chooser (ppmrecon/model/chooser.py): per-pixel weights over "
                                   "consistent candidates, on a generated data set's training split; scores "
                                   "its validation split; writes <out>/chooser.pt.")
    c.add_argument("data", type=Path, help="data-set folder made by `ppmrecon-train generate`")
    c.add_argument("--out", type=Path, required=True, help="run folder (state.pt, history.json, chooser.pt)")
    c.add_argument("--config", type=config_file("chooser"), default=builtin_configs("chooser").get("cpu"),
                   metavar="NAME|FILE.json",
                   help=f"chooser settings: a JSON file or a shipped config ({', '.join(builtin_configs('chooser'))}; "
                        "default: cpu)")
    c.add_argument("--base-model", default=None, metavar="CKPT",
                   help="the model whose guard and guide make the envelope (default: the shipped one)")
    c.add_argument("--steps", type=positive_int, default=None, help="training steps (overrides the config)")
    c.add_argument("--seed", type=int, default=None)
    c.add_argument("--resume", action="store_true", help="continue the run folder's training")
    c.add_argument("--max-seconds", type=positive_float, default=None,
                   help="stop at the first saved state after this many seconds (then --resume)")
    c.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads")
    c.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    return p


def _gpus(text: str) -> str | int:
    """argparse type of --ray-gpus: "auto" or an integer >= 0."""
    return text if text == "auto" else nonnegative_int(text)


def _warn(msg: str) -> None:
    sys.stderr.write(f"{PROG}: warning: {msg}\n")


def _hours(seconds: float) -> str:
    """A duration in the unit that reads best: s, min or h."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 7200 else f"{seconds / 3600:.1f} h"


def _estimate(cfg, args: argparse.Namespace) -> int:
    """``generate --estimate``: the measured cost of the data set, one row per family."""
    from .datagen import estimate

    est = estimate(cfg, seconds=args.estimate_seconds, workers=args.workers, out=args.out, quiet=args.quiet)
    name = Path(args.config).stem if args.config else "cpu"
    print(f"{PROG} generate --estimate: config {name}, {est['scenes']} scenes at {cfg.resolution[0]}x"
          f"{cfg.resolution[1]}; {est['workers']} worker(s) of {est['threads']} Dr.Jit thread(s), "
          f"{est['seconds_timed']:g} s of passes timed per item after its first")
    print(f"{'family':24s} {'input s/pass':>12s} {'reference s/pass':>16s} {'first pass s':>13s} {'scene (worker-s)':>17s}")
    for family, f in est["families"].items():
        print(f"{family:24s} {f['input_pass_seconds']:12.4f} {f['reference_pass_seconds']:16.4f} "
              f"{max(f['input_first_seconds'], f['reference_first_seconds']):13.2f} {f['scene_seconds']:17.0f}")
    line = (f"{PROG}: whole data set: {_hours(est['worker_seconds'])} of worker time (inputs "
            f"{_hours(est['input_seconds'])}, references {_hours(est['reference_seconds'])}), about "
            f"{_hours(est['wall_seconds'])} with {est['workers']} worker(s) on this machine")
    if args.out is not None:
        line += (f"; {args.out}: {est['items_done']} items finished, "
                 f"{_hours(est['remaining_worker_seconds'])} of worker time left "
                 f"(about {_hours(est['remaining_wall_seconds'])})")
    print(line)
    if est["finished_projected_seconds"] > 0:
        print(f"{PROG}: the finished items took {_hours(est['finished_seconds'])} against "
              f"{_hours(est['finished_projected_seconds'])} projected "
              f"({est['finished_seconds'] / est['finished_projected_seconds']:.2f}x)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    if args.command == "generate":
        from .datagen import DataConfig, generate

        cfg = DataConfig.load(args.config)
        if args.scenes:
            cfg.scenes = args.scenes
        if args.families:
            cfg.families = tuple(f.strip() for f in args.families.split(",") if f.strip())
            cfg.validate(f"--families {args.families}")
        if args.reference_chunks:
            cfg.reference_chunks = args.reference_chunks
            cfg.validate(f"--reference-chunks {args.reference_chunks}")
        if args.estimate:
            if args.ray:
                raise UsageError("--estimate times the work items on this machine: it does not take --ray")
            return _estimate(cfg, args)
        if args.out is None:
            raise UsageError("generate: --out is required (the data set's folder), unless --estimate")
        runner = None
        if args.ray:
            from .raygen import RayRunner

            runner = RayRunner(args.ray, cpus_per_task=args.ray_cpus_per_task, gpus=args.ray_gpus,
                               retries=args.ray_retries)
        manifest = generate(cfg, args.out, workers=args.workers, quiet=args.quiet, runner=runner)
        scenes = manifest["scenes"]
        inputs = [f for s in scenes for f in s.get("inputs", [])]
        agree = [s["agreement"]["relmse_normalised_trimmed"] for s in scenes if s.get("agreement")]
        line = (f"{PROG}: data set {args.out}: {len(scenes)} scenes, {len(inputs)} inputs "
                f"({sum(f.get('fireflies', 0) for f in inputs)} firefly pixels), "
                f"{manifest.get('generation_seconds', 0.0):.0f}s of generation")
        if agree:
            line += (f"; reference agreement relMSE (mean-normalised, trimmed) median "
                     f"{float(np.median(agree)):.2e}, worst {max(agree):.2e}")
        print(line)
        return 0

    import torch

    if args.command == "chooser":
        return _chooser(args)

    from .loop import TrainConfig, train

    cfg = TrainConfig.load(args.config) if args.config else TrainConfig()
    for key in ("preset", "epochs", "batch", "lr", "seed"):
        if getattr(args, key) is not None:
            setattr(cfg, key, getattr(args, key))
    if args.steps_per_epoch is not None:
        cfg.steps_per_epoch = args.steps_per_epoch
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise UsageError("--device cuda: no CUDA device is available to torch")
    from .distributed import init, launched_by_torchrun

    if args.nproc_per_node is not None:
        if not args.ddp or launched_by_torchrun():
            raise UsageError("--nproc-per-node: only with --ddp and outside torchrun (torchrun's own "
                             "--nproc-per-node sets the processes there)")
        return _torchrun_standalone(args.nproc_per_node, list(sys.argv[1:] if argv is None else argv))
    dist = init(args.device, required=args.ddp)
    try:
        history = train(args.data, args.out, cfg, resume=args.resume, device=args.device,
                        quiet=args.quiet, warn=_warn, max_seconds=args.max_seconds, dist=dist)
    finally:
        if dist is not None:
            dist.close()
    if dist is not None and not dist.main:
        return 0
    if history and history[-1].get("val"):
        v = history[-1]["val"]
        print(f"{PROG}: {args.out}/model.pt after {history[-1]['epoch']} epochs: validation relMSE "
              f"{v['output']:.4f}, best single input {v['best_single']:.4f} ({v['ratio']:.2f}x)")
    return 0


def _chooser(args: argparse.Namespace) -> int:
    """``ppmrecon-train chooser``."""
    import torch

    from ..cli_common import Progress
    from .chooser import ChooserTrainConfig, train_chooser

    if args.config is None:
        raise UsageError("--config: no chooser config given and none ships with the package")
    cfg = ChooserTrainConfig.load(args.config)
    if args.steps is not None:
        cfg.steps = args.steps
    if args.seed is not None:
        cfg.seed = args.seed
    if args.threads:
        torch.set_num_threads(args.threads)
    bar = Progress("chooser", total=cfg.steps, quiet=args.quiet)

    def report(step: int, value: float) -> None:
        bar.update(step, force=step == cfg.steps, loss=f"{value:.3f}")

    try:
        history = train_chooser(args.data, args.out, cfg, args.base_model, args.resume, _warn, report,
                                args.max_seconds)
    finally:
        bar.close()
    if not history["finished"]:
        done = history["losses"][-1]["step"] if history["losses"] else 0
        print(f"{PROG}: {args.out}: stopped at step {done} of {cfg.steps}; continue with --resume")
        return 0
    v = history.get("validation")
    line = f"{PROG}: {args.out}/chooser.pt after {cfg.steps} steps on {history['train_images']} images"
    if v:
        c, e = v["chooser"], v["envelope"]
        line += (f"; validation ({v['images']} images): {c['ratio']:.3f} of the best input (envelope "
                 f"{e['ratio']:.3f}), 8x8 {c['ratio_8x8']:.2f} ({e['ratio_8x8']:.2f}), worse than best "
                 f"{c['worse']} ({e['worse']})")
    print(line)
    return 0


def _torchrun_standalone(nproc: int, argv: list[str]) -> int:
    """Run this command again in ``nproc`` processes of a one-machine torchrun group;
    returns torchrun's exit status."""
    import subprocess

    rest, skip = [], False
    for a in argv:  # the same arguments less --nproc-per-node (torchrun takes it)
        if skip:
            skip = False
        elif a == "--nproc-per-node":
            skip = True
        elif not a.startswith("--nproc-per-node="):
            rest.append(a)
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={nproc}",
           "-m", "ppmrecon.train", *rest]
    return subprocess.run(cmd).returncode


def entry() -> None:
    code = run_main(PROG, main)
    distributed = sys.modules.get("ppmrecon.train.distributed")
    if distributed is not None and distributed.joined:
        distributed.exit_process(code)
    raise SystemExit(code)


if __name__ == "__main__":  # pragma: no cover
    entry()
