"""ppmrecon: multi-bandwidth progressive photon mapping on Mitsuba 3 and a consistent
learned post-reconstruction (Choi & Moon 2021).

The Python API (:mod:`ppmrecon.api`; NumPy arrays in and out)::

    import ppmrecon
    buf = ppmrecon.render("cornell_caustics", passes=32)   # or a path, an mi.Scene, a scene dict
    rgb = ppmrecon.denoise(buf)                             # (H, W, 3) float32
    ppmrecon.save("cbox_denoised.exr", rgb)
    ppmrecon.compare(rgb, ppmrecon.load_image("reference.exr"))

``ppmrecon.register_integrator()`` adds a Mitsuba 3 integrator ``ppm`` for
``mi.render`` (see :mod:`ppmrecon.mitsuba_plugin`).
"""

from __future__ import annotations

import importlib
from typing import Any

from .api import BufferFile, builtin_scenes, denoise, load_buffers, load_image, load_model, save

__version__ = "0.1.0"
__all__ = ["render", "denoise", "load_buffers", "load_image", "load_model", "save", "compare",
           "builtin_scenes", "register_integrator", "BufferFile"]


def __getattr__(name: str) -> Any:
    # render and compare are modules that are also the API functions (ppmrecon._callable);
    # importing them here on first use keeps `import ppmrecon` free of Mitsuba and torch.
    if name in ("render", "compare"):
        return importlib.import_module(f".{name}", __name__)
    if name == "register_integrator":
        return importlib.import_module(".mitsuba_plugin", __name__).register_integrator
    raise AttributeError(f"module 'ppmrecon' has no attribute '{name}'")
