"""Shared command-line plumbing: one-line errors with exit codes, a stderr progress bar."""

from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path
from typing import Callable, Sequence

from .errors import PpmreconError, UsageError


class ArgumentParser(argparse.ArgumentParser):
    """argparse with exit code 2 and a single 'prog: error: ...' line for usage errors."""

    def error(self, message: str) -> None:  # type: ignore[override]
        sys.stderr.write(f"{self.prog}: error: {message} (see --help)\n")
        raise SystemExit(2)


def run_main(prog: str, main: Callable[[Sequence[str] | None], int],
             argv: Sequence[str] | None = None) -> int:
    """Run ``main`` and turn :class:`PpmreconError` into one stderr line and its exit code."""
    try:
        return int(main(argv) or 0)
    except PpmreconError as exc:
        sys.stderr.write(f"{prog}: error: {exc}\n")
        return exc.exit_code
    except KeyboardInterrupt:
        sys.stderr.write(f"{prog}: interrupted\n")
        return 130


def _int_at_least(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"must be {'positive' if minimum == 1 else f'>= {minimum}'}, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer > 0."""
    return _int_at_least(text, 1)


def nonnegative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _int_at_least(text, 0)


def _finite_float(text: str, minimum: float, inclusive: bool) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
    if not ((value >= minimum if inclusive else value > minimum) and value < float("inf")):
        kind = "a number >= 0" if inclusive else "a positive number"
        raise argparse.ArgumentTypeError(f"must be {kind}, got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0."""
    return _finite_float(text, 0.0, inclusive=False)


def nonnegative_float(text: str) -> float:
    """argparse type: a finite float >= 0."""
    return _finite_float(text, 0.0, inclusive=True)


class Progress:
    """A one-line progress bar on stderr (silent when ``quiet``).

    ``update(done, **stats)`` redraws at most every ``interval`` seconds; stats are
    printed as ``key=value`` after the bar.
    """

    def __init__(self, label: str, total: int | None = None, quiet: bool = False,
                 interval: float = 0.25, stream=None):
        self.label, self.total, self.quiet = label, total, quiet
        self.interval = interval
        self.stream = stream or sys.stderr
        self.start = time.perf_counter()
        self._last = 0.0
        self._drawn = False

    def update(self, done: int, force: bool = False, **stats: str | float | int) -> None:
        if self.quiet:
            return
        now = time.perf_counter()
        if not force and now - self._last < self.interval:
            return
        self._last = now
        elapsed = now - self.start
        if self.total:
            frac = min(1.0, done / self.total)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            head = f"{self.label} [{bar}] {done}/{self.total}"
        else:
            head = f"{self.label} {done}"
        extra = " ".join(f"{k}={v}" for k, v in stats.items())
        line = f"\r{head} {elapsed:6.1f}s {extra}"
        if self.stream.isatty():
            line += "\x1b[K"
        self.stream.write(line)
        self.stream.flush()
        self._drawn = True

    def close(self) -> None:
        if self._drawn and not self.quiet:
            self.stream.write("\n")
            self.stream.flush()


def expand_paths(items: Sequence[str], what: str = "file",
                 exclude: Callable[[Path], bool] | None = None) -> list[Path]:
    """Path arguments -> files, in order, each once. An argument with glob characters
    that is not itself a file is a pattern (its sorted matches, less those ``exclude``
    rejects); a pattern that matches nothing is a one-line usage error naming ``what``."""
    out: list[Path] = []
    for item in items:
        if glob.has_magic(item) and not Path(item).exists():
            matches = [Path(m) for m in sorted(glob.glob(item))]
            matches = [m for m in matches if exclude is None or not exclude(m)]
            if not matches:
                raise UsageError(f"{item}: no {what} matches this pattern")
            out += matches
        else:
            out.append(Path(item))
    seen: set[Path] = set()
    unique = []
    for path in out:
        if path.resolve() not in seen:
            seen.add(path.resolve())
            unique.append(path)
    return unique
