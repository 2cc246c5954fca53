"""The render contract: what :class:`~controlgs_adapter.training.Trainer` and
:func:`~controlgs_adapter.evaluation.evaluate_grid` render with (:mod:`controlgs_adapter.rendering.protocol`
describes the protocol and holds :func:`~controlgs_adapter.rendering.protocol.render_view`).

:class:`Renderer` is the contract; :class:`ModelRenderer` renders the models that bring their own
``visible_anchors`` and ``render`` (every family the library loads), :class:`FunctionRenderer` turns
a render function into a renderer. Imports no registry and no wrapper.
"""

from __future__ import annotations

from typing import Any, Callable, Protocol, runtime_checkable

import torch
from torch import nn

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import Camera

__all__ = ["Renderer", "ModelRenderer", "FunctionRenderer", "default_renderer", "model_device"]


@runtime_checkable
class Renderer(Protocol):
    """What :class:`~controlgs_adapter.training.Trainer` and
    :func:`~controlgs_adapter.evaluation.evaluate_grid` render with (module docstring)."""

    def visible(self, model: Any, camera: Camera) -> torch.Tensor | None:
        """``BoolTensor[A]`` mask, ``LongTensor[R]`` anchor ids in decoder-row order, or None (all)."""
        ...

    def render(self, model: Any, camera: Camera, visible: torch.Tensor | None,
               background: torch.Tensor | None) -> torch.Tensor:
        """sRGB ``[3, camera.height, camera.width]`` of the ``visible`` anchors over ``background``."""
        ...


class ModelRenderer:
    """Renders models that bring their own ``visible_anchors(camera)`` and ``render(camera,
    visible, background)`` (returning a ``RasterOutput`` or an image): every family the library loads."""

    @staticmethod
    def fits(model: Any) -> bool:
        """True if ``model`` has callable ``visible_anchors`` and ``render``."""
        return callable(getattr(model, "visible_anchors", None)) and callable(getattr(model, "render", None))

    def visible(self, model: Any, camera: Camera) -> torch.Tensor | None:
        return model.visible_anchors(camera)

    def render(self, model: Any, camera: Camera, visible: torch.Tensor | None,
               background: torch.Tensor | None) -> torch.Tensor:
        out = model.render(camera, visible, background)
        return getattr(out, "color", out)

    def __repr__(self) -> str:
        return "ModelRenderer()"


class FunctionRenderer:
    """A render function as a :class:`Renderer`.

    Args:
        render: ``render(model, camera, visible, background)`` -> sRGB ``[3, H, W]`` (or an object
            with ``.color``; a dict with ``"render"``, as Scaffold-GS's renderer returns, works too).
        visible: ``visible(model, camera)`` -> mask / ids / None; None: every anchor is decoded.
    """

    def __init__(self, render: Callable[..., Any],
                 visible: Callable[[Any, Camera], torch.Tensor | None] | None = None) -> None:
        if not callable(render) or (visible is not None and not callable(visible)):
            raise InputValueError(f"FunctionRenderer takes callables, got render={render!r}, visible={visible!r}")
        self._render, self._visible = render, visible

    def visible(self, model: Any, camera: Camera) -> torch.Tensor | None:
        return None if self._visible is None else self._visible(model, camera)

    def render(self, model: Any, camera: Camera, visible: torch.Tensor | None,
               background: torch.Tensor | None) -> torch.Tensor:
        out = self._render(model, camera, visible, background)
        if isinstance(out, dict) and "render" in out:
            out = out["render"]
        return getattr(out, "color", out)

    def __repr__(self) -> str:
        name = getattr(self._render, "__qualname__", repr(self._render))
        return f"FunctionRenderer({name})"


def default_renderer(model: Any) -> ModelRenderer | None:
    """A :class:`ModelRenderer` when ``model`` has ``visible_anchors`` and ``render``, else None: what
    :meth:`Backend.renderer <controlgs_adapter.backend.Backend.renderer>` gives by default and what
    :func:`~controlgs_adapter.rendering.protocol.renderer_for` falls back to for a model no backend knows."""
    return ModelRenderer() if ModelRenderer.fits(model) else None


def model_device(model: Any) -> torch.device:
    """Device of ``model``'s first parameter or buffer; for a plain Python model (Scaffold-GS's
    ``GaussianModel``) of its first module or tensor attribute; CPU when it has none."""
    for attr in ("parameters", "buffers"):
        fn = getattr(model, attr, None)
        if callable(fn):
            for t in fn():
                return t.device
    for value in getattr(model, "__dict__", {}).values():
        if isinstance(value, torch.Tensor):
            return value.device
        if isinstance(value, nn.Module):
            for t in value.parameters():
                return t.device
    return torch.device("cpu")


def _model_float_dtype(model: Any) -> torch.dtype | None:
    """Dtype of ``model``'s first floating-point parameter or buffer (searched as :func:`model_device`
    searches), or None when it has none."""
    for attr in ("parameters", "buffers"):
        fn = getattr(model, attr, None)
        if callable(fn):
            for t in fn():
                if t.is_floating_point():
                    return t.dtype
    for value in getattr(model, "__dict__", {}).values():
        tensors = value.parameters() if isinstance(value, nn.Module) else (value,) if isinstance(value, torch.Tensor) else ()
        for t in tensors:
            if t.is_floating_point():
                return t.dtype
    return None
