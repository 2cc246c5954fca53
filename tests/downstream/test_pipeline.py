"""Tests of ``controlgs_adapter.downstream.pipeline``: composing the registered stages. Their order (by
``order``, name and ``after``/``before`` anchors), building from a scene configuration (the lens from the
optics), running (equal to the composed functionals, domain conversions only around stages that run,
identities skipped at no cost), the recorded intermediates, the no-supersampling baseline, the display's
reference as displayed, gradients, the optics in the pipeline, and the refusals naming the argument."""

from __future__ import annotations

from collections import Counter

import pytest
import torch
from helpers.stage_contract import StageCalls
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.downstream import pipeline as pipeline_module
from controlgs_adapter.downstream.color import linear_to_srgb, primaries_to_rgb, rgb_to_primaries, srgb_to_linear
from controlgs_adapter.downstream.display import DisplayMapping, display_mapping, display_power
from controlgs_adapter.downstream.foveation import Foveation
from controlgs_adapter.downstream.lens import BankMap, DisplayLUTMap, LensPrewarp, RadialMap, lens_prewarp, pixel_grid
from controlgs_adapter.downstream.oled import OLEDEmission, oled_emission
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import AreaResample, area_resample
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.hookspecs import hookimpl

D = torch.float64
K = [[0.08], [0.1], [0.12]]
ALL = {"lens": {"coefficients": K}, "resample": True, "display": True, "foveation": True}

_CALLS: list[str] = []  # names of the _Scale stages processed, in call order


class _Scale(Stage):
    """A stage multiplying by ``factor`` in its domain; the identity (skipped) when ``skip`` is set."""

    name = "scale"
    domain = "linear"
    order = 15.0

    def __init__(self, factor: float = 1.0, skip: bool = False) -> None:
        super().__init__()
        self.factor, self.skip = factor, skip

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        return self.skip

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        _CALLS.append(self.name)
        return image * self.factor


def _stage(name: str, order: float = 100.0, *, after: str | None = None, before: str | None = None,
           domain: str = "linear", factor: float = 1.0, skip: bool = False) -> Stage:
    """A :class:`_Scale` stage named ``name`` with its own order, anchors and domain."""
    attrs = {"name": name, "order": order, "after": after, "before": before, "domain": domain}
    return type(name.title(), (_Scale,), attrs)(factor, skip)


def _manual(image, state, gt, k=K):
    """E_s written out with the functionals (the reference the pipeline must equal)."""
    grid, _ = RadialMap(k).double()(tuple(image.shape[-2:]), image.dtype, image.device)

    def post(img):  # the stages before the display: pre-warp (per primary) and resampling
        return area_resample(lens_prewarp(srgb_to_linear(img), grid, basis="primaries"), state.downsample)

    x = display_mapping(post(image), state.power_saving, post(gt))  # P_ref: the ground truth as displayed
    x = oled_emission(x, tuple(gt.shape[-2:]))
    return linear_to_srgb(x)


# ----------------------------------------------------------------------------- order
def test_builtins_are_registered_and_ordered_by_their_orders():
    """Built-in orders: foveation 5, lens 10, resample 20, display 30, oled 40, optics 50; a third-party
    stage without an order runs after every built-in (100); equal orders go by name."""
    assert {"lens", "resample", "display", "oled", "foveation", "optics"} <= set(plugins.stages())
    assert Pipeline.from_config(["display", "resample", "lens", "foveation"]).names == \
        ["foveation", "lens", "resample", "display", "oled"]
    assert Pipeline.from_config({"lens": True, "oled": False}).names == ["lens"]
    fillers = [_stage(f"at{o}", o) for o in (100.1, 99.9, 4.9, 5.1, 9.9, 10.1, 19.9, 20.1, 29.9, 30.1, 39.9, 40.1, 45.0, 55.0)]
    pipe = Pipeline([_stage("plain"), *fillers, OLEDEmission(), Foveation(), AreaResample(), DisplayMapping(),
                     LensPrewarp(), PSFOptics(mode="distortion")])
    assert pipe.names == ["at4.9", "foveation", "at5.1", "at9.9", "lens", "at10.1", "at19.9", "resample", "at20.1",
                          "at29.9", "display", "at30.1", "at39.9", "oled", "at40.1", "at45.0", "optics", "at55.0",
                          "at99.9", "plain", "at100.1"]
    assert Pipeline([_stage("b", 1.0), _stage("a", 1.0), _stage("c", 0.5)]).names == ["c", "a", "b"]


def test_stages_anchored_after_or_before_a_stage():
    """A stage with ``after`` goes right after its anchor, behind the stages already placed after it (those
    after the same anchor keep their own (order, name) order, whatever the sequence); one with ``before``
    right before its anchor; anchors chain."""
    base = list(Pipeline.from_config(["resample", "display"]).stages)
    for stages in ([_stage("b", 50.0, after="resample"), _stage("a", 60.0, after="resample")],
                   [_stage("a", 60.0, after="resample"), _stage("b", 50.0, after="resample")]):
        assert Pipeline([*stages, *base]).names == ["resample", "b", "a", "display", "oled"]
    same = [_stage("q", 50.0, after="resample"), _stage("p", 50.0, after="resample")]
    assert Pipeline([*same, *base]).names == ["resample", "p", "q", "display", "oled"]
    p = Pipeline([_stage("a", 10.0), _stage("b", 20.0), _stage("q", 7.0, after="a"), _stage("p", 3.0, after="a")])
    assert p.names == ["a", "p", "q", "b"]
    chained = [_stage("y", after="x"), _stage("x", after="resample"), _stage("w", before="display"),
               _stage("v", before="display")]
    assert Pipeline([*chained, *base]).names == ["resample", "x", "y", "v", "w", "display", "oled"]


def test_an_absent_anchor_is_placed_by_its_registered_order():
    """An anchor that is registered but not in the pipeline stands at its registered order: "after" goes
    behind every plain stage of order <= it, "before" in front of the first plain stage of order >= it, and
    first when no plain stage comes before. E.g. after resample (20) without resampling: after foveation (5)
    and lens (10), before display (30)."""
    p = Pipeline([DisplayMapping(), _stage("after_resample", after="resample", domain="srgb"), LensPrewarp(), Foveation()])
    assert p.names == ["foveation", "lens", "after_resample", "display"]
    p = Pipeline([_stage("x30", 30.0), _stage("aft", 1.0, after="display"), _stage("bef", 99.0, before="display"),
                  _stage("x20", 20.0), _stage("x40", 40.0)])
    assert p.names == ["x20", "bef", "x30", "aft", "x40"]
    assert Pipeline([_stage("x20", 20.0), _stage("first", 99.0, before="lens")]).names == ["first", "x20"]
    assert Pipeline([_stage("x20", 20.0), _stage("late", 0.0, after="lens")]).names == ["late", "x20"]


def test_placement_errors():
    with pytest.raises(InputValueError, match="cycle.*'a'"):
        Pipeline([_stage("a", after="b"), _stage("b", after="a")])
    with pytest.raises(InputValueError, match="'c'.*'nowhere'.*registered"):
        Pipeline([_stage("c", after="nowhere")])
    with pytest.raises(InputValueError, match="'d'.*after='display'.*before='resample'"):
        Pipeline.from_config({"resample": True, "display": True, "d": _stage("d", after="display", before="resample")})


# ----------------------------------------------------------------------------- construction
def test_construction_refusals_name_what_is_wrong(monkeypatch):
    with pytest.raises(InputValueError, match=r"stages\[0\].*Stage.*Identity"):
        Pipeline([torch.nn.Identity()])  # type: ignore[list-item]
    with pytest.raises(InputValueError, match=r"stages\[1\].*Stage.*Identity"):
        Pipeline([_stage("a"), torch.nn.Identity()])  # type: ignore[list-item]
    with pytest.raises(InputValueError, match=r"unique.*\['a'\]"):
        Pipeline([_stage("a"), _stage("b"), _stage("a")])
    with pytest.raises(InputValueError, match=r"unique.*\['lens'\]"):
        Pipeline([LensPrewarp(), LensPrewarp()])
    nameless = _stage("x", 1.0)
    nameless.name = ""
    with pytest.raises(InputValueError, match=r"stages\[1\] \(X\) has no name"):
        Pipeline([_stage("a", 1.0), nameless])
    with pytest.raises(InputValueError, match="stage 'hsv' has domain 'hsv'"):
        Pipeline([_stage("hsv", 1.0, domain="hsv")])
    with pytest.raises(InputValueError, match=r"effects\['resample'\].*'lens'"):
        Pipeline.from_config({"resample": LensPrewarp()})
    with pytest.raises(InputValueError, match=r"effects\['resample'\]: .*no_such_option"):
        Pipeline.from_config({"resample": {"no_such_option": 1}})
    with pytest.raises(InputValueError, match=r"effects\['display'\].*got str"):
        Pipeline.from_config({"display": "yes"})
    with pytest.raises(InputValueError, match=r"effects\['lens'\] must be .* got int"):
        Pipeline.from_config({"lens": 3})
    with pytest.raises(InputValueError, match="'blur'.*registered") as e:
        Pipeline.from_config({"blur": True})
    assert "optics plug-in" not in str(e.value)
    registered = pipeline_module._registered_stages()
    monkeypatch.setattr(pipeline_module, "_registered_stages", lambda: {k: v for k, v in registered.items() if k != "optics"})
    with pytest.raises(InputValueError, match=r"'optics'.*optics plug-in"):
        Pipeline.from_config({"optics": True})


def test_from_config_names_oled_and_values():
    """Names or a mapping of them; the display emission ``oled`` is always there unless set to False;
    False or None leave a stage out; a dict gives constructor options; a ready stage is taken as it is."""
    assert Pipeline.from_config(["display", "resample"]).names == ["resample", "display", "oled"]
    assert Pipeline.from_config({"display": True, "oled": False}).names == ["display"]
    assert Pipeline.from_config({}).names == ["oled"]
    assert Pipeline.from_config({"resample": None, "display": False}).names == ["oled"]
    assert Pipeline.from_config({"resample": {"max_factor": 3.0}})["resample"].max_factor == 3.0
    assert "optics" in Pipeline.from_config({"optics": True})
    own = LensPrewarp(coefficients=[[0.2]] * 3)
    assert Pipeline.from_config({"lens": own})["lens"] is own


def test_from_config_lens_without_optics_is_the_analytic_radial_map():
    p = Pipeline.from_config({"lens": True})
    assert isinstance(p["lens"].map, RadialMap) and p["lens"].basis == "primaries"
    q = Pipeline.from_config({"lens": {"coefficients": [[0.1], [0.2], [0.3]], "basis": "rgb"}})
    assert q["lens"].map.coefficients.flatten().tolist() == pytest.approx([0.1, 0.2, 0.3])
    assert q["lens"].basis == "rgb"


def test_from_config_lens_follows_the_optics():
    """With optics, ``"lens": True`` is the display LUT fitted for the bank, following the optics' mode;
    ``source: chief_rays`` the bank's chief rays in the optics' placement (the bank's LUT at each size);
    other options build an ordinary lens (mixing both kinds is refused); an optics stage without a bank
    leaves the radial lens."""
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion"}})
    lut = p["lens"].map
    assert isinstance(lut, DisplayLUTMap) and lut.table_mode() == "distortion"
    p["optics"].mode = "fast"
    assert lut.table_mode() == "exact"
    q = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": True})
    assert isinstance(q["lens"].map, BankMap) and q["lens"].basis == "rgb"
    s = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion", "placement": "stretch"}})
    assert s["optics"].placement == "stretch" and s["lens"].map.placement == "stretch"
    bank = s["optics"].bank
    for size in ((27, 48), (48, 27), (40, 40)):
        grid, gain = Pipeline.from_config({"lens": {"source": "chief_rays"}, "optics": True})["lens"].map(
            size, torch.float32, torch.device("cpu"))
        want = LensPrewarp.from_psf_bank(bank, size).map(size, torch.float32, torch.device("cpu"))[0]
        assert gain is None and torch.allclose(grid, want, atol=1e-6)
    with pytest.raises(InputValueError, match=r"effects\['lens'\]: .*unexpected keyword argument 'source'"):
        Pipeline.from_config({"lens": {"source": "chief_rays", "coefficients": [[0.1]] * 3}, "optics": True})
    assert isinstance(Pipeline.from_config({"lens": {"coefficients": [[0.1]] * 3}, "optics": True})["lens"].map, RadialMap)
    assert "lens" not in Pipeline.from_config({"lens": False, "optics": True})
    assert "lens" not in Pipeline.from_config({"lens": None, "optics": True})
    own = LensPrewarp(coefficients=[[0.2]] * 3)
    assert Pipeline.from_config({"lens": own, "optics": True})["lens"] is own
    bankless = Pipeline.from_config({"lens": True, "optics": _stage("optics", 50.0)})
    assert bankless.names == ["lens", "oled", "optics"] and isinstance(bankless["lens"].map, RadialMap)


def test_lookup_by_name_and_module_recursion():
    p = Pipeline([_stage("a"), _stage("b", 1.0)])
    assert p["a"].name == "a" and "b" in p and "c" not in p and 3 not in p
    with pytest.raises(KeyError, match=r"'c'.*\['b', 'a'\]"):
        p["c"]
    seen: list[str] = []
    Pipeline.from_config({"lens": True, "resample": True}).apply(lambda m: seen.append(type(m).__name__))
    assert "AreaResample" in seen and seen[-1] == "Pipeline"  # nn.Module.apply, not shadowed by the stages


# ----------------------------------------------------------------------------- running
def test_pipeline_equals_the_composed_functionals():
    g = torch.Generator().manual_seed(3)
    image = torch.rand(2, 3, 20, 16, dtype=D, generator=g)
    gt = torch.rand(2, 3, 20, 16, dtype=D, generator=g)
    p = Pipeline.from_config(ALL).double()
    for state in (RuntimeState(2.5, 0.4), RuntimeState(1.0, 0.6), RuntimeState(4.0, 0.0)):
        out = p(image, state, reference=gt)
        assert out.shape == image.shape
        assert torch.allclose(out, _manual(image, state, gt), atol=1e-12)


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
        image = torch.rand(3, 8, 8, dtype=D)
        out = p(image, RuntimeState(2.0, 0.0))
        x = area_resample(lens_prewarp(srgb_to_linear(image), RadialMap(K).double()((8, 8), D, "cpu")[0],
                                       basis="primaries"), 2.0)
        assert torch.allclose(_Sharpen.seen[-1], linear_to_srgb(x), atol=1e-12)  # it received sRGB
        x = srgb_to_linear(linear_to_srgb(x) * 1.1) * torch.tensor([1.0, 0.9, 0.8], dtype=D)[:, None, None]
        assert torch.allclose(out, linear_to_srgb(oled_emission(x, (8, 8))), atol=1e-12)
        # anchors absent from the pipeline: placed by the anchor's registered order
        assert Pipeline.from_config({"sharpen": True, "display": True, "oled": False}).names == ["sharpen", "display"]
    finally:
        plugins.unregister_plugin(name)


def test_pipeline_converts_domains_only_around_stages_that_run():
    lin, enc = _stage("lin", 1.0, factor=2.0), _stage("enc", 2.0, domain="srgb", factor=0.5)
    image = torch.rand(3, 3, 3, dtype=D)
    assert torch.allclose(Pipeline([lin, enc]).double()(image), linear_to_srgb(srgb_to_linear(image) * 2.0) * 0.5, atol=1e-12)
    only_srgb = Pipeline([_stage("lin", 1.0, skip=True), enc]).double()(image)
    assert torch.allclose(only_srgb, image * 0.5, atol=1e-15)  # skipped linear stage: no round trip


def test_what_is_off_or_identity_costs_nothing():
    """A stage that is the identity at the state is neither called nor converted around (the input object
    comes back when nothing runs); the display runs at rho = 0 when a reference is given; a stage that is
    not configured never runs; ``active`` names the stages that would run, with or without a reference."""
    p = Pipeline.from_config({"lens": {"coefficients": [[0.0]] * 3}, "resample": True, "display": True, "foveation": True})
    counter = StageCalls(p)
    image = torch.rand(3, 12, 12)
    assert p(image, RuntimeState(1.0, 0.0)) is image
    assert sum(counter.calls.values()) == 0
    p(image, RuntimeState(2.0, 0.0))
    assert counter.calls == Counter({"resample": 1, "oled": 1})
    p(image, RuntimeState(1.0, 0.0), reference=torch.rand(3, 12, 12))  # rho 0 with a GT: mapped to P_ref
    assert counter.calls == Counter({"resample": 1, "oled": 1, "display": 1})
    assert p.active(RuntimeState(3.0, 0.2)) == ["resample", "display", "oled"]
    off = Pipeline.from_config({"resample": True})  # display not configured: never runs
    counter_off = StageCalls(off)
    off(image, RuntimeState(2.0, 0.9))
    assert counter_off.calls == Counter({"resample": 1, "oled": 1})
    q = Pipeline.from_config(["resample", "display"])
    gt = torch.rand(3, 8, 8)
    assert q.active(RuntimeState()) == [] and q.active(RuntimeState(), reference=gt) == ["display"]
    s = RuntimeState(downsample=2.0, power_saving=0.0)
    assert q.active(s) == ["resample", "oled"] and q.active(s, reference=gt) == ["resample", "display", "oled"]
    assert q.active(RuntimeState(), native_size=(8, 8)) == []
    assert q.active(RuntimeState(power_saving=0.5), native_size=(8, 8)) == ["display"]
    b, a, c = _stage("b", 1.0, factor=3.0), _stage("a", 1.0, factor=2.0), _stage("c", 0.5, skip=True)
    r = Pipeline([b, a, c]).double()
    assert r.active(RuntimeState()) == ["a", "b"]
    _CALLS.clear()
    image = torch.tensor([0.2, 0.5, 0.9], dtype=D)[:, None, None].expand(3, 2, 2)
    eye, rec = r.run_recorded(image)
    assert _CALLS == ["a", "b"] and rec["stages_run"] == ["a", "b"]  # c is the identity: not called
    assert torch.allclose(eye, linear_to_srgb(srgb_to_linear(image) * 6.0), atol=1e-12)
    assert torch.equal(rec["post"], eye) and torch.equal(rec["displayed"], eye) and torch.equal(rec["rendered"], image)


def test_recorded_intermediates():
    """``run_recorded`` returns the eye image (equal to ``forward``'s, keeping its graph) and detached copies:
    the rendered image; ``post`` (taken before the first physical stage, at the display size); ``displayed``
    (after the display emission, before the optics); the eye; the stages that ran and the diagnostics the
    stages recorded. Without a physical stage ``post`` and ``displayed`` are the eye image."""
    image, gt = torch.rand(3, 16, 16), torch.rand(3, 16, 16)
    p = Pipeline.from_config(ALL)
    out, inter = p.run_recorded(image, RuntimeState(2.0, 0.5), reference=gt)
    assert set(inter) >= {"rendered", "post", "displayed", "eye", "stages_run", "diagnostics"}
    assert inter["rendered"].shape == (3, 16, 16) and inter["post"].shape == (3, 8, 8)
    assert inter["displayed"].shape == (3, 16, 16) and torch.equal(inter["eye"], out.detach())
    assert torch.equal(inter["displayed"], out)  # no optics: the eye sees the display
    assert inter["stages_run"] == ["lens", "resample", "display", "oled"]
    assert 0.0 <= float(inter["diagnostics"]["display.clipped_fraction"]) <= 1.0
    assert torch.equal(p(image, RuntimeState(2.0, 0.5), reference=gt), out)
    assert torch.equal(p(image), p(image, RuntimeState()))

    q = Pipeline([_stage("scale", 15.0, factor=0.5), *Pipeline.from_config(["resample", "display"]).stages])
    img = torch.full((3, 4, 4), 0.5, dtype=D)
    lin = float(srgb_to_linear(img)[0, 0, 0])
    eye, rec = q.run_recorded(img, RuntimeState(downsample=2.0, power_saving=0.5))
    # scale by 0.5, resample (flat), display scales by 1 - rho = 0.5, oled back to 4 x 4
    assert rec["stages_run"] == ["scale", "resample", "display", "oled"]
    assert rec["post"].shape == (3, 2, 2)
    assert float(rec["post"][0, 0, 0]) == pytest.approx(float(linear_to_srgb(torch.full((3, 1, 1), lin * 0.25, dtype=D))[0, 0, 0]))
    assert rec["displayed"].shape == (3, 4, 4) and torch.allclose(rec["displayed"], eye)
    assert rec["rendered"] is not img and torch.equal(rec["rendered"], img)
    assert float(rec["diagnostics"]["display.scale"]) == pytest.approx(0.5)
    eye1, rec1 = q.run_recorded(img, RuntimeState(power_saving=0.5))   # d = 1: oled skipped, no physical stage
    assert rec1["stages_run"] == ["scale", "display"]
    assert torch.equal(rec1["displayed"], rec1["post"]) and torch.equal(rec1["post"], eye1)
    assert torch.allclose(eye1, linear_to_srgb(torch.full((3, 4, 4), lin * 0.25, dtype=D)))
    eye3, rec3 = q.run_recorded(img.clone().requires_grad_(True), RuntimeState(downsample=2.0, power_saving=0.5))
    assert eye3.requires_grad and not any(rec3[k].requires_grad for k in ("rendered", "post", "displayed", "eye"))
    _, rec4 = Pipeline([_stage("scale", 15.0, factor=0.5)]).run_recorded(img.clone().requires_grad_(True))
    assert not rec4["post"].requires_grad and not rec4["displayed"].requires_grad
    _, rec2 = Pipeline([_stage("a")]).run_recorded(img)
    assert rec2["stages_run"] == ["a"] and rec2["diagnostics"] == {}

    physical = Pipeline([_stage("pre", 1.0, factor=0.5), _stage("oled", 40.0, factor=2.0), _stage("optics", 50.0, factor=3.0)]).double()
    image = torch.rand(3, 2, 3, dtype=D)
    eye, rec = physical.run_recorded(image)
    lin = srgb_to_linear(image)
    assert torch.allclose(rec["post"], linear_to_srgb(lin * 0.5), atol=1e-12)
    assert torch.allclose(rec["displayed"], linear_to_srgb(lin * 1.0), atol=1e-12)  # after oled, before optics
    assert torch.allclose(eye, linear_to_srgb(lin * 3.0), atol=1e-12)
    assert rec["stages_run"] == ["pre", "oled", "optics"]


def test_no_ss_baseline_gets_its_native_size_from_the_reference_or_the_argument():
    """An image rendered at the display size passes the resampling untouched and is emitted at the native
    size, taken from the reference or given; the display maps it to the reference's power. The emission
    uses the pixel-centre rule (display pixel floor((i + 0.5) n / S))."""
    p = Pipeline.from_config(["resample"])
    small = torch.rand(3, 4, 4, dtype=D, generator=torch.Generator().manual_seed(1))
    expect = linear_to_srgb(oled_emission(srgb_to_linear(small), (8, 8)))
    assert torch.allclose(p(small, RuntimeState(downsample=2.0), reference=torch.rand(3, 8, 8, dtype=D)), expect, atol=1e-12)
    assert torch.allclose(p(small, RuntimeState(downsample=2.0), native_size=(8, 8)), expect, atol=1e-12)
    assert p.names == ["resample", "oled"]
    image_low = torch.rand(3, 8, 6, dtype=D)  # rendered at camera.scaled(2.5) of 20 x 16
    gt = torch.rand(3, 20, 16, dtype=D)
    q = Pipeline.from_config({"resample": True, "display": True})
    out, inter = q.run_recorded(image_low, RuntimeState(2.5, 0.3), reference=gt)
    want = linear_to_srgb(oled_emission(display_mapping(srgb_to_linear(image_low), 0.3, srgb_to_linear(gt)), (20, 16)))
    assert out.shape == (3, 20, 16) and torch.allclose(out, want, atol=1e-12)
    assert inter["post"].shape == (3, 8, 6)
    img = torch.rand(3, 4, 6, dtype=D)
    out = Pipeline([OLEDEmission()])(img, RuntimeState(downsample=2.0), reference=torch.rand(3, 8, 9, dtype=D))
    assert torch.allclose(out, img[:, [0, 0, 1, 1, 2, 2, 3, 3]][:, :, [0, 1, 1, 2, 3, 3, 4, 5, 5]], atol=1e-12)


@pytest.mark.parametrize("d", [1.0, 2.5])
def test_the_display_reference_is_the_ground_truth_as_displayed(d):
    """P_ref is the power of the ground truth through the stages that ran before the display (here the lens
    with its black corners and the resampling), so a perfect render gets scale 1 - rho at every rho (the
    displayed power is below the ground truth's own); ``p_ref="ground_truth"`` would brighten it."""
    gt = torch.rand(3, 20, 20, dtype=D, generator=torch.Generator().manual_seed(14))
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True}).double()
    grid, _ = pipe["lens"].map((20, 20), D, "cpu")
    shown = area_resample(lens_prewarp(srgb_to_linear(gt), grid, basis="primaries"), d)   # float64 functional reference
    assert float(display_power(shown)) < 0.99 * float(display_power(gt, encoding="srgb"))
    for rho in (0.0, 0.2, 0.4, 0.6, 0.8):
        _, inter = pipe.run_recorded(gt, RuntimeState(d, rho), reference=gt)
        diag = inter["diagnostics"]
        assert float(diag["display.scale"]) == pytest.approx(1.0 - rho, abs=1e-12)
        assert float(diag["display.power_ref"]) == pytest.approx(float(display_power(shown)), rel=1e-12)
        assert float(diag["display.power_target"]) == pytest.approx((1.0 - rho) * float(display_power(shown)), rel=1e-12)
    old = Pipeline.from_config({"lens": True, "resample": True, "display": {"p_ref": "ground_truth"}}).double()
    _, inter = old.run_recorded(gt, RuntimeState(d, 0.0), reference=gt)
    assert float(inter["diagnostics"]["display.scale"]) > 1.02
    rgb = Pipeline.from_config({"lens": {"basis": "rgb"}, "display": True, "oled": False}).double()
    _, rec = rgb.run_recorded(gt, RuntimeState(power_saving=0.0), reference=gt)
    assert float(rec["diagnostics"]["display.power_ref"]) == pytest.approx(
        float(display_power(rgb["lens"](srgb_to_linear(gt)))), rel=1e-12)
    assert float(rec["diagnostics"]["display.scale"]) == pytest.approx(1.0, rel=1e-12)
    with pytest.raises(InputValueError, match="p_ref"):
        Pipeline.from_config({"display": {"p_ref": "gt"}})


def test_call_refusals_name_the_argument():
    p = Pipeline.from_config(ALL)
    with pytest.raises(ShapeError, match="image"):
        p(torch.rand(4, 8, 8), RuntimeState())
    with pytest.raises(InputValueError, match="state must be a RuntimeState, got dict"):
        p(torch.rand(3, 8, 8), {"downsample": 2})  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="image.*non-finite"):
        p(torch.full((3, 8, 8), float("nan")), RuntimeState(2.0))
    bad = torch.rand(3, 4, 4)
    bad[0, 1, 1] = float("nan")
    with pytest.raises(InputValueError, match="reference"):
        p(torch.rand(3, 4, 4), reference=bad)
    other = "cuda" if torch.cuda.is_available() else "meta"  # meta: a second device without a GPU
    with pytest.raises(InputValueError, match="reference="):
        p(torch.rand(3, 8, 8), RuntimeState(2.0, 0.3), reference=torch.rand(3, 8, 8, device=other))
    one = Pipeline([OLEDEmission()])
    img = torch.rand(3, 4, 6, dtype=D)
    for native in ((3, 6), (4, 5)):  # either side smaller than the image
        with pytest.raises(ShapeError, match=r"image \[3, 4, 6\] is larger than the native size"):
            one(img, RuntimeState(downsample=2.0), native_size=native)
    with pytest.raises(ShapeError, match=r"reference must be at native_size \(8, 11\)"):
        one(img, RuntimeState(downsample=2.0), reference=torch.rand(3, 8, 12, dtype=D), native_size=(8, 11))
    with pytest.raises(ShapeError, match="larger"):
        Pipeline.from_config({"resample": True, "display": True})(torch.rand(3, 30, 30), RuntimeState(2.0),
                                                                  reference=torch.rand(3, 20, 16))
    plain = torch.rand(3, 4, 4)
    assert torch.allclose(Pipeline([_stage("a")])(plain, None, reference=torch.rand(3, 4, 4)), plain, atol=1e-6)  # decode + encode


def test_functionals_pass_non_finite_values_through_unchecked():
    """The pipeline checks its input once; the stages' functionals accept any value."""
    x = torch.full((3, 2, 2), 0.5, dtype=D)
    x[0, 0, 0] = float("nan")
    ident = pixel_grid((2, 2), D)[None].expand(3, -1, -1, -1).contiguous()
    for f in (srgb_to_linear, linear_to_srgb, rgb_to_primaries, primaries_to_rgb,
              lambda t: oled_emission(t, (4, 4)), lambda t: area_resample(t, 2.0), lambda t: lens_prewarp(t, ident),
              lambda t: display_power(t)[None, None, None].expand(3, 1, 1), lambda t: display_mapping(t, 0.5)):
        assert bool(torch.isnan(f(x)).any())
    assert bool(torch.isnan(display_mapping(torch.full((3, 1, 1), 0.5, dtype=D), 0.5, x)).all())  # a NaN reference power


# ----------------------------------------------------------------------------- gradients
@settings(max_examples=15, deadline=None)
@given(st.floats(1.0, 8.0), st.floats(0.0, 0.999), st.sampled_from(["black", "no_blue", "random"]))
def test_no_nan_in_value_or_gradient(d, rho, kind):
    image = torch.rand(3, 16, 16, dtype=D)
    if kind == "black":
        image.zero_()
    elif kind == "no_blue":
        image[2] = 0
    image.requires_grad_(True)
    gt = torch.rand(3, 16, 16, dtype=D) if kind != "black" else torch.zeros(3, 16, 16, dtype=D)
    out = Pipeline.from_config(ALL).double()(image, RuntimeState(d, rho), reference=gt)
    (grad,) = torch.autograd.grad(out.sum(), image)
    assert torch.isfinite(out).all() and torch.isfinite(grad).all()


@pytest.mark.parametrize("lens, states", [({"coefficients": K}, [RuntimeState(2.0, 0.3), RuntimeState(1.5, 0.0)]),
                                          (True, [RuntimeState(2.0, 0.3), RuntimeState(1.0, 0.0)])])
def test_gradcheck_pipeline(lens, states):
    """Through the lens (given coefficients or the default), resampling and the display with the ground truth
    as displayed, with and without power saving."""
    image = (torch.rand(3, 8, 8, dtype=D) * 0.6 + 0.2).requires_grad_(True)
    gt = torch.rand(3, 8, 8, dtype=D) * 0.5
    p = Pipeline.from_config({**ALL, "lens": lens}).double()
    for state in states:
        assert torch.autograd.gradcheck(lambda x: p(x, state, reference=gt), (image,))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: pipeline on CUDA vs CPU not run")
def test_pipeline_on_cuda_matches_cpu():
    image, gt = torch.rand(3, 32, 32, dtype=D), torch.rand(3, 32, 32, dtype=D)
    p = Pipeline.from_config(ALL).double()
    cpu = p(image, RuntimeState(2.5, 0.4), reference=gt)
    gpu = p.cuda()(image.cuda(), RuntimeState(2.5, 0.4), reference=gt.cuda())
    assert torch.allclose(gpu.cpu(), cpu, atol=1e-10)


# ----------------------------------------------------------------------------- with the optics
def test_pipeline_with_the_optics_stage():
    """The optics run last, after the display emission: the eye is the optics of the displayed image, and
    differs from it; a batch keeps its shape."""
    p = Pipeline.from_config({**ALL, "optics": {"mode": "distortion"}})
    assert p.names[-2:] == ["oled", "optics"]
    image, gt = torch.rand(3, 32, 32), torch.rand(3, 32, 32)
    eye, inter = p.run_recorded(image, RuntimeState(2.0, 0.3), reference=gt)
    displayed = srgb_to_linear(inter["displayed"])
    assert torch.allclose(eye, linear_to_srgb(psf_optics(displayed, p["optics"].bank, mode="distortion")), atol=1e-5)
    assert inter["stages_run"] == ["lens", "resample", "display", "oled", "optics"]
    assert not torch.allclose(inter["displayed"], eye, atol=1e-3)
    only = Pipeline.from_config({"optics": {"mode": "distortion"}})
    batch = torch.rand(1, 3, 32, 32)
    out = only(batch, RuntimeState())
    assert out.shape == batch.shape and torch.isfinite(out).all()


def test_flat_field_through_the_pipeline_is_smooth_for_16_9():
    """Lens pre-warp + exact PSF optics on a flat 16:9 field: finite, symmetric, and no rougher than
    the same display band of a square image (the shading is the lens's smooth fall-off: its second
    difference is the square image's to 1e-12, no seam)."""
    p = Pipeline.from_config({"lens": True, "optics": {"mode": "exact"}}).double()
    eye = p(torch.full((3, 54, 96), 0.5, dtype=D), RuntimeState())
    square = p(torch.full((3, 96, 96), 0.5, dtype=D), RuntimeState())
    assert torch.isfinite(eye).all()

    def rough(img: torch.Tensor, m: int = 6) -> float:
        inner = img[:, m:-m, m:-m]
        d2x = (inner[..., 2:] - 2 * inner[..., 1:-1] + inner[..., :-2]).abs().max()
        d2y = (inner[:, 2:] - 2 * inner[:, 1:-1] + inner[:, :-2]).abs().max()
        return float(max(d2x, d2y))

    assert rough(eye) <= rough(square) + 1e-12 and rough(eye) < 7e-3
    assert torch.allclose(eye, eye.flip(-1), atol=1e-5) and torch.allclose(eye, eye.flip(-2), atol=1e-5)
    assert torch.allclose(eye[:, 27], square[:, 48], atol=1e-3)     # the display's horizontal axis


def _patch(x: torch.Tensor, u: float, v: float, r: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    i, j = int((v + 1) / 2 * h), int((u + 1) / 2 * w)
    return x[..., i - r:i + r, j - r:j + r].mean()


@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_ground_truth_through_the_default_pipeline_comes_back_within_three_percent(mode):
    """A flat and a smooth ground truth through lens, resampling, display and optics (d = 1, rho = 0): in the
    centre and towards every corner the eye's linear light is the ground truth's within 3 %."""
    h = 96
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h, dtype=D), torch.linspace(-1, 1, h, dtype=D), indexing="ij")
    smooth = torch.stack([0.5 + 0.2 * torch.cos(2 * xx + yy), 0.45 + 0.2 * torch.sin(xx - 2 * yy), 0.4 + 0.1 * xx * yy])
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True, "optics": {"mode": mode}}).double()
    for gt in (torch.full((3, h, h), 0.6, dtype=D), smooth):
        eye = srgb_to_linear(pipe(gt, RuntimeState(), reference=gt))
        ref = srgb_to_linear(gt)
        for u, v in ((0.0, 0.0), (0.8, 0.8), (-0.8, -0.8), (0.8, -0.8), (-0.8, 0.8)):
            ratio = float(_patch(eye, u, v, 3) / _patch(ref, u, v, 3))
            assert abs(ratio - 1.0) < 0.03, (u, v, ratio)
