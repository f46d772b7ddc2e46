"""Render chosen scenes of a data set first, each as its own one-scene data set (issue 12).

    .venv/bin/python benchmarks/targeted_data.py --config v2_cpu --index 21,23,28,36,39 --out data [--workers 1]

Scene i of a data config is the scene of seed ``first_seed + i`` in family ``family_of(i)``
(:func:`ppmrecon.train.datagen.plan`); its inputs and references depend on nothing else. So
the data set ``<out>/t<iiii>`` made here from a config with ``scenes`` 1, ``first_seed`` =
``first_seed + i`` and that one family holds, bit for bit, the renders the full data set
will hold for scene i (checked below before anything is rendered). Use it to re-render the
scenes a benchmark flagged (the images worse than their best input) before the rest of a
long generation, and score them with ``bench_guide.py --data <out>/t<iiii> ...``.
Generation is ``ppmrecon-train generate`` itself: resumable, one line per failure.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import asdict, replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon.cli_common import positive_int  # noqa: E402
from ppmrecon.errors import PpmreconError  # noqa: E402
from ppmrecon.fileio import write_json  # noqa: E402
from ppmrecon.train.cli import builtin_configs, config_file  # noqa: E402
from ppmrecon.train.datagen import DataConfig, generate, plan  # noqa: E402
from ppmrecon.train.scenegen import family_of  # noqa: E402


def one_scene_config(cfg: DataConfig, index: int) -> DataConfig:
    """The config whose only scene is scene ``index`` of ``cfg``."""
    return replace(cfg, scenes=1, first_seed=cfg.first_seed + index, families=(family_of(index, cfg.families),))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=config_file("data"), default=builtin_configs("data").get("v2_cpu"),
                    metavar="NAME|FILE.json", help="the full data set's config (default: v2_cpu)")
    ap.add_argument("--index", required=True, help="comma-separated scene indices of that data set")
    ap.add_argument("--out", type=Path, required=True, help="parent folder: one data set t<iiii> per index")
    ap.add_argument("--workers", type=positive_int, default=1)
    ap.add_argument("--quiet", "-q", action="store_true")
    args = ap.parse_args()
    try:
        indices = [int(v) for v in args.index.split(",")]
    except ValueError:
        sys.exit(f"targeted_data: --index: expected comma-separated integers, got {args.index!r}")
    if min(indices) < 0:
        sys.exit(f"targeted_data: --index: {min(indices)} is negative")
    try:
        cfg = DataConfig.load(args.config)
    except (PpmreconError, ValueError) as exc:
        sys.exit(f"targeted_data: {exc}")
    full = plan(replace(cfg, scenes=max(indices) + 1))
    for i in indices:
        one = one_scene_config(cfg, i)
        mine = plan(one)[0]
        if (mine["family"], mine["seed"], mine["params"]) != (full[i]["family"], full[i]["seed"], full[i]["params"]):
            sys.exit(f"targeted_data: scene {i} of {args.config} cannot be rendered alone (its parameters differ)")
        out = args.out / f"t{i:04d}"
        out.mkdir(parents=True, exist_ok=True)
        write_json(out / "config.json", {**asdict(one), "_doc": f"scene {i} ({full[i]['id']}) of {args.config}"})
        print(f"{out}: scene {i} = {full[i]['id']}, seed {mine['seed']}", flush=True)
        try:
            generate(one, out, workers=args.workers, quiet=args.quiet)
        except PpmreconError as exc:                        # a foreign data set in the folder, a failed item
            sys.exit(f"targeted_data: {exc}")


if __name__ == "__main__":
    main()
