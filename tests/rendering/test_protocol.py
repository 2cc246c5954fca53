"""Tests of ``controlgs_adapter.rendering.protocol``: ``renderer_for`` (which renderer a model gets), ``as_renderer``
and ``render_view`` (the image it accepts, the adapter's conditions, the modules it restricts them to, and a
render of another object than the wrapped one)."""

from __future__ import annotations

import copy
import importlib.util
from types import SimpleNamespace
from typing import Any

import math

import pytest
import torch
from helpers.render_stubs import Renders, small_camera
from helpers.scaffold_standin import ScaffoldStandIn
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.errors import InjectionMissedError, InputValueError, ShapeError
from controlgs_adapter.rendering.protocol import FunctionRenderer, ModelRenderer, Renderer, as_renderer, render_view, renderer_for
from controlgs_adapter.state import Camera

needs_skimage = pytest.mark.skipif(importlib.util.find_spec("skimage") is None, reason="the built-in scene needs scikit-image")

STATE = RuntimeState(downsample=2, power_saving=0.4)
CAM = Camera(torch.eye(4), torch.tensor([[4.0, 0.0, 2.5], [0.0, 4.0, 1.0], [0.0, 0.0, 1.0]]), 5, 2)


def _returns(image: torch.Tensor) -> FunctionRenderer:
    def my_render(model: Any, camera: Camera, visible: Any, background: Any) -> torch.Tensor:
        return image

    return FunctionRenderer(my_render)


class _PlainModel:
    """A plain Python model (Scaffold-GS's GaussianModel style): tensors as attributes, an int one first."""

    def __init__(self, dtype: torch.dtype) -> None:
        self.counts = torch.zeros(3, dtype=torch.long)
        self._xyz = torch.zeros(4, 3, dtype=dtype)


def _perturb(cgs: ControlGS, seed: int) -> None:
    """Random adapter parameters: the conditioned decode differs from the backbone's."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in cgs.injector.parameters():
            p.add_(0.5 * torch.randn(p.shape, generator=gen))


# ----------------------------------------------------------------------------- renderer_for and as_renderer

@needs_skimage
def test_loaded_models_render_through_their_own_renderer(tiny):
    """A model a backend loads renders itself (ModelRenderer); a model no backend recognises needs renderer=, named
    by its type (a plain object without visible_anchors, Scaffold-GS's GaussianModel that renders with outside
    code, a recognised model whose render is hidden)."""
    scene, model = tiny
    r = renderer_for(model)
    assert type(r) is ModelRenderer and isinstance(r, Renderer) and as_renderer(None, model) is not None
    cam = scene.test_cameras[0]
    with torch.no_grad():
        want = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert torch.equal(render_view(None, model, cam, None, scene.background), want)
    assert type(renderer_for(Renders(None))) is ModelRenderer
    with pytest.raises(InputValueError, match=r"a SimpleNamespace has no visible_anchors\(camera\).*pass renderer="):
        renderer_for(SimpleNamespace(render=lambda *a: None))
    with pytest.raises(InputValueError, match="renderer="):
        renderer_for(ScaffoldStandIn(num_anchors=5))

    class NoRender(type(model)):  # type: ignore[misc]
        render = None

    hidden = NoRender.__new__(NoRender)
    hidden.__dict__.update(model.__dict__)
    with pytest.raises(InputValueError, match="a NoRender has no visible_anchors"):
        renderer_for(hidden)


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
    fr = FunctionRenderer(lambda *a: None)
    assert as_renderer(fr, None) is fr and isinstance(fr, Renderer)

    def fn(m: Any, c: Any, v: Any, bg: Any) -> torch.Tensor:
        return torch.ones(3, 3, 4)

    wrapped = as_renderer(fn, None)
    assert type(wrapped) is FunctionRenderer and wrapped.visible(None, small_camera()) is None
    assert torch.equal(wrapped.render(None, small_camera(), None, None), torch.ones(3, 3, 4))

    # attributes named visible / render that are not callable: neither a Renderer nor a function
    with pytest.raises(InputValueError, match="renderer must be None, a Renderer .* got SimpleNamespace"):
        as_renderer(SimpleNamespace(visible=None, render=None), None)
    with pytest.raises(InputValueError, match="got int"):
        as_renderer(42, None)

    class HalfRenderer:  # has the two names, but visible is not callable
        visible = None

        def render(self, *a: Any) -> Any:
            return None

    with pytest.raises(InputValueError, match="got HalfRenderer"):
        as_renderer(HalfRenderer(), None)
    model = Renders(None)
    assert type(as_renderer(None, model)) is ModelRenderer


# ----------------------------------------------------------------------------- render_view

def test_render_view_refuses_what_is_not_an_image() -> None:
    cam = small_camera(width=5, height=2)
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


def test_an_image_on_another_device_is_refused_naming_the_renderer() -> None:
    model = nn.Linear(2, 2)
    with pytest.raises(InputValueError, match=r"renderer FunctionRenderer\(.*my_render\) returned an image on meta; "
                                              r"the model is on cpu"):
        render_view(None, model, CAM, None, renderer=_returns(torch.zeros(3, 2, 5, device="meta")))
    on_meta = nn.Linear(2, 2, device="meta")
    with pytest.raises(InputValueError, match="returned an image on cpu; the model is on meta"):
        render_view(None, on_meta, CAM, None, renderer=_returns(torch.zeros(3, 2, 5)))


@pytest.mark.parametrize("model, image_dtype, wanted", [
    (nn.Linear(2, 2), torch.float64, "torch.float32"),
    (nn.Linear(2, 2), torch.float16, "torch.float32"),
    (nn.Linear(2, 2), torch.uint8, "torch.float32"),
    (nn.Linear(2, 2).double(), torch.float32, "torch.float64"),
    (_PlainModel(torch.float64), torch.float32, "torch.float64"),
    (None, torch.float16, "torch.float32 or torch.float64"),
    (None, torch.int64, "torch.float32 or torch.float64"),
])
def test_an_image_of_another_dtype_is_refused_naming_the_renderer(model: Any, image_dtype: torch.dtype,
                                                                  wanted: str) -> None:
    with pytest.raises(InputValueError, match=rf"renderer FunctionRenderer\(.*my_render\) returned a {image_dtype} image; "
                                              rf"expected {wanted}"):
        render_view(None, model, CAM, None, renderer=_returns(torch.zeros(3, 2, 5, dtype=image_dtype)))


@pytest.mark.parametrize("value, count", [(math.nan, 1), (math.inf, 1), (-math.inf, 1), ("all-nan", 30)])
def test_a_non_finite_image_is_refused_naming_the_renderer(value: Any, count: int) -> None:
    image = torch.rand(3, 2, 5)
    if value == "all-nan":
        image.fill_(math.nan)
    else:
        image[1, 1, 3] = value
    with pytest.raises(InputValueError, match=rf"renderer FunctionRenderer\(.*my_render\) returned an image with {count} "
                                              r"non-finite value"):
        render_view(None, nn.Linear(2, 2), CAM, None, renderer=_returns(image))


def test_a_sparse_image_is_refused_naming_the_renderer() -> None:
    with pytest.raises(InputValueError, match=r"renderer FunctionRenderer\(.*my_render\) returned a torch.sparse_coo image"):
        render_view(None, nn.Linear(2, 2), CAM, None, renderer=_returns(torch.rand(3, 2, 5).to_sparse()))


@pytest.mark.parametrize("model, image_dtype", [(nn.Linear(2, 2), torch.float32), (nn.Linear(2, 2).double(), torch.float64),
                                                (_PlainModel(torch.float64), torch.float64), (None, torch.float32),
                                                (None, torch.float64)])
def test_an_image_on_the_model_device_and_dtype_is_returned(model: Any, image_dtype: torch.dtype) -> None:
    image = torch.rand(3, 2, 5, dtype=image_dtype)
    assert render_view(None, model, CAM, None, renderer=_returns(image)) is image


@needs_skimage
def test_render_view_without_adapter_or_state_is_the_bare_backbone(tiny):
    scene, model = tiny
    cam = scene.test_cameras[0]
    with torch.no_grad():
        bare = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert bare.amax() > 0.1  # the camera sees the scene
        cgs = ControlGS.wrap(model)
        try:
            _perturb(cgs, 0)
            assert not torch.equal(render_view(cgs, model, cam, STATE, scene.background), bare)
            assert torch.equal(render_view(cgs, model, cam, None, scene.background), bare)  # no state: no condition
            assert torch.equal(render_view(None, model, cam, STATE, scene.background), bare)  # no adapter
        finally:
            cgs.unwrap()


@needs_skimage
def test_render_view_modules_restrict_the_injection(tiny: Any) -> None:
    scene, model = tiny
    cam = scene.test_cameras[0]
    cgs = ControlGS.wrap(model)
    try:
        _perturb(cgs, 1)
        with torch.no_grad():
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


@needs_skimage
def test_a_render_of_another_object_than_the_wrapped_one_is_caught(tiny):
    """The renderer renders a copy made before wrapping: render_view raises naming the decoders that never ran;
    inside ``conditioned`` a RuntimeWarning says so; on_miss takes only its documented values."""
    scene, model = tiny
    cam = scene.test_cameras[0]
    other = copy.deepcopy(model)  # e.g. a copy made before wrapping: its decoders carry no hooks
    cgs = ControlGS.wrap(model)
    try:
        stale = FunctionRenderer(lambda m, c, v, bg: other.render(c, v, bg), visible=lambda m, c: m.visible_anchors(c))
        with pytest.raises(InjectionMissedError, match=r"mlp_opacity\.0, mlp_cov\.0, mlp_color\.0"):
            render_view(cgs, model, cam, STATE, scene.background, renderer=stale)
        with pytest.warns(RuntimeWarning, match="no wrapped decoder ran"), torch.no_grad():
            with cgs.conditioned(STATE, cam, model.visible_anchors(cam)):
                other.render(cam, model.visible_anchors(cam))
        with pytest.raises(InputValueError, match="on_miss"):
            with cgs.conditioned(STATE, cam, on_miss="sometimes"):
                pass
        render_view(cgs, model, cam, STATE, scene.background)  # the wrapped object itself: fine
    finally:
        cgs.unwrap()
