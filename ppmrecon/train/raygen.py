"""Training-data generation on a Ray cluster (``ppmrecon-train generate --ray ...``).

The same work items as the local pool (:func:`.datagen.work_item`: one input seed, one
reference render or one chunk of a reference's passes) run as Ray tasks; the driver
keeps the manifest, the resumability and the files of the local path
(:func:`.datagen.generate` does all the bookkeeping, this module only runs items).

* Files: a task renders into a temporary folder on its own node and returns the files'
  bytes; the driver writes them (atomically) into the data set, so no shared file
  system is needed and the files are those a local worker writes.
* GPU or CPU: with ``gpus="auto"``, as many tasks as the cluster has GPUs run at a time
  as GPU tasks (``num_gpus=1``, Mitsuba's ``cuda_ad_rgb``) and the others as CPU tasks
  (``num_cpus=cpus_per_task``, ``llvm_ad_rgb``); each free slot takes the next item, so a
  mixed cluster keeps both kinds of worker busy; the slots are counted again after every
  finished task, so nodes that join later are used. The manifest's ``items`` record the
  variant each item ran on (CUDA and LLVM renders agree only statistically).
* Failures: a task whose worker dies (killed, out of memory) or that raises is retried
  up to ``retries`` times by Ray (``max_retries``, ``retry_exceptions``); after that it
  comes back as a failed item, which :func:`.datagen.generate` records in the manifest
  and reports, never drops.

Ray is an optional dependency (``pip install 'ppmrecon[distributed]'``); nothing else
in ppmrecon imports this module.
"""

from __future__ import annotations

import shutil
import tempfile
from collections import deque
from pathlib import Path
from typing import Any, Callable, Iterator

from ..errors import UsageError
from ..fileio import atomic_write
from .datagen import _job_ids, one_line, work_item

INSTALL_HINT = "Ray is not installed: install ppmrecon[distributed] (pip install 'ppmrecon[distributed]')"
GPU_VARIANT, CPU_VARIANT = "cuda_ad_rgb", "llvm_ad_rgb"
#: Ray task retries after the first attempt (worker deaths and raised exceptions alike).
DEFAULT_RETRIES = 2


def import_ray() -> Any:
    """The ``ray`` module, or a one-line UsageError saying how to install it."""
    try:
        import ray
    except ImportError:
        raise UsageError(f"--ray: {INSTALL_HINT}") from None
    return ray


def connect(address: str) -> Any:
    """Join the Ray cluster at ``address`` ("auto": the one this machine belongs to, or
    RAY_ADDRESS; "local": start a private one on this machine) unless this process is
    connected already (e.g. a test's ``ray.init``). Returns the ``ray`` module."""
    ray = import_ray()
    if ray.is_initialized():
        return ray
    try:
        if address == "local":
            ray.init(include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    except Exception as exc:  # ConnectionError, ValueError, RuntimeError: all "no cluster there"
        raise UsageError(f"--ray {address}: cannot connect to a Ray cluster ({one_line(exc)}); "
                         "start one with `ray start --head`, or use --ray local") from None
    return ray


def _remote_item(job: dict[str, Any], item: Callable[[dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
    """Body of a Ray task: render ``job`` with ``item`` into a temporary folder of this
    node and return the result with the files' bytes (``blobs``)."""
    tmp = tempfile.mkdtemp(prefix="ppmrecon-item-")
    try:
        res = item({**job, "folder": tmp})
        res["blobs"] = {p.name: p.read_bytes() for p in sorted(Path(tmp).iterdir()) if p.is_file()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return res


def store_blobs(folder: str | Path, blobs: dict[str, bytes]) -> None:
    """Write a task's files into ``folder`` (atomically, each)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in blobs.items():
        atomic_write(folder / Path(name).name, lambda tmp, data=data: Path(tmp).write_bytes(data))


class RayRunner:
    """Runs :func:`.datagen.work_item` jobs as Ray tasks (see the module docstring).

    ``gpus``: "auto" (one GPU task per GPU of the cluster, CPU tasks for the rest of the
    CPUs), or an int: at most that many GPU tasks at a time (0: CPU only).
    ``item``: the function a task runs (tests wrap it to inject failures)."""

    def __init__(self, address: str = "auto", cpus_per_task: int = 1, gpus: str | int = "auto",
                 retries: int = DEFAULT_RETRIES, item: Callable[[dict[str, Any]], dict[str, Any]] = work_item):
        self.ray = connect(address)
        self.cpus_per_task = max(1, int(cpus_per_task))
        self.gpus = gpus
        have = int(self.ray.cluster_resources().get("GPU", 0))
        if gpus != "auto" and int(gpus) > have:
            raise UsageError(f"--ray-gpus {gpus}: the Ray cluster has {have} GPU(s)")
        self.retries = retries
        self.item = item
        self.threads = self.cpus_per_task
        gpu_slots, cpu_slots = self.slots()
        self.label = f"Ray: {cpu_slots} CPU + {gpu_slots} GPU task slots"
        self._task = self.ray.remote(_remote_item)

    def slots(self) -> tuple[int, int]:
        """(GPU tasks, CPU tasks) the cluster runs at a time now; asked again after every
        finished task, so nodes that join (autoscaling) are used."""
        resources = self.ray.cluster_resources()
        have = int(resources.get("GPU", 0))
        gpu = have if self.gpus == "auto" else min(int(self.gpus), have)
        # A GPU task still takes one CPU (Ray's default); the rest run CPU tasks.
        spare = int(resources.get("CPU", 1)) - gpu
        return gpu, max(0 if gpu else 1, spare // self.cpus_per_task)

    def _submit(self, job: dict[str, Any], gpu: bool) -> Any:
        job = {**job, "variant": GPU_VARIANT if gpu else CPU_VARIANT}
        opts = {"num_cpus": 1 if gpu else self.cpus_per_task, "num_gpus": 1 if gpu else 0,
                "max_retries": self.retries, "retry_exceptions": True}
        return self._task.options(**opts).remote(job, self.item)

    def run(self, jobs: list[dict[str, Any]]) -> Iterator[dict[str, Any]]:
        pending = deque(jobs)
        running: dict[Any, tuple[dict[str, Any], bool]] = {}
        while pending or running:
            capacity = dict(zip((True, False), self.slots()))
            for gpu in (True, False):
                busy = sum(1 for _, g in running.values() if g == gpu)
                for _ in range(max(0, capacity[gpu] - busy)):
                    if not pending:
                        break
                    job = pending.popleft()
                    running[self._submit(job, gpu)] = (job, gpu)
            ready, _ = self.ray.wait(list(running), num_returns=1)
            job, _ = running.pop(ready[0])
            try:
                res = self.ray.get(ready[0])
            except Exception as exc:  # RayTaskError (raised every attempt), WorkerCrashedError, ...
                cause = getattr(exc, "cause", None)
                yield {**_job_ids(job), "error": one_line(cause if isinstance(cause, BaseException) else exc),
                       "attempts": self.retries + 1}
                continue
            store_blobs(job["folder"], res.pop("blobs"))
            yield res
