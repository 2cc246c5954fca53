"""Rendering: the render contract (:mod:`.renderer`), the rasterizer contract (:mod:`.rasterizer`) and
the choice among registered rasterizers (:mod:`.rasterizers`), the pure-torch EWA splatter
(:mod:`.splatter`) and its float64 brute-force reference (:mod:`.splatter_reference`); the render
protocol of the application (:mod:`.protocol`: ``render_view``, ``renderer_for``, ``as_renderer``).

The names below are re-exported on first access, so that importing a module of this package (the
splatter, a contract) does not load the wrapper that :mod:`.protocol` builds on.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from .protocol import as_renderer as as_renderer
    from .protocol import render_view as render_view
    from .protocol import renderer_for as renderer_for
    from .renderer import FunctionRenderer as FunctionRenderer
    from .renderer import ModelRenderer as ModelRenderer
    from .renderer import Renderer as Renderer
    from .renderer import model_device as model_device

#: public names loaded on first access: name -> module
_LAZY: dict[str, str] = {
    "Renderer": "controlgs_adapter.rendering.renderer", "ModelRenderer": "controlgs_adapter.rendering.renderer",
    "FunctionRenderer": "controlgs_adapter.rendering.renderer", "model_device": "controlgs_adapter.rendering.renderer",
    "renderer_for": "controlgs_adapter.rendering.protocol", "as_renderer": "controlgs_adapter.rendering.protocol",
    "render_view": "controlgs_adapter.rendering.protocol",
}

__all__ = ["Renderer", "ModelRenderer", "FunctionRenderer", "renderer_for", "as_renderer", "render_view",
           "model_device"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'controlgs_adapter.rendering' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
