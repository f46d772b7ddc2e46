"""Previews: linear radiance -> sRGB 8-bit PNG (no extra dependency), side-by-side strips.

PNGs are for looking at results only; numbers are always computed on the EXRs.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import Sequence

import numpy as np

from .fileio import atomic_write


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
    atomic_write(path, lambda tmp: Path(tmp).write_bytes(png))


def side_by_side(images: Sequence[np.ndarray], gap: int = 4, exposure: float = 1.0) -> np.ndarray:
    """Linear (H, W, 3) images of one size -> one sRGB uint8 strip, left to right."""
    h = images[0].shape[0]
    parts = []
    for k, img in enumerate(images):
        if k:
            parts.append(np.full((h, gap, 3), 255, np.uint8))
        parts.append(to_srgb8(img, exposure))
    return np.concatenate(parts, axis=1)


def load_for_preview(path: str | os.PathLike, layer: str = "z1") -> np.ndarray:
    """An (H, W, 3) image from a buffer file (its ``layer``) or a plain R,G,B EXR."""
    from . import buffers as B

    channels, _ = B.read_channels(path)
    if all(c in channels for c in B.RGB):
        return np.stack([channels[c] for c in B.RGB], -1)
    names = [f"{layer}.{c}" for c in B.RGB]
    if all(n in channels for n in names):
        return np.stack([channels[n] for n in names], -1)
    raise B.MissingLayerError(path, f"no R,G,B or {layer}.R,G,B channels to preview", channel=names[0])


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m ppmrecon.preview OUT.png IN.exr [IN.exr ...]``: side-by-side sRGB PNG."""
    from .cli_common import ArgumentParser

    p = ArgumentParser(prog="python -m ppmrecon.preview",
                       description="Write EXR images side by side as one sRGB PNG "
                                   "(buffer files show their ~z^1 layer unless --layer).")
    p.add_argument("output", type=Path, help="PNG to write")
    p.add_argument("inputs", type=Path, nargs="+", help="EXR files (same size)")
    p.add_argument("--layer", default="z1", help="layer shown for buffer files (default: z1)")
    p.add_argument("--exposure", type=float, default=1.0, help="linear scale before sRGB (default: 1)")
    args = p.parse_args(argv)
    images = [load_for_preview(f, args.layer) for f in args.inputs]
    if len({img.shape for img in images}) != 1:
        from .errors import UsageError
        raise UsageError(f"{args.output}: inputs differ in size: " + ", ".join(f"{f} {i.shape[1]}x{i.shape[0]}" for f, i in zip(args.inputs, images)))
    write_png(args.output, side_by_side(images, exposure=args.exposure))
    return 0


if __name__ == "__main__":  # pragma: no cover
    from .cli_common import run_main

    raise SystemExit(run_main("ppmrecon.preview", main))
