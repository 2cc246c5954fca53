"""render_view refuses an image on another device or of another dtype than the model's, naming the renderer."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.protocol import FunctionRenderer, render_view
from controlgs_adapter.state import Camera

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


@pytest.mark.parametrize("model, image_dtype", [(nn.Linear(2, 2), torch.float32), (nn.Linear(2, 2).double(), torch.float64),
                                                (_PlainModel(torch.float64), torch.float64), (None, torch.float32),
                                                (None, torch.float64)])
def test_an_image_on_the_model_device_and_dtype_is_returned(model: Any, image_dtype: torch.dtype) -> None:
    image = torch.rand(3, 2, 5, dtype=image_dtype)
    assert render_view(None, model, CAM, None, renderer=_returns(image)) is image


import copy
import os
from types import SimpleNamespace

from helpers.scaffold_standin import ScaffoldStandIn

import controlgs_adapter.benchmarking.accuracy_time as at
from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.benchmarking.accuracy_time import BenchSettings
from controlgs_adapter.errors import InjectionMissedError, ShapeError
from controlgs_adapter.rendering.protocol import ModelRenderer, Renderer, as_renderer, renderer_for
from controlgs_adapter.scene import load_builtin_scene

pytest.importorskip("skimage")



STATE = RuntimeState(downsample=2, power_saving=0.4)


@pytest.fixture(scope="module")
def tiny_2():
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    torch.manual_seed(0)  # from_points draws from the global generator: the same model whatever ran before
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=20)
    return scene, model.eval()


def test_loaded_models_render_through_their_own_renderer(tiny_2):
    scene, model = tiny_2
    r = renderer_for(model)
    assert type(r) is ModelRenderer and isinstance(r, Renderer) and as_renderer(None, model) is not None
    cam = scene.test_cameras[0]
    with torch.no_grad():
        want = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert torch.equal(render_view(None, model, cam, None, scene.background), want)


def test_render_of_another_object_is_caught(tiny_2):
    scene, model = tiny_2
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


def test_renderer_errors(tiny_2):
    scene, model = tiny_2
    with pytest.raises(InputValueError, match="renderer="):
        renderer_for(ScaffoldStandIn(num_anchors=5))  # Scaffold-GS's GaussianModel renders with outside code
    with pytest.raises(InputValueError, match="renderer must be"):
        as_renderer(42, model)
    with pytest.raises(InputValueError, match="callables"):
        FunctionRenderer(lambda *a: None, visible="mask")
    cam = scene.test_cameras[0]
    with pytest.raises(ShapeError, match=r"expected an sRGB image \[3, 16, 16\]"):
        render_view(None, model, cam, None, renderer=lambda m, c, v, bg: torch.zeros(3, 8, 8))


def test_render_view_without_adapter_or_state_is_the_bare_backbone(tiny_2):
    scene, model = tiny_2
    cam = scene.test_cameras[0]
    with torch.no_grad():
        bare = model.render(cam, model.visible_anchors(cam), scene.background).color
        assert bare.amax() > 0.1  # the camera sees the scene
        cgs = ControlGS.wrap(model)
        try:
            gen = torch.Generator().manual_seed(0)
            for p in cgs.injector.parameters():  # an adapter that changes the decode
                p.add_(0.5 * torch.randn(p.shape, generator=gen))
            assert not torch.equal(render_view(cgs, model, cam, STATE, scene.background), bare)
            assert torch.equal(render_view(cgs, model, cam, None, scene.background), bare)  # no state: no condition
            assert torch.equal(render_view(None, model, cam, STATE, scene.background), bare)  # no adapter
        finally:
            cgs.unwrap()


def test_ss_rows_read_the_rho_0_column_of_each_method(tiny: Any) -> None:
    """A hand-made grid (rho = 0 second, so its index matters): per-view PSNR base + 10 i + p + v / 2, whose
    view mean at (i, p) is base + 10 i + p + 0.25; the rows take p = 1 (rho = 0)."""
    from controlgs_adapter.evaluation import GridResult

    scene, model = tiny

    def psnr(base: float) -> dict[str, torch.Tensor]:
        i, p, v = torch.meshgrid(torch.arange(2.0), torch.arange(2.0), torch.arange(2.0), indexing="ij")
        return {"psnr": (base + 10 * i + p + 0.5 * v).double()}

    grid = GridResult(downsample=(1.0, 2.5), power_saving=(0.4, 0.0),
                      per_view={"no_ss": psnr(100.0), "ss": psnr(200.0), "k0": psnr(300.0)})
    import controlgs_adapter.rendering.protocol as protocol

    sizes: list[tuple[int, Any, Any]] = []
    real = protocol.render_view

    def recorded(cgs: Any, m: Any, cam: Any, state: Any, *args: Any, **kw: Any) -> Any:
        sizes.append((cam.width, cgs, state))
        return real(cgs, m, cam, state, *args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(protocol, "render_view", recorded)
        rows = at.ss_rows(model, scene, grid, BenchSettings(repeats=1))
    # per d: the bare backbone at S / d and at S (16 px), interleaved, a warm-up and one timed call each
    assert sizes == [(16, None, None)] * 4 + [(round(16 / 2.5), None, None), (16, None, None)] * 2
    assert [r["d"] for r in rows] == [1.0, 2.5]
    assert [(r["psnr_no_ss"], r["psnr_ss"], r["psnr_controlgs"]) for r in rows] == [
        (101.25, 201.25, 301.25), (111.25, 211.25, 311.25)]
    assert all(r["render_s_no_ss"] > 0 and r["render_s_ss"] > 0 for r in rows)


def test_render_overhead_counts_and_sizes(tiny: Any, tmp_path: Any) -> None:
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import builtin_backbone_dir

    scene, model = tiny
    cgs = ControlGS.wrap(model)  # lens, resample, display with N = 8
    adapter = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    import controlgs_adapter.rendering.protocol as protocol

    seen: list[tuple[Any, ...]] = []
    real = protocol.render_view

    def recorded(cgs: Any, m: Any, cam: Any, state: Any, *args: Any, **kw: Any) -> Any:
        seen.append((cgs is None, cam is scene.test_cameras[0], None if state is None else
                     (state.downsample, state.power_saving)))
        return real(cgs, m, cam, state, *args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(protocol, "render_view", recorded)
        o = at.render_overhead(model, scene, adapter, tmp_path, repeats=2)
    # bare, then through the adapter at d = 2, rho = 0.4, on the first test camera: a warm-up and two timed calls
    assert seen == [(True, True, None), (False, True, (2.0, 0.4))] * 3
    assert o["render_s_ss"] > 0 and o["render_s_controlgs"] > 0
    assert o["params_conditions"] == model.num_anchors * 3 * 8
    assert o["params_backbone"] == float(sum(t.numel() for t in model.state_dict().values() if t.is_floating_point()))
    assert o["params_conditions"] < o["params_adapter"] < o["params_conditions"] * 2
    assert o["bytes_adapter"] == os.path.getsize(adapter)
    fp16 = tmp_path / "fp16.controlgs.safetensors"
    assert o["bytes_adapter_fp16"] == os.path.getsize(fp16)
    # float16: the conditions take half the bytes (the header is the same order of size)
    assert o["bytes_adapter"] - o["bytes_adapter_fp16"] >= 0.9 * 2 * o["params_conditions"]
    folder = builtin_backbone_dir(scene.variant) / "point_cloud"
    want = sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(folder) for f in files)
    assert o["bytes_backbone"] == want > 0
    assert not any(p.name.startswith("k0") for p in tmp_path.iterdir())  # writes only its fp16 copy


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
