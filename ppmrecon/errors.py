"""User-facing errors: each carries a one-line message and the exit code a command uses.

Exit codes follow SPEC section 9: 2 for usage errors (bad option, bad input file),
1 for runtime failures.
"""

from __future__ import annotations


class PpmreconError(Exception):
    """An error whose message is meant for the user, printed as one line."""

    exit_code: int = 1


class UsageError(PpmreconError):
    """The user asked for something invalid (option value, missing file)."""

    exit_code = 2


class BackendError(PpmreconError):
    """No usable Mitsuba/Dr.Jit backend (e.g. no libLLVM >= 16)."""

    exit_code = 1
