"""Training-data generation: buffer files at several pass counts and a reference per
generated scene, with a JSON manifest (SPEC section 6).

For scene i (family ``family_of(i)``, seed ``first_seed + i``):

* one multi-bandwidth SPPM render per input seed, snapshotted at every pass count of
  ``input_passes`` (the N = 8 file is the first 8 passes of the N = 32 render);
* one reference: single-bandwidth SPPM with ``reference_passes`` (>= 16x the largest
  input) passes of ``reference_photons`` photons.

Scenes are split into train and validation as whole scenes (every
``validation_every``-th scene is validation). Work items run in parallel worker
processes; finished items (files present and valid) are skipped on a rerun, so an
interrupted generation resumes where it stopped. The manifest records scene parameters,
budgets, file names and timings.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from .. import buffers as B
from ..cli_common import Progress
from ..errors import UsageError
from ..fileio import load_json_config, read_json, write_json
from .scenegen import family_of, sample_params

MANIFEST = "manifest.json"
MANIFEST_VERSION = 1


@dataclass
class DataConfig:
    """Budgets of a generated data set (``configs/data/*.json``)."""

    scenes: int = 24
    first_seed: int = 1000
    validation_every: int = 5
    resolution: tuple[int, int] = (96, 96)
    photons: int = 32768
    input_passes: tuple[int, ...] = (8, 16, 32)
    seeds: tuple[int, ...] = (0, 1)
    reference_passes: int = 512
    reference_photons: int = 65536
    max_depth: int = 8

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DataConfig":
        cfg = load_json_config(path, cls, "data config")
        cfg.resolution = tuple(cfg.resolution)  # type: ignore[assignment]
        cfg.input_passes = tuple(sorted(cfg.input_passes))  # type: ignore[assignment]
        cfg.seeds = tuple(cfg.seeds)  # type: ignore[assignment]
        cfg.validate(str(path))
        return cfg

    def validate(self, where: str = "data config") -> None:
        if self.scenes <= 0 or self.photons <= 0 or self.reference_photons <= 0 or self.max_depth <= 0:
            raise UsageError(f"{where}: scenes, photons and max_depth must be positive")
        if len(self.input_passes) < 3 or min(self.input_passes) <= 0:
            raise UsageError(f"{where}: input_passes needs at least three positive pass counts")
        if len(self.seeds) < 2:
            raise UsageError(f"{where}: seeds needs at least two seeds")
        if self.reference_passes < 16 * max(self.input_passes):
            raise UsageError(f"{where}: reference_passes must be >= 16x the largest input pass count "
                             f"({16 * max(self.input_passes)})")
        if len(self.resolution) != 2 or min(self.resolution) < 8:
            raise UsageError(f"{where}: resolution must be [width, height], each >= 8")


def scene_id(index: int) -> str:
    return f"{index:04d}_{family_of(index)}"


def input_name(passes: int, seed: int) -> str:
    return f"input_n{passes:04d}_s{seed}.exr"


REFERENCE = "reference.exr"


def plan(cfg: DataConfig) -> list[dict[str, Any]]:
    """The scenes of a data set: id, family, split, params (no rendering)."""
    scenes = []
    for i in range(cfg.scenes):
        family = family_of(i)
        scenes.append({
            "id": scene_id(i), "family": family, "seed": cfg.first_seed + i,
            "split": "val" if i % cfg.validation_every == 0 else "train",
            "params": sample_params(family, cfg.first_seed + i),
        })
    return scenes


def _valid(path: Path, buffer: bool) -> bool:
    try:
        if buffer:
            B.read_buffers(path)
        else:
            B.read_rgb(path)
        return True
    except Exception:
        return False


def _work_item(job: dict[str, Any]) -> dict[str, Any]:
    """Render one item in a worker process: all snapshots of one input seed, or the reference."""
    from ..backend import choose_variant

    choose_variant()
    import drjit as dr
    import mitsuba as mi

    if job.get("threads"):
        dr.set_thread_count(job["threads"])
    from ..render.integrator import Renderer, RenderSettings
    from .scenegen import build_scene

    cfg = DataConfig(**job["config"])
    folder = Path(job["folder"])
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = mi.load_dict(build_scene(job["params"], *cfg.resolution))
    name = f"generated:{job['id']}"
    files: list[dict[str, Any]] = []
    if job["kind"] == "reference":
        r = Renderer(scene, RenderSettings(passes=cfg.reference_passes, photons=cfg.reference_photons,
                                           seed=10_000 + job["scene_seed"], layout="single",
                                           max_depth=cfg.max_depth), scene_name=name)
        res = r.run()
        B.write_rgb(folder / REFERENCE, res.estimates[0], header=res.header)
        files.append({"file": REFERENCE, "passes": res.passes, "photons": cfg.reference_photons,
                      "seconds": res.seconds})
    else:
        seed = job["seed"]
        r = Renderer(scene, RenderSettings(passes=max(cfg.input_passes), photons=cfg.photons,
                                           seed=seed * 7919 + job["scene_seed"], max_depth=cfg.max_depth),
                     scene_name=name)
        snapshots = set(cfg.input_passes)

        def on_pass(rr: Renderer) -> None:
            if rr.passes_done in snapshots:
                res = rr.result()
                res.header["ppmrecon.data.seed"] = seed
                B.write_buffers(folder / input_name(rr.passes_done, seed), res.buffer_file())
                files.append({"file": input_name(rr.passes_done, seed), "passes": rr.passes_done,
                              "seed": seed, "photons": cfg.photons, "seconds": rr.seconds})

        r.run(on_pass)
    return {"id": job["id"], "kind": job["kind"], "seed": job.get("seed"), "files": files,
            "wall_seconds": time.perf_counter() - t0}


def load_manifest(root: str | os.PathLike) -> dict[str, Any]:
    """Read ``root/manifest.json`` with a one-line error when absent or broken."""
    path = Path(root) / MANIFEST
    manifest = read_json(path, "manifest", f"generate data with `ppmrecon-train generate --out {root}`")
    if manifest.get("version", 0) > MANIFEST_VERSION:
        raise UsageError(f"{path}: manifest version {manifest.get('version')} is newer than this ppmrecon")
    return manifest


def generate(cfg: DataConfig, out: str | os.PathLike, workers: int = 1, quiet: bool = False) -> dict[str, Any]:
    """Generate (or complete) the data set ``out`` for ``cfg``; returns the manifest."""
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    mpath = root / MANIFEST
    scenes = plan(cfg)
    manifest: dict[str, Any] = {"version": MANIFEST_VERSION, "config": asdict(cfg), "scenes": scenes}
    if mpath.exists():
        old = load_manifest(root)
        if old.get("config") != json.loads(json.dumps(asdict(cfg))):
            raise UsageError(f"{mpath}: the data set was generated with another configuration; "
                             "use a new --out folder")
        manifest["generation_seconds"] = old.get("generation_seconds", 0.0)
        done = {s["id"]: s for s in old["scenes"]}
        for s in scenes:
            for key in ("inputs", "reference", "seconds"):
                if key in done.get(s["id"], {}):
                    s[key] = done[s["id"]][key]

    jobs = []
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    for s in scenes:
        folder = root / s["id"]
        s.setdefault("inputs", [])
        for seed in cfg.seeds:
            wanted = [folder / input_name(n, seed) for n in cfg.input_passes]
            if all(_valid(p, True) for p in wanted) and all(
                    any(f["file"] == p.name for f in s["inputs"]) for p in wanted):
                continue
            s["inputs"] = [f for f in s["inputs"] if f.get("seed") != seed]
            jobs.append({"kind": "inputs", "seed": seed})
            jobs[-1].update(id=s["id"], scene_seed=s["seed"], params=s["params"], folder=str(folder),
                            config=asdict(cfg), threads=threads)
        if not (_valid(folder / REFERENCE, False) and s.get("reference")):
            s.pop("reference", None)
            jobs.append({"kind": "reference", "id": s["id"], "scene_seed": s["seed"], "params": s["params"],
                         "folder": str(folder), "config": asdict(cfg), "threads": threads})
    write_json(mpath, manifest)

    by_id = {s["id"]: s for s in scenes}
    progress = Progress(f"ppmrecon-train generate {root}", total=len(jobs), quiet=quiet)
    progress.update(0, force=True)
    t0 = time.perf_counter()
    results = []
    if jobs:
        ctx = mp.get_context("spawn")
        with ctx.Pool(processes=max(1, workers)) as pool:
            for k, res in enumerate(pool.imap_unordered(_work_item, jobs), 1):
                s = by_id[res["id"]]
                if res["kind"] == "reference":
                    s["reference"] = res["files"][0]
                else:
                    s["inputs"] = sorted(s["inputs"] + res["files"], key=lambda f: (f["seed"], f["passes"]))
                s["seconds"] = s.get("seconds", 0.0) + res["wall_seconds"]
                results.append(res)
                write_json(mpath, manifest)
                progress.update(k, force=True, scene=res["id"])
    progress.close()
    manifest["generation_seconds"] = manifest.get("generation_seconds", 0.0) + (time.perf_counter() - t0)
    write_json(mpath, manifest)
    return manifest
