"""Data-parallel training with PyTorch DDP (``torchrun ... -m ppmrecon.train fit``).

Launch N processes per machine with ``torchrun --nproc-per-node N -m ppmrecon.train fit
DATA --out RUN [--ddp]`` (and ``--nnodes``/``--rdzv-endpoint`` across machines). Each
process is one rank: gloo on CPU, nccl on GPU (``--device cuda``; rank r uses the GPU
``LOCAL_RANK``). What one step computes is the step of one process with the same
global batch:

* every rank draws the same global batch plan (:meth:`.dataset.PatchSampler.plan`)
  from the catalogue of the whole training set, and cuts the patches of the samples
  in its shard (:func:`.dataset.load_split` with ``shard``), b_r of the B rows;
* rank r's loss is its rows' mean loss times b_r W / B, and DDP averages gradients over
  the W ranks, so the gradient is the global batch's mean gradient, the one of a single
  process (up to float rounding); clipping and Adam then run identically on all ranks;
* the loss that is logged is all-reduced, validation sums are all-reduced over the
  sharded validation set, and rank 0 alone writes checkpoints (atomically);
* ``--resume`` reads the run folder on rank 0 and sends its files to the other ranks,
  so it needs no shared file system.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
import torch.distributed as tdist

from ..errors import UsageError

TORCHRUN_ENV = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
LAUNCH_HINT = "launch with `torchrun --nproc-per-node N -m ppmrecon.train fit ...`"
#: Set once this process has joined a process group (see :func:`exit_process`).
joined = False


@dataclass
class Dist:
    """This process's place in the process group."""

    rank: int
    world: int
    local_rank: int
    backend: str
    _tmp: list[str] = field(default_factory=list)

    @property
    def main(self) -> bool:
        return self.rank == 0

    def device(self, kind: str) -> torch.device:
        """The device of this rank: ``cuda:LOCAL_RANK`` for CUDA, else the CPU."""
        return torch.device(f"cuda:{self.local_rank}") if kind == "cuda" else torch.device(kind)

    def all_sum(self, values: list[float]) -> list[float]:
        """Element-wise sum over the ranks (float64)."""
        t = torch.tensor(values, dtype=torch.float64, device=self._comm_device())
        tdist.all_reduce(t, op=tdist.ReduceOp.SUM)
        return t.cpu().tolist()

    def gather(self, obj: Any) -> list[Any]:
        """``obj`` of every rank, in rank order."""
        out: list[Any] = [None] * self.world
        tdist.all_gather_object(out, obj)
        return out

    def broadcast(self, obj: Any) -> Any:
        """Rank 0's ``obj`` on every rank."""
        box = [obj if self.main else None]
        tdist.broadcast_object_list(box, src=0)
        return box[0]

    def replicate(self, folder: Path, names: tuple[str, ...]) -> Path:
        """A folder holding rank 0's copies of ``folder``/names (those that exist): the
        folder itself on rank 0, a private temporary copy elsewhere."""
        blobs = self.broadcast({n: (folder / n).read_bytes() for n in names if (folder / n).is_file()}
                               if self.main else None)
        if self.main:
            return folder
        tmp = tempfile.mkdtemp(prefix=f"ppmrecon-rank{self.rank}-")
        self._tmp.append(tmp)
        for name, data in blobs.items():
            (Path(tmp) / name).write_bytes(data)
        return Path(tmp)

    def _comm_device(self) -> torch.device:
        return torch.device(f"cuda:{self.local_rank}") if self.backend == "nccl" else torch.device("cpu")

    def close(self) -> None:
        for tmp in self._tmp:
            shutil.rmtree(tmp, ignore_errors=True)
        if tdist.is_initialized():
            # all ranks leave together: a rank tearing down its connections while another
            # still uses them can abort that one at exit
            tdist.barrier()
            tdist.destroy_process_group()


def launched_by_torchrun() -> bool:
    return all(k in os.environ for k in TORCHRUN_ENV)


def init(device: str, required: bool = False) -> Dist | None:
    """Join the process group torchrun set up (gloo on CPU, nccl for ``device`` "cuda").
    None when not launched by torchrun (or with one process) unless ``required`` (``--ddp``),
    which then fails with a one-line hint if torchrun's environment is missing."""
    if not launched_by_torchrun():
        if required:
            missing = ", ".join(k for k in TORCHRUN_ENV if k not in os.environ)
            raise UsageError(f"--ddp: not started by torchrun ({missing} unset); {LAUNCH_HINT}")
        return None
    world = int(os.environ["WORLD_SIZE"])
    if world == 1 and not required:
        return None
    backend = "nccl" if device == "cuda" else "gloo"
    local_rank = int(os.environ["LOCAL_RANK"])
    if backend == "nccl":
        if not torch.cuda.is_available():
            raise UsageError("--device cuda: no CUDA device is available to torch")
        torch.cuda.set_device(local_rank)
    tdist.init_process_group(backend=backend)
    global joined
    joined = True
    return Dist(rank=tdist.get_rank(), world=tdist.get_world_size(), local_rank=local_rank, backend=backend)


def exit_process(code: int) -> None:
    """End a process that joined a process group: flush and leave without the
    interpreter's finalisation. With torch 2.13's gloo, about one run in ten aborted there
    (SIGABRT, "terminate called without an active exception") even after a barrier and
    destroy_process_group, failing the torchrun job after all its work was done (reproduced
    with a 10-line gloo script); everything this process writes is written and closed
    before, atomically."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
