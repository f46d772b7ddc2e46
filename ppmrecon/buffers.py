"""The buffer file: the single owner of the multi-layer EXR schema (SPEC section 2).

One render produces one scanline, ZIP-compressed, float32 OpenEXR with the layers

    y.{R,G,B,V,r}, z1..z4.{R,G,B,V,r}   five bandwidth estimates, the variance of the
                                         mean (averaged over RGB) and the current radius
    albedo.{R,G,B}, normal.{X,Y,Z}, depth.Z   G-buffers

and ``ppmrecon.*`` header attributes. References and denoised outputs are plain
``R,G,B`` EXRs (optionally with extra debug layers). Every other module imports the
names from here; writers are atomic (temporary file + rename in the same folder) and
readers validate (layers, shapes, pixel types, NaN/Inf, negative radiance, schema
version) and raise a :class:`BufferFileError` subclass whose message names the file,
the channel and the problem.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .errors import UsageError
from .fileio import atomic_write

SCHEMA_VERSION = 1

#: Estimate layers in schema order: ~y (smallest bandwidth, hit point A) then
#: ~z^1..~z^4 (bandwidth chains 2..5, increasing, hit point B).
ESTIMATES: tuple[str, ...] = ("y", "z1", "z2", "z3", "z4")
N_ESTIMATES = len(ESTIMATES)
RGB: tuple[str, ...] = ("R", "G", "B")
VARIANCE = "V"
RADIUS = "r"
ESTIMATE_CHANNELS: tuple[str, ...] = RGB + (VARIANCE, RADIUS)

ALBEDO, NORMAL, DEPTH = "albedo", "normal", "depth"
GBUFFER_CHANNELS: dict[str, tuple[str, ...]] = {
    ALBEDO: RGB,
    NORMAL: ("X", "Y", "Z"),
    DEPTH: ("Z",),
}

#: Header attribute names (SPEC section 2). Extra ``ppmrecon.*`` keys are allowed
#: (controller parameters, stop reason) and round-trip unchanged.
H_VERSION = "ppmrecon.version"
H_METHOD = "ppmrecon.method"
H_KERNEL = "ppmrecon.kernel"
H_PASSES = "ppmrecon.passes"
H_PHOTONS = "ppmrecon.photons_per_pass"
H_ALPHA = "ppmrecon.alpha"
H_KNN = "ppmrecon.knn"
H_SEED = "ppmrecon.seed"
H_SCENE = "ppmrecon.scene"
H_SECONDS = "ppmrecon.render_seconds"
H_STOPPED = "ppmrecon.stopped"
#: What the scene import approximated (one note a line; absent when nothing was).
H_IMPORT_NOTES = "ppmrecon.import_notes"
REQUIRED_HEADER: tuple[str, ...] = (
    H_VERSION, H_METHOD, H_KERNEL, H_PASSES, H_PHOTONS, H_ALPHA, H_KNN, H_SEED,
    H_SCENE, H_SECONDS,
)
PREFIX = "ppmrecon."

_EXR_MAGIC = b"\x76\x2f\x31\x01"


def channel_names() -> list[str]:
    """All channel names of a buffer file, in a fixed order."""
    names = [f"{e}.{c}" for e in ESTIMATES for c in ESTIMATE_CHANNELS]
    names += [f"{layer}.{c}" for layer, chans in GBUFFER_CHANNELS.items() for c in chans]
    return names


# ----------------------------------------------------------------------------- errors

class BufferFileError(UsageError):
    """A buffer or image file cannot be used; the message names file, channel, problem."""

    def __init__(self, path: str | os.PathLike, problem: str, channel: str | None = None):
        self.path = str(path)
        self.channel = channel
        self.problem = problem
        where = f"{self.path}" + (f", channel '{channel}'" if channel else "")
        super().__init__(f"{where}: {problem}")


class NotExrError(BufferFileError):
    """The file does not start with the OpenEXR magic number."""


class TruncatedFileError(BufferFileError):
    """The file starts like an EXR but cannot be read completely."""


class MissingLayerError(BufferFileError):
    """A layer or channel the schema requires is absent."""


class ShapeMismatchError(BufferFileError):
    """Channels of one file have different sizes."""


class PixelTypeError(BufferFileError):
    """A channel is not floating point (UINT)."""


class NonFiniteError(BufferFileError):
    """A channel holds NaN or Inf."""


class NegativeRadianceError(BufferFileError):
    """A radiance, variance or radius channel holds negative values."""


class SchemaVersionError(BufferFileError):
    """The file was written by a newer schema than this program understands."""


# ------------------------------------------------------------------------ data types

@dataclass
class BufferFile:
    """The content of one buffer file, images in (H, W, C) float32, top row first.

    ``estimates[k]`` is layer ``ESTIMATES[k]`` (k = 0 is ~y); ``variances`` and
    ``radii`` are (5, H, W); ``header`` holds the ``ppmrecon.*`` attributes.
    """

    estimates: np.ndarray      # (5, H, W, 3)
    variances: np.ndarray      # (5, H, W)
    radii: np.ndarray          # (5, H, W)
    albedo: np.ndarray         # (H, W, 3)
    normal: np.ndarray         # (H, W, 3)
    depth: np.ndarray          # (H, W)
    header: dict[str, Any] = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.depth.shape[0]), int(self.depth.shape[1])

    def channels(self) -> dict[str, np.ndarray]:
        """Flatten into ``{"layer.channel": (H, W) float32}``."""
        out: dict[str, np.ndarray] = {}
        for k, name in enumerate(ESTIMATES):
            for c, cname in enumerate(RGB):
                out[f"{name}.{cname}"] = self.estimates[k, ..., c]
            out[f"{name}.{VARIANCE}"] = self.variances[k]
            out[f"{name}.{RADIUS}"] = self.radii[k]
        for layer, arr in ((ALBEDO, self.albedo), (NORMAL, self.normal)):
            for c, cname in enumerate(GBUFFER_CHANNELS[layer]):
                out[f"{layer}.{cname}"] = arr[..., c]
        out[f"{DEPTH}.Z"] = self.depth
        return {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in out.items()}


# ---------------------------------------------------------------------------- writing

def encode_notes(notes: list[str]) -> str:
    """Import notes as one header string, one note a line (notes are one line each)."""
    return "\n".join(" ".join(str(n).split()) for n in notes)


def decode_notes(header: Mapping[str, Any]) -> list[str]:
    """The import notes of a header (empty when the import approximated nothing)."""
    text = header.get(H_IMPORT_NOTES, "")
    return [line for line in str(text).splitlines() if line.strip()]


def _header_value(key: str, value: Any) -> Any:
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, str):
        return value
    raise UsageError(f"header attribute '{key}': unsupported type {type(value).__name__}")


def write_exr(path: str | os.PathLike, channels: Mapping[str, np.ndarray],
              header: Mapping[str, Any] | None = None) -> None:
    """Write ``channels`` (name -> (H, W) array) as a float32 ZIP scanline EXR, atomically.

    The data go to a temporary file in the destination folder that is renamed over
    ``path`` only once complete, so an interrupted write never leaves a partial file
    under the final name. NaN/Inf are refused before anything is written.
    """
    import OpenEXR

    path = Path(path)
    if not channels:
        raise UsageError(f"{path}: nothing to write (no channels)")
    shapes = {np.shape(v) for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ShapeMismatchError(path, f"channels must share one (H, W) shape, got {sorted(shapes)}")
    data: dict[str, np.ndarray] = {}
    for name, arr in channels.items():
        a = np.ascontiguousarray(arr, dtype=np.float32)
        if not np.isfinite(a).all():
            raise NonFiniteError(path, "refusing to write NaN/Inf", channel=name)
        data[name] = a
    hdr: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in (header or {}).items():
        hdr[key] = _header_value(key, value)

    def write(tmp: str) -> None:
        with OpenEXR.File(hdr, data) as f:
            f.write(tmp)

    atomic_write(path, write)


def write_buffers(path: str | os.PathLike, buf: BufferFile) -> None:
    """Write a buffer file (all layers of SPEC section 2 plus header), atomically."""
    header = {H_VERSION: SCHEMA_VERSION}
    header.update({k: v for k, v in buf.header.items() if k.startswith(PREFIX)})
    header[H_VERSION] = SCHEMA_VERSION
    missing = [k for k in REQUIRED_HEADER if k not in header]
    if missing:
        raise UsageError(f"{path}: buffer header lacks {', '.join(missing)}")
    write_exr(path, buf.channels(), header)


def write_rgb(path: str | os.PathLike, rgb: np.ndarray,
              extra: Mapping[str, np.ndarray] | None = None,
              header: Mapping[str, Any] | None = None) -> None:
    """Write an (H, W, 3) image as a plain ``R,G,B`` EXR; ``extra`` adds named channels."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise UsageError(f"{path}: expected an (H, W, 3) image, got shape {rgb.shape}")
    channels = {c: rgb[..., i] for i, c in enumerate(RGB)}
    channels.update(extra or {})
    write_exr(path, channels, header)


# ---------------------------------------------------------------------------- reading

def _open_channels(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    import OpenEXR

    if not path.exists():
        raise UsageError(f"{path}: no such file")
    if path.is_dir():
        raise UsageError(f"{path}: is a folder, expected an EXR file")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != _EXR_MAGIC:
        raise NotExrError(path, "not an OpenEXR file (bad magic number)")
    try:
        # Some tools write each layer as its own part: merge every part's channels.
        with OpenEXR.File(str(path), separate_channels=True) as f:
            header = dict(f.header())
            raw = {name: (ch.pixels, ch.type()) for part in f.parts
                   for name, ch in part.channels.items()}
    except Exception as exc:  # the bindings raise RuntimeError for any read failure
        raise TruncatedFileError(path, f"truncated or corrupt EXR ({exc})") from None

    channels: dict[str, np.ndarray] = {}
    shape = None
    for name, (pixels, ptype) in sorted(raw.items()):
        if pixels is None or pixels.dtype.kind != "f" or "UINT" in str(ptype):
            raise PixelTypeError(path, f"pixel type {ptype} is not floating point", channel=name)
        if pixels.ndim != 2:
            raise ShapeMismatchError(path, f"expected a 2-D channel, got shape {pixels.shape}", channel=name)
        if shape is None:
            shape = pixels.shape
        elif pixels.shape != shape:
            raise ShapeMismatchError(path, f"size {pixels.shape} differs from {shape}", channel=name)
        arr = pixels.astype(np.float32, copy=False)  # float16 input is accepted
        if not np.isfinite(arr).all():
            bad = int((~np.isfinite(arr)).sum())
            raise NonFiniteError(path, f"{bad} NaN/Inf value(s)", channel=name)
        channels[name] = arr
    return channels, header


def _check_version(path: Path, header: Mapping[str, Any]) -> None:
    version = header.get(H_VERSION)
    if version is None:
        return
    try:
        version = int(version)
    except (TypeError, ValueError):
        raise SchemaVersionError(path, f"unreadable schema version {version!r}", channel=H_VERSION) from None
    if version > SCHEMA_VERSION:
        raise SchemaVersionError(
            path, f"schema version {version} is newer than this ppmrecon understands "
                  f"({SCHEMA_VERSION}); upgrade ppmrecon", channel=H_VERSION)


def _require(path: Path, channels: Mapping[str, np.ndarray], names: list[str], hint: str = "") -> None:
    missing = [n for n in names if n not in channels]
    if not missing:
        return
    layers = sorted({n.split(".")[0] for n in missing})
    msg = f"missing layer(s) {', '.join(layers)}"
    if hint:
        msg += f"; {hint}"
    raise MissingLayerError(path, msg, channel=missing[0])


def _nonnegative(path: Path, channels: Mapping[str, np.ndarray], names: list[str]) -> None:
    for n in names:
        arr = channels[n]
        if arr.size and float(arr.min()) < 0.0:
            raise NegativeRadianceError(path, f"negative value {float(arr.min()):g}", channel=n)


RENDER_HINT = "this looks like a plain image; make a buffer file with `ppmrecon-render SCENE --output FILE.exr`"


def read_buffers(path: str | os.PathLike) -> BufferFile:
    """Read and validate a buffer file (SPEC section 2)."""
    path = Path(path)
    channels, header = _open_channels(path)
    _check_version(path, header)
    _require(path, channels, channel_names(), hint=RENDER_HINT)
    radiance = [f"{e}.{c}" for e in ESTIMATES for c in ESTIMATE_CHANNELS] + [f"{ALBEDO}.{c}" for c in RGB] + [f"{DEPTH}.Z"]
    _nonnegative(path, channels, radiance)
    est = np.stack([np.stack([channels[f"{e}.{c}"] for c in RGB], -1) for e in ESTIMATES])
    var = np.stack([channels[f"{e}.{VARIANCE}"] for e in ESTIMATES])
    rad = np.stack([channels[f"{e}.{RADIUS}"] for e in ESTIMATES])
    albedo = np.stack([channels[f"{ALBEDO}.{c}"] for c in RGB], -1)
    normal = np.stack([channels[f"{NORMAL}.{c}"] for c in GBUFFER_CHANNELS[NORMAL]], -1)
    meta = {k: v for k, v in header.items() if k.startswith(PREFIX)}
    return BufferFile(est, var, rad, albedo, normal, channels[f"{DEPTH}.Z"], meta)


def read_rgb(path: str | os.PathLike, allow_negative: bool = False) -> tuple[np.ndarray, dict[str, Any]]:
    """Read a plain ``R,G,B`` EXR (reference or denoised output) as (H, W, 3) float32."""
    path = Path(path)
    channels, header = _open_channels(path)
    _check_version(path, header)
    _require(path, channels, list(RGB))
    if not allow_negative:
        _nonnegative(path, channels, list(RGB))
    rgb = np.stack([channels[c] for c in RGB], -1)
    return rgb, {k: v for k, v in header.items() if k.startswith(PREFIX)}


def read_channels(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read every channel of an EXR (validated for type, shape and finiteness)."""
    path = Path(path)
    channels, header = _open_channels(path)
    _check_version(path, header)
    return channels, header
