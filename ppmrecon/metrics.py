"""Error metrics (SPEC section 7).

relMSE (Rousselle et al. 2011, as used by paper 002 and its public code): per pixel

    relMSE_c = mean_l (yhat_{c,l} - y_{c,l})^2 / ((mean_l y_{c,l})^2 + 0.01)

averaged over pixels. Works on numpy arrays (computed in float64, returns a float) and
on torch tensors (keeps dtype and autograd, returns a 0-d tensor). The colour channels
lie on ``channel_axis``: -1 for (H, W, 3) images, 1 for (B, 3, H, W) tensors.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

RELMSE_EPS = 0.01


def _check(est: Any, ref: Any) -> None:
    if tuple(est.shape) != tuple(ref.shape):
        raise ValueError(f"estimate and reference shapes differ: {tuple(est.shape)} vs {tuple(ref.shape)}")


def relmse_map(est: Any, ref: Any, channel_axis: int = -1) -> Any:
    """Per-pixel relMSE (the channel axis reduced away)."""
    _check(est, ref)
    if isinstance(est, torch.Tensor) or isinstance(ref, torch.Tensor):
        est, ref = torch.as_tensor(est), torch.as_tensor(ref)
        sq = (est - ref).square().mean(dim=channel_axis)
        return sq / (ref.mean(dim=channel_axis).square() + RELMSE_EPS)
    est = np.asarray(est, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    sq = np.square(est - ref).mean(axis=channel_axis)
    return sq / (np.square(ref.mean(axis=channel_axis)) + RELMSE_EPS)


def relmse(est: Any, ref: Any, channel_axis: int = -1) -> Any:
    """relMSE averaged over all pixels: a float for numpy input, a 0-d tensor for torch."""
    m = relmse_map(est, ref, channel_axis)
    return m.mean() if isinstance(m, torch.Tensor) else float(m.mean())


def deciding_pixels(excess: np.ndarray) -> int:
    """How many pixels decide that an image is worse than its best input: the fewest whose
    per-pixel relMSE excess over that input's (``excess`` (H, W), ours - best), taken out,
    leaves ours no worse; 0 where it is not worse. A verdict decided by a handful of pixels
    (a light's edge, a pixel whose reference is 0) is a different failure from a systematic one."""
    total = float(excess.sum(dtype=np.float64))
    if total <= 0:
        return 0
    remaining = total - np.cumsum(np.sort(excess, axis=None)[::-1].astype(np.float64))
    done = remaining <= 1e-9 * total                       # the sum's own rounding
    return int(np.argmax(done) + 1) if done.any() else int(excess.size)


def relmse_scaled(est: np.ndarray, ref: np.ndarray, channel_axis: int = -1) -> float:
    """relMSE of both images divided by the reference's mean: the same figure for a scene
    and the scene with every light 1e4 times brighter. Plain relMSE's 0.01 is absolute, so
    on a scene of mean 1e-4 it scores the few pixels above 0.1 alone (a light's edge) and
    on one of mean 1e2 a pixel that should be black counts as much as a hundred lit ones
    (issue 12's data span 1e-4 to 1e4). An all-black reference keeps the plain figure."""
    m = float(np.asarray(ref, dtype=np.float64).mean())
    m = m if m > 0 else 1.0
    return relmse(np.asarray(est, dtype=np.float64) / m, np.asarray(ref, dtype=np.float64) / m, channel_axis)


def relmse_trimmed(est: np.ndarray, ref: np.ndarray, discard: float = 1e-3, channel_axis: int = -1) -> float:
    """relMSE over the pixels left after dropping the ``discard`` fraction with the largest
    error, as denoising comparisons often report next to plain relMSE: a handful of
    fireflies can otherwise decide the whole figure."""
    m = np.sort(relmse_map(est, ref, channel_axis).ravel())
    keep = max(1, int(round(m.size * (1.0 - discard))))
    return float(m[:keep].mean())


def block_means(img: np.ndarray, block: int = 8) -> np.ndarray:
    """Means of ``block`` x ``block`` tiles of an (H, W, C) image, (H // block, W // block, C);
    a partial last row/column of tiles is left out (every mean covers a full tile)."""
    img = np.asarray(img, dtype=np.float64)
    h, w = (img.shape[0] // block) * block, (img.shape[1] // block) * block
    if h == 0 or w == 0:
        raise ValueError(f"image {img.shape[:2]} is smaller than one {block}x{block} block")
    tiles = img[:h, :w].reshape(h // block, block, w // block, block, *img.shape[2:])
    return tiles.mean(axis=(1, 3))


def relmse_blocks(est: np.ndarray, ref: np.ndarray, block: int = 8) -> float:
    """Low-frequency error (SPEC section 7): relMSE of the ``block`` x ``block`` tile means
    of (H, W, 3) images. Noise averages out inside a tile, a smooth bias does not, so a
    reconstruction that trades noise for blur shows here and not in plain relMSE."""
    _check(est, ref)
    return relmse(block_means(est, block), block_means(ref, block))


#: Rec. 709 / sRGB luminance weights of linear R, G, B (Mitsuba's ``luminance``).
LUMINANCE_WEIGHTS = (0.212671, 0.715160, 0.072169)


def luminance(img: np.ndarray) -> np.ndarray:
    """Luminance of an (..., 3) linear RGB image, float64, channel axis reduced away."""
    return np.asarray(img, dtype=np.float64) @ np.asarray(LUMINANCE_WEIGHTS)


def luminance_ratio(est: np.ndarray, ref: np.ndarray) -> float:
    """Mean luminance of ``est`` over that of ``ref`` (1 = same overall brightness; a
    biased estimator or a lost light path shows here whatever the noise); NaN if the
    reference is black."""
    _check(est, ref)
    denominator = float(luminance(ref).mean())
    return float(luminance(est).mean()) / denominator if denominator > 0 else float("nan")


#: A pixel is a firefly when its estimate exceeds FIREFLY_FACTOR x (reference +
#: FIREFLY_FLOOR x the reference image's mean); see :func:`firefly_mask`.
FIREFLY_FACTOR = 10.0
FIREFLY_FLOOR = 0.01


def firefly_mask(est: np.ndarray, ref: np.ndarray, factor: float = FIREFLY_FACTOR,
                 floor: float = FIREFLY_FLOOR, channel_axis: int = -1) -> np.ndarray:
    """Firefly pixels of ``est`` against ``ref`` (boolean map, channel axis reduced away):

        mean_l est_{c,l} > factor * (mean_l ref_{c,l} + floor * mean(ref))

    on the channel means, as relMSE uses them. The test is scale-free (radiance x 1e4
    finds the same pixels), and the floor, a fraction of the reference image's mean, keeps
    pixels that are black in the reference from counting every speck of noise there."""
    _check(est, ref)
    e = np.asarray(est, dtype=np.float64).mean(axis=channel_axis)
    r = np.asarray(ref, dtype=np.float64).mean(axis=channel_axis)
    return e > factor * (r + floor * float(r.mean()))


def firefly_count(est: np.ndarray, ref: np.ndarray, factor: float = FIREFLY_FACTOR,
                  floor: float = FIREFLY_FLOOR, channel_axis: int = -1) -> int:
    """How many pixels :func:`firefly_mask` flags."""
    return int(firefly_mask(est, ref, factor, floor, channel_axis).sum())
