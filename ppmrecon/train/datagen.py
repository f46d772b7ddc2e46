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
``validation_every``-th scene is validation). Work items (one input seed, one reference
render, or one chunk of a reference's passes) run in parallel: local worker processes,
or Ray tasks on a cluster (:mod:`.raygen`, ``--ray``), which give the same files and
manifest. Finished items (files present and valid) are skipped on a rerun, so an
interrupted generation resumes where it stopped, and the same configuration with more
scenes grows a data set (scene i depends on i alone: the first ones are kept as they
are, and a growing set can be trained on while it grows); an item whose worker raised (or, on
Ray, failed all its retries) is recorded as failed in the manifest's ``items`` and the
run ends with an error naming it, never dropped silently.

With ``reference_chunks`` = K > 1 each reference render is split into K ranges of
passes (:func:`reference_chunk_bounds`), rendered as separate items, each of which
stores its Welford state (per-pixel mean and M2 over its passes); once all K exist they
are merged (:func:`..render.estimates.merge_welford`) into the reference. References
are SPPM, whose radius at pass i depends only on the initial radii and i, and pass i's
random numbers only on (seed, i): a chunk renders exactly the passes of the one long
run (:meth:`..render.integrator.Renderer.start_at`), so the merged mean *is* the
single run's estimate, up to float32 rounding of the running mean (not a mean of
independent shorter runs, which would carry the larger bias of the shorter run).
The manifest records scene parameters, budgets, file names and per-item wall times.
:func:`estimate` (``generate --estimate``) measures what a configuration would cost on the
machine at hand before any of it is rendered: a few timed passes of each family's first
scene, projected over every item (:func:`project`).
Manifest version 2 adds the reference halves, their agreement, firefly counts and the
``items`` table; readers take version 1 too (:mod:`.dataset` needs only
``reference.exr`` and the inputs), and a version-1 data set can be completed with a
config that keeps the version-1 values of the new keys (``LEGACY_CONFIG``).
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterator, Protocol

import numpy as np

from .. import buffers as B
from ..cli_common import Progress
from ..errors import PpmreconError, UsageError
from ..fileio import load_json_config, read_json, write_json
from ..metrics import firefly_mask, relmse, relmse_trimmed
from .scenegen import FAMILIES, LEGACY_FAMILIES, RADIANCE_LOG10, family_of, sample_params

if TYPE_CHECKING:                      # Mitsuba is imported in the worker processes only
    from ..render.integrator import Renderer, RenderSettings

MANIFEST = "manifest.json"
#: Chunk files: the Welford state of a range of a reference's passes (see module doc).
CHUNK_FORMAT = "ppmrecon-reference-chunk"
MANIFEST_VERSION = 2
REFERENCE = "reference.exr"
REFERENCE_HALVES = ("reference_a.exr", "reference_b.exr")
#: Random streams of the two reference renders (half a keeps the version-1 seed).
REFERENCE_SEED_BASE = (10_000, 1_000_000)
#: How long a timing item of ``estimate`` waits for the others of its round to be ready.
BARRIER_SECONDS = 300.0
#: Worst fraction of pixels left out of the trimmed agreement (SPEC section 7).
AGREEMENT_TRIM = 1e-3
#: Values of the keys added in manifest version 2 that make exactly a version-1 data set.
LEGACY_CONFIG: dict[str, Any] = {"families": list(LEGACY_FAMILIES), "radiance_log10": None, "references": 1}
#: Config keys added later within manifest version 2, with the value data made before had.
LATER_DEFAULTS: dict[str, Any] = {"reference_chunks": 1}


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
    #: Ranges of passes each reference render is split into (separate work items, merged
    #: exactly; see the module docstring). 1: one item per reference render.
    reference_chunks: int = 1

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
        if not 1 <= self.reference_chunks <= self.reference_passes:
            raise UsageError(f"{where}: reference_chunks must lie in 1..reference_passes "
                             f"({self.reference_passes}), got {self.reference_chunks}")
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


def reference_chunk_bounds(passes: int, chunks: int) -> list[tuple[int, int]]:
    """(first, last) pass, 1-based and inclusive, of each of ``chunks`` ranges that
    split passes 1..``passes`` as evenly as possible."""
    return [(c * passes // chunks + 1, (c + 1) * passes // chunks) for c in range(chunks)]


def chunk_name(reference: str, chunk: int, chunks: int) -> str:
    """File of chunk ``chunk`` (0-based) of reference render ``reference``."""
    return f"{Path(reference).stem}.chunk{chunk + 1:02d}of{chunks:02d}.npz"


def write_chunk(path: str | os.PathLike, mean: np.ndarray, m2: np.ndarray, meta: dict[str, Any]) -> None:
    """A chunk's Welford state (mean, M2: (3, pixels)) and its JSON record, atomically."""
    from ..render.state import write_state

    write_state(path, {"format": CHUNK_FORMAT, **_as_json(meta)}, {"mean": mean, "m2": m2})


def read_chunk(path: str | os.PathLike) -> tuple[dict[str, Any], np.ndarray, np.ndarray] | None:
    """(record, mean, M2) of a chunk file, or None if it is absent, cut or not a chunk."""
    from ..render.state import META_KEY

    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z[META_KEY]).decode("utf-8"))
            mean, m2 = z["mean"], z["m2"]
    except Exception:
        return None
    if not isinstance(meta, dict) or meta.get("format") != CHUNK_FORMAT or mean.shape != m2.shape:
        return None
    if not (np.isfinite(mean).all() and np.isfinite(m2).all()):
        return None
    return meta, mean, m2


def _chunk_valid(path: Path, first: int, last: int, seed: int) -> bool:
    got = read_chunk(path)
    return got is not None and (got[0].get("first_pass"), got[0].get("last_pass"), got[0].get("count"),
                                got[0].get("seed")) == (first, last, last - first + 1, seed)


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


def _job_ids(job: dict[str, Any]) -> dict[str, Any]:
    """What names a work item in its result (scene, kind, input seed, half, chunk)."""
    return {"id": job["id"], "kind": job["kind"], "seed": job.get("seed"), "half": job.get("half"),
            "chunk": job.get("chunk")}


def describe_item(res: dict[str, Any]) -> str:
    """A work item in words: scene id and item key, e.g. ``0001_glossy reference_a_c02``."""
    return f"{res['id']} {_item_key(res['kind'], res.get('seed'), res.get('half'), res.get('chunk'))}"


def item_settings(job: dict[str, Any], cfg: "DataConfig", passes: int) -> "RenderSettings":
    """The render settings of work item ``job`` run to pass ``passes``: an input seed's
    five-chain render at ``photons`` per pass, or a reference half's single-bandwidth SPPM
    render at ``reference_photons`` with its own random stream (:data:`REFERENCE_SEED_BASE`)."""
    from ..render.integrator import RenderSettings

    if job["kind"] == "reference":
        return RenderSettings(passes=passes, photons=cfg.reference_photons,
                              seed=REFERENCE_SEED_BASE[job["half"]] + job["scene_seed"], layout="single",
                              max_depth=cfg.max_depth)
    return RenderSettings(passes=passes, photons=cfg.photons, seed=job["seed"] * 7919 + job["scene_seed"],
                          max_depth=cfg.max_depth)


def _time_item(job: dict[str, Any], make: Callable[[], "Renderer"], passes: int) -> dict[str, Any]:
    """Time an item's first pass (compilation, the k-NN initial radii) on a renderer from
    ``make()``, then, on a second one placed halfway through the item's ``passes``
    (:meth:`Renderer.start_at`: the first passes' larger radii gather more photons, so
    they cost more than the bulk of a long render) and after one untimed pass, passes for
    ``job["estimate"]`` seconds (at least two); nothing is written. With ``job["barrier"]``
    the items running at once start their timed passes together, so that they share the
    cores as ``generate``'s workers do (one core's rate would flatter a busy machine)."""
    first = make()
    first.run_pass()
    bulk = make()
    bulk.start_at(max(1, passes // 2))
    bulk.run_pass()
    barrier = job.get("barrier")
    if barrier is not None:
        try:
            barrier.wait(timeout=BARRIER_SECONDS)
        except threading.BrokenBarrierError:      # the last round may hold fewer items than workers
            pass
    start, stop, timed = bulk.seconds, time.perf_counter() + job["estimate"], 0
    while timed < 2 or time.perf_counter() < stop:
        bulk.run_pass()
        timed += 1
    return {**_job_ids(job), "first_seconds": first.seconds, "pass_seconds": (bulk.seconds - start) / timed,
            "passes_timed": timed}


def work_item(job: dict[str, Any]) -> dict[str, Any]:
    """Render one item (in a worker process or Ray task) into ``job["folder"]``: all
    snapshots of one input seed, one reference render, or one chunk of a reference's
    passes. Returns the item's files and times; raises on failure. Meant for a worker
    process: ``job["threads"]`` sets Dr.Jit's thread count of the whole process (after
    which Mitsuba 3.9's ``Bitmap.write`` of an EXR deadlocks, so not in a process that
    goes on using Mitsuba's image I/O)."""
    from ..backend import choose_variant

    variant = choose_variant(job.get("variant"))
    import drjit as dr
    import mitsuba as mi

    if job.get("threads"):
        dr.set_thread_count(job["threads"])
    from ..render.integrator import Renderer
    from .scenegen import build_scene

    cfg = DataConfig(**job["config"])
    folder = None if job.get("estimate") else Path(job["folder"])   # a timing run writes nothing
    t0 = time.perf_counter()
    scene = mi.load_dict(build_scene(job["params"], *cfg.resolution))
    name = f"generated:{job['id']}"
    if folder is None:
        passes = cfg.reference_passes if job["kind"] == "reference" else max(cfg.input_passes)
        return _time_item(job, lambda: Renderer(scene, item_settings(job, cfg, passes), scene_name=name), passes)
    folder.mkdir(parents=True, exist_ok=True)
    files: list[dict[str, Any]] = []
    if job["kind"] == "reference":
        half, chunk = job["half"], job.get("chunk")
        first, last = ((1, cfg.reference_passes) if chunk is None
                       else reference_chunk_bounds(cfg.reference_passes, cfg.reference_chunks)[chunk])
        settings = item_settings(job, cfg, last)
        r = Renderer(scene, settings, scene_name=name)
        r.start_at(first)
        res = r.run()
        seed = settings.seed
        entry = {"photons": cfg.reference_photons, "seed": seed, "seconds": res.seconds}
        if chunk is None:
            fname = reference_files(cfg)[half]
            B.write_rgb(folder / fname, res.estimates[0], header=res.header)
            files.append({"file": fname, "passes": res.passes, **entry})
        else:
            fname = chunk_name(reference_files(cfg)[half], chunk, cfg.reference_chunks)
            acc = r.means[0]
            write_chunk(folder / fname, np.array(acc.mean), np.array(acc.m2),
                        {"first_pass": first, "last_pass": last, "count": acc.n, "seed": seed,
                         "width": r.width, "height": r.height, "header": res.header})
            files.append({"file": fname, "first_pass": first, "last_pass": last, "passes": acc.n, **entry})
        render_seconds = res.seconds
    else:
        seed = job["seed"]
        r = Renderer(scene, item_settings(job, cfg, max(cfg.input_passes)), scene_name=name)
        snapshots = set(cfg.input_passes)

        def on_pass(rr: Renderer) -> None:
            if rr.passes_done in snapshots:
                res = rr.result()
                res.header["ppmrecon.data.seed"] = seed
                B.write_buffers(folder / input_name(rr.passes_done, seed), res.buffer_file())
                files.append({"file": input_name(rr.passes_done, seed), "passes": rr.passes_done,
                              "seed": seed, "photons": cfg.photons, "seconds": rr.seconds})

        render_seconds = r.run(on_pass).seconds
    return {**_job_ids(job), "files": files, "wall_seconds": time.perf_counter() - t0,
            "render_seconds": render_seconds, "variant": variant}


def one_line(exc: BaseException) -> str:
    """An exception as one line: its type and the first line of its message."""
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def _local_item(job: dict[str, Any]) -> dict[str, Any]:
    """:func:`work_item` in a local pool process; a failure comes back as a result with
    ``error`` (recorded in the manifest) instead of ending the whole pool."""
    try:
        return work_item(job)
    except Exception as exc:
        return {**_job_ids(job), "error": one_line(exc), "attempts": 1}


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
    config = {**LEGACY_CONFIG, **LATER_DEFAULTS}
    config.update(manifest.get("config", {}))
    return _as_json(config)


def _item_key(kind: str, seed: int | None = None, half: int | None = None, chunk: int | None = None) -> str:
    if kind == "inputs":
        return f"inputs_s{seed}"
    return f"reference_{'ab'[half or 0]}" + ("" if chunk is None else f"_c{chunk + 1:02d}")


def _merge_chunks(root: Path, s: dict[str, Any], cfg: DataConfig) -> bool:
    """Merge the chunks of every reference render whose chunks are all listed and valid
    into the reference file (sample-count-weighted Welford merge, i.e. the mean over all
    its passes); returns whether a reference was written."""
    from ..render.estimates import merge_welford

    folder = root / s["id"]
    listed = {f["file"] for f in s.get("references", [])}
    entries = {f["file"]: f for f in s.get("chunks", [])}
    changed = False
    for name in reference_files(cfg):
        names = [chunk_name(name, c, cfg.reference_chunks) for c in range(cfg.reference_chunks)]
        if name in listed or not all(n in entries for n in names):
            continue
        parts = [read_chunk(folder / n) for n in names]
        if any(p is None for p in parts):
            continue  # found and redone by the next rerun's validity check
        mean, _, n = merge_welford([(p[1], p[2], int(p[0]["count"])) for p in parts])
        meta = parts[-1][0]
        header = dict(meta["header"])
        seconds = sum(float(p[0]["header"].get(B.H_SECONDS, 0.0)) for p in parts)
        header.update({B.H_PASSES: n, B.H_SECONDS: seconds, "ppmrecon.data.chunks": cfg.reference_chunks})
        for key in [k for k in header if k.startswith("ppmrecon.nonfinite")]:
            header[key] = sum(int(p[0]["header"].get(key, 0)) for p in parts)
        rgb = mean.reshape(3, meta["height"], meta["width"]).transpose(1, 2, 0).astype(np.float32)
        B.write_rgb(folder / name, rgb, header=header)
        s["references"] = sorted(s.get("references", []) + [
            {"file": name, "passes": n, "photons": cfg.reference_photons, "seed": meta["seed"],
             "seconds": seconds, "chunks": cfg.reference_chunks}], key=lambda f: f["file"])
        changed = True
    return changed


def _finish_scene(root: Path, s: dict[str, Any], cfg: DataConfig) -> bool:
    """Once a scene's reference renders exist: write the mean reference and the agreement
    (two halves), then count fireflies in every input that lacks the count. Returns
    whether anything changed; cheap, so it runs after every item and on every rerun."""
    folder = root / s["id"]
    changed = cfg.reference_chunks > 1 and _merge_chunks(root, s, cfg)
    refs = {f["file"]: f for f in s.get("references", [])}
    names = reference_files(cfg)
    if not all(n in refs for n in names):
        return changed
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


class GenerationError(PpmreconError):
    """Work items failed (recorded in the manifest); a rerun retries them."""

    exit_code = 1


class Runner(Protocol):
    """Where work items run: :class:`LocalRunner` or :class:`.raygen.RayRunner`."""

    #: Short name for the progress line.
    label: str
    #: Dr.Jit threads per item.
    threads: int

    def run(self, jobs: list[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        """Yield one result per job, in the order they finish: :func:`work_item`'s return
        value with its files in the job's ``folder``, or ``_job_ids`` plus ``error``."""
        ...


class LocalRunner:
    """A pool of ``workers`` spawned processes on this machine."""

    def __init__(self, workers: int = 1, threads: int | None = None):
        self.workers = max(1, workers)
        self.label = f"{self.workers} local worker{'s' if self.workers > 1 else ''}"
        # Dr.Jit threads: by default the cores shared out between the workers
        self.threads = threads or max(1, (os.cpu_count() or 1) // self.workers)

    def run(self, jobs: list[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        ctx = mp.get_context("spawn")  # Dr.Jit and torch do not survive fork
        with ctx.Pool(processes=self.workers) as pool:
            yield from pool.imap_unordered(_local_item, jobs)


def _record(s: dict[str, Any], res: dict[str, Any], cfg: DataConfig) -> None:
    """Fold one item's result into its scene's manifest entry."""
    key = _item_key(res["kind"], res.get("seed"), res.get("half"), res.get("chunk"))
    if "error" in res:
        s["items"][key] = {"failed": res["error"], "attempts": res.get("attempts")}
        return
    if res["kind"] == "reference" and res.get("chunk") is not None:
        s["chunks"] = sorted(s["chunks"] + res["files"], key=lambda f: f["file"])
        budget = {"passes": res["files"][0]["passes"], "photons": cfg.reference_photons}
    elif res["kind"] == "reference":
        s["references"] = sorted(s["references"] + res["files"], key=lambda f: f["file"])
        budget = {"passes": cfg.reference_passes, "photons": cfg.reference_photons}
    else:
        s["inputs"] = sorted(s["inputs"] + res["files"], key=lambda f: (f["seed"], f["passes"]))
        budget = {"passes": max(cfg.input_passes), "photons": cfg.photons}
    s["items"][key] = {**budget, "render_seconds": res["render_seconds"], "wall_seconds": res["wall_seconds"],
                       "variant": res.get("variant")}
    s["seconds"] = s.get("seconds", 0.0) + res["wall_seconds"]


def _existing_manifest(mpath: Path, cfg: DataConfig) -> dict[str, Any]:
    """The manifest at ``mpath`` of a data set that ``cfg`` may complete or grow; one line
    (UsageError) where it was generated with another configuration or has more scenes."""
    old = load_manifest(mpath.parent)
    stored, wanted = stored_config(old), _as_json(asdict(cfg))
    if {**stored, "scenes": 0} != {**wanted, "scenes": 0}:
        raise UsageError(f"{mpath}: the data set was generated with another configuration; "
                         "use a new --out folder")
    if wanted["scenes"] < stored["scenes"]:
        raise UsageError(f"{mpath}: the data set has {stored['scenes']} scenes; --scenes "
                         f"{wanted['scenes']} would drop some (it can only grow)")
    return old


def generate(cfg: DataConfig, out: str | os.PathLike, workers: int = 1, quiet: bool = False,
             runner: Runner | None = None) -> dict[str, Any]:
    """Generate (or complete) the data set ``out`` for ``cfg``; returns the manifest.

    Items run on ``runner`` (default: a local pool of ``workers`` processes). Raises
    :class:`GenerationError` naming the failed items after all others are done."""
    runner = runner or LocalRunner(workers)
    cfg.validate()
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    mpath = root / MANIFEST
    scenes = plan(cfg)
    manifest: dict[str, Any] = {"version": MANIFEST_VERSION, "config": asdict(cfg), "scenes": scenes}
    if mpath.exists():
        old = _existing_manifest(mpath, cfg)
        manifest["generation_seconds"] = old.get("generation_seconds", 0.0)
        done = {s["id"]: s for s in old["scenes"]}
        for s in scenes:
            prev = done.get(s["id"], {})
            for key in ("inputs", "reference", "references", "chunks", "agreement", "items", "seconds"):
                if key in prev:
                    s[key] = prev[key]
            if cfg.references == 1 and "reference" in prev and "references" not in prev:
                s["references"] = [prev["reference"]]  # a version-1 scene

    jobs = []
    for s in scenes:
        folder = root / s["id"]
        s.setdefault("inputs", [])
        s.setdefault("references", [])
        s.setdefault("items", {})
        if cfg.reference_chunks > 1:
            s.setdefault("chunks", [])
        common = {"id": s["id"], "scene_seed": s["seed"], "params": s["params"], "folder": str(folder),
                  "config": asdict(cfg), "threads": runner.threads}
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
            if cfg.reference_chunks == 1:
                jobs.append({"kind": "reference", "half": half, **common})
                continue
            seed = REFERENCE_SEED_BASE[half] + s["seed"]
            bounds = reference_chunk_bounds(cfg.reference_passes, cfg.reference_chunks)
            for c, (first, last) in enumerate(bounds):
                cname = chunk_name(name, c, cfg.reference_chunks)
                if _chunk_valid(folder / cname, first, last, seed) and any(f["file"] == cname for f in s["chunks"]):
                    continue
                s["chunks"] = [f for f in s["chunks"] if f["file"] != cname]
                jobs.append({"kind": "reference", "half": half, "chunk": c, **common})
        _finish_scene(root, s, cfg)
    write_json(mpath, manifest)

    by_id = {s["id"]: s for s in scenes}
    progress = Progress(f"ppmrecon-train generate {root} ({runner.label})", total=len(jobs), quiet=quiet)
    progress.update(0, force=True)
    t0 = time.perf_counter()
    failed: list[dict[str, Any]] = []
    if jobs:
        for k, res in enumerate(runner.run(jobs), 1):
            s = by_id[res["id"]]
            _record(s, res, cfg)
            if "error" in res:
                failed.append(res)
            else:
                _finish_scene(root, s, cfg)
            write_json(mpath, manifest)
            progress.update(k, force=True, scene=res["id"], failed=len(failed))
    progress.close()
    manifest["generation_seconds"] = manifest.get("generation_seconds", 0.0) + (time.perf_counter() - t0)
    write_json(mpath, manifest)
    if failed:
        first = failed[0]
        more = f"; {len(failed) - 1} more failed (see 'items' in {mpath})" if len(failed) > 1 else ""
        raise GenerationError(f"{mpath}: work item {describe_item(first)} failed after "
                              f"{first.get('attempts') or 1} attempt(s): {first['error']}{more}; "
                              "rerun the same command to retry")
    return manifest


def project(cfg: DataConfig, timings: dict[str, dict[str, float]], workers: int = 1,
            done: dict[str, set[str]] | None = None) -> dict[str, Any]:
    """The cost of generating ``cfg`` from per-family timings (family -> ``input_first_seconds``,
    ``input_pass_seconds``, ``reference_first_seconds``, ``reference_pass_seconds``): an item
    costs its first pass (compilation, the k-NN initial radii; paid again by every reference
    chunk, which starts from its own pass) plus its other passes at the timed rate, and every
    scene of a family what the family's timings say. ``done`` (scene id -> finished item
    keys, as a manifest's ``items``) leaves items out of the remaining cost. Wall times
    assume ``workers`` items at once, all busy."""
    done = done or {}
    chunks = reference_chunk_bounds(cfg.reference_passes, cfg.reference_chunks)
    families: dict[str, dict[str, Any]] = {}
    for family, t in timings.items():
        items = {_item_key("inputs", seed): t["input_first_seconds"]
                 + (max(cfg.input_passes) - 1) * t["input_pass_seconds"] for seed in cfg.seeds}
        for half in range(cfg.references):
            for c, (first, last) in enumerate(chunks):
                key = _item_key("reference", half=half, chunk=None if cfg.reference_chunks == 1 else c)
                items[key] = t["reference_first_seconds"] + (last - first) * t["reference_pass_seconds"]
        families[family] = {**t, "items": items, "scene_seconds": sum(items.values())}
    total = inputs = remaining = 0.0
    scenes = plan(cfg)
    for s in scenes:
        for key, seconds in families[s["family"]]["items"].items():
            total += seconds
            inputs += seconds if key.startswith("inputs") else 0.0
            remaining += 0.0 if key in done.get(s["id"], set()) else seconds
    return {"families": families, "scenes": len(scenes), "workers": workers, "worker_seconds": total,
            "input_seconds": inputs, "reference_seconds": total - inputs, "remaining_worker_seconds": remaining,
            "items_done": sum(len(v) for v in done.values()), "wall_seconds": total / workers,
            "remaining_wall_seconds": remaining / workers}


def estimate(cfg: DataConfig, seconds: float = 5.0, workers: int = 1, out: str | os.PathLike | None = None,
             quiet: bool = False, runner: Runner | None = None) -> dict[str, Any]:
    """What generating ``cfg`` would cost on this machine, measured, not guessed
    (:func:`project` of timed passes).

    The first scene of each family (its photon paths, and so its pass cost, depend on the
    family more than on the seed) renders one input seed and one reference half: its first
    pass, then passes from halfway through the item for ``seconds`` (:func:`_time_item`), in
    ``workers`` processes that start their timed passes together (a local pool), so the
    cores are shared as ``generate`` shares them.
    With ``out`` (an existing data set of the same configuration) the items its manifest
    records as finished are left out of the remaining cost, and what they took
    (``finished_seconds``, their manifest's ``wall_seconds``) is set beside what the
    projection says of them (``finished_projected_seconds``). Snapshot and reference writes
    are not timed (under a second an item): a projection."""
    runner = runner or LocalRunner(workers)
    cfg.validate()
    finished: dict[str, dict[str, float]] = {}          # scene id -> item key -> its wall seconds
    if out is not None and (Path(out) / MANIFEST).exists():
        old = _existing_manifest(Path(out) / MANIFEST, cfg)
        finished = {s["id"]: {k: v.get("wall_seconds", 0.0) for k, v in s.get("items", {}).items() if "failed" not in v}
                    for s in old["scenes"]}
    scenes = plan(cfg)
    sample: dict[str, dict[str, Any]] = {}
    for s in scenes:
        sample.setdefault(s["family"], s)
    parallel = getattr(runner, "workers", 1)
    with contextlib.ExitStack() as stack:
        barrier = None
        if isinstance(runner, LocalRunner) and parallel > 1:
            barrier = stack.enter_context(mp.get_context("spawn").Manager()).Barrier(parallel)
        jobs = [{"kind": kind, "seed": cfg.seeds[0], "half": 0, "estimate": seconds, "id": s["id"],
                 "scene_seed": s["seed"], "params": s["params"], "config": asdict(cfg), "threads": runner.threads,
                 "barrier": barrier} for s in sample.values() for kind in ("inputs", "reference")]
        progress = Progress(f"ppmrecon-train generate --estimate ({runner.label})", total=len(jobs), quiet=quiet)
        timed: dict[tuple[str, str], dict[str, Any]] = {}
        for k, res in enumerate(runner.run(jobs), 1):
            if "error" in res:
                raise GenerationError(f"--estimate: timing {res['id']} {res['kind']} failed: {res['error']}")
            timed[(res["id"], res["kind"])] = res
            progress.update(k, force=True, scene=res["id"])
            if barrier is not None and len(jobs) - k < parallel:
                barrier.abort()       # a last round smaller than the pool: its items need not wait
        progress.close()
    timings = {}
    for family, s in sample.items():
        t_in, t_ref = timed[(s["id"], "inputs")], timed[(s["id"], "reference")]
        timings[family] = {"scene": s["id"], "input_first_seconds": t_in["first_seconds"],
                           "input_pass_seconds": t_in["pass_seconds"],
                           "reference_first_seconds": t_ref["first_seconds"],
                           "reference_pass_seconds": t_ref["pass_seconds"]}
    result = project(cfg, timings, parallel, {i: set(v) for i, v in finished.items()})
    family = {s["id"]: s["family"] for s in scenes}
    # the projection checked against what the finished items took
    result["finished_seconds"] = sum(t for items in finished.values() for t in items.values())
    result["finished_projected_seconds"] = sum(result["families"][family[i]]["items"].get(k, 0.0)
                                               for i, items in finished.items() for k in items)
    return {"config": asdict(cfg), "seconds_timed": seconds, "threads": runner.threads, **result}
