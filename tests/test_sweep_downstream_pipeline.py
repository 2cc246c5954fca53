"""Mutation-sweep tests of the downstream pipeline (stage placement, ``from_config`` branches, the
call's checks and recorded intermediates) and of the pre-warp fit (refusals, defaults, the PSF
centroids and the fill of unmeasured pixels), against values worked out by hand or by brute force."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter import plugins
from controlgs_adapter.downstream.color import linear_to_srgb, srgb_to_linear
from controlgs_adapter.downstream.display import display_power
from controlgs_adapter.downstream.lens import BankMap, DisplayLUTMap, LensPrewarp, RadialMap
from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.downstream.stage import Stage
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import RuntimeState

D = torch.float64
needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


def _mk(name: str, order: float = 100.0, after: str | None = None, before: str | None = None) -> Stage:
    return type(name.title(), (Stage,), {"name": name, "order": order, "after": after, "before": before,
                                         "process": lambda self, i, s, c: i})()


# ---------------------------------------------------------------- placement of stages


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


# ---------------------------------------------------------------- from_config


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


# ---------------------------------------------------------------- the call


class _Scale(Stage):
    name, domain, order = "scale", "linear", 15.0

    def process(self, image, state, ctx):
        return image * 0.5


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
    _, rec2 = Pipeline([_mk("a")]).run_recorded(img)
    assert rec2["stages_run"] == ["a"] and rec2["diagnostics"] == {}


def test_the_display_reference_is_the_ground_truth_through_the_stages_that_ran():
    # lens (analytic radial map, black corners) + display with p_ref="displayed": P_ref is the power of
    # the warped linear ground truth, not of the ground truth itself
    p = Pipeline.from_config({"lens": {"basis": "rgb"}, "display": True, "oled": False}).double()
    gt = torch.rand(3, 8, 8, dtype=D, generator=torch.Generator().manual_seed(2)) * 0.5 + 0.25
    _, rec = p.run_recorded(gt, RuntimeState(power_saving=0.0), reference=gt)
    warped = p["lens"](srgb_to_linear(gt))
    assert float(rec["diagnostics"]["display.power_ref"]) == pytest.approx(float(display_power(warped)), rel=1e-12)
    assert float(display_power(warped)) < 0.99 * float(display_power(gt, encoding="srgb"))
    assert float(rec["diagnostics"]["display.scale"]) == pytest.approx(1.0, rel=1e-12)  # a perfect render
    # resampling before the display: P_ref of the area-averaged warped ground truth
    q = Pipeline.from_config({"lens": {"basis": "rgb"}, "resample": True, "display": True}).double()
    _, rec2 = q.run_recorded(gt, RuntimeState(downsample=2.0, power_saving=0.2), reference=gt)
    ref2 = display_power(area_resample(q["lens"](srgb_to_linear(gt)), 2.0))
    assert float(rec2["diagnostics"]["display.power_ref"]) == pytest.approx(float(ref2), rel=1e-12)
    assert float(rec2["diagnostics"]["display.power_target"]) == pytest.approx(0.8 * float(ref2), rel=1e-12)
