"""The render protocol's branches one by one (issue 15 section 5): what counts as a model that renders
itself, how a renderer's return value is unwrapped (tensor, ``.color``, ``{"render": ...}``), which
objects ``as_renderer`` keeps, wraps or refuses, ``model_device``'s search order, and ``render_view``'s
``modules`` and refusals."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import pytest
import torch
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.rendering import (FunctionRenderer, ModelRenderer, Renderer, as_renderer, model_device,
                                         render_view, renderer_for)
from controlgs_adapter.state import Camera

STATE = RuntimeState(downsample=2, power_saving=0.4)


def _camera(width: int = 4, height: int = 3) -> Camera:
    k = torch.tensor([[4.0, 0.0, width / 2], [0.0, 4.0, height / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, width, height)


class Renders:
    """Brings its own visible_anchors / render; render returns ``self.out`` (whatever a test sets)."""

    def __init__(self, out: Any) -> None:
        self.out = out
        self.seen: list[Any] = []

    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        return torch.tensor([True, False, True])

    def render(self, camera: Camera, visible: Any, background: Any = None) -> Any:
        self.seen.append((visible, background))
        return self.out


# ---------------------------------------------------------------- ModelRenderer
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
        vis = r.visible(model, _camera())
        assert torch.equal(vis, torch.tensor([True, False, True]))
        assert r.render(model, _camera(), vis, bg) is image
        assert model.seen[0][0] is vis and model.seen[0][1] is bg


def test_renderer_for_a_model_no_backend_recognises() -> None:
    """No backend matches a bare object: ModelRenderer when it renders itself, else a refusal naming the type."""
    assert type(renderer_for(Renders(None))) is ModelRenderer
    with pytest.raises(InputValueError, match=r"a SimpleNamespace has no visible_anchors\(camera\).*pass renderer="):
        renderer_for(SimpleNamespace(render=lambda *a: None))


def test_renderer_for_a_recognised_model_without_a_render_of_its_own(tiny: Any) -> None:
    """A backend recognises the model but its renderer() gives None (here: the model's render hidden)."""
    _, model = tiny

    class NoRender(type(model)):  # type: ignore[misc]
        render = None

    hidden = NoRender.__new__(NoRender)
    hidden.__dict__.update(model.__dict__)
    with pytest.raises(InputValueError, match="a NoRender has no visible_anchors"):
        renderer_for(hidden)


# ---------------------------------------------------------------- FunctionRenderer
def test_function_renderer_unwraps_every_documented_return_form() -> None:
    image = torch.rand(3, 3, 4)
    calls: list[tuple[Any, ...]] = []

    def fn(result: Any) -> Any:
        def render(m: Any, c: Any, v: Any, bg: Any) -> Any:
            calls.append((m, c, v, bg))
            return result
        return render

    cam, bg, vis = _camera(), torch.zeros(3), torch.tensor([0, 2])
    assert FunctionRenderer(fn(image)).render("m", cam, vis, bg) is image
    assert FunctionRenderer(fn(SimpleNamespace(color=image))).render("m", cam, vis, bg) is image
    assert FunctionRenderer(fn({"render": image, "viewspace_points": 0})).render("m", cam, vis, bg) is image
    # a dict holding an object with .color: both unwrappings apply
    assert FunctionRenderer(fn({"render": SimpleNamespace(color=image)})).render("m", cam, vis, bg) is image
    other = {"image": image}  # no "render" key: returned as is (render_view then refuses it)
    assert FunctionRenderer(fn(other)).render("m", cam, vis, bg) is other
    assert calls[0] == ("m", cam, vis, bg)  # arguments in the protocol's order


def test_function_renderer_visible_default_and_given() -> None:
    cam = _camera()
    assert FunctionRenderer(lambda *a: None).visible("m", cam) is None  # no prefilter: every anchor
    ids = torch.tensor([3, 1])
    r = FunctionRenderer(lambda *a: None, visible=lambda m, c: ids if (m, c) == ("m", cam) else None)
    assert r.visible("m", cam) is ids


def test_function_renderer_refuses_non_callables_and_names_itself() -> None:
    with pytest.raises(InputValueError, match="FunctionRenderer takes callables, got render=42"):
        FunctionRenderer(42)  # type: ignore[arg-type]
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


# ---------------------------------------------------------------- as_renderer
def test_as_renderer_keeps_protocol_objects_wraps_functions_and_refuses_the_rest() -> None:
    class Obj:
        def visible(self, m: Any, c: Any) -> None:
            return None

        def render(self, m: Any, c: Any, v: Any, bg: Any) -> torch.Tensor:
            return torch.zeros(3, 3, 4)

    class CallableObj(Obj):  # follows the protocol AND is callable: kept as is, not wrapped
        def __call__(self, *a: Any) -> None:
            raise AssertionError("a protocol object is not called as a function")

    obj, cobj = Obj(), CallableObj()
    assert as_renderer(obj, None) is obj and as_renderer(cobj, None) is cobj

    def fn(m: Any, c: Any, v: Any, bg: Any) -> torch.Tensor:
        return torch.ones(3, 3, 4)

    wrapped = as_renderer(fn, None)
    assert type(wrapped) is FunctionRenderer and wrapped.visible(None, _camera()) is None
    assert torch.equal(wrapped.render(None, _camera(), None, None), torch.ones(3, 3, 4))

    # attributes named visible / render that are not callable: neither a Renderer nor a function
    with pytest.raises(InputValueError, match="renderer must be None, a Renderer .* got SimpleNamespace"):
        as_renderer(SimpleNamespace(visible=None, render=None), None)
    with pytest.raises(InputValueError, match="got int"):
        as_renderer(42, None)
    model = Renders(None)
    assert type(as_renderer(None, model)) is ModelRenderer


# ---------------------------------------------------------------- model_device
def test_model_device_search_order() -> None:
    meta = torch.device("meta")
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


# ---------------------------------------------------------------- render_view
def test_render_view_refuses_what_is_not_an_image() -> None:
    cam = _camera(width=5, height=2)
    with pytest.raises(ShapeError, match=r"returned dict for a 5x2 camera; expected an sRGB image \[3, 2, 5\]"):
        render_view(None, None, cam, None, renderer=lambda m, c, v, bg: {"image": 0})
    with pytest.raises(ShapeError, match=r"returned \[2, 5, 3\] for a 5x2 camera"):  # height and width swapped
        render_view(None, None, cam, None, renderer=lambda m, c, v, bg: torch.zeros(2, 5, 3))
    with pytest.raises(ShapeError, match=r"returned \[3, 5, 2\]"):
        render_view(None, None, cam, None, renderer=lambda m, c, v, bg: torch.zeros(3, 5, 2))
    with pytest.raises(ShapeError, match=r"returned \[1, 3, 2, 5\]"):
        render_view(None, None, cam, None, renderer=lambda m, c, v, bg: torch.zeros(1, 3, 2, 5))
    bg = torch.tensor([0.25, 0.5, 0.75])
    out = render_view(None, None, cam, None, bg, renderer=lambda m, c, v, b: b.view(3, 1, 1).expand(3, 2, 5))
    assert torch.equal(out[:, 1, 4], bg)  # the background reaches the renderer


def test_render_view_modules_restrict_the_injection(tiny: Any) -> None:
    scene, model = tiny
    cam = scene.test_cameras[0]
    cgs = ControlGS.wrap(model)
    try:
        gen = torch.Generator().manual_seed(1)
        with torch.no_grad():
            for p in cgs.injector.parameters():
                p.add_(0.5 * torch.randn(p.shape, generator=gen))
            bare = render_view(None, model, cam, None, scene.background)
            full = render_view(cgs, model, cam, STATE, scene.background)
            display = render_view(cgs, model, cam, STATE, scene.background, modules=("display",))
            display_str = render_view(cgs, model, cam, STATE, scene.background, modules="display")
            with cgs.conditioned(STATE, cam, model.visible_anchors(cam), modules=("display",)):
                direct = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert not torch.equal(display, full) and not torch.equal(display, bare)
        assert torch.equal(display, direct) and torch.equal(display_str, direct)
        with pytest.raises(InputValueError, match=r"modules \['bloom'\] are not wrapped"):
            render_view(cgs, model, cam, STATE, modules=("bloom",))
    finally:
        cgs.unwrap()


def test_renderer_protocol_is_runtime_checkable() -> None:
    assert isinstance(ModelRenderer(), Renderer) and isinstance(FunctionRenderer(lambda *a: None), Renderer)
    assert not isinstance(lambda *a: None, Renderer)
