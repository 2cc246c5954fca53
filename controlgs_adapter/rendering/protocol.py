"""The render protocol: how training and evaluation get an image out of a (wrapped) backbone.

A :class:`Renderer` answers two questions for a camera:

* ``visible(model, camera)``: which anchors the render decodes, as the decoders see their rows:
  a ``BoolTensor[A]`` mask (rows = the visible anchors, ascending), a ``LongTensor[R]`` of anchor
  ids (row ``i`` = anchor ``ids[i]``), or None (all anchors);
* ``render(model, camera, visible, background)``: the sRGB image ``[3, H, W]`` (float, the
  camera's size) of those anchors over ``background`` (``[3]`` or None: the renderer's default).

``model`` is the user's own model object. :meth:`ControlGS.wrap` changes it in place (hooks on the
decoders' first layers; TorchScript decoders replaced by eager copies on that same object), so a
renderer that calls the model's decoders gets the injection inside a ``conditioned`` block. A
render that never reaches the hooked layers (a copy of the model, a forwarding wrapper, decoders
cached before wrapping) raises :class:`~controlgs_adapter.errors.InjectionMissedError` naming them.

Every family the library loads (the reference :class:`NeuralGaussianModel`, Octree-GS, HAC/HAC++,
ContextGS, CompGS) renders through :class:`ModelRenderer` (its ``visible_anchors`` and ``render``);
:func:`renderer_for` picks it. Your own code (the Scaffold-GS CUDA renderer, say) plugs in as any
object with the two methods, or as a function (:class:`FunctionRenderer`)::

    trainer = Trainer(gaussians, views, renderer=FunctionRenderer(my_render, visible=my_prefilter))
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import torch

from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import InputValueError, NoMatchingBackendError, ShapeError
from controlgs_adapter.plugins import select_backend
from controlgs_adapter.state import Camera, RuntimeState

from .renderer import FunctionRenderer, ModelRenderer, Renderer, _model_float_dtype, default_renderer, model_device

__all__ = ["Renderer", "ModelRenderer", "FunctionRenderer", "renderer_for", "as_renderer", "render_view",
           "model_device"]


def renderer_for(model: Any) -> Renderer:
    """The renderer of a loaded model: its backend's (``Backend.renderer``), else
    :class:`ModelRenderer` when the model has ``visible_anchors`` and ``render``.

    Raises:
        InputValueError: the model cannot render itself (pass ``renderer=``).
    """
    try:
        found = select_backend(model).renderer(model)
    except NoMatchingBackendError:
        found = default_renderer(model)
    if found is None:
        raise InputValueError(
            f"a {type(model).__name__} has no visible_anchors(camera) / render(camera, visible, background) of its "
            "own: pass renderer= (an object with visible(model, camera) and render(model, camera, visible, "
            "background), or FunctionRenderer(your_render_function)); see docs/how-to/own-renderer.md")
    return found


def as_renderer(renderer: Renderer | Callable[..., Any] | None, model: Any) -> Renderer:
    """``renderer`` as a :class:`Renderer`: None -> :func:`renderer_for` ``(model)``; an object with
    ``visible`` and ``render`` as is; a function -> ``FunctionRenderer(renderer)`` (all anchors)."""
    if renderer is None:
        return renderer_for(model)
    if isinstance(renderer, Renderer) and callable(renderer.visible) and callable(renderer.render):
        return renderer
    if callable(renderer):
        return FunctionRenderer(renderer)
    raise InputValueError(f"renderer must be None, a Renderer (visible + render) or a render function, "
                          f"got {type(renderer).__name__}")


def render_view(cgs: ControlGS | None, model: Any, camera: Camera, state: RuntimeState | None,
                background: torch.Tensor | None = None, *, modules: Sequence[str] | None = None,
                renderer: Renderer | Callable[..., Any] | None = None) -> torch.Tensor:
    """Render ``camera`` with ``renderer`` (default :func:`renderer_for` ``(model)``): through the
    adapter ``cgs`` at ``state`` (restricted to ``modules`` if given), or the bare backbone when
    ``cgs`` or ``state`` is None. Returns sRGB ``[3, H, W]`` at the camera's size.

    Raises:
        InjectionMissedError: a conditioned render never called the wrapped decoders.
        ShapeError: the renderer returned something else than ``[3, H, W]``.
        InputValueError: the image is not on the model's device (:func:`model_device`), not of its
            floating-point dtype (float32 or float64 when the model has no floating-point tensor), not a
            dense tensor, or holds NaN/Inf.
    """
    r = as_renderer(renderer, model)
    visible = r.visible(model, camera)
    if cgs is None or state is None:
        image = r.render(model, camera, visible, background)
    else:
        with cgs.conditioned(state, camera, visible, modules=modules, on_miss="raise"):
            image = r.render(model, camera, visible, background)
    if isinstance(image, torch.Tensor) and image.layout != torch.strided:
        raise InputValueError(f"renderer {r!r} returned a {image.layout} image; expected a dense (strided) tensor")
    if not isinstance(image, torch.Tensor) or tuple(image.shape) != (3, camera.height, camera.width):
        got = list(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
        raise ShapeError(f"renderer {r!r} returned {got} for a {camera.width}x{camera.height} camera; "
                         f"expected an sRGB image [3, {camera.height}, {camera.width}]")
    device, dtype = model_device(model), _model_float_dtype(model)
    if image.device != device:
        raise InputValueError(f"renderer {r!r} returned an image on {image.device}; the model is on {device} "
                              f"(render on the model's device, or move the image there)")
    wanted = (torch.float32, torch.float64) if dtype is None else (dtype,)
    if image.dtype not in wanted:
        raise InputValueError(f"renderer {r!r} returned a {image.dtype} image; expected "
                              f"{' or '.join(map(str, wanted))} (the model's floating-point dtype)")
    bad = 0 if image.is_meta else int((~torch.isfinite(image.detach())).sum())  # one host sync per rendered view
    if bad:
        raise InputValueError(f"renderer {r!r} returned an image with {bad} non-finite value(s) (NaN or Inf)")
    return image
