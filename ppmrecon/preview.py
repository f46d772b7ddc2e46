"""Previews: linear radiance -> sRGB 8-bit PNG (no extra dependency), side-by-side strips.

PNGs are for looking at results only; numbers are always computed on the EXRs.
"""

from __future__ import annotations

import os
import struct
import tempfile
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from .buffers import _default_mode


def to_srgb8(rgb: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Clamp, apply the sRGB transfer curve (IEC 61966-2-1) and quantise to uint8."""
    x = np.clip(np.nan_to_num(np.asarray(rgb, np.float64) * exposure, nan=0.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, rgb8: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 image as an 8-bit RGB PNG, atomically."""
    h, w, _ = rgb8.shape
    raw = b"".join(b"\x00" + rgb8[y].tobytes() for y in range(h))  # filter type 0 per row

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
           + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent or ".")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(png)
        os.chmod(tmp, _default_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def side_by_side(images: Sequence[np.ndarray], gap: int = 4, exposure: float = 1.0) -> np.ndarray:
    """Linear (H, W, 3) images of one size -> one sRGB uint8 strip, left to right."""
    h = images[0].shape[0]
    parts = []
    for k, img in enumerate(images):
        if k:
            parts.append(np.full((h, gap, 3), 255, np.uint8))
        parts.append(to_srgb8(img, exposure))
    return np.concatenate(parts, axis=1)
