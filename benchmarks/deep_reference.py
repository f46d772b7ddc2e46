"""Deeper references for chosen scenes of a generated data set (issue 12): how far is the
data set's own reference from converged, and which images' scores does its error decide?

    .venv/bin/python benchmarks/deep_reference.py --data data/t0028 [--scene ID ...] [--passes 4096]

For each scene, two independent single-bandwidth SPPM renders of ``--passes`` passes at the
data set's reference photon count and resolution, with seeds of their own (neither the
data set's references' nor its inputs'), written beside the data set's files as
``deep_reference_a.exr``, ``deep_reference_b.exr`` and their mean ``deep_reference.exr``
(resumable: a finished half is not rendered again), plus ``deep_reference.json``: passes,
seeds, seconds, and per reference (the data set's mean, each of its halves, the deep mean)
its relMSE against the deep mean or the other deep half. ``bench_guide.py --data ...
--deep-references`` then scores every input against ``deep_reference.exr``.

Why: the two references of a data-set scene agree where they are both dark by chance. In a
region that only rare, powerful photons reach (a caustic through a glass sphere), a 512-pass
reference is itself a speckle field, mostly 0 with a few pixels of 1e3, and a denoised pixel
near the regional mean is scored as a catastrophic error against a reference pixel of ~1.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.cli_common import positive_int  # noqa: E402
from ppmrecon.errors import PpmreconError  # noqa: E402
from ppmrecon.fileio import write_json  # noqa: E402
from ppmrecon.metrics import relmse  # noqa: E402
from ppmrecon.train.datagen import REFERENCE, DataConfig, load_manifest, stored_config, work_item  # noqa: E402

DEEP = "deep_reference.exr"
DEEP_HALVES = ("deep_reference_a.exr", "deep_reference_b.exr")
#: What each scene's deep renders were: passes, photons, seeds, seconds, agreement.
DEEP_RECORD = "deep_reference.json"
#: Added to a scene's seed for the deep renders: their seeds (REFERENCE_SEED_BASE + this +
#: scene seed) are neither the data set's references' nor its inputs'.
DEEP_SEED_OFFSET = 7_000_000


def deep_half(data: Path, scene: dict, cfg: DataConfig, half: int) -> dict:
    """Render (or find) deep half ``half`` of ``scene``; returns its record."""
    folder = data / scene["id"]
    path = folder / DEEP_HALVES[half]
    if path.exists():
        _, header = B.read_rgb(path)
        passes = int(float(header.get(B.H_PASSES, -1)))
        if passes != cfg.reference_passes:
            sys.exit(f"deep_reference: {path}: has {passes} passes, not --passes {cfg.reference_passes} "
                     "(remove it, or rerun with its pass count)")
        return {"file": path.name, "passes": passes, "reused": True}
    tmp = folder / f".deep_{half}"
    job = {"kind": "reference", "half": half, "id": scene["id"], "params": scene["params"],
           "scene_seed": scene["seed"] + DEEP_SEED_OFFSET, "folder": str(tmp), "config": asdict(cfg)}
    res = work_item(job)
    rendered = tmp / res["files"][0]["file"]
    rendered.replace(path)   # same folder tree: an atomic rename
    shutil.rmtree(tmp, ignore_errors=True)
    return {"file": path.name, "passes": res["files"][0]["passes"], "seed": res["files"][0]["seed"],
            "seconds": res["render_seconds"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="a generated data set (ppmrecon-train generate)")
    ap.add_argument("--scene", action="append", default=[], help="scene id (repeat; default: every scene)")
    ap.add_argument("--passes", type=positive_int, default=4096, help="passes of each deep half (default 4096)")
    args = ap.parse_args()
    try:
        manifest = load_manifest(args.data)
        cfg = replace(DataConfig(**stored_config(manifest)), reference_passes=args.passes, reference_chunks=1,
                      references=2)
    except (PpmreconError, TypeError, ValueError) as exc:
        sys.exit(f"deep_reference: {args.data}: {exc}")
    scenes = [s for s in manifest["scenes"] if not args.scene or s["id"] in args.scene]
    missing = set(args.scene) - {s["id"] for s in scenes}
    if missing:
        sys.exit(f"deep_reference: --scene: {args.data} has no scene {', '.join(sorted(missing))}")
    for scene in scenes:
        t0 = time.perf_counter()
        halves = [deep_half(args.data, scene, cfg, h) for h in (0, 1)]
        folder = args.data / scene["id"]
        a, b = (B.read_rgb(folder / name)[0] for name in DEEP_HALVES)
        deep = 0.5 * (a + b)
        B.write_rgb(folder / DEEP, deep.astype(np.float32), header={B.H_PASSES: str(2 * args.passes)})
        ref = B.read_rgb(folder / REFERENCE)[0] if (folder / REFERENCE).exists() else None
        from bench_guide import reference_error   # its definition of a reference's own error

        agreement = {"deep halves a vs b": relmse(a, b),
                     "deep mean's own error (|a - b|^2 / 4)": reference_error(a, b)["relmse"]}
        if ref is not None:
            agreement["data set reference vs deep mean"] = relmse(ref, deep)
            for name in ("reference_a.exr", "reference_b.exr"):
                if (folder / name).exists():
                    agreement[f"data set {name} vs deep mean"] = relmse(B.read_rgb(folder / name)[0], deep)
        write_json(folder / DEEP_RECORD, {"passes_per_half": args.passes, "photons": cfg.reference_photons,
                                                    "halves": halves, "relmse": agreement})
        figures = "; ".join(f"{k} {v:.3g}" for k, v in agreement.items())
        print(f"{scene['id']}: {time.perf_counter() - t0:.0f}s; {figures}", flush=True)


if __name__ == "__main__":
    main()
