"""Tests of ``controlgs_adapter.rendering.renderer``: the ``Renderer`` protocol, ``ModelRenderer`` (models that render
themselves), ``FunctionRenderer`` (a render function and its return forms) and ``model_device``."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest
import torch
from helpers.render_stubs import Renders, small_camera
from helpers.scaffold_standin import ScaffoldStandIn
from torch import nn

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.renderer import FunctionRenderer, ModelRenderer, Renderer, model_device


def test_renderer_protocol_is_runtime_checkable() -> None:
    assert isinstance(ModelRenderer(), Renderer) and isinstance(FunctionRenderer(lambda *a: None), Renderer)
    assert not isinstance(lambda *a: None, Renderer)


# ----------------------------------------------------------------------------- ModelRenderer

def test_model_renderer_fits_needs_both_methods_callable() -> None:
    assert ModelRenderer.fits(Renders(None))
    assert not ModelRenderer.fits(SimpleNamespace(visible_anchors=lambda c: None))          # no render
    assert not ModelRenderer.fits(SimpleNamespace(render=lambda c, v, b: None))              # no visible_anchors
    assert not ModelRenderer.fits(SimpleNamespace(visible_anchors=1, render=lambda *a: 0))   # not callable
    assert not ModelRenderer.fits(SimpleNamespace(visible_anchors=lambda c: None, render="x"))
    assert repr(ModelRenderer()) == "ModelRenderer()"


def test_model_renderer_unwraps_color_and_passes_visible_and_background() -> None:
    image = torch.rand(3, 3, 4)
    bg = torch.tensor([0.1, 0.2, 0.3])
    for out in (image, SimpleNamespace(color=image, alpha=None)):  # a plain image or a RasterOutput-like object
        model = Renders(out)
        r = ModelRenderer()
        vis = r.visible(model, small_camera())
        assert torch.equal(vis, torch.tensor([True, False, True]))
        assert r.render(model, small_camera(), vis, bg) is image
        assert model.seen[0][0] is vis and model.seen[0][1] is bg


# ----------------------------------------------------------------------------- FunctionRenderer

def test_function_renderer_unwraps_every_documented_return_form() -> None:
    image = torch.rand(3, 3, 4)
    calls: list[tuple[Any, ...]] = []

    def fn(result: Any) -> Any:
        def render(m: Any, c: Any, v: Any, bg: Any) -> Any:
            calls.append((m, c, v, bg))
            return result
        return render

    cam, bg, vis = small_camera(), torch.zeros(3), torch.tensor([0, 2])
    assert FunctionRenderer(fn(image)).render("m", cam, vis, bg) is image
    assert FunctionRenderer(fn(SimpleNamespace(color=image))).render("m", cam, vis, bg) is image
    assert FunctionRenderer(fn({"render": image, "viewspace_points": 0})).render("m", cam, vis, bg) is image
    # a dict holding an object with .color: both unwrappings apply
    assert FunctionRenderer(fn({"render": SimpleNamespace(color=image)})).render("m", cam, vis, bg) is image
    other = {"image": image}  # no "render" key: returned as is (render_view then refuses it)
    assert FunctionRenderer(fn(other)).render("m", cam, vis, bg) is other
    assert calls[0] == ("m", cam, vis, bg)  # arguments in the protocol's order


def test_function_renderer_visible_default_and_given() -> None:
    cam = small_camera()
    assert FunctionRenderer(lambda *a: None).visible("m", cam) is None  # no prefilter: every anchor
    ids = torch.tensor([3, 1])
    r = FunctionRenderer(lambda *a: None, visible=lambda m, c: ids if (m, c) == ("m", cam) else None)
    assert r.visible("m", cam) is ids
    mask = torch.tensor([True, False])
    assert FunctionRenderer(lambda *a: None, visible=lambda m, c: mask).visible(None, None) is mask


def test_function_renderer_refuses_non_callables_and_names_itself() -> None:
    for bad in (3, 42):
        with pytest.raises(InputValueError, match=f"FunctionRenderer.*render={bad}"):
            FunctionRenderer(bad)  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="visible='mask'"):
        FunctionRenderer(lambda *a: None, visible="mask")  # type: ignore[arg-type]

    def my_render(m: Any, c: Any, v: Any, bg: Any) -> None:
        return None

    assert repr(FunctionRenderer(my_render)) == (
        "FunctionRenderer(test_function_renderer_refuses_non_callables_and_names_itself.<locals>.my_render)")

    class CallableObj:  # no __qualname__ on the instance: its repr is used
        def __call__(self, *a: Any) -> None:
            return None

        def __repr__(self) -> str:
            return "obj"

    assert repr(FunctionRenderer(CallableObj())) == "FunctionRenderer(obj)"


# ----------------------------------------------------------------------------- model_device

def test_model_device_search_order() -> None:
    """A module's parameters, then its buffers; a plain object's first tensor or module with parameters, in
    attribute order; else the CPU."""
    meta = torch.device("meta")
    assert model_device(ScaffoldStandIn(num_anchors=5)) == torch.device("cpu")
    assert model_device(object()) == torch.device("cpu")
    assert model_device(nn.Linear(2, 2).to(meta)) == meta
    only_buffers = nn.Module()
    only_buffers.register_buffer("b", torch.zeros(2, device=meta))
    assert model_device(only_buffers) == meta  # a module without parameters: its buffers

    class ParamsFirst(nn.Module):  # parameters before buffers
        def __init__(self) -> None:
            super().__init__()
            self.register_buffer("b", torch.zeros(2, device=meta))
            self.w = nn.Parameter(torch.zeros(2))

    assert model_device(ParamsFirst()) == torch.device("cpu")

    class Plain:  # a plain object: its first tensor or module attribute, in attribute order
        def __init__(self, *values: Any) -> None:
            for i, v in enumerate(values):
                setattr(self, f"a{i}", v)

    assert model_device(Plain(3, torch.zeros(1, device=meta))) == meta
    assert model_device(Plain(nn.ReLU(), torch.zeros(1, device=meta))) == meta  # a module without parameters: skipped
    assert model_device(Plain(nn.Linear(1, 1, device=meta), torch.zeros(1))) == meta
    assert model_device(Plain(torch.zeros(1), nn.Linear(1, 1, device=meta))) == torch.device("cpu")
    assert model_device(Plain(nn.ReLU())) == torch.device("cpu")
