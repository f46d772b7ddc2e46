"""Tiled inference: buffer file -> network logits -> consistent combination (paper 002 Eq. 6).

The estimator is ``yhat_c = sum_j sum_{i in Omega_c} w^j_{c,i} (~y_i + ~z^j_c - ~z^j_i)``
with the weights predicted by the network (see :mod:`ppmrecon.model.combine`).

With the model's firefly guard (:mod:`.guard`; on when its checkpoint says so, or when
asked), the inputs are guarded first, on the whole image, and each tile's combination is
clamped into the band of its five inputs; without it, the combination is clamped at 0
(radiance is nonnegative). Both keep the result consistent. With the model's denoiser
guide (:mod:`.guide`; likewise on when asked), OIDN's image of the guarded ~z^4 is made
once on the whole image and every tile's logits are the network's plus the guide's prior
(:func:`.guide.prior_logits`): only the weights change, so consistency does not. In the
guide's "envelope" mode the network and Eq. 6 are skipped: the output is OIDN's image held
inside the range of each pixel's five estimates (:func:`.guide.envelope`). The image is processed
in square tiles. Each tile is extended by a halo of
``receptive radius + K//2`` pixels (clipped at the image border), so the logits and the
window of every kept pixel see exactly what they would see on the whole image: tiled
and untiled results agree up to floating-point rounding. Tiling bounds the memory of
the 4 K^2 logits per pixel, which is what dominates at full resolution.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import replace
from contextlib import contextmanager
from typing import Callable, Iterator, NamedTuple

import numpy as np
import torch

from ..buffers import BufferFile
from ..errors import PpmreconError, UsageError
from .combine import NonFiniteLogitsError, combine_with_weights, logit_channels
from .features import ModelInputs, buffer_scales, from_buffer
from .guard import GuardConfig, finish, floor_of, guard_buffer, image_scale, passes_of
from .chooser import Chooser, band, candidates, features
from .guide import (ENVELOPE_MODES, Aim, GuideConfig, GuideImages, cascade_aim, dark_level, envelope, guide_images,
                    guided_logits, speckle_field, y_spike_mask, z_spike_mask)
from .guide import planes as guide_planes_of
from .kpn import KPN

#: Automatic tiles keep the logits of one tile (with halo) below this size ...
TILE_BUDGET_BYTES = 256 * 1024 ** 2
#: ... and are otherwise about this large: small enough that a tile's temporaries stay
#: in cache (measured fastest on a 2-core Xeon), large enough that the halo costs little.
CACHE_TILE = 128
MIN_TILE = 32

ProgressFn = Callable[[int, int], None]


class ChooserInputs(NamedTuple):
    """What the chooser reads for one image (:func:`chooser_inputs`)."""

    features: torch.Tensor     # (C, H, W), a view of pixel-major memory
    candidates: torch.Tensor   # (K, 3, H, W), likewise
    lo: torch.Tensor           # (H, W, 3): the band of the five estimates
    hi: torch.Tensor


class Denoised(NamedTuple):
    rgb: np.ndarray                    # (H, W, 3) float32
    weights_per_z: np.ndarray | None   # (4, H, W) float32: sum_i w^j_{c,i}, the share of ~z^j;
    #                                    None for the guide's envelope (no Eq. 6 weights)


class NonFiniteOutputError(PpmreconError):
    """The network or the combination produced NaN/Inf (never written to disk)."""


def auto_tile(model: KPN, height: int, width: int) -> int:
    """Tile side: ~:data:`CACHE_TILE` (at least 8 halos), within :data:`TILE_BUDGET_BYTES` of logits."""
    per_pixel = logit_channels(model.window) * 4
    budget_side = int((TILE_BUDGET_BYTES / per_pixel) ** 0.5) - 2 * model.preset.halo
    side = min(max(CACHE_TILE, 8 * model.preset.halo), budget_side)
    return max(MIN_TILE, min(side, max(height, width)))


def resolve_precision(precision: str, device: torch.device) -> str:
    """``auto`` -> bfloat16 where the hardware has native bf16 matmul, else float32."""
    if precision != "auto":
        if precision not in ("float32", "bfloat16"):
            raise UsageError(f"precision must be auto, float32 or bfloat16, got '{precision}'")
        return precision
    if device.type == "cuda":
        return "bfloat16" if torch.cuda.is_bf16_supported() else "float32"
    try:
        native = torch.cpu._is_amx_tile_supported() or torch.cpu._is_avx512_bf16_supported()
    except AttributeError:  # older torch without the probes
        native = False
    return "bfloat16" if native else "float32"


def _tiles(height: int, width: int, tile: int) -> list[tuple[int, int, int, int]]:
    return [(y0, min(y0 + tile, height), x0, min(x0 + tile, width))
            for y0 in range(0, height, tile) for x0 in range(0, width, tile)]


@contextmanager
def _one_thread_per_op() -> Iterator[None]:
    """Run torch ops single-threaded (restored afterwards).

    Tiles are spread over worker threads instead: thousands of small ops per image each
    paying an OpenMP barrier are fast on an idle machine but collapse (tens of times
    slower, measured) when other processes share the cores; independent tiles do not.
    """
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


InputSource = Callable[[slice, slice], ModelInputs]


def denoise_inputs(inputs: ModelInputs, model: KPN, tile: int | None = None,
                   device: str | torch.device = "cpu", progress: ProgressFn | None = None,
                   precision: str = "auto", workers: int | None = None,
                   guard: GuardConfig | None = None) -> Denoised:
    """Run network + combiner over prepared :class:`ModelInputs` (batch of one).

    The inputs are taken as they are: guarding them is the caller's (training data
    are guarded when loaded); only the output band of ``guard`` (default: the model's)
    is applied here.
    """
    def source(rows: slice, cols: slice) -> ModelInputs:
        return ModelInputs(*(None if t is None else t[..., rows, cols] for t in inputs))

    _, _, height, width = inputs.y.shape
    guard = model.guard if guard is None else guard
    combined = _denoise(source, height, width, model, tile, device, progress, precision, workers)
    return _finish(combined, inputs.y[0], inputs.z[0], guard)


def denoise(buf: BufferFile, model: KPN, tile: int | None = None, device: str | torch.device = "cpu",
            progress: ProgressFn | None = None, precision: str = "auto",
            workers: int | None = None, guard: GuardConfig | None = None,
            guide: GuideConfig | None = None) -> Denoised:
    """Denoise one buffer file: ``(rgb (H, W, 3), weights_per_z (4, H, W))``.

    ``tile=None`` picks the tile size (:func:`auto_tile`); a tile at least as large as
    the image means no tiling. ``progress(done, total)`` is called after each tile.
    ``precision`` (``auto``, ``float32``, ``bfloat16``; see :func:`resolve_precision`)
    applies to the network only (see :meth:`KPN.predict`). Features are
    computed per tile (with the whole image's normalisers), so no full-resolution
    feature tensor is ever held. ``guard`` overrides the model's firefly guard
    (:attr:`KPN.guard`); the guard is consistent, so switching it on never changes
    what the result converges to. ``guide`` likewise overrides the model's denoiser
    guide (:attr:`KPN.guide`, :mod:`.guide`): in "weights" mode it only shapes the weights;
    in "envelope" mode the result is the guide held in the range of each pixel's five
    estimates (:func:`.guide.envelope`), the network is not run and ``weights_per_z`` is None.
    """
    guard = model.guard if guard is None else guard
    guide = model.guide if guide is None else guide
    buf = guard_buffer(buf, guard)                      # whole image: medians need no halo
    scales = buffer_scales(buf, model.features)
    if model.features.guide and not guide.enabled:
        raise UsageError("this model takes the denoiser guide as input: it cannot run with the guide off")
    # header problems fail early, before the guide (whose channels need no header)
    from_buffer(buf, replace(model.features, guide=False), (slice(0, 1), slice(0, 1)), scales)
    scale = float(scales.radiance[0]) if scales.radiance is not None else None   # already computed
    if guide.enabled and guide.mode in ENVELOPE_MODES:
        chooser = model.chooser if guide.mode == "chooser" else None
        if guide.mode == "chooser" and chooser is None:
            raise UsageError("guide mode 'chooser': this model has no chooser "
                             "(train one with `ppmrecon-train chooser`, or use --guide-mode envelope)")
        scale = _scale(buf) if scale is None else scale
        aim = buffer_aim(buf, guide, guard, scale)
        images, planes = buffer_guide_images(buf, guide, guard, scale, need_y=chooser is not None, aim=aim)
        result = buffer_envelope(buf, planes, guard, guide, device, None if chooser else progress, scale, aim)
        if chooser is None:
            return result
        return _choose(buf, result.rgb, images, chooser, scale, device, progress, guide, guard)
    planes = buffer_guide(buf, guide, guard, scale) if guide.enabled else None

    def source(rows: slice, cols: slice) -> ModelInputs:
        return from_buffer(buf, model.features, (rows, cols), scales, planes)

    height, width = buf.shape
    combined = _denoise(source, height, width, model, tile, device, progress, precision, workers)
    est = torch.from_numpy(np.ascontiguousarray(buf.estimates, np.float32)).permute(0, 3, 1, 2)   # (5, 3, H, W)
    return _finish(combined, est[0], est[1:], guard)


def buffer_guide(buf: BufferFile, guide: GuideConfig, guard: GuardConfig,
                 scale: float | None = None) -> torch.Tensor:
    """:func:`.guide.guide_planes` of a whole (guarded) buffer file, (1, 4, H, W);
    ``scale``: the file's :func:`.guard.image_scale` when the caller has it already."""
    return buffer_guide_images(buf, guide, guard, scale)[1]


def buffer_aim(buf: BufferFile, guide: GuideConfig, guard: GuardConfig, scale: float | None = None) -> Aim | None:
    """:func:`.guide.cascade_aim` of a whole (guarded) buffer file; None where the guide's
    cascade is off (or the guard, whose anchor width it takes, is), or the render has fewer
    passes than its ``cascade_passes``; below ``cascade_y_up`` passes its step to ~y goes down
    only; ``scale``: the file's :func:`.guard.image_scale` when the caller has it already."""
    if not (guide.cascade and guide.mode in ENVELOPE_MODES and guard.enabled and guard.anchor > 0):
        return None
    passes = passes_of(buf)
    if guide.cascade_passes and passes < guide.cascade_passes:
        return None                   # too few passes for its variance test (GuideConfig.cascade_passes)
    # channels-first in memory: the per-channel means and steps of the tests run ~15% faster
    # than on the buffer's pixel-major layout, and the pulled ~z^j come out in it
    est = torch.from_numpy(np.ascontiguousarray(buf.estimates, np.float32)).permute(0, 3, 1, 2).contiguous()[None]
    var = torch.from_numpy(np.ascontiguousarray(buf.variances, np.float32))[None]
    radii = torch.from_numpy(np.ascontiguousarray(buf.radii, np.float32))[None]
    y, z = est[:, 0], est[:, 1:]
    with torch.no_grad():
        dark = dark_level(guide, guard, _scale(buf) if scale is None else scale) if guide.anchor_free_dark else 0.0
        return cascade_aim(z, var, radii, guide, guard.anchor, speckle_field(y, z, var, guide.anchor_free, dark), y,
                           y_up=not (guide.cascade_y_up and passes < guide.cascade_y_up))


def buffer_guide_images(buf: BufferFile, guide: GuideConfig, guard: GuardConfig, scale: float | None = None,
                        need_y: bool = False, aim: Aim | None = None) -> tuple[GuideImages, torch.Tensor]:
    """:func:`.guide.guide_images` of a whole (guarded) buffer file and the guide's planes
    (1, 4, H, W); ``need_y``: OIDN's image of ~y is made even where the guide does not use it;
    ``aim`` (:func:`buffer_aim`; made here where the guide's cascade is on and it is None):
    OIDN denoises its t, with its variance, in place of the guide's source estimate."""
    if scale is None:
        scale = _scale(buf)
    aim = buffer_aim(buf, guide, guard, scale) if aim is None else aim
    floor = floor_of(guard)
    estimates, variances, chosen = buf.estimates, buf.variances, guide
    if aim is not None:               # OIDN's inputs are ~y and t alone: two layers, not a copy of five
        estimates = np.stack((estimates[0], aim.t[0].permute(1, 2, 0).numpy()))
        variances = np.stack((variances[0], aim.variance[0, 0].numpy()))
        chosen = replace(guide, source=1)
    images = guide_images(estimates, buf.albedo, buf.normal, chosen, scale, floor, variances, need_y, passes_of(buf))
    return images, guide_planes_of(images.guide, guide, scale, floor)


def _scale(buf: BufferFile) -> float:
    est = torch.from_numpy(np.ascontiguousarray(buf.estimates, np.float32)).permute(0, 3, 1, 2)[None]
    return float(image_scale(est))


def chooser_inputs(buf: BufferFile, envelope_rgb: np.ndarray, images: GuideImages,
                   scale: float | None = None, guide: GuideConfig | None = None,
                   guard: GuardConfig | None = None) -> ChooserInputs:
    """The chooser's features (C, H, W), candidates (K, 3, H, W) and band of a whole (guarded)
    buffer file, its envelope (H, W, 3) and its guide's images (:func:`buffer_guide_images`
    with ``need_y``), ``scale`` its :func:`.guard.image_scale` when the caller has it;
    ``guide`` and ``guard``: the band leaves out the guide's lone ~y spikes as the envelope
    does (:func:`.guide.y_spike_mask`) and holds its ~z^j spikes at ~y (:func:`.guide.z_spike_mask`;
    None: the full range);
    training (:mod:`..train.chooser`) and inference share this. Both are
    views of pixel-major memory (the buffer's own layout): the chooser's convolutions run
    channels-last on them without a copy."""
    est = torch.from_numpy(np.ascontiguousarray(buf.estimates, np.float32))             # (5, H, W, 3)
    y, z = est[0], est[1:]
    hwc = [torch.from_numpy(np.ascontiguousarray(a, np.float32)) for a in (envelope_rgb, buf.albedo, buf.normal)]
    oidn = [t.permute(1, 2, 0) for t in (images.guide, images.source, images.y)]
    scale = _scale(buf) if scale is None else scale
    spikes = z_out = None
    if guide is not None and guard is not None:
        yc, zc = y.permute(2, 0, 1)[None], z.permute(0, 3, 1, 2)[None]
        spikes = y_spike_mask(yc, zc, guide, guard, scale)
        if guide.z_spike:
            var = torch.from_numpy(np.ascontiguousarray(buf.variances, np.float32))[None]
            z_out = z_spike_mask(yc, zc, var, guide, guard, scale)[0].permute(1, 2, 0)
    lo, hi = band(y, z, None if spikes is None else spikes[0].permute(1, 2, 0))
    if z_out is not None:             # the envelope's range of ~y alone (:func:`.guide.envelope`)
        lo, hi = torch.where(z_out, y, lo), torch.where(z_out, y, hi)
    cands = candidates(hwc[0], *oidn, z, lo, hi)
    feats = features(cands, y, lo, hi, torch.from_numpy(np.ascontiguousarray(buf.variances, np.float32)), hwc[1],
                     hwc[2], scale, passes_of(buf))
    return ChooserInputs(feats.permute(2, 0, 1), cands.permute(2, 3, 0, 1), lo, hi)


def _choose(buf: BufferFile, envelope_rgb: np.ndarray, images: GuideImages, chooser: Chooser, scale: float,
            device: str | torch.device, progress: ProgressFn | None, guide: GuideConfig,
            guard: GuardConfig) -> Denoised:
    """The chooser (:mod:`.chooser`) on a whole (guarded) buffer file: no tiles (its
    memory is a few dozen floats per pixel, about 0.7 GB at 1920x1080)."""
    device = torch.device(device)
    feats, cands, lo, hi = chooser_inputs(buf, envelope_rgb, images, scale, guide, guard)
    image = chooser.to(device).eval().predict(feats[None].to(device), cands[None].to(device))[0].permute(1, 2, 0)
    # a convex combination of band-held candidates is in the band; the clamp removes rounding
    image = torch.clamp(image, lo.to(device), hi.to(device))
    if progress is not None:
        progress(1, 1)
    if not torch.isfinite(image).all():
        raise NonFiniteOutputError("the chooser produced NaN/Inf (radiance beyond float32 range?)")
    return Denoised(image.contiguous().cpu().numpy(), None)


def buffer_envelope(buf: BufferFile, planes: torch.Tensor, guard: GuardConfig, guide: GuideConfig,
                    device: str | torch.device = "cpu", progress: ProgressFn | None = None,
                    scale: float | None = None, aim: Aim | None = None) -> Denoised:
    """The guide's envelope (:func:`.guide.envelope`) of a whole (guarded) buffer file: no
    network, no tiles (a few whole-image passes of elementwise work and one blur);
    ``scale``: the file's :func:`.guard.image_scale` when the caller has it already; ``aim``:
    the file's :func:`buffer_aim` (made here where the guide's cascade is on and it is None)."""
    device = torch.device(device)
    if (guide.y_spike or guide.anchor_spikes or guide.z_spike or guide.anchor_free_dark) and scale is None:
        scale = _scale(buf)
    aim = buffer_aim(buf, guide, guard, scale) if aim is None else aim
    if aim is not None:
        aim = Aim(*(None if a is None else a.to(device) for a in aim))
    est = torch.from_numpy(np.ascontiguousarray(buf.estimates, np.float32)).permute(0, 3, 1, 2).to(device)
    def variance_of(k: int) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(buf.variances[k], np.float32))[None, None].to(device)

    m = guide.anchor_source
    wider = variance_of(m + 1) if guide.anchor_select and m + 1 < len(buf.variances) else None
    passes = passes_of(buf) if guide.terms_passes else None
    spike_variances = (variance_of(0), variance_of(len(buf.variances) - 1)) if guide.anchor_spikes else None
    variances = (torch.from_numpy(np.ascontiguousarray(buf.variances, np.float32))[None].to(device)
                 if guide.z_spike or guide.anchor_free or guide.range_sigma else None)
    with torch.no_grad():
        image = envelope(planes.to(device), est[None, 0], est[None, 1:], variance_of(m), guard, guide, scale or 0.0,
                         wider, passes, spike_variances, variances, aim)
    if progress is not None:
        progress(1, 1)
    if not torch.isfinite(image).all():
        raise NonFiniteOutputError("the envelope produced NaN/Inf (radiance beyond float32 range?)")
    return Denoised(image[0].permute(1, 2, 0).contiguous().cpu().numpy(), None)


def _finish(combined: Denoised, y: torch.Tensor, z: torch.Tensor, guard: GuardConfig) -> Denoised:
    """The whole-image steps after Eq. 6 (:func:`..guard.finish`: anchor, band, or the clamp
    at 0) on the raw combination; y (3, H, W) and z (4, 3, H, W) are the guarded inputs."""
    image = torch.from_numpy(combined.rgb).permute(2, 0, 1)[None]
    with torch.no_grad():
        image = finish(image, y[None].float(), z[None].float(), guard)
    if not torch.isfinite(image).all():
        raise NonFiniteOutputError("the combination produced NaN/Inf (radiance beyond float32 range?)")
    return Denoised(image[0].permute(1, 2, 0).contiguous().numpy(), combined.weights_per_z)


def _denoise(source: InputSource, height: int, width: int, model: KPN, tile: int | None,
             device: str | torch.device, progress: ProgressFn | None, precision: str,
             workers: int | None) -> Denoised:
    """The tile loop: Eq. 6 per tile, unclamped (:func:`_finish` follows on the whole
    image). On the CPU, ``workers`` threads (default: torch's thread count) denoise tiles
    side by side, each op single-threaded; on a GPU, one tile at a time."""
    device = torch.device(device)
    precision = resolve_precision(precision, device)
    model = model.to(device).eval()
    if tile is None:
        tile = auto_tile(model, height, width)
    if tile < 1:
        raise UsageError(f"tile size must be positive, got {tile}")
    halo, r = model.preset.halo, model.window // 2
    rgb = torch.empty(3, height, width)
    weights = torch.empty(4, height, width)
    boxes = _tiles(height, width, tile)

    def run_tile(box: tuple[int, int, int, int]) -> None:
        y0, y1, x0, x1 = box
        ya, yb = max(y0 - halo, 0), min(y1 + halo, height)
        xa, xb = max(x0 - halo, 0), min(x1 + halo, width)
        with torch.no_grad():                     # grad mode is per thread
            inp = source(slice(ya, yb), slice(xa, xb))
            logits = model.predict(inp.features.to(device), precision)
            # Eq. 6 for the kept pixels needs their window's terms only: a ring of K//2
            # pixels (the rest of the halo fed the network's receptive field)
            ca, cb = max(y0 - ya - r, 0), min(y1 - ya + r, yb - ya)
            cc, cd = max(x0 - xa - r, 0), min(x1 - xa + r, xb - xa)
            crop = (..., slice(ca, cb), slice(cc, cd))
            y, z = inp.y[crop].to(device), inp.z[crop].to(device)
            planes = None if inp.guide is None else inp.guide[crop].to(device)
            logits = guided_logits(logits[crop], y, z, planes, model.window, model.guide)
            try:
                out = combine_with_weights(y, z, logits, method="loop", consume=True)
            except NonFiniteLogitsError:
                raise NonFiniteOutputError("the network produced NaN/Inf weights; the checkpoint is broken "
                                           "or does not fit this input") from None
            image = out.image
        keep = (slice(None), slice(y0 - ya - ca, y1 - ya - ca), slice(x0 - xa - cc, x1 - xa - cc))
        rgb[:, y0:y1, x0:x1] = image[0][keep].cpu()                # tiles are disjoint: no lock needed
        weights[:, y0:y1, x0:x1] = out.weights_per_z[0][keep].cpu()

    def report(done: int) -> None:
        if progress is not None:
            progress(done, len(boxes))

    if device.type != "cpu":
        for n, box in enumerate(boxes):
            run_tile(box)
            report(n + 1)
    else:
        n_workers = max(1, min(len(boxes), workers or torch.get_num_threads()))
        with _one_thread_per_op(), ThreadPoolExecutor(n_workers, thread_name_prefix="denoise") as pool:
            futures = [pool.submit(run_tile, box) for box in boxes]
            try:
                for n, fut in enumerate(as_completed(futures)):
                    fut.result()
                    report(n + 1)
            except BaseException:
                for fut in futures:
                    fut.cancel()
                raise
    # NaN/Inf propagate through _finish (blur, band, clamp), which checks the final image.
    return Denoised(rgb.permute(1, 2, 0).contiguous().numpy(), weights.numpy())
