"""Render state files: what ``ppmrecon-render --resume FILE.exr`` continues from.

Next to an output ``FILE.exr`` the renderer keeps ``FILE.exr.state.npz``: an
uncompressed numpy archive (no pickles) with every accumulator of the render (Welford
means and M2 of each chain, the G-buffer means, the controller's radii and CPPM/FPPM cell
statistics; see :meth:`.integrator.Renderer.export_state`) and one JSON record,
``__meta__``, that ties it to

* the output it belongs to: the SHA-256 of FILE.exr as written with this state (and of
  the output of the previous save, see below),
* the scene: its name or path and :attr:`.scene.LoadedScene.content_hash`, and the film
  size,
* the render settings (method, photons, seed, kernel, ... everything but the budget),
* the ppmrecon version and the state format.

Any mismatch is a one-line :class:`StateError`, never a silent fresh start.

Saving is ordered so that a process killed at any instant leaves a pair that resumes:
the output goes to a temporary file, is hashed, the state (naming that hash and the
hash of the output it replaces) is renamed into place, and only then the output. A kill
between the two renames leaves the new state beside the previous output, which the
state accepts (its ``previous_sha256``); the state alone holds all the render's data.
The pass index is part of the state, so the random streams of the next pass (seeded by
seed and pass index, :mod:`.rng`) are those an uninterrupted render would have used.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .. import __version__
from ..errors import UsageError
from ..fileio import atomic_write, file_sha256, staged_file

STATE_FORMAT = "ppmrecon-render-state"
STATE_VERSION = 1
SUFFIX = ".state.npz"
META_KEY = "__meta__"
#: RenderSettings fields that are the render's budget, not its definition.
BUDGET_FIELDS = ("passes", "time_budget")


class StateError(UsageError):
    """A state file that cannot be resumed; the message names the file and why."""

    def __init__(self, path: str | os.PathLike, problem: str):
        super().__init__(f"{path}: {problem}")


def state_path(output: str | os.PathLike) -> Path:
    """The state file that belongs to output ``FILE.exr``: ``FILE.exr.state.npz``."""
    output = Path(output)
    return output.with_name(output.name + SUFFIX)


@dataclass
class SavedState:
    """A state file's content: the JSON record and the accumulator arrays."""

    meta: dict[str, Any]
    arrays: dict[str, np.ndarray]

    @property
    def settings(self) -> dict[str, Any]:
        return self.meta["settings"]

    @property
    def counters(self) -> dict[str, Any]:
        return self.meta["counters"]

    @property
    def passes(self) -> int:
        return int(self.meta["counters"]["passes"])


def settings_record(settings: Any) -> dict[str, Any]:
    """The settings of a :class:`.integrator.RenderSettings` that define the render."""
    return {k: v for k, v in asdict(settings).items() if k not in BUDGET_FIELDS}


def write_state(path: str | os.PathLike, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Write a state file atomically (temporary file + rename)."""
    record = np.frombuffer(json.dumps(meta).encode("utf-8"), dtype=np.uint8)

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            np.savez(f, **{META_KEY: record}, **arrays)

    atomic_write(path, write)


def read_state(path: str | os.PathLike) -> SavedState:
    """Read and check a state file (format, version); one-line StateError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise StateError(path, "no such render state file")
    try:
        with np.load(path, allow_pickle=False) as z:
            if META_KEY not in z.files:
                raise StateError(path, "not a ppmrecon render state (no __meta__ record)")
            meta = json.loads(bytes(z[META_KEY]).decode("utf-8"))
            arrays = {k: z[k] for k in z.files if k != META_KEY}
    except StateError:
        raise
    except Exception as exc:  # zipfile, numpy and json each raise their own kinds for a cut file
        raise StateError(path, f"truncated or corrupt render state ({type(exc).__name__}: "
                               f"{str(exc).splitlines()[0] if str(exc) else 'unreadable'})") from None
    if not isinstance(meta, dict) or meta.get("format") != STATE_FORMAT:
        raise StateError(path, "not a ppmrecon render state")
    if meta.get("state_version") != STATE_VERSION:
        raise StateError(path, f"state format {meta.get('state_version')} is not the one this ppmrecon "
                               f"reads ({STATE_VERSION}); start a new render")
    if meta.get("ppmrecon_version") != __version__:
        raise StateError(path, f"written by ppmrecon {meta.get('ppmrecon_version')}, this is {__version__}: "
                               f"a render continues only with the version that started it; start a new render")
    for key in ("output", "scene", "settings", "counters"):
        if not isinstance(meta.get(key), dict):
            raise StateError(path, f"render state lacks its '{key}' record")
    for name, arr in arrays.items():
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise StateError(path, f"array '{name}' holds NaN/Inf")
    return SavedState(meta, arrays)


def check_output(output: str | os.PathLike, saved: SavedState, path: str | os.PathLike) -> str:
    """Check that ``output`` is the file ``saved`` was written with (or the one it
    replaced, if the writer stopped between the two renames); returns its SHA-256."""
    output = Path(output)
    if not output.is_file():
        raise UsageError(f"{output}: no such file")
    digest = file_sha256(output)
    record = saved.meta["output"]
    if digest not in (record.get("sha256"), record.get("previous_sha256")):
        raise StateError(path, f"does not belong to {output} as it is now (content hash differs: the file "
                               f"was changed or replaced after the render wrote it)")
    return digest


def check_scene(loaded: Any, saved: SavedState, path: str | os.PathLike) -> None:
    """Check that ``loaded`` (a LoadedScene at the saved film size) is the saved scene."""
    scene = saved.meta["scene"]
    if loaded.content_hash != scene.get("sha256"):
        raise StateError(path, f"was rendered from another scene than {loaded.label} (content hash differs: "
                               f"the scene or a file it references changed since)")
    if (loaded.width, loaded.height) != (scene.get("width"), scene.get("height")):
        raise StateError(path, f"film size {scene.get('width')}x{scene.get('height')} differs from the "
                               f"scene's {loaded.width}x{loaded.height}")


def scene_record(loaded: Any, spec: str) -> dict[str, Any]:
    """The state's scene record for a LoadedScene given on the command line as ``spec``."""
    return {"spec": spec, "name": loaded.name, "sha256": loaded.content_hash,
            "width": loaded.width, "height": loaded.height}


def save_with_state(output: str | os.PathLike, write_output: Callable[[str], None],
                    meta: dict[str, Any], arrays: dict[str, np.ndarray], previous: str | None) -> str:
    """Write ``output`` (by ``write_output(tmp_name)``) and its state, in the order the
    module docstring gives; ``previous`` is the hash of the output this one replaces.
    Returns the new output's SHA-256."""
    output = Path(output)
    with staged_file(output) as tmp:
        write_output(tmp)
        digest = file_sha256(tmp)
        record = dict(meta)
        record.update(format=STATE_FORMAT, state_version=STATE_VERSION, ppmrecon_version=__version__,
                      output={"name": output.name, "sha256": digest, "previous_sha256": previous})
        write_state(state_path(output), record, arrays)
    return digest
