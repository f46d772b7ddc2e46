"""The renderer: scene -> photons -> eye paths -> grid -> gather -> five estimates.

Also callable: ``ppmrecon.render(scene, passes=..., ...)`` is :func:`ppmrecon.api.render`
(see :mod:`ppmrecon._callable`).
"""

import sys

from .._callable import CallableModule

sys.modules[__name__].__class__ = CallableModule
