"""Generate ``water_surface.ply``: the displaced water height field of ``water_caustic.xml``.

A 64x64-vertex grid over x, z in [-1, 1] at height 0 (the scene's to_world places it),
displaced in y by a sum of four directional sine waves (amplitude 1.2-2.5 cm,
wavelength 0.35-0.8) whose curvature focuses light about 0.5-0.8 below the surface, so
the caustic network is sharp on the pool floor. Vertex normals are analytic (smooth
shading), faces are triangles. Deterministic; run from anywhere:

    python ppmrecon/data/scenes/make_water_surface.py
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

N = 64
# (amplitude, wavelength, direction angle in degrees, phase)
WAVES = ((0.025, 0.80, 20.0, 0.3), (0.018, 0.55, 110.0, 1.7),
         (0.014, 0.42, 250.0, 4.1), (0.012, 0.35, 335.0, 2.2))


def height_field(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Height y(x, z) and its partial derivatives dy/dx, dy/dz."""
    y = np.zeros_like(x)
    dx = np.zeros_like(x)
    dz = np.zeros_like(x)
    for amp, wavelength, angle, phase in WAVES:
        k = 2 * np.pi / wavelength
        ux, uz = np.cos(np.radians(angle)), np.sin(np.radians(angle))
        arg = k * (ux * x + uz * z) + phase
        y += amp * np.sin(arg)
        dx += amp * k * ux * np.cos(arg)
        dz += amp * k * uz * np.cos(arg)
    return y, dx, dz


def build() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.linspace(-1.0, 1.0, N)
    x, z = np.meshgrid(t, t, indexing="xy")
    y, dx, dz = height_field(x, z)
    pos = np.stack([x, y, z], -1).reshape(-1, 3)
    nrm = np.stack([-dx, np.ones_like(x), -dz], -1).reshape(-1, 3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    i = np.arange(N * N).reshape(N, N)
    a, b, c, d = i[:-1, :-1], i[:-1, 1:], i[1:, :-1], i[1:, 1:]
    # Counter-clockwise seen from +y, so the geometric normal agrees with the shading normal.
    tri = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                          np.stack([b, c, d], -1).reshape(-1, 3)])
    return pos.astype("<f4"), nrm.astype("<f4"), tri.astype("<i4")


def write_ply(path: Path) -> None:
    pos, nrm, tri = build()
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment ppmrecon water height field, see make_water_surface.py\n"
        f"element vertex {len(pos)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(tri)}\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    verts = np.concatenate([pos, nrm], 1).astype("<f4")
    faces = bytearray()
    for t in tri:
        faces += struct.pack("<B3i", 3, *t)
    path.write_bytes(header.encode("ascii") + verts.tobytes() + bytes(faces))


if __name__ == "__main__":
    out = Path(__file__).with_name("water_surface.ply")
    write_ply(out)
    print(out, out.stat().st_size, "bytes")
