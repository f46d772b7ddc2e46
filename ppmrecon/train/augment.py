"""Training augmentation: the eight flips/rotations of the square (dihedral group D4),
applied identically to every layer of a patch (kornia's exact flips; a 90-degree turn is
a transpose followed by a vertical flip, exact too, no resampling).

The normal channels are vectors, so they turn with the image. They are treated in the
camera's frame (x right, y up): for our generated scenes the camera looks along -z with
+y up, where camera and world axes agree, which is what the test checks (a rotated
normal map equals the normal map of the rotated scene). In that frame

    horizontal flip      (n_x, n_y) -> (-n_x,  n_y)
    90 degrees CCW       (n_x, n_y) -> (-n_y,  n_x)
    180 degrees          (n_x, n_y) -> (-n_x, -n_y)

and n_z (towards the camera) is unchanged.
"""

from __future__ import annotations

import torch
from kornia.geometry.transform import hflip, rot180, vflip


def transform_image(x: torch.Tensor, turns: int, flip: bool) -> torch.Tensor:
    """Apply an optional horizontal flip, then ``turns`` x 90 degrees counter-clockwise,
    to the last two (H, W) axes of ``x`` (any leading shape)."""
    lead = x.shape[:-2]
    x = x.reshape(-1, 1, *x.shape[-2:])
    if flip:
        x = hflip(x)
    if turns % 2:
        x = vflip(x.transpose(-1, -2))
    if turns % 4 >= 2:
        x = rot180(x)
    return x.reshape(*lead, *x.shape[-2:])


def transform_normals(n: torch.Tensor, turns: int, flip: bool) -> torch.Tensor:
    """Turn normal vectors (..., 3, H, W) the way :func:`transform_image` turns the image
    (the caller moves the pixels; this maps the vector components)."""
    nx, ny, nz = n.unbind(-3)
    if flip:
        nx = -nx
    for _ in range(turns % 4):
        nx, ny = -ny, nx
    return torch.stack([nx, ny, nz], -3)
