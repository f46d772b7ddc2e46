"""Training-data generation: buffer files at several pass counts and references per
generated scene, with a JSON manifest (SPEC section 6).

For scene i (family ``family_of(i, families)``, seed ``first_seed + i``):

* one multi-bandwidth SPPM render per input seed, snapshotted at every pass count of
  ``input_passes`` (the N = 16 file is the first 16 passes of the N = 1024 render);
* ``references`` = 2 (the default): two independent single-bandwidth SPPM renders,
  ``reference_a.exr`` and ``reference_b.exr``, each ``reference_passes`` passes of
  ``reference_photons`` photons with its own seed. The training reference
  ``reference.exr`` is their mean, and the manifest records their *agreement*: the
  relMSE between the two (plain and with the 0.1% largest pixel errors left out, both
  averaged over the two ways round; also on both images divided by their mean,
  ``relmse_normalised``, which unlike relMSE's +0.01 does not depend on the radiance
  scale). Two independent renders with noise sigma^2 each
  differ by 2 sigma^2 and their mean has sigma^2 / 2, so the mean's own relMSE is about
  a quarter of the agreement (``mean_relmse_estimate``); bias, which both halves share,
  is not in that figure. ``references`` = 1 is the layout of version-1 data sets: one
  render (the seed of half a) written as ``reference.exr``.

Per input file the manifest counts *fireflies* against the training reference: pixels
where ~y or ~z^4 is a firefly by :func:`ppmrecon.metrics.firefly_mask` (more than 10x
(reference + 1% of the reference's image mean), on channel means). ~y (hit point A, the
smallest bandwidth) shows photon and A-path fireflies, ~z^4 (hit point B, the largest
bandwidth) mostly eye-path fireflies that every ~z^j shares.

Scenes are split into train and validation as whole scenes (every
``validation_every``-th scene is validation). Work items (one input seed, or one
reference render) run in parallel worker processes; finished items (files present and
valid) are skipped on a rerun, so an interrupted generation resumes where it stopped.
The manifest records scene parameters, budgets, file names and per-item wall times.
Manifest version 2 adds the reference halves, their agreement, firefly counts and the
``items`` table; readers take version 1 too (:mod:`.dataset` needs only
``reference.exr`` and the inputs), and a version-1 data set can be completed with a
config that keeps the version-1 values of the new keys (``LEGACY_CONFIG``).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import buffers as B
from ..cli_common import Progress
from ..errors import UsageError
from ..fileio import load_json_config, read_json, write_json
from ..metrics import firefly_mask, relmse, relmse_trimmed
from .scenegen import FAMILIES, LEGACY_FAMILIES, RADIANCE_LOG10, family_of, sample_params

MANIFEST = "manifest.json"
MANIFEST_VERSION = 2
REFERENCE = "reference.exr"
REFERENCE_HALVES = ("reference_a.exr", "reference_b.exr")
#: Random streams of the two reference renders (half a keeps the version-1 seed).
REFERENCE_SEED_BASE = (10_000, 1_000_000)
#: Worst fraction of pixels left out of the trimmed agreement (SPEC section 7).
AGREEMENT_TRIM = 1e-3
#: Values of the keys added in manifest version 2 that make exactly a version-1 data set.
LEGACY_CONFIG: dict[str, Any] = {"families": list(LEGACY_FAMILIES), "radiance_log10": None, "references": 1}


@dataclass
class DataConfig:
    """Budgets of a generated data set (``ppmrecon/data/configs/data/*.json``)."""

    scenes: int = 24
    first_seed: int = 1000
    validation_every: int = 5
    resolution: tuple[int, int] = (96, 96)
    photons: int = 32768
    input_passes: tuple[int, ...] = (8, 16, 32)
    seeds: tuple[int, ...] = (0, 1)
    reference_passes: int = 512
    reference_photons: int = 65536
    #: Segments of a whole path (Mitsuba's max_depth); -1 = unbounded with roulette.
    max_depth: int = 8
    #: Scene families, in round-robin order over the scene index (default: all).
    families: tuple[str, ...] = FAMILIES
    #: Global emitter scale 10^U(lo, hi) per scene; None: none (scale 1).
    radiance_log10: tuple[float, float] | None = RADIANCE_LOG10
    #: Independent reference renders per scene: 2 (mean + agreement) or 1 (version 1).
    references: int = 2

    def __post_init__(self) -> None:
        # JSON gives lists; the manifest comparison and hashing want tuples
        self.resolution = tuple(self.resolution)  # type: ignore[assignment]
        self.input_passes = tuple(sorted(self.input_passes))  # type: ignore[assignment]
        self.seeds = tuple(self.seeds)  # type: ignore[assignment]
        self.families = tuple(self.families)  # type: ignore[assignment]
        if self.radiance_log10 is not None:
            self.radiance_log10 = tuple(self.radiance_log10)  # type: ignore[assignment]

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DataConfig":
        cfg = load_json_config(path, cls, "data config")
        cfg.validate(str(path))
        return cfg

    def validate(self, where: str = "data config") -> None:
        if self.scenes <= 0 or self.photons <= 0 or self.reference_photons <= 0:
            raise UsageError(f"{where}: scenes and photons must be positive")
        if self.max_depth == 0 or self.max_depth < -1:
            raise UsageError(f"{where}: max_depth must be positive (path segments) or -1 (unbounded), "
                             f"got {self.max_depth}")
        if len(self.input_passes) < 3 or min(self.input_passes) <= 0:
            raise UsageError(f"{where}: input_passes needs at least three positive pass counts")
        if len(self.seeds) < 2 or len(set(self.seeds)) != len(self.seeds):
            raise UsageError(f"{where}: seeds needs at least two different seeds")
        if self.references not in (1, 2):
            raise UsageError(f"{where}: references must be 1 or 2, got {self.references}")
        # The reference (all its renders together) gets at least 16x the photons of the
        # largest input: passes x photons per pass.
        need = 16 * max(self.input_passes) * self.photons
        have = self.references * self.reference_passes * self.reference_photons
        if have < need:
            raise UsageError(f"{where}: the reference budget (references x reference_passes x reference_photons "
                             f"= {have}) must be >= 16x the largest input's photons ({need})")
        if len(self.resolution) != 2 or min(self.resolution) < 8:
            raise UsageError(f"{where}: resolution must be [width, height], each >= 8")
        unknown = [f for f in self.families if f not in FAMILIES]
        if not self.families or unknown:
            raise UsageError(f"{where}: unknown scene famil{'ies' if len(unknown) > 1 else 'y'} "
                             f"{', '.join(unknown) or '(none given)'} (choose from {', '.join(FAMILIES)})")
        if self.radiance_log10 is not None and (len(self.radiance_log10) != 2
                                                or not self.radiance_log10[0] <= self.radiance_log10[1]):
            raise UsageError(f"{where}: radiance_log10 must be [lo, hi] with lo <= hi, or null")


def _as_json(value: Any) -> Any:
    return json.loads(json.dumps(value))


def scene_id(index: int, families: tuple[str, ...] | list[str] = FAMILIES) -> str:
    return f"{index:04d}_{family_of(index, families)}"


def input_name(passes: int, seed: int) -> str:
    return f"input_n{passes:04d}_s{seed}.exr"


def reference_files(cfg: DataConfig) -> tuple[str, ...]:
    """The reference renders of a scene: the two halves, or the single version-1 file."""
    return REFERENCE_HALVES if cfg.references == 2 else (REFERENCE,)


def plan(cfg: DataConfig) -> list[dict[str, Any]]:
    """The scenes of a data set: id, family, split, params (no rendering)."""
    scenes = []
    for i in range(cfg.scenes):
        family = family_of(i, cfg.families)
        scenes.append({
            "id": scene_id(i, cfg.families), "family": family, "seed": cfg.first_seed + i,
            "split": "val" if i % cfg.validation_every == 0 else "train",
            "params": sample_params(family, cfg.first_seed + i, radiance_log10=cfg.radiance_log10),
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
    """Render one item in a worker process: all snapshots of one input seed, or one
    reference render."""
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
        half = job["half"]
        seed = REFERENCE_SEED_BASE[half] + job["scene_seed"]
        r = Renderer(scene, RenderSettings(passes=cfg.reference_passes, photons=cfg.reference_photons,
                                           seed=seed, layout="single", max_depth=cfg.max_depth), scene_name=name)
        res = r.run()
        fname = reference_files(cfg)[half]
        B.write_rgb(folder / fname, res.estimates[0], header=res.header)
        files.append({"file": fname, "passes": res.passes, "photons": cfg.reference_photons,
                      "seed": seed, "seconds": res.seconds})
        render_seconds = res.seconds
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

        render_seconds = r.run(on_pass).seconds
    return {"id": job["id"], "kind": job["kind"], "seed": job.get("seed"), "half": job.get("half"),
            "files": files, "wall_seconds": time.perf_counter() - t0, "render_seconds": render_seconds}


def load_manifest(root: str | os.PathLike) -> dict[str, Any]:
    """Read ``root/manifest.json`` with a one-line error when absent or broken."""
    path = Path(root) / MANIFEST
    manifest = read_json(path, "manifest", f"generate data with `ppmrecon-train generate --out {root}`")
    if manifest.get("version", 0) > MANIFEST_VERSION:
        raise UsageError(f"{path}: manifest version {manifest.get('version')} is newer than this ppmrecon")
    return manifest


def stored_config(manifest: dict[str, Any]) -> dict[str, Any]:
    """The manifest's data config with every key a version-1 manifest lacks set to the
    value that made version-1 data (so such a data set compares equal to its config)."""
    config = dict(LEGACY_CONFIG)
    config.update(manifest.get("config", {}))
    return _as_json(config)


def _item_key(kind: str, seed: int | None = None, half: int | None = None) -> str:
    return f"inputs_s{seed}" if kind == "inputs" else f"reference_{'ab'[half or 0]}"


def _finish_scene(root: Path, s: dict[str, Any], cfg: DataConfig) -> bool:
    """Once a scene's reference renders exist: write the mean reference and the agreement
    (two halves), then count fireflies in every input that lacks the count. Returns
    whether anything changed; cheap, so it runs after every item and on every rerun."""
    folder = root / s["id"]
    refs = {f["file"]: f for f in s.get("references", [])}
    names = reference_files(cfg)
    if not all(n in refs for n in names):
        return False
    changed = False
    if cfg.references == 2 and not (s.get("reference") and s.get("agreement") and _valid(folder / REFERENCE, False)):
        (a, header), (b, _) = (B.read_rgb(folder / n) for n in names)
        header = dict(header)
        header[B.H_SEED] = ",".join(str(refs[n]["seed"]) for n in names)
        header[B.H_SECONDS] = sum(refs[n]["seconds"] for n in names)
        header["ppmrecon.data.reference"] = "mean of " + " and ".join(names)
        B.write_rgb(folder / REFERENCE, 0.5 * (a + b), header=header)
        plain = 0.5 * (relmse(a, b) + relmse(b, a))
        trimmed = 0.5 * (relmse_trimmed(a, b, AGREEMENT_TRIM) + relmse_trimmed(b, a, AGREEMENT_TRIM))
        # relMSE's +0.01 makes a dim scene (radiance scale 1e-4) look converged whatever its
        # noise: the same figures on images divided by their mean do not depend on the scale
        m = max(float(np.mean(0.5 * (a + b))), 1e-30)
        an, bn = a / m, b / m
        s["agreement"] = {"relmse": plain, "relmse_a_vs_b": relmse(a, b), "relmse_b_vs_a": relmse(b, a),
                          "relmse_trimmed": trimmed, "trim": AGREEMENT_TRIM,
                          "mean_relmse_estimate": plain / 4, "mean_relmse_trimmed_estimate": trimmed / 4,
                          "image_mean": m, "relmse_normalised": 0.5 * (relmse(an, bn) + relmse(bn, an)),
                          "relmse_normalised_trimmed": 0.5 * (relmse_trimmed(an, bn, AGREEMENT_TRIM)
                                                              + relmse_trimmed(bn, an, AGREEMENT_TRIM))}
        s["reference"] = {"file": REFERENCE, "passes": cfg.reference_passes, "photons": cfg.reference_photons,
                          "renders": 2, "seconds": header[B.H_SECONDS]}
        for f in s.get("inputs", []):  # counted against the old mean: count again
            f.pop("fireflies", None)
        changed = True
    elif cfg.references == 1 and not s.get("reference"):
        s["reference"] = dict(refs[REFERENCE])
        changed = True
    pending = [f for f in s.get("inputs", []) if "fireflies" not in f]
    if pending:
        ref, _ = B.read_rgb(folder / REFERENCE)
        for f in pending:
            try:
                buf = B.read_buffers(folder / f["file"])
            except B.BufferFileError:
                continue  # found and redone by the next rerun's validity check
            y, z4 = firefly_mask(buf.estimates[0], ref), firefly_mask(buf.estimates[-1], ref)
            f["fireflies"] = int((y | z4).sum())
            f["fireflies_y"], f["fireflies_z4"] = int(y.sum()), int(z4.sum())
        changed = True
    return changed


def generate(cfg: DataConfig, out: str | os.PathLike, workers: int = 1, quiet: bool = False) -> dict[str, Any]:
    """Generate (or complete) the data set ``out`` for ``cfg``; returns the manifest."""
    cfg.validate()
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    mpath = root / MANIFEST
    scenes = plan(cfg)
    manifest: dict[str, Any] = {"version": MANIFEST_VERSION, "config": asdict(cfg), "scenes": scenes}
    if mpath.exists():
        old = load_manifest(root)
        if stored_config(old) != _as_json(asdict(cfg)):
            raise UsageError(f"{mpath}: the data set was generated with another configuration; "
                             "use a new --out folder")
        manifest["generation_seconds"] = old.get("generation_seconds", 0.0)
        done = {s["id"]: s for s in old["scenes"]}
        for s in scenes:
            prev = done.get(s["id"], {})
            for key in ("inputs", "reference", "references", "agreement", "items", "seconds"):
                if key in prev:
                    s[key] = prev[key]
            if cfg.references == 1 and "reference" in prev and "references" not in prev:
                s["references"] = [prev["reference"]]  # a version-1 scene

    jobs = []
    threads = max(1, (os.cpu_count() or 1) // max(1, workers))
    for s in scenes:
        folder = root / s["id"]
        s.setdefault("inputs", [])
        s.setdefault("references", [])
        s.setdefault("items", {})
        common = {"id": s["id"], "scene_seed": s["seed"], "params": s["params"], "folder": str(folder),
                  "config": asdict(cfg), "threads": threads}
        for seed in cfg.seeds:
            wanted = [folder / input_name(n, seed) for n in cfg.input_passes]
            if all(_valid(p, True) for p in wanted) and all(
                    any(f["file"] == p.name for f in s["inputs"]) for p in wanted):
                continue
            s["inputs"] = [f for f in s["inputs"] if f.get("seed") != seed]
            jobs.append({"kind": "inputs", "seed": seed, **common})
        for half, name in enumerate(reference_files(cfg)):
            if _valid(folder / name, False) and any(f["file"] == name for f in s["references"]):
                continue
            s["references"] = [f for f in s["references"] if f["file"] != name]
            s.pop("reference", None)  # the mean (or the single reference) is redone
            s.pop("agreement", None)
            jobs.append({"kind": "reference", "half": half, **common})
        _finish_scene(root, s, cfg)
    write_json(mpath, manifest)

    by_id = {s["id"]: s for s in scenes}
    progress = Progress(f"ppmrecon-train generate {root}", total=len(jobs), quiet=quiet)
    progress.update(0, force=True)
    t0 = time.perf_counter()
    if jobs:
        ctx = mp.get_context("spawn")
        with ctx.Pool(processes=max(1, workers)) as pool:
            for k, res in enumerate(pool.imap_unordered(_work_item, jobs), 1):
                s = by_id[res["id"]]
                if res["kind"] == "reference":
                    s["references"] = sorted(s["references"] + res["files"], key=lambda f: f["file"])
                    budget = {"passes": cfg.reference_passes, "photons": cfg.reference_photons}
                else:
                    s["inputs"] = sorted(s["inputs"] + res["files"], key=lambda f: (f["seed"], f["passes"]))
                    budget = {"passes": max(cfg.input_passes), "photons": cfg.photons}
                s["items"][_item_key(res["kind"], res["seed"], res["half"])] = {
                    **budget, "render_seconds": res["render_seconds"], "wall_seconds": res["wall_seconds"]}
                s["seconds"] = s.get("seconds", 0.0) + res["wall_seconds"]
                _finish_scene(root, s, cfg)
                write_json(mpath, manifest)
                progress.update(k, force=True, scene=res["id"])
    progress.close()
    manifest["generation_seconds"] = manifest.get("generation_seconds", 0.0) + (time.perf_counter() - t0)
    write_json(mpath, manifest)
    return manifest
