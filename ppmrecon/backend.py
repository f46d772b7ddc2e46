"""The backend chooser: which Mitsuba 3 variant runs the renderer.

``cuda_ad_rgb`` when an NVIDIA GPU and driver are usable, ``llvm_ad_rgb`` otherwise;
``scalar_rgb`` never (far too slow for a wavefront photon mapper). Dr.Jit's LLVM backend
needs a libLLVM it can JIT with: Debian 12's preinstalled 14/15 crash at the first
kernel ("Cannot select ... fminimum"), so before drjit is imported we point
``DRJIT_LIBLLVM_PATH`` at a libLLVM >= 16 unless the user already set it.

Force a variant with the environment variable ``PPMRECON_VARIANT`` or the commands'
``--variant`` option.
"""

from __future__ import annotations

import glob
import os
import re
import sys
from pathlib import Path

from .errors import BackendError

VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")
ENV_VARIANT = "PPMRECON_VARIANT"
MIN_LLVM = 16
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)
INSTALL_HINT = ("no libLLVM >= 16 found for Mitsuba's CPU backend: run `apt-get install libllvm19` "
                "(or ./scripts/setup.sh), or set DRJIT_LIBLLVM_PATH to a libLLVM >= 16")


def _llvm_major(path: str) -> int | None:
    name = os.path.basename(path)
    m = re.match(r"libLLVM[-.]?(\d+)", name) or re.match(r"libLLVM\.so\.(\d+)", name)
    if not m:
        m = re.search(r"llvm-(\d+)/", path)
    return int(m.group(1)) if m else None


def find_libllvm(min_version: int = MIN_LLVM) -> str | None:
    """Path of the newest libLLVM shared library with major version >= ``min_version``."""
    best: tuple[int, str] | None = None
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is None or major < min_version or not os.path.isfile(path):
                continue
            if best is None or major > best[0]:
                best = (major, path)
    return best[1] if best else None


def _configure_llvm() -> str | None:
    """Set DRJIT_LIBLLVM_PATH unless the user did; the path in use, or None if none found."""
    user = os.environ.get("DRJIT_LIBLLVM_PATH")
    if user:
        return user
    path = find_libllvm()
    if path:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def _cuda_usable() -> bool:
    # A driver without a device (or no driver) makes drjit report no CUDA backend.
    if not (os.path.exists("/dev/nvidiactl") or glob.glob("/usr/lib/*/libcuda.so*")
            or glob.glob("/usr/lib64/libcuda.so*")):
        return False
    import drjit as dr
    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:
        return False


_chosen: str | None = None


def choose_variant(force: str | None = None) -> str:
    """Pick and activate the Mitsuba variant; returns its name.

    ``force`` (or ``$PPMRECON_VARIANT``) selects one of :data:`VARIANTS` explicitly.
    Raises :class:`BackendError` with a one-line install hint when nothing is usable.
    """
    global _chosen
    force = force or os.environ.get(ENV_VARIANT) or None
    if force is not None and force not in VARIANTS:
        raise BackendError(f"--variant/{ENV_VARIANT}: unknown variant '{force}' (choose {', '.join(VARIANTS)})")
    llvm = _configure_llvm()
    if force is None:
        force = "cuda_ad_rgb" if _cuda_usable() else "llvm_ad_rgb"
    if force == "llvm_ad_rgb" and llvm is None:
        raise BackendError(INSTALL_HINT)
    import mitsuba as mi
    try:
        mi.set_variant(force)
    except (ImportError, AttributeError, RuntimeError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        hint = INSTALL_HINT if force == "llvm_ad_rgb" else "no usable NVIDIA GPU/driver"
        raise BackendError(f"cannot activate Mitsuba variant {force}: {first} ({hint})") from None
    _chosen = force
    return force


def active_variant() -> str | None:
    """The variant chosen by :func:`choose_variant` in this process, if any."""
    return _chosen


def device_name(variant: str) -> str:
    """A short description of where ``variant`` runs, for logs and headers."""
    if variant.startswith("cuda"):
        return "cuda"
    return f"llvm ({os.cpu_count()} threads, {Path(os.environ.get('DRJIT_LIBLLVM_PATH', '?')).name})"


if __name__ == "__main__":  # pragma: no cover - diagnostic helper
    print(choose_variant(sys.argv[1] if len(sys.argv) > 1 else None))
