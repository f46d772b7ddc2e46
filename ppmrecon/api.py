"""The Python API: render, denoise, load, save and compare, NumPy arrays in and out.

Exported at the top level of the package::

    import ppmrecon
    buf = ppmrecon.render("water_caustic", passes=32)   # a BufferFile: five estimates + G-buffers
    rgb = ppmrecon.denoise(buf)                          # (H, W, 3) float32, the shipped model
    ppmrecon.save("water.exr", buf); ppmrecon.save("water_denoised.exr", rgb)
    ppmrecon.compare(rgb, reference)                     # {"relmse": ..., ...}

The commands share these functions' cores (scene loading, the renderer, the model
lookup, the scorer): ``ppmrecon-render FILE`` writes what ``ppmrecon.render(FILE)``
returns, ``ppmrecon-denoise`` what ``ppmrecon.denoise`` returns.

``ppmrecon.render`` and ``ppmrecon.compare`` are also the names of the renderer's
subpackage and of the ``ppmrecon-compare`` module; those two modules are callable
(:class:`ppmrecon._callable.CallableModule`) and calling them calls the functions here,
so ``import ppmrecon.render.cli`` keeps working beside ``ppmrecon.render(...)``.

Errors are :class:`ppmrecon.errors.UsageError` (one line naming the file, option or
argument and the problem), as the commands print them.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np

from . import buffers as B
from .buffers import BufferFile
from .errors import UsageError

if TYPE_CHECKING:  # pragma: no cover
    import mitsuba as mi

    from .model.kpn import KPN
    from .render.integrator import RenderSettings
    from .scene.loader import LoadedScene

__all__ = ["render", "denoise", "load_buffers", "load_image", "load_model", "save", "compare", "builtin_scenes",
           "BufferFile"]


def render(scene: str | os.PathLike | None | mi.Scene | Mapping[str, Any] = None, passes: int | None = 16,
           method: str = "sppm", photons: int = 1 << 17, resolution: tuple[int, int] | int | None = None,
           seed: int = 0, *, time_budget: float | None = None, max_depth: int | None = None,
           rr_depth: int | None = None, kernel: str = "constant", direct: str = "all", alpha: float = 2.0 / 3.0,
           knn: int = 20, method_params: Mapping[str, Any] | None = None, variant: str | None = None,
           progress: Callable[[int, float], None] | None = None) -> BufferFile:
    """Render a scene with multi-bandwidth progressive photon mapping.

    ``scene``: a built-in name (``ppmrecon.builtin_scenes()``), a path to a Mitsuba 3
    or 0.6 XML file, a loaded ``mi.Scene`` or a Mitsuba scene dict (``mi.load_dict``
    form); None is the default built-in scene. ``method``: the bandwidth controller,
    as ``ppmrecon-render --method`` (``sppm``, ``cppm``, ``fppm``, ...); ``method_params``
    passes its options, e.g. ``{"significance": 0.01}`` for ``cppm``. ``passes`` (or ``time_budget`` in seconds, or both:
    whichever ends first), ``photons`` per pass, ``resolution`` ((W, H), or W keeping
    the aspect ratio), ``seed``: as the ``ppmrecon-render`` options of the same names;
    ``max_depth``/``rr_depth`` default to the scene's integrator values.
    ``progress(passes_done, seconds)`` is called after every pass.

    Returns the :class:`BufferFile`: ``estimates`` (5, H, W, 3) (``~y, ~z^1..~z^4``),
    ``variances`` and ``radii`` (5, H, W), ``albedo``, ``normal`` (H, W, 3), ``depth``
    (H, W) and the ``header`` a buffer file records.

    >>> import ppmrecon
    >>> buf = ppmrecon.render("plane_point", passes=2, photons=4096, resolution=16)
    >>> buf.estimates.shape, buf.header["ppmrecon.passes"]
    ((5, 16, 16, 3), 2)
    >>> float(buf.estimates[1].mean()) > 0   # ~z^1: the plane is lit
    True
    """
    from .backend import VARIANTS, choose_variant
    from .render.integrator import Renderer
    from .scene.loader import load_scene

    if variant is not None or (_active_variant() not in VARIANTS and type(scene).__name__ != "Scene"):
        choose_variant(variant)  # a script's own variant is kept; its mi.Scene is bound to it
    loaded = load_scene(scene, resolution=resolution)
    if passes is None and time_budget is None:
        raise UsageError("render: give passes or time_budget")
    if not 0.0 < alpha < 1.0:
        raise UsageError(f"render: alpha must lie in (0, 1), got {alpha}")
    settings = render_settings(loaded, max_depth=max_depth, rr_depth=rr_depth, method=method, passes=passes,
                               time_budget=time_budget, photons=photons, seed=seed, kernel=kernel, alpha=alpha,
                               knn=knn, direct=direct, method_params=dict(method_params or {}))
    try:
        renderer = Renderer(loaded.scene, settings, scene_name=loaded.name)
    except (TypeError, ValueError) as exc:  # settings and controller options are checked here
        raise UsageError(f"render: {exc}") from None
    on_pass = None if progress is None else (lambda r: progress(r.passes_done, r.seconds))
    result = renderer.run(on_pass)
    stamp_header(result.header, str(_active_variant()), loaded.notes)
    return result.buffer_file()


def render_settings(loaded: LoadedScene, max_depth: int | None = None, rr_depth: int | None = None,
                    **options: Any) -> RenderSettings:
    """The render settings for a loaded scene (``ppmrecon-render`` builds its own with
    this too): ``max_depth``/``rr_depth`` default to the scene integrator's values,
    ``options`` are :class:`~ppmrecon.render.integrator.RenderSettings` fields."""
    from .render.integrator import RenderSettings

    scene_max_depth, scene_rr_depth = loaded.depths()
    return RenderSettings(max_depth=scene_max_depth if max_depth is None else max_depth,
                          rr_depth=rr_depth or scene_rr_depth, **options)


def stamp_header(header: dict[str, Any], variant: str, notes: list[str]) -> None:
    """Record in a render's header the Mitsuba variant it ran on and what the scene
    import approximated (as every buffer file written by ppmrecon does)."""
    header["ppmrecon.variant"] = variant
    if notes:
        header[B.H_IMPORT_NOTES] = B.encode_notes(notes)


def _active_variant() -> str | None:
    """The Mitsuba variant active in this process (the caller's or ours), if any."""
    import sys

    mi = sys.modules.get("mitsuba")
    return None if mi is None else mi.variant()


def load_model(model: str | os.PathLike | KPN | None = None) -> KPN:
    """A denoising network: the shipped default (None), a checkpoint file, or a model
    object (returned as it is).

    >>> import ppmrecon
    >>> ppmrecon.api.load_model().preset.name
    'tiny'
    """
    from .model import checkpoint

    if model is None or isinstance(model, (str, os.PathLike)):
        return checkpoint.load_checkpoint(checkpoint.model_path(model)).model
    return model


def denoise(buffers: BufferFile | str | os.PathLike, model: str | os.PathLike | KPN | None = None, *,
            guard: str = "on", guide: str = "on", guide_quality: str | None = None,
            guide_denoiser: str | None = None, guide_nlm_k: float | None = None,
            guide_nlm_radius: float | None = None, guide_nlm_y_passes: float | None = None,
            guide_nlm_y_k: float | None = None, guide_nlm_joint_passes: float | None = None,
            guide_nlm_joint_k: float | None = None, guide_anchor_free_dark: float | None = None,
            guide_nlm_albedo: float | None = None, guide_nlm_albedo_eps: float | None = None,
            guide_nlm_albedo_channels: str | None = None,
            guide_range_sigma: float | None = None, guide_range_sigma_rel: float | None = None,
            guide_range_sigma_width: float | None = None, guide_range_sigma_isolated: float | None = None,
            guide_mode: str | None = None, guide_y_weight: float | None = None,
            guide_y_spike: float | None = None, guide_anchor_settled: float | None = None,
            guide_anchor_select: float | None = None, guide_terms_passes: float | None = None,
            guide_anchor_spikes: float | None = None, guide_y_found: float | None = None,
            guide_z_spike: float | None = None, guide_anchor_free: float | None = None,
            guide_y_empty: float | None = None, guide_redistribute: float | None = None,
            guide_cascade: float | None = None, guide_cascade_passes: float | None = None,
            guide_cascade_y: float | None = None, guide_cascade_y_up: float | None = None,
            tile: int | None = None,
            device: str = "cpu",
            precision: str = "auto") -> np.ndarray:
    """The consistent reconstruction of a render (the guide's envelope, or paper 002 Eq. 6):
    (H, W, 3) float32.

    ``buffers``: a :class:`BufferFile` (what :func:`render` returns) or the path of a
    buffer file. ``model``: None for the model shipped with ppmrecon, a checkpoint path,
    or a loaded model (:func:`load_model`). ``guard``: the firefly guard, ``on``
    (default), ``off`` or ``model`` (as the checkpoint was trained), as
    ``ppmrecon-denoise --guard``; ``guide``: the denoiser guide (OIDN of ~z^4),
    likewise; ``guide_quality``: OIDN's mode for the guide (``high``, ``balanced``,
    ``fast``; None: the model's); ``guide_denoiser``: what denoises the guide's images,
    ``oidn``, ``nlm`` (variance-normalised NL-means for the source and ~y) or ``nlm_source``
    (for the source, OIDN for ~y; None: the model's), as ``--guide-denoiser``, with
    ``guide_nlm_k`` / ``guide_nlm_radius`` / ``guide_nlm_y_passes`` / ``guide_nlm_y_k`` /
    ``guide_nlm_joint_passes`` / ``guide_nlm_joint_k`` / ``guide_nlm_albedo`` / ``guide_nlm_albedo_eps``
    as ``--guide-nlm-k`` / ``--guide-nlm-radius`` / ``--guide-nlm-y-passes`` / ``--guide-nlm-y-k`` /
    ``--guide-nlm-joint-passes`` / ``--guide-nlm-joint-k`` / ``--guide-nlm-albedo`` / ``--guide-nlm-albedo-eps``,
    and ``guide_nlm_albedo_channels`` (``mean`` or ``rgb``) as ``--guide-nlm-albedo-channels``;
    ``guide_range_sigma`` / ``guide_range_sigma_rel`` / ``guide_range_sigma_width`` /
    ``guide_range_sigma_isolated`` as ``--guide-range-sigma`` / ``--guide-range-sigma-rel`` /
    ``--guide-range-sigma-width`` / ``--guide-range-sigma-isolated``;
    ``guide_mode``: ``envelope`` (OIDN's image held inside
    the range of each pixel's five estimates), ``chooser`` (a learned per-pixel mix of the
    envelope and other images held in that range; a checkpoint with a chooser, as the
    shipped one) or ``weights`` (the prior of Eq. 6's weights, corrected by the network;
    None: the model's), as ``--guide-mode``;
    ``guide_y_weight``: the weight of OIDN's image of ~y in the guide (>= 0; None: the
    model's), as ``--guide-y-weight``; ``guide_y_spike``: leave ~y out of a pixel's range
    where it is a lone spike this many times above the ~z^j (0 = off, else > 1; None: the
    model's), as ``--guide-y-spike``; ``guide_anchor_settled``: the anchor only where its
    low-pass is settled (ratio r0, 0 = off; None: the model's), as ``--guide-anchor-settled``;
    ``guide_anchor_select``: the anchor aimed between ~z^m and the wider ~z^(m+1) by how far
    their low-passes differ (factor k >= 0, 0 = off; None: the model's), as
    ``--guide-anchor-select``; ``guide_terms_passes``: the envelope's range widened towards
    Eq. 6's terms by the share 1 / (1 + N / M) (M >= 0, 0 = off; None: the model's), as
    ``--guide-terms-passes``; ``guide_anchor_spikes``: the anchor kept from spreading an
    isolated bright pixel of its aim, that pixel set to the inverse-variance mean of ~y and
    ~z^4 (factor R > 1, 0 = off; None: the model's), as ``--guide-anchor-spikes``;
    ``guide_y_found``: ~y's share in the guide scaled by the local share of pixels where ~y
    is not sparser than ~z^4 (Gaussian width in px, 0 = off; None: the model's), as
    ``--guide-y-found``; ``guide_z_spike``: hold a pixel at ~y where its four ~z^j are a lone
    spike over a settled ~y, each this many times above it (0 = off, else > 1; None: the
    model's), as ``--guide-z-spike``; ``guide_anchor_free``: where all five estimates are
    unsettled at this ratio, the anchored value held in the range widened to its
    neighbourhood's (0 = off; None: the model's), as
    ``--guide-anchor-free``; ``guide_anchor_free_dark``: a pixel whose ~z^4 reads at most this
    many times the guard's floor x the image's scale is dark, not a speckle (0 = only an empty
    ~z^4; None: the model's), as ``--guide-anchor-free-dark``;
    ``guide_y_empty``: ~y's share in the guide scaled by the local share
    of pixels where ~y did not read 0 while ~z^4 rests on more than one event (Gaussian width
    in px, 0 = off; None: the model's), as ``--guide-y-empty``; ``guide_redistribute``: what
    the final clamp took given back to the pixels around within their ranges (Gaussian width
    in px, 0 = off; None: the model's), as ``--guide-redistribute``; ``guide_cascade``: the
    anchor's aim stepped on down to ~z^2 and ~z^1 where the wider estimates' bandwidth bias
    shows beyond this many times the narrower one's noise, the range's wide ends pulled to it
    and OIDN given it in place of ~z^4 (factor k >= 0, 0 = off; None: the model's), as
    ``--guide-cascade``; ``guide_cascade_passes``: renders of fewer passes run without the
    cascade (0 = every N; None: the model's), as ``--guide-cascade-passes``;
    ``guide_cascade_y``: the cascade's aim taken one step further, to ~y, where ~y's low-pass
    departs from it by more than this many times ~y's noise and ~z^1 departs the same way
    (factor k >= 0, 0 = off; None: the model's), as ``--guide-cascade-y``;
    ``guide_cascade_y_up``: renders of fewer passes take that step down only (0 = up and down
    at every N; None: the model's), as ``--guide-cascade-y-up``; ``tile``,
    ``device``, ``precision`` as its options.

    >>> import ppmrecon
    >>> buf = ppmrecon.render("plane_point", passes=2, photons=4096, resolution=16)
    >>> rgb = ppmrecon.denoise(buf)
    >>> rgb.shape, rgb.dtype.name
    ((16, 16, 3), 'float32')
    >>> bool((rgb >= 0).all())
    True
    """
    from .model.cli import (guard_choice, guide_choice, torch_device, with_guide_albedo_channels,
                            with_guide_denoiser, with_guide_mode,
                            with_guide_numbers, with_guide_quality)
    from .model.infer import denoise as run

    for name, value in (("guard", guard), ("guide", guide)):
        if value not in ("on", "off", "model"):
            raise UsageError(f"denoise: {name} must be on, off or model, got {value!r}")
    buf = load_buffers(buffers) if isinstance(buffers, (str, os.PathLike)) else buffers
    if not isinstance(buf, BufferFile):
        raise UsageError(f"denoise: expected a BufferFile or a buffer-file path, got {type(buffers).__name__}")
    net = load_model(model)
    chosen = with_guide_quality(guide_choice(guide, net.guide), guide_quality, "denoise: guide_quality",
                                "guide=")
    chosen = with_guide_mode(chosen, guide_mode, "denoise: guide_mode", "guide=")
    chosen = with_guide_denoiser(chosen, guide_denoiser, "denoise: guide_denoiser", "guide=")
    chosen = with_guide_albedo_channels(chosen, guide_nlm_albedo_channels, "denoise: guide_nlm_albedo_channels",
                                        "guide=")
    chosen = with_guide_numbers(chosen, {"y_weight": guide_y_weight, "y_spike": guide_y_spike,
                                         "anchor_settled": guide_anchor_settled, "anchor_select": guide_anchor_select,
                                         "terms_passes": guide_terms_passes, "anchor_spikes": guide_anchor_spikes,
                                         "y_found": guide_y_found, "z_spike": guide_z_spike,
                                         "anchor_free": guide_anchor_free, "y_empty": guide_y_empty,
                                         "redistribute": guide_redistribute, "cascade": guide_cascade,
                                         "cascade_passes": guide_cascade_passes, "cascade_y": guide_cascade_y,
                                         "cascade_y_up": guide_cascade_y_up, "nlm_k": guide_nlm_k,
                                         "nlm_radius": guide_nlm_radius, "nlm_y_passes": guide_nlm_y_passes,
                                         "nlm_y_k": guide_nlm_y_k, "nlm_joint_passes": guide_nlm_joint_passes,
                                         "nlm_joint_k": guide_nlm_joint_k, "nlm_albedo": guide_nlm_albedo,
                                         "nlm_albedo_eps": guide_nlm_albedo_eps,
                                         "anchor_free_dark": guide_anchor_free_dark,
                                         "range_sigma": guide_range_sigma,
                                         "range_sigma_rel": guide_range_sigma_rel,
                                         "range_sigma_width": guide_range_sigma_width,
                                         "range_sigma_isolated": guide_range_sigma_isolated},
                                lambda flag: "denoise: " + flag[2:].replace("-", "_"), "guide=")
    return run(buf, net, tile=tile, device=torch_device(device), precision=precision,
               guard=guard_choice(guard, net.guard), guide=chosen).rgb


def load_buffers(path: str | os.PathLike) -> BufferFile:
    """Read and validate a buffer file written by ``ppmrecon-render`` or :func:`save`.

    >>> import pathlib, tempfile, ppmrecon
    >>> buf = ppmrecon.render("plane_point", passes=2, photons=4096, resolution=16)
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> ppmrecon.save(folder / "plane.exr", buf)
    >>> again = ppmrecon.load_buffers(folder / "plane.exr")
    >>> bool((again.estimates == buf.estimates).all()), again.header["ppmrecon.scene"]
    (True, 'plane_point')
    """
    return B.read_buffers(path)


def load_image(path: str | os.PathLike) -> np.ndarray:
    """Read a plain R,G,B EXR (a reference, a denoised output) as (H, W, 3) float32.

    >>> import pathlib, tempfile, numpy as np, ppmrecon
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "ramp.exr"
    >>> ramp = np.linspace(0, 1, 2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    >>> ppmrecon.save(path, ramp)
    >>> bool((ppmrecon.api.load_image(path) == ramp).all())
    True
    """
    return B.read_rgb(path)[0]


def _image(data: Any, what: str) -> np.ndarray:
    """An (H, W, 3) float32 array from a NumPy array or anything ``np.asarray`` takes
    (a CPU torch tensor, a Mitsuba TensorXf, a bitmap)."""
    if hasattr(data, "detach"):  # torch: leave the autograd graph
        data = data.detach().cpu()
    rgb = np.asarray(data, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise UsageError(f"{what}: expected an (H, W, 3) image, got shape {rgb.shape}")
    return rgb


def save(path: str | os.PathLike, data: BufferFile | np.ndarray, header: Mapping[str, Any] | None = None) -> None:
    """Write a :class:`BufferFile` as a buffer file, or an (H, W, 3) image (NumPy,
    torch, ...) as a plain R,G,B EXR; atomically, float32, ZIP. ``header`` adds
    ``ppmrecon.*`` attributes to an image.

    >>> import pathlib, tempfile, torch, ppmrecon
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "noise.exr"
    >>> ppmrecon.save(path, torch.rand(4, 6, 3), header={"ppmrecon.note": "a torch tensor"})
    >>> ppmrecon.api.load_image(path).shape
    (4, 6, 3)
    """
    if Path(path).suffix.lower() != ".exr":
        raise UsageError(f"{path}: ppmrecon writes OpenEXR; name the file .exr")
    if isinstance(data, BufferFile):
        B.write_buffers(path, data)
    else:
        B.write_rgb(path, _image(data, str(path)), header=header)


def compare(image: np.ndarray | BufferFile | str | os.PathLike,
            reference: np.ndarray | str | os.PathLike, layer: str = "z1") -> dict[str, Any]:
    """Score an image against a reference, as ``ppmrecon-compare`` does: ``relmse``,
    ``relmse_8x8`` (relMSE of 8x8 block means; None below 8 pixels), ``relmse_trimmed``
    (without the 0.1 % largest pixel errors), ``luminance_ratio`` (None when the
    reference is black), and the ``passes`` and ``method`` of a buffer file.

    ``image``: an (H, W, 3) array, a :class:`BufferFile` (its ``layer``: ``y``, ``z1``
    .. ``z4``), or an EXR path; ``reference``: an array or an R,G,B EXR path, the
    image's size or an integer multiple of it (area-averaged down).

    >>> import ppmrecon
    >>> buf = ppmrecon.render("plane_point", passes=2, photons=4096, resolution=16)
    >>> scores = ppmrecon.compare(buf.estimates[0], buf.estimates[4])   # ~y against ~z^4
    >>> sorted(scores)
    ['layer', 'luminance_ratio', 'method', 'passes', 'relmse', 'relmse_8x8', 'relmse_trimmed']
    >>> 0 < scores["relmse"] < 1
    True
    >>> ppmrecon.compare(buf, buf.estimates[1])["relmse"]   # a buffer file's layer z1 against itself
    0.0
    """
    from . import compare as C

    header: dict[str, Any] = {}
    label = "image"
    if isinstance(image, (str, os.PathLike)):
        label = os.fspath(image)
        images, header = C.load_images(Path(image), (layer,))
        name, img = images[0]
    elif isinstance(image, BufferFile):
        if layer not in B.ESTIMATES:
            raise UsageError(f"compare: layer '{layer}': choose from {', '.join(B.ESTIMATES)}")
        name, img, header = layer, image.estimates[B.ESTIMATES.index(layer)], image.header
    else:
        name, img = "rgb", _image(image, "compare: image")
    ref_label = os.fspath(reference) if isinstance(reference, (str, os.PathLike)) else "reference"
    ref = B.read_rgb(reference)[0] if isinstance(reference, (str, os.PathLike)) else _image(reference, ref_label)
    ref = C.fit_reference(ref, img.shape[:2], Path(ref_label), Path(label))
    scores = asdict(C.score(Path(label), name, img, ref, header))
    scores.pop("file")
    # Plain floats (NumPy 2 prints np.float64(...)), None where a score is undefined.
    return {k: float(v) if isinstance(v, (float, np.floating)) else v for k, v in scores.items()}


def builtin_scenes() -> dict[str, Path]:
    """Built-in scene names -> their XML files (inside the installed package).

    >>> import ppmrecon
    >>> sorted(ppmrecon.builtin_scenes())[:2]
    ['cornell_caustics', 'diffuse_glossy']
    """
    from .scene.loader import builtin_scenes as scenes

    return scenes()
