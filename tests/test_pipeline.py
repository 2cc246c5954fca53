"""The end-to-end operator E_s (paper Eq. 9): composition, order, domains, skipping, records."""

from __future__ import annotations

from collections import Counter

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import plugins
from controlgs_adapter.downstream.color import linear_to_srgb, srgb_to_linear
from controlgs_adapter.downstream.display import display_mapping
from controlgs_adapter.downstream.lens import LensPrewarp, RadialMap, lens_prewarp
from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.downstream.stage import Stage
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.hookspecs import hookimpl
from controlgs_adapter.state import RuntimeState

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


def test_no_ss_baseline_input_at_display_size():
    image_low = torch.rand(3, 8, 6, dtype=torch.float64)  # rendered at camera.scaled(2.5) of 20 x 16
    gt = torch.rand(3, 20, 16, dtype=torch.float64)
    p = Pipeline.from_config({"resample": True, "display": True})
    out, inter = p.run_recorded(image_low, RuntimeState(2.5, 0.3), reference=gt)
    expected = linear_to_srgb(oled_emission(display_mapping(srgb_to_linear(image_low), 0.3, srgb_to_linear(gt)), (20, 16)))
    assert out.shape == (3, 20, 16) and torch.allclose(out, expected, atol=1e-12)
    assert inter["post"].shape == (3, 8, 6)
    with pytest.raises(ShapeError, match="larger"):
        p(torch.rand(3, 30, 30), RuntimeState(2.0), reference=gt)


class _Counter:
    """Counts stage calls through forward pre-hooks (the real stages run)."""

    def __init__(self, pipeline: Pipeline) -> None:
        self.calls: Counter[str] = Counter()
        for s in pipeline.stages:
            s.register_forward_pre_hook(lambda mod, args: self.calls.update([mod.name]))


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


def test_trainable_lens_runs_in_training_even_at_identity():
    lens = LensPrewarp.learned(hidden=8, layers=1, frequencies=0)
    p = Pipeline([lens])
    counter = _Counter(p)
    image = torch.rand(3, 6, 6)
    p.eval()(image, RuntimeState())
    assert counter.calls["lens"] == 0
    out = p.train()(image, RuntimeState())
    out.sum().backward()
    assert counter.calls["lens"] == 1 and lens.map.mlp[-1].bias.grad is not None


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
    from controlgs_adapter.downstream.optics.stage import psf_optics

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


def test_stages_are_plain_modules_with_functional_twins():
    """Every built-in stage runs as ``stage(image)`` (default state, the image's size as native
    size) and has a functional twin named after it in snake case (kornia's scheme)."""
    import re

    import controlgs_adapter.downstream as ds
    import controlgs_adapter.downstream.optics as dso

    image = torch.rand(1, 3, 12, 12, dtype=torch.float64)
    for name, info in plugins.stages().items():
        if info.source != plugins.BUILTIN_DIST:
            continue
        cls = info.obj
        twin = re.sub(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", cls.__name__).lower()
        assert callable(getattr(ds, twin, None) or getattr(dso, twin, None)), (cls.__name__, twin)
        if name in ("optics", "display") or cls is ds.LensPrewarp:
            continue  # need a bank / run at the default state below
        out = cls()(image)
        assert out.shape == image.shape
    assert torch.equal(ds.DisplayMapping()(image), ds.display_mapping(image, 0.0))


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
