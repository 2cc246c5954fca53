"""Tests of ``controlgs_adapter.downstream.pipeline``."""

from __future__ import annotations

from collections import Counter

import pytest
import torch
from helpers.banks import D64
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.downstream.color import linear_to_srgb, rgb_to_primaries, srgb_to_linear
from controlgs_adapter.downstream.display import display_mapping, display_power
from controlgs_adapter.downstream.lens import BankMap, DisplayLUTMap, LensPrewarp, LUTMap, RadialMap, lens_prewarp
from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics, set_optics_mode
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.prewarp_fit import fit_prewarp
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.hookspecs import hookimpl
from controlgs_adapter.losses import image_loss

STATE = RuntimeState()


def test_the_pipeline_lens_follows_the_optics_placement():
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion", "placement": "stretch"}})
    assert p["optics"].placement == "stretch" and p["lens"].map.placement == "stretch"
    bank = p["optics"].bank
    for size in ((27, 48), (48, 27), (40, 40)):
        grid, gain = Pipeline.from_config({"lens": {"source": "chief_rays"}, "optics": True})["lens"].map(
            size, torch.float32, torch.device("cpu"))
        lut = LensPrewarp.from_psf_bank(bank, size).map(size, torch.float32, torch.device("cpu"))[0]
        assert gain is None and torch.allclose(grid, lut, atol=1e-6)


def test_flat_field_through_the_pipeline_is_smooth_for_16_9():
    """Lens pre-warp + exact PSF optics on a flat 16:9 field: finite, symmetric, and no rougher than
    the same display band of a square image (the shading is the lens's smooth fall-off: its second
    difference is the square image's to 1e-12, no seam)."""
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "exact"}}).double()
    eye = p(torch.full((3, 54, 96), 0.5, dtype=torch.float64), STATE)
    square = p(torch.full((3, 96, 96), 0.5, dtype=torch.float64), STATE)
    assert torch.isfinite(eye).all()

    def rough(img: torch.Tensor, m: int = 6) -> float:
        inner = img[:, m:-m, m:-m]
        d2x = (inner[..., 2:] - 2 * inner[..., 1:-1] + inner[..., :-2]).abs().max()
        d2y = (inner[:, 2:] - 2 * inner[:, 1:-1] + inner[:, :-2]).abs().max()
        return float(max(d2x, d2y))

    assert rough(eye) <= rough(square) + 1e-12 and rough(eye) < 7e-3
    assert torch.allclose(eye, eye.flip(-1), atol=1e-5) and torch.allclose(eye, eye.flip(-2), atol=1e-5)
    assert torch.allclose(eye[:, 27], square[:, 48], atol=1e-3)     # the display's horizontal axis


class _ModelessOptics(Stage):
    """A third-party optics stage with no ``mode``."""

    name = "optics"
    order = 50.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        return image


def test_an_optics_stage_without_modes_is_refused_not_silently_ignored():
    with pytest.raises(InputValueError, match="PSFOptics.*_ModelessOptics"):
        set_optics_mode(Pipeline([_ModelessOptics()]), "fast")
    pipeline = Pipeline.from_config({"resample": True})  # no optics stage: nothing to set
    set_optics_mode(pipeline, "fast")
    assert "optics" not in pipeline


F64 = torch.float64


def test_pipeline_refuses_an_image_larger_than_native_and_a_reference_at_another_size():
    from controlgs_adapter.downstream.oled import OLEDEmission
    from controlgs_adapter.downstream.pipeline import Pipeline

    p = Pipeline([OLEDEmission()])
    img = torch.rand(3, 4, 6, dtype=F64)
    state = RuntimeState(downsample=2.0)
    for native in ((3, 6), (4, 5)):  # either side smaller than the image
        with pytest.raises(ShapeError, match="larger than the native size"):
            p(img, state, native_size=native)
    with pytest.raises(ShapeError, match="reference must be at native_size"):
        p(img, state, reference=torch.rand(3, 8, 12, dtype=F64), native_size=(8, 11))
    # the native size taken from the reference: box emission to it (display pixel floor((i + 0.5) n / S))
    out = p(img, state, reference=torch.rand(3, 8, 9, dtype=F64))
    assert torch.allclose(out, img[:, [0, 0, 1, 1, 2, 2, 3, 3]][:, :, [0, 1, 1, 2, 3, 3, 4, 5, 5]], atol=1e-12)


@pytest.fixture(scope="module")
def cardboard():
    return PSFBank.default()


def test_optics_stage_in_the_pipeline(cardboard):
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.state import RuntimeState

    pipe = Pipeline.from_config({"optics": {"mode": "distortion"}})
    assert "optics" in pipe.names
    img = torch.rand(1, 3, 32, 32)
    out = pipe(img, RuntimeState(downsample=1.0, power_saving=0.0))
    assert out.shape == img.shape and torch.isfinite(out).all()
    stage = PSFOptics(mode="exact")
    gray = torch.full((3, 32, 32), 0.5, dtype=D64)
    res = stage(gray, RuntimeState(downsample=1.0, power_saving=0.0), None)
    assert res[:, 14:18, 14:18].sub(0.5).abs().max() < 0.02            # grey stays grey near the centre
    with pytest.raises(ValueError, match="mode"):
        stage.mode = "blurry"


K = [[0.08], [0.1], [0.12]]


ALL = {"lens": {"coefficients": K}, "resample": True, "display": True, "foveation": True}


def _manual(image, state, gt, k=K):
    """E_s written out with the functionals (the reference the pipeline must equal)."""
    grid, _ = RadialMap(k).double()(tuple(image.shape[-2:]), image.dtype, image.device)

    def post(img):  # the stages before the display: pre-warp (per primary) and resampling
        return area_resample(lens_prewarp(srgb_to_linear(img), grid, basis="primaries"), state.downsample)

    x = display_mapping(post(image), state.power_saving, post(gt))  # P_ref: the ground truth as displayed
    x = oled_emission(x, tuple(gt.shape[-2:]))
    return linear_to_srgb(x)


class _Counter:
    """Counts stage calls through forward pre-hooks (the real stages run)."""

    def __init__(self, pipeline: Pipeline) -> None:
        self.calls: Counter[str] = Counter()
        for s in pipeline.stages:
            s.register_forward_pre_hook(lambda mod, args: self.calls.update([mod.name]))


class _Sharpen(Stage):
    """A third-party stage working on encoded sRGB, inserted right after the resampling."""

    name = "sharpen"
    domain = "srgb"
    after = "resample"
    seen: list = []

    def forward(self, image, state, ctx):
        type(self).seen.append(image.detach().clone())
        return image * 1.1


class _Tint(Stage):
    name = "tint"
    domain = "linear"
    before = "display"

    def forward(self, image, state, ctx):
        return image * torch.tensor([1.0, 0.9, 0.8], dtype=image.dtype)[:, None, None]


class _Plugin:
    @hookimpl
    def controlgs_register_stages(self):
        return [_Sharpen, _Tint]


def test_builtins_are_registered_and_ordered():
    names = set(plugins.stages())
    assert {"lens", "resample", "display", "oled", "foveation"} <= names
    p = Pipeline.from_config(["display", "resample", "lens", "foveation"])
    assert p.names == ["foveation", "lens", "resample", "display", "oled"]
    assert Pipeline.from_config({"lens": True, "oled": False}).names == ["lens"]


def test_pipeline_equals_the_composed_functionals():
    g = torch.Generator().manual_seed(3)
    image = torch.rand(2, 3, 20, 16, dtype=torch.float64, generator=g)
    gt = torch.rand(2, 3, 20, 16, dtype=torch.float64, generator=g)
    p = Pipeline.from_config(ALL).double()
    for state in (RuntimeState(2.5, 0.4), RuntimeState(1.0, 0.6), RuntimeState(4.0, 0.0)):
        out = p(image, state, reference=gt)
        ref = _manual(image, state, gt)
        assert out.shape == image.shape
        assert torch.allclose(out, ref, atol=1e-12)


def test_what_is_off_or_identity_costs_nothing():
    p = Pipeline.from_config({"lens": {"coefficients": [[0.0]] * 3}, "resample": True, "display": True, "foveation": True})
    counter = _Counter(p)
    image = torch.rand(3, 12, 12)
    assert p(image, RuntimeState(1.0, 0.0)) is image  # no stage, no conversion
    assert sum(counter.calls.values()) == 0
    p(image, RuntimeState(2.0, 0.0))
    assert counter.calls == Counter({"resample": 1, "oled": 1})
    p(image, RuntimeState(1.0, 0.0), reference=torch.rand(3, 12, 12))  # rho 0 with a GT: mapped to P_ref
    assert counter.calls == Counter({"resample": 1, "oled": 1, "display": 1})
    assert p.active(RuntimeState(3.0, 0.2)) == ["resample", "display", "oled"]
    off = Pipeline.from_config({"resample": True})  # display not configured: never runs
    counter_off = _Counter(off)
    off(image, RuntimeState(2.0, 0.9))
    assert counter_off.calls == Counter({"resample": 1, "oled": 1})


def test_record_intermediates_and_diagnostics():
    image = torch.rand(3, 16, 16)
    gt = torch.rand(3, 16, 16)
    p = Pipeline.from_config(ALL)
    out, inter = p.run_recorded(image, RuntimeState(2.0, 0.5), reference=gt)
    assert set(inter) >= {"rendered", "post", "displayed", "eye", "stages_run", "diagnostics"}
    assert inter["rendered"].shape == (3, 16, 16) and inter["post"].shape == (3, 8, 8)
    assert inter["displayed"].shape == (3, 16, 16) and torch.equal(inter["eye"], out.detach())
    assert torch.equal(inter["displayed"], out)  # no optics: the eye sees the display
    assert inter["stages_run"] == ["lens", "resample", "display", "oled"]
    assert 0.0 <= float(inter["diagnostics"]["display.clipped_fraction"]) <= 1.0
    assert torch.equal(p(image, RuntimeState(2.0, 0.5), reference=gt), out)


def test_third_party_stages_are_inserted_and_get_their_domain():
    name = plugins.register_plugin(_Plugin(), name="test-stages")
    try:
        p = Pipeline.from_config({**ALL, "sharpen": True, "tint": True}).double()
        assert p.names == ["foveation", "lens", "resample", "sharpen", "tint", "display", "oled"]
        image = torch.rand(3, 8, 8, dtype=torch.float64)
        state = RuntimeState(2.0, 0.0)
        out = p(image, state)
        x = area_resample(lens_prewarp(srgb_to_linear(image), RadialMap(K).double()((8, 8), torch.float64, "cpu")[0],
                                       basis="primaries"), 2.0)
        assert torch.allclose(_Sharpen.seen[-1], linear_to_srgb(x), atol=1e-12)  # it received sRGB
        x = srgb_to_linear(linear_to_srgb(x) * 1.1) * torch.tensor([1.0, 0.9, 0.8], dtype=torch.float64)[:, None, None]
        assert torch.allclose(out, linear_to_srgb(oled_emission(x, (8, 8))), atol=1e-12)
        # anchors absent from the pipeline: placed by the anchor's registered order
        assert Pipeline.from_config({"sharpen": True, "display": True, "oled": False}).names == ["sharpen", "display"]
    finally:
        plugins.unregister_plugin(name)


def test_config_errors():
    with pytest.raises(InputValueError, match="unknown stage 'blur'"):
        Pipeline.from_config({"blur": True})
    if "optics" not in plugins.stages():
        with pytest.raises(InputValueError, match="optics plug-in"):
            Pipeline.from_config({"optics": True})
    else:
        assert "optics" in Pipeline.from_config({"optics": True})
    with pytest.raises(InputValueError, match="effects\\['lens'\\]"):
        Pipeline.from_config({"lens": 3})
    with pytest.raises(InputValueError, match="unique"):
        Pipeline([LensPrewarp(), LensPrewarp()])
    with pytest.raises(InputValueError, match="stages\\[0\\]"):
        Pipeline([torch.nn.Identity()])  # type: ignore[list-item]


def test_call_errors_name_the_argument():
    p = Pipeline.from_config(ALL)
    with pytest.raises(ShapeError, match="image"):
        p(torch.rand(4, 8, 8), RuntimeState())
    with pytest.raises(InputValueError, match="state"):
        p(torch.rand(3, 8, 8), {"downsample": 2})  # type: ignore[arg-type]
    with pytest.raises(ShapeError, match="reference"):
        p(torch.rand(3, 8, 8), RuntimeState(), reference=torch.rand(3, 9, 9), native_size=(8, 8))
    with pytest.raises(InputValueError, match="non-finite"):
        p(torch.full((3, 8, 8), float("nan")), RuntimeState(2.0))


def test_device_mismatch_names_the_arguments():
    other = "cuda" if torch.cuda.is_available() else "meta"  # meta: a second device without a GPU
    p = Pipeline.from_config(ALL)
    with pytest.raises(InputValueError, match="reference="):
        p(torch.rand(3, 8, 8), RuntimeState(2.0, 0.3), reference=torch.rand(3, 8, 8, device=other))
    with pytest.raises(InputValueError, match="grid="):
        lens_prewarp(torch.rand(3, 8, 8), torch.zeros(3, 8, 8, 2, device=other))
    with pytest.raises(InputValueError, match="reference="):
        display_mapping(torch.rand(3, 8, 8), 0.3, torch.rand(3, 8, 8, device=other))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: pipeline on CUDA vs CPU not run")
def test_pipeline_on_cuda_matches_cpu():
    image, gt = torch.rand(3, 32, 32, dtype=torch.float64), torch.rand(3, 32, 32, dtype=torch.float64)
    p = Pipeline.from_config(ALL).double()
    cpu = p(image, RuntimeState(2.5, 0.4), reference=gt)
    gpu = p.cuda()(image.cuda(), RuntimeState(2.5, 0.4), reference=gt.cuda())
    assert torch.allclose(gpu.cpu(), cpu, atol=1e-10)


@settings(max_examples=15, deadline=None)
@given(st.floats(1.0, 8.0), st.floats(0.0, 0.999), st.sampled_from(["black", "no_blue", "random"]))
def test_no_nan_in_value_or_gradient(d, rho, kind):
    image = torch.rand(3, 16, 16, dtype=torch.float64)
    if kind == "black":
        image.zero_()
    elif kind == "no_blue":
        image[2] = 0
    image.requires_grad_(True)
    gt = torch.rand(3, 16, 16, dtype=torch.float64) if kind != "black" else torch.zeros(3, 16, 16, dtype=torch.float64)
    out = Pipeline.from_config(ALL).double()(image, RuntimeState(d, rho), reference=gt)
    (grad,) = torch.autograd.grad(out.sum(), image)
    assert torch.isfinite(out).all() and torch.isfinite(grad).all()


def test_gradcheck_pipeline():
    image = (torch.rand(3, 8, 8, dtype=torch.float64) * 0.6 + 0.2).requires_grad_(True)
    gt = torch.rand(3, 8, 8, dtype=torch.float64) * 0.5
    p = Pipeline.from_config(ALL).double()
    for state in (RuntimeState(2.0, 0.3), RuntimeState(1.5, 0.0)):
        assert torch.autograd.gradcheck(lambda x: p(x, state, reference=gt), (image,))


def test_pipeline_with_the_optics_stage():
    if "optics" not in plugins.stages():
        pytest.skip("optics stage not registered")

    p = Pipeline.from_config({**ALL, "optics": {"mode": "distortion"}})
    assert p.names[-2:] == ["oled", "optics"]
    default_lens = Pipeline.from_config({"lens": {"source": "chief_rays"}, "optics": {"mode": "distortion"}})["lens"]
    bank_lens = LensPrewarp.from_psf_bank(p["optics"].bank, (40, 40))
    grid, _ = default_lens.map((40, 40), torch.float32, torch.device("cpu"))
    assert torch.allclose(grid, bank_lens.map((40, 40), torch.float32, torch.device("cpu"))[0], atol=1e-4)
    image, gt = torch.rand(3, 32, 32), torch.rand(3, 32, 32)
    eye, inter = p.run_recorded(image, RuntimeState(2.0, 0.3), reference=gt)
    displayed = srgb_to_linear(inter["displayed"])
    assert torch.allclose(eye, linear_to_srgb(psf_optics(displayed, p["optics"].bank, mode="distortion")), atol=1e-5)
    assert inter["stages_run"] == ["lens", "resample", "display", "oled", "optics"]
    assert not torch.allclose(inter["displayed"], eye, atol=1e-3)


def test_placement_errors():
    class A(Stage):
        name, after = "a", "b"

        def forward(self, image, state, ctx):
            return image

    class B(Stage):
        name, after = "b", "a"

        def forward(self, image, state, ctx):
            return image

    class C(Stage):
        name, after = "c", "nowhere"

        def forward(self, image, state, ctx):
            return image

    class D(Stage):
        name, after, before = "d", "display", "resample"

        def forward(self, image, state, ctx):
            return image

    with pytest.raises(InputValueError, match="cycle"):
        Pipeline([A(), B()])
    with pytest.raises(InputValueError, match="'nowhere'"):
        Pipeline([C()])
    with pytest.raises(InputValueError, match="contradict"):
        Pipeline.from_config({"resample": True, "display": True, "d": D()})


def test_chained_and_before_placement():
    def make(name_, after_=None, before_=None):
        return type(name_.title(), (Stage,), {"name": name_, "after": after_, "before": before_,
                                               "forward": lambda self, image, state, ctx: image})()

    stages = [make("y", "x"), make("x", "resample"), make("w", None, "display"), make("v", None, "display")]
    p = Pipeline([*stages, *Pipeline.from_config(["resample", "display"]).stages])
    assert p.names == ["resample", "x", "y", "v", "w", "display", "oled"]


def test_run_recorded_and_forward_agree():
    p = Pipeline.from_config({"lens": False, "resample": True, "display": True, "oled": True})
    image, gt = torch.rand(3, 16, 16), torch.rand(3, 16, 16)
    state = RuntimeState(2.0, 0.3)
    eye, inter = p.run_recorded(image, state, reference=gt)
    assert isinstance(p(image, state, reference=gt), torch.Tensor)
    assert torch.equal(eye, p(image, state, reference=gt)) and inter["stages_run"] == ["resample", "display", "oled"]
    assert torch.equal(p(image), p(image, RuntimeState()))


def test_module_apply_still_recurses_through_a_pipeline():
    p = Pipeline.from_config({"lens": True, "resample": True})
    seen: list[str] = []
    p.apply(lambda m: seen.append(type(m).__name__))  # nn.Module.apply, not shadowed by the stages
    assert "AreaResample" in seen and seen[-1] == "Pipeline"


needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


GEN = torch.Generator().manual_seed(14)


FIELD = [(0.0, 0.0), (0.85, 0.85), (-0.85, -0.85), (0.85, -0.85), (-0.85, 0.0), (0.0, 0.85), (0.5, 0.5)]


# ----------------------------------------------------------------------------- dots per primary
def _dot_centroid_errors(pipe: Pipeline, size: tuple[int, int], field=FIELD) -> torch.Tensor:
    """``[dots, 3]`` distance (px) of each primary's eye centroid from the rendered dot's centre."""
    h, w = size
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                            indexing="ij")
    centres = [((u + 1) / 2 * w, (v + 1) / 2 * h) for u, v in field]
    dots = torch.stack([0.5 * torch.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 2).expand(3, h, w) for cx, cy in centres])
    with torch.no_grad():
        prim = rgb_to_primaries(srgb_to_linear(pipe(linear_to_srgb(dots), RuntimeState())))   # [dots, 3, H, W]
    r = max(6, min(h, w) // 8)
    errs = []
    for k, (cx, cy) in enumerate(centres):
        m = prim[k] * (((xx - cx).abs() < r) & ((yy - cy).abs() < r))
        s = m.sum((1, 2))
        errs.append(torch.hypot((m * xx).sum((1, 2)) / s - cx, (m * yy).sum((1, 2)) / s - cy))
    return torch.stack(errs)


# ----------------------------------------------------------------------------- P_ref on the displayed GT
@pytest.mark.parametrize("d", [1.0, 2.5])
def test_a_perfect_render_gets_display_scale_one_at_every_rho(d):
    gt = torch.rand(3, 20, 20, dtype=torch.float64, generator=GEN)
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True}).double()
    grid, _ = pipe["lens"].map((20, 20), torch.float64, "cpu")
    shown = area_resample(lens_prewarp(srgb_to_linear(gt), grid, basis="primaries"), d)   # float64 functional reference
    for rho in (0.0, 0.2, 0.4, 0.6, 0.8):
        _, inter = pipe.run_recorded(gt, RuntimeState(d, rho), reference=gt)
        diag = inter["diagnostics"]
        assert float(diag["display.scale"]) == pytest.approx(1.0 - rho, abs=1e-12)
        assert float(diag["display.power_ref"]) == pytest.approx(float(display_power(shown)), rel=1e-12)
    old = Pipeline.from_config({"lens": True, "resample": True, "display": {"p_ref": "ground_truth"}}).double()
    _, inter = old.run_recorded(gt, RuntimeState(d, 0.0), reference=gt)
    assert float(inter["diagnostics"]["display.scale"]) > 1.02       # the former rule brightens a perfect render
    with pytest.raises(InputValueError, match="p_ref"):
        Pipeline.from_config({"display": {"p_ref": "gt"}})


def test_active_sees_the_reference():
    pipe = Pipeline.from_config({"resample": True, "display": True})
    gt = torch.rand(3, 8, 8)
    assert pipe.active(RuntimeState()) == []
    assert pipe.active(RuntimeState(), reference=gt) == ["display"]


@needs_optics
def test_the_paper_per_rgb_chief_ray_warp_misses_by_lateral_colour():
    """Sensitivity: the per-RGB warp of the bank's chief rays (the former default) puts the primaries
    of a dot at (0.85, 0.85) apart by more than a pixel at 256 px in exact mode (here at 96 px)."""
    pipe = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": {"mode": "exact"}}).double()
    assert isinstance(pipe["lens"].map, BankMap)
    err = _dot_centroid_errors(pipe, (96, 96), [(0.85, 0.85)])
    assert float(err.max()) > 0.3


@needs_optics
def test_the_lut_follows_the_optics_mode():
    pipe = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion"}})
    lut = pipe["lens"].map
    assert lut.table_mode() == "distortion"
    pipe["optics"].mode = "fast"
    assert lut.table_mode() == "exact"


def _stage(name: str, after: str, order: float) -> Stage:
    return type(name.title(), (Stage,), {"name": name, "after": after, "order": order,
                                          "forward": lambda self, image, state, ctx: image})()


def test_stages_placed_after_the_same_stage_keep_their_order():
    base = list(Pipeline.from_config(["resample", "display"]).stages)
    for stages in ([_stage("b", "resample", 50.0), _stage("a", "resample", 60.0)],
                   [_stage("a", "resample", 60.0), _stage("b", "resample", 50.0)]):
        assert Pipeline([*stages, *base]).names == ["resample", "b", "a", "display", "oled"]
    same = [_stage("q", "resample", 50.0), _stage("p", "resample", 50.0)]
    assert Pipeline([*same, *base]).names == ["resample", "p", "q", "display", "oled"]


def _smooth_images(n: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    a = torch.stack([torch.cos(4 * xx + yy), torch.sin(3 * yy - xx), xx * yy]) * 0.3 + 0.45
    return torch.stack([a, a.flip(-1)])


@pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")
def test_fit_reduces_the_eye_loss_and_bakes():
    torch.manual_seed(0)
    images = _smooth_images(32)
    pipe = Pipeline.from_config({"lens": LensPrewarp.learned(hidden=32, layers=2, frequencies=2),
                                 "optics": {"mode": "distortion"}})

    def eye_loss() -> float:
        with torch.no_grad():
            return sum(float(image_loss(pipe(img, RuntimeState(), reference=img), img)) for img in images) / 2

    before = eye_loss()
    losses = fit_prewarp(pipe, images, steps=60, lr=1e-2, generator=torch.Generator().manual_seed(0))
    assert len(losses) == 60 and pipe.training  # the pipeline's mode is restored
    after = eye_loss()
    assert after < 0.8 * before
    baked = pipe["lens"].bake((32, 32))
    assert isinstance(baked.map, LUTMap)
    pipe.stages[pipe.names.index("lens")] = baked
    assert abs(eye_loss() - after) < 1e-3


D = torch.float64


def _mk(name: str, order: float = 100.0, after: str | None = None, before: str | None = None) -> Stage:
    return type(name.title(), (Stage,), {"name": name, "order": order, "after": after, "before": before,
                                         "process": lambda self, i, s, c: i})()


class _Scale(Stage):
    name, domain, order = "scale", "linear", 15.0

    def process(self, image, state, ctx):
        return image * 0.5


def test_an_absent_registered_anchor_places_by_its_order_before_and_after():
    # "display" is registered at order 30 but not in the pipeline: "after" goes behind every plain
    # stage of order <= 30, "before" in front of the first plain stage of order >= 30
    p = Pipeline([_mk("x30", 30.0), _mk("aft", 1.0, after="display"), _mk("bef", 99.0, before="display"),
                  _mk("x20", 20.0), _mk("x40", 40.0)])
    assert p.names == ["x20", "bef", "x30", "aft", "x40"]
    # no plain stage before the anchor's order: the stage goes first
    assert Pipeline([_mk("x20", 20.0), _mk("first", 99.0, before="lens")]).names == ["first", "x20"]
    assert Pipeline([_mk("x20", 20.0), _mk("late", 0.0, after="lens")]).names == ["late", "x20"]


def test_stages_after_one_anchor_keep_their_own_order():
    p = Pipeline([_mk("a", 10.0), _mk("b", 20.0), _mk("q", 7.0, after="a"), _mk("p", 3.0, after="a")])
    assert p.names == ["a", "p", "q", "b"]


def test_pipeline_refuses_non_stages_by_index_and_type():
    with pytest.raises(InputValueError, match=r"stages\[1\] must be a Stage instance, got Identity"):
        Pipeline([_mk("a"), torch.nn.Identity()])  # type: ignore[list-item]
    with pytest.raises(InputValueError, match=r"stage names must be unique, got duplicates \['a'\]"):
        Pipeline([_mk("a"), _mk("b"), _mk("a")])


def test_lookup_by_name():
    p = Pipeline([_mk("a"), _mk("b", 1.0)])
    assert p["a"].name == "a" and "b" in p and "c" not in p and 3 not in p
    with pytest.raises(KeyError, match=r"no stage 'c' in this pipeline \(stages: \['b', 'a'\]\)"):
        p["c"]


def test_from_config_names_oled_and_values():
    assert Pipeline.from_config(["display", "resample"]).names == ["resample", "display", "oled"]
    assert Pipeline.from_config({"display": True, "oled": False}).names == ["display"]
    assert Pipeline.from_config({}).names == ["oled"]
    p = Pipeline.from_config({"resample": {"max_factor": 3.0}})
    assert p["resample"].max_factor == 3.0
    with pytest.raises(InputValueError, match=r"effects\['display'\] must be a bool, a dict of options or a Stage, got str"):
        Pipeline.from_config({"display": "yes"})
    with pytest.raises(InputValueError, match="unknown stage 'blur'; registered stages: ") as e:
        Pipeline.from_config({"blur": True})
    assert "optics plug-in" not in str(e.value)


def test_from_config_lens_without_optics_is_the_analytic_radial_map():
    p = Pipeline.from_config({"lens": True})
    assert isinstance(p["lens"].map, RadialMap) and p["lens"].basis == "primaries"
    q = Pipeline.from_config({"lens": {"coefficients": [[0.1], [0.2], [0.3]], "basis": "rgb"}})
    assert q["lens"].map.coefficients.flatten().tolist() == pytest.approx([0.1, 0.2, 0.3])
    assert q["lens"].basis == "rgb"


@needs_optics
def test_from_config_lens_follows_the_optics():
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion"}})
    assert isinstance(p["lens"].map, DisplayLUTMap) and p["lens"].map.table_mode() == "distortion"
    q = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": True})
    assert isinstance(q["lens"].map, BankMap) and q["lens"].basis == "rgb"
    # options beyond the optics-building ones: an ordinary lens from its constructor, refused here
    with pytest.raises(InputValueError, match=r"effects\['lens'\]: .*unexpected keyword argument 'source'"):
        Pipeline.from_config({"lens": {"source": "chief_rays", "coefficients": [[0.1]] * 3}, "optics": True})
    assert isinstance(Pipeline.from_config({"lens": {"coefficients": [[0.1]] * 3}, "optics": True})["lens"].map, RadialMap)
    assert "lens" not in Pipeline.from_config({"lens": False, "optics": True})
    assert "lens" not in Pipeline.from_config({"lens": None, "optics": True})
    own = LensPrewarp(coefficients=[[0.2]] * 3)
    assert Pipeline.from_config({"lens": own, "optics": True})["lens"] is own


def test_from_config_lens_with_an_optics_stage_without_a_bank():
    optics = _mk("optics", 50.0)
    p = Pipeline.from_config({"lens": True, "optics": optics})
    assert p.names == ["lens", "oled", "optics"] and isinstance(p["lens"].map, RadialMap)


def test_call_checks_sizes_and_the_reference():
    p = Pipeline([_mk("a")])
    with pytest.raises(ShapeError, match="larger than the native size"):
        p(torch.rand(3, 4, 4), native_size=(3, 4))
    with pytest.raises(ShapeError, match="larger than the native size"):
        p(torch.rand(3, 4, 4), native_size=(4, 3))
    with pytest.raises(ShapeError, match=r"reference must be at native_size \(4, 4\)"):
        p(torch.rand(3, 4, 4), reference=torch.rand(3, 4, 5), native_size=(4, 4))
    bad = torch.rand(3, 4, 4)
    bad[0, 1, 1] = float("nan")
    with pytest.raises(InputValueError, match="reference"):
        p(torch.rand(3, 4, 4), reference=bad)
    img = torch.rand(3, 4, 4)
    assert torch.allclose(p(img, None, reference=torch.rand(3, 4, 4)), img, atol=1e-6)  # decode + encode


def test_no_ss_baseline_gets_its_native_size_from_the_reference_or_the_argument():
    p = Pipeline.from_config(["resample"])
    small = torch.rand(3, 4, 4, dtype=D, generator=torch.Generator().manual_seed(1))
    expect = linear_to_srgb(oled_emission(srgb_to_linear(small), (8, 8)))
    out = p(small, RuntimeState(downsample=2.0), reference=torch.rand(3, 8, 8, dtype=D))
    assert torch.allclose(out, expect, atol=1e-12)
    assert torch.allclose(p(small, RuntimeState(downsample=2.0), native_size=(8, 8)), expect, atol=1e-12)
    assert p.names == ["resample", "oled"]


def test_active_stages_with_and_without_a_reference():
    p = Pipeline.from_config(["resample", "display"])
    s = RuntimeState(downsample=2.0, power_saving=0.0)
    assert p.active(s) == ["resample", "oled"]
    assert p.active(s, reference=torch.rand(3, 8, 8)) == ["resample", "display", "oled"]
    assert p.active(RuntimeState(), native_size=(8, 8)) == []
    assert p.active(RuntimeState(power_saving=0.5), native_size=(8, 8)) == ["display"]


def test_recorded_intermediates_by_hand():
    p = Pipeline([_Scale(), *Pipeline.from_config(["resample", "display"]).stages])
    img = torch.full((3, 4, 4), 0.5, dtype=D)
    lin = float(srgb_to_linear(img)[0, 0, 0])
    eye, rec = p.run_recorded(img, RuntimeState(downsample=2.0, power_saving=0.5))
    # scale by 0.5, resample (flat), display scales by 1 - rho = 0.5, oled back to 4 x 4
    assert rec["stages_run"] == ["scale", "resample", "display", "oled"]
    assert rec["post"].shape == (3, 2, 2) and float(rec["post"][0, 0, 0]) == pytest.approx(float(linear_to_srgb(
        torch.full((3, 1, 1), lin * 0.25, dtype=D))[0, 0, 0]))
    assert rec["displayed"].shape == (3, 4, 4) and torch.allclose(rec["displayed"], eye)
    assert rec["rendered"] is not img and torch.equal(rec["rendered"], img)
    assert float(rec["diagnostics"]["display.scale"]) == pytest.approx(0.5)
    # d = 1: oled skipped: "displayed" is the post-processed frame; no physical stage: post is the eye
    eye1, rec1 = p.run_recorded(img, RuntimeState(power_saving=0.5))
    assert rec1["stages_run"] == ["scale", "display"]
    assert torch.equal(rec1["displayed"], rec1["post"]) and torch.equal(rec1["post"], eye1)
    assert torch.allclose(eye1, linear_to_srgb(torch.full((3, 4, 4), lin * 0.25, dtype=D)))
    # the intermediates are detached copies; the eye keeps its graph
    eye3, rec3 = p.run_recorded(img.clone().requires_grad_(True), RuntimeState(downsample=2.0, power_saving=0.5))
    assert eye3.requires_grad
    assert not any(rec3[k].requires_grad for k in ("rendered", "post", "displayed", "eye"))
    _, rec4 = Pipeline([_Scale()]).run_recorded(img.clone().requires_grad_(True))  # no physical stage
    assert not rec4["post"].requires_grad and not rec4["displayed"].requires_grad
    _, rec2 = Pipeline([_mk("a")]).run_recorded(img)
    assert rec2["stages_run"] == ["a"] and rec2["diagnostics"] == {}


_CALLS: list[str] = []  # names of the _Scale stages processed, in call order


class _Scale_2(Stage):
    """A stage multiplying by ``factor`` in its domain; the identity (skipped) when factor is 1."""

    name = "scale"
    domain = "linear"
    order = 15.0

    def __init__(self, factor: float = 2.0) -> None:
        super().__init__()
        self.factor = factor

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        return self.factor == 1.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        _CALLS.append(self.name)
        return image * self.factor


def _stage_2(name: str, order: float, domain: str = "linear", factor: float = 1.0) -> Stage:
    return type(name.title(), (_Scale_2,), {"name": name, "order": order, "domain": domain})(factor)


def test_pipeline_refusals_name_what_is_wrong():
    nameless = _stage_2("x", 1.0)
    nameless.name = ""
    with pytest.raises(InputValueError, match=r"stages\[1\] \(X\) has no name"):
        Pipeline([_stage_2("a", 1.0), nameless])
    with pytest.raises(InputValueError, match="stage 'hsv' has domain 'hsv'"):
        Pipeline([_stage_2("hsv", 1.0, "hsv")])
    with pytest.raises(InputValueError, match="effects\\['resample'\\] is a stage named 'lens'"):
        Pipeline.from_config({"resample": LensPrewarp()})
    with pytest.raises(InputValueError, match="effects\\['resample'\\]"):
        Pipeline.from_config({"resample": {"no_such_option": 1}})
    with pytest.raises(ShapeError, match="larger than the native size"):
        Pipeline([_stage_2("a", 1.0)])(torch.rand(3, 4, 4), native_size=(4, 3))
    assert Pipeline.from_config({"resample": None, "display": False}).names == ["oled"]
