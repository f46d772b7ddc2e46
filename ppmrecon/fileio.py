"""Small file helpers shared by every writer and config reader.

``atomic_write`` gives every output the same guarantee (SPEC section 9): the data go to
a temporary file in the destination folder, renamed over the final name only once
complete, so an interrupted write never leaves a partial file there.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from contextlib import contextmanager
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable, Iterator, TypeVar

from .errors import UsageError

T = TypeVar("T")


def default_mode() -> int:
    """The permissions a plain ``open(..., "w")`` would give under the current umask."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


@contextmanager
def staged_file(path: str | os.PathLike) -> Iterator[str]:
    """Yield the name of a temporary file next to ``path``; when the block ends normally
    it is renamed to ``path``, on any exception removed. Lets a caller do more (hash the
    file, write a companion file) between writing the data and publishing them."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise UsageError(f"{path}: output folder '{folder}' does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, default_mode())  # mkstemp makes 0600; outputs get the usual umask
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call ``write(tmp_name)`` on a temporary file next to ``path``, then rename it to
    ``path``; on any exception the temporary file is removed and nothing is renamed."""
    with staged_file(path) as tmp:
        write(tmp)


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_json(path: str | os.PathLike, what: str, missing_hint: str = "") -> Any:
    """Parse a JSON file; a missing file or bad JSON is a one-line :class:`UsageError`."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UsageError(f"{path}: no such {what}{'; ' + missing_hint if missing_hint else ''}") from None
    except json.JSONDecodeError as exc:
        raise UsageError(f"{path}: broken {what}, not valid JSON ({exc.msg} at line {exc.lineno})") from None


def unknown_keys(cls: type, data: Any) -> list[str]:
    """The keys of mapping ``data`` that are not fields of dataclass ``cls``, sorted."""
    return sorted(set(data) - {f.name for f in fields(cls)})


def load_json_config(path: str | os.PathLike, cls: type[T], what: str) -> T:
    """Read a JSON config into dataclass ``cls``; keys starting with ``_`` are comments.
    Missing file, bad JSON and unknown keys are one-line :class:`UsageError`s."""
    raw = read_json(path, what)
    if not isinstance(raw, dict):
        raise UsageError(f"{path}: a {what} must be a JSON object")
    raw = {k: v for k, v in raw.items() if not k.startswith("_")}
    unknown = unknown_keys(cls, raw)
    if unknown:
        raise UsageError(f"{path}: unknown key(s) {', '.join(unknown)}")
    try:
        return cls(**raw)
    except TypeError as exc:
        raise UsageError(f"{path}: {exc}") from None


def write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def write_json(path: str | os.PathLike, data: Any) -> None:
    """Write ``data`` as indented JSON, atomically."""
    write_text(path, json.dumps(data, indent=1))
