"""Modules that are also the API functions of the same name.

``ppmrecon.render`` is the renderer's subpackage and ``ppmrecon.compare`` the module of
``ppmrecon-compare``; the API (:mod:`ppmrecon.api`) wants ``ppmrecon.render(...)`` and
``ppmrecon.compare(...)`` as well. Binding functions to those names in the package would
break ``import ppmrecon.render.cli`` and ``mock.patch("ppmrecon.render...")`` (they look
the submodule up as an attribute), so the two modules instead get this class, whose
call forwards to the API function.
"""

from __future__ import annotations

import inspect
import types
from typing import Any


class CallableModule(types.ModuleType):
    """A module whose call is ``ppmrecon.api.<last part of its name>``."""

    def _api_function(self) -> Any:
        from . import api

        return getattr(api, self.__name__.rsplit(".", 1)[-1])

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self._api_function()(*args, **kwargs)

    @property
    def __signature__(self) -> inspect.Signature:  # inspect.signature(ppmrecon.render) shows the API's
        return inspect.signature(self._api_function())
