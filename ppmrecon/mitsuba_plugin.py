"""A Mitsuba 3 integrator plugin: progressive photon mapping inside ``mi.render``.

    import mitsuba as mi, ppmrecon
    mi.set_variant("llvm_ad_rgb")
    ppmrecon.register_integrator()                       # registers type "ppm"
    scene = mi.load_dict(mi.cornell_box())
    integrator = mi.load_dict({"type": "ppm", "passes": 32, "denoise": True})
    image = mi.render(scene, integrator=integrator)      # TensorXf (H, W, 3 + 32)
    rgb = image.numpy()[..., :3]                         # the denoised image
    buffers = integrator.buffers                         # the BufferFile, as ppmrecon.render returns

The integrator's ``render()`` runs :func:`ppmrecon.api.render` on the scene and returns
the denoised image (``denoise`` true, the default; the shipped model unless ``model``
names a checkpoint) or ~z^1, the second-smallest bandwidth estimate, in the first three
channels, followed by the buffer file's channels as AOVs (``aov_names()``: ``y.R`` ..
``z4.r``, ``albedo.*``, ``normal.*``, ``depth.Z``; SPEC section 2). ``mi.render(...,
spp=N)`` with N > 0 renders N passes; ``seed`` is the render seed.

Properties: ``passes`` (16), ``photons`` (131072), ``method`` (``sppm``, ``cppm``,
``fppm``), ``max_depth`` (-1: unbounded), ``rr_depth`` (5), ``direct`` (``all``,
``glossy``, ``none``), ``denoise`` (true), ``model`` (checkpoint path; default the
shipped one), ``guard`` (``on``, ``off``, ``model``).

It renders the scene's first sensor only (the photon mapper's film) and is not
differentiable: ``mi.render`` with gradients, ``render_forward``/``render_backward``
are refused.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from . import buffers as B
from .errors import UsageError

#: Integrator properties and their defaults (the types the XML/dict values are read as).
DEFAULTS: dict[str, Any] = {"passes": 16, "photons": 1 << 17, "method": "sppm", "max_depth": -1,
                            "rr_depth": 5, "direct": "all", "denoise": True, "model": "", "guard": "on"}


def aov_names() -> list[str]:
    """The AOV channels the integrator adds after R, G, B: every buffer-file channel."""
    return B.channel_names()


def buffers_to_image(buf: B.BufferFile, rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3 + len(aov_names())) float32: ``rgb`` then the buffer file's channels."""
    channels = buf.channels()
    return np.concatenate([rgb] + [channels[n][..., None] for n in aov_names()], axis=-1).astype(np.float32)


def register_integrator(name: str = "ppm") -> None:
    """Register the integrator with Mitsuba under ``name`` for the active variant
    (``llvm_ad_rgb`` or ``cuda_ad_rgb``; one is activated if none is). Call it again
    after ``mi.set_variant`` to another variant.

    >>> import mitsuba as mi, ppmrecon
    >>> ppmrecon.register_integrator()
    >>> box = mi.cornell_box()
    >>> box["sensor"]["film"].update(width=8, height=8)
    >>> scene = mi.load_dict(box)
    >>> integrator = mi.load_dict({"type": "ppm", "passes": 2, "photons": 4096, "denoise": False})
    >>> image = mi.render(scene, integrator=integrator)
    >>> image.shape, len(integrator.aov_names())
    ((8, 8, 35), 32)
    >>> bool((image.numpy()[..., :3] == integrator.buffers.estimates[1]).all())   # ~z^1
    True
    """
    from .backend import VARIANTS
    from .scene.common import ensure_variant

    ensure_variant()
    import mitsuba as mi

    if mi.variant() not in VARIANTS:
        raise UsageError(f"register_integrator: Mitsuba variant {mi.variant()} is active; the ppmrecon renderer "
                         f"runs {' or '.join(VARIANTS)}")

    class PPMIntegrator(mi.SamplingIntegrator):
        """Multi-bandwidth progressive photon mapping (+ the consistent denoiser)."""

        def __init__(self, props: mi.Properties):
            super().__init__(props)
            self.options = {key: props.get(key, default) for key, default in DEFAULTS.items()}
            self.buffers: B.BufferFile | None = None  # the last render's buffers

        def render(self, scene: mi.Scene, sensor: Any = 0, seed: int = 0, spp: int = 0,
                   develop: bool = True, evaluate: bool = True) -> mi.TensorXf:
            from . import api

            first = scene.sensors()[0]
            if not (sensor == 0 or sensor is first):
                raise UsageError("ppm integrator: renders the scene's first sensor only")
            o = self.options
            self.buffers = api.render(scene, passes=int(spp) if spp else int(o["passes"]), method=o["method"],
                                      photons=int(o["photons"]), seed=int(seed), max_depth=int(o["max_depth"]),
                                      rr_depth=int(o["rr_depth"]), direct=o["direct"])
            rgb = (api.denoise(self.buffers, o["model"] or None, guard=o["guard"]) if o["denoise"]
                   else self.buffers.estimates[1])
            return mi.TensorXf(buffers_to_image(self.buffers, rgb))

        def render_forward(self, *args: Any, **kwargs: Any) -> None:
            raise UsageError("ppm integrator: not differentiable")

        render_backward = render_forward

        def aov_names(self) -> list[str]:
            return aov_names()

        def to_string(self) -> str:
            return "PPMIntegrator[" + ", ".join(f"{k} = {v}" for k, v in self.options.items()) + "]"

    mi.register_integrator(name, lambda props: PPMIntegrator(props))
