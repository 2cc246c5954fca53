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
    # the intermediates are detached copies; the eye keeps its graph
    eye3, rec3 = p.run_recorded(img.clone().requires_grad_(True), RuntimeState(downsample=2.0, power_saving=0.5))
    assert eye3.requires_grad
    assert not any(rec3[k].requires_grad for k in ("rendered", "post", "displayed", "eye"))
    _, rec4 = Pipeline([_Scale()]).run_recorded(img.clone().requires_grad_(True))  # no physical stage
    assert not rec4["post"].requires_grad and not rec4["displayed"].requires_grad
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


# ---------------------------------------------------------------- the pre-warp fit


def test_fit_bank_prewarp_refusals_name_the_argument():
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    with pytest.raises(InputValueError, match="optics must be an optics stage or a PSFBank, got Identity"):
        fit_bank_prewarp(torch.nn.Identity())
    if "optics" not in plugins.stages():
        return
    from controlgs_adapter.downstream.optics.stage import PSFOptics

    optics = PSFOptics()
    for size in (7, 8.0, "16"):
        with pytest.raises(InputValueError, match="size must be an int >= 8"):
            fit_bank_prewarp(optics, size)  # type: ignore[arg-type]
    for size, pool in [(16, 0), (16, 3), (8, 4), (16, 2.0)]:  # 8 / 4 = 2 samples < 4
        with pytest.raises(InputValueError, match="pool must be an int >= 1 dividing size into >= 4 samples"):
            fit_bank_prewarp(optics, size, pool=pool)  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="modes must be a non-empty subset"):
        fit_bank_prewarp(optics, 16, modes=())
    from controlgs_adapter.downstream.optics.bank import PSFBank

    for bank in (PSFBank.default(), None):  # a bank or None is made an optics stage first
        with pytest.raises(InputValueError, match="size must be an int >= 8"):
            fit_bank_prewarp(bank, 7)


def _fill_by_hand() -> tuple[torch.Tensor, torch.Tensor, list[list[float]]]:
    # 3 x 3, valid (0, 0) = 1 and (0, 2) = 3. Round 1 (3 x 3 means of valid neighbours): (0, 1) = 2,
    # (1, 0) = 1, (1, 1) = 2, (1, 2) = 3; round 2: (2, 0) = (1 + 2) / 2, (2, 1) = (1 + 2 + 3) / 3, (2, 2) = 2.5
    values = torch.zeros(1, 3, 3, 1, dtype=D)
    values[0, 0, 0, 0], values[0, 0, 2, 0] = 1.0, 3.0
    values[0, 1, 1, 0] = 99.0  # an invalid pixel's value is never used
    valid = torch.zeros(1, 3, 3, dtype=torch.bool)
    valid[0, 0, 0] = valid[0, 0, 2] = True
    return values, valid, [[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.5, 2.0, 2.5]]


def test_fill_invalid_by_hand_and_nothing_measured():
    from controlgs_adapter.downstream.prewarp_fit import _fill_invalid

    values, valid, expect = _fill_by_hand()
    flat = [v for row in expect for v in row]
    assert _fill_invalid(values, valid)[0, ..., 0].flatten().tolist() == pytest.approx(flat)
    # two channels x two components are filled independently
    both = torch.cat([values, -values], dim=-1).expand(2, 3, 3, 2)
    out = _fill_invalid(both, valid.expand(2, 3, 3))
    assert out[1, ..., 1].flatten().tolist() == pytest.approx([-v for v in flat])
    with pytest.raises(InputValueError, match="no display pixel could be measured"):
        _fill_invalid(values, torch.zeros_like(valid))


@needs_optics
def test_psf_centroids_are_the_bilinear_first_moments_of_the_field_psfs():
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.prewarp_fit import _psf_centroids

    bank = PSFBank.default()
    k = bank.psf.shape[-1]

    def moment(l_: int, gy: int, gx: int) -> tuple[float, float]:  # brute force, float64
        psf = bank.psf[l_, gy, gx].double()
        taps = torch.arange(k, dtype=D) - k // 2
        pitch = float(bank.psf_pitch_mm[l_, gy, gx])
        return (float((psf * taps[None, :]).sum()) * pitch / (bank.display_mm[0] / 2),
                float((psf * taps[:, None]).sum()) * pitch / (bank.display_mm[1] / 2))

    fx, fy = bank.field_x.double(), bank.field_y.double()
    pts = torch.tensor([[[float(fx[3]), float(fy[5])],                                       # a field sample
                         [0.5 * float(fx[7] + fx[8]), 0.5 * float(fy[10] + fy[11])],          # a cell centre
                         [1.5, -1.5]]], dtype=D)                                              # beyond: clamped
    c = _psf_centroids(bank, pts, D)
    assert c.shape == (3, 1, 3, 2)
    for l_ in range(3):
        assert c[l_, 0, 0].tolist() == pytest.approx(moment(l_, 5, 3), abs=1e-9)
        corners = [moment(l_, gy, gx) for gy in (10, 11) for gx in (7, 8)]
        assert c[l_, 0, 1].tolist() == pytest.approx([sum(v[i] for v in corners) / 4 for i in range(2)], abs=1e-9)
        assert c[l_, 0, 2].tolist() == pytest.approx(moment(l_, 0, len(fx) - 1), abs=1e-9)
    assert float(c.abs().max()) > 1e-4  # the moments are not all zero (coma off axis)


@needs_optics
def test_exact_mode_fit_measures_centroids_and_flattens_by_brute_force():
    from controlgs_adapter.downstream.color import primaries_to_rgb_matrix, rgb_to_primaries_matrix
    from controlgs_adapter.downstream.lens import pixel_grid
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.stage import StageContext

    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    bank = PSFBank.default()
    # energy radiometry: the lens's brightness fall-off needs a gain; its mode is replaced by "exact"
    stage = PSFOptics(bank, mode="distortion", radiometry="energy")
    lut = fit_bank_prewarp(stage, 8, modes=("exact",))  # defaults: pool 2, 4 gain iterations
    assert lut.modes == ("exact",) and lut.placement == "fit" and stage.mode == "distortion"
    assert (lut.meta["size"], lut.meta["pool"], lut.meta["gain_iterations"]) == ([8, 8], 2, 4)
    assert lut.meta["radiometry"] == "energy" and set(lut.meta["residuals"]) == {"exact"}
    # measured: the 6 x 6 inner pixels whose light stays inside the frame (36 / 64, a regression pin);
    # the fixed point takes the 7 % fall-off to below 0.2 % at the centroids in 4 iterations
    assert lut.meta["residuals"]["exact"]["measured_fraction"] == 0.5625
    assert lut.meta["residuals"]["exact"]["flat_max_abs"] < 2e-3
    assert 0.0 <= lut.meta["seconds"] < 600.0
    disp, gain = lut.displacement_exact.double(), lut.gain_exact.double()
    assert disp.shape == (3, 4, 4, 2) and gain.shape == (3, 4, 4)
    # brute force: the eye image of every single lit display pixel (one primary at a time)
    optics = PSFOptics(bank, mode="exact", placement="stretch", radiometry="energy").double()
    to_p, to_rgb = rgb_to_primaries_matrix(), primaries_to_rgb_matrix()

    def op(s: torch.Tensor) -> torch.Tensor:  # primaries [B, 3, 8, 8] -> primaries
        out = optics(torch.einsum("ij,bjhw->bihw", to_rgb, s), RuntimeState(), StageContext((8, 8)))
        return torch.einsum("ij,bjhw->bihw", to_p, out)

    p = pixel_grid((8, 8), D)
    ones = torch.eye(3 * 64, dtype=D).reshape(3 * 64, 3, 8, 8)
    eye = op(ones).reshape(3, 8, 8, 3, 8, 8)  # [lit primary, lit y, lit x, eye primary, y, x]
    light = eye.sum(dim=(3, 4, 5))
    cx = (eye.sum(3) * p[..., 0]).sum(dim=(3, 4)) / light
    cy = (eye.sum(3) * p[..., 1]).sum(dim=(3, 4)) / light
    centroid_disp = torch.stack([cx, cy], -1) - p  # [3, 8, 8, 2]
    pooled = centroid_disp.reshape(3, 4, 2, 4, 2, 2).mean(dim=(2, 4))
    # the central 2 x 2 cells (pixels 2..5) are measured: the table holds the centroids there
    assert torch.allclose(disp[:, 1:3, 1:3], pooled[:, 1:3, 1:3], atol=1e-5)
    # the gain brings a flat field back to flat at the centre: within 3.5 % (pooled 2 x 2 at 8 px)
    # where the uncorrected energy fall-off reaches 7 %
    flat = op(lut((8, 8), D, "cpu")[1][None])[0]
    assert float((flat[:, 2:6, 2:6] - 1.0).abs().max()) < 0.035
    assert float((op(torch.ones(1, 3, 8, 8, dtype=D))[0, :, 2:6, 2:6] - 1.0).abs().max()) > 0.06
    assert float(gain.min()) > 1.0  # brightens everywhere against the fall-off


class _Lens(Stage):
    name, domain, order = "lens", "linear", 10.0

    def __init__(self) -> None:
        super().__init__()
        self.offset = torch.nn.Parameter(torch.zeros(3, dtype=D))

    def process(self, image, state, ctx):
        return image + self.offset[:, None, None]


def test_fit_prewarp_loss_and_learning_rate_defaults():
    from controlgs_adapter.metrics import ssim
    from controlgs_adapter.downstream.prewarp_fit import fit_prewarp

    g = torch.Generator().manual_seed(5)
    images = torch.rand(1, 3, 16, 16, generator=g, dtype=D) * 0.5 + 0.25
    targets = (images + 0.1 * torch.rand(1, 3, 16, 16, generator=g, dtype=D)).clamp(0, 1)
    pipe = Pipeline([_Lens()]).eval()
    losses = fit_prewarp(pipe, images, targets, steps=1)
    # the paper's 3DGS loss 0.8 L1 + 0.2 (1 - SSIM), no MSE; the lens is the identity at step 1
    l1 = float((images[0] - targets[0]).abs().mean())
    expect = 0.8 * l1 + 0.2 * (1.0 - float(ssim(images[0], targets[0], data_range=1.0).mean()))
    assert losses == [pytest.approx(expect, rel=1e-6)]
    # Adam's first step moves every parameter with a gradient by lr = 1e-3
    assert pipe["lens"].offset.abs().tolist() == pytest.approx([1e-3] * 3, rel=1e-4)
    assert not pipe.training  # the caller's mode comes back
    fast = Pipeline([_Lens()])
    fit_prewarp(fast, images, targets, steps=1, lr=0.02)
    assert fast["lens"].offset.abs().tolist() == pytest.approx([0.02] * 3, rel=1e-4)
    assert fast.training
    assert len(fit_prewarp(pipe, images, steps=3, lr=1e-2)) == 3
    for kwargs in ({"lr": 0.0}, {"lr": -1.0}, {"steps": 0}):
        with pytest.raises(InputValueError, match="steps must be >= 1 and lr > 0"):
            fit_prewarp(pipe, images, **kwargs)
    with pytest.raises(InputValueError, match="targets must have dtype"):
        fit_prewarp(pipe, images, targets.float(), steps=1)


class _WideOnly(Stage):
    """Runs only for a native size wider than 10 pixels (a stage whose cost depends on the size)."""

    name = "wide"

    def is_identity(self, state, ctx=None):
        return ctx is None or ctx.native_size[1] <= 10

    def process(self, image, state, ctx):
        return image


def test_active_passes_the_native_size_to_the_stages():
    p = Pipeline([_WideOnly()])
    assert p.active(RuntimeState(), reference=torch.rand(3, 4, 20)) == ["wide"]
    assert p.active(RuntimeState(), reference=torch.rand(3, 20, 4)) == []
    assert p.active(RuntimeState(), native_size=(4, 11)) == ["wide"]
    assert p.active(RuntimeState(), reference=torch.rand(3, 4, 20), native_size=(20, 4)) == []
    assert p.active(RuntimeState()) == []  # no size known: (0, 0)


@needs_optics
def test_reach_of_a_display_pixels_light_by_hand():
    from controlgs_adapter.downstream.lens import pixel_grid
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.prewarp_fit import _reach

    bank = PSFBank.default()
    assert bank.psf.shape[-1] == 33 and bank.display_mm == (24.0, 24.0) and bank.field_x.numel() == 30
    # the 30 field samples sit at the pixel centres of a 30-pixel grid: the pitch there is the bank's own;
    # 1.5 x the half-window 33 // 2 + 0.5 = 16.5 samples, over the 12 mm half display
    p = pixel_grid((30, 30), D)
    reach = _reach("exact", bank, p, D)
    # (rtol: the field coordinates are stored in float32, so the samples sit 1e-8 off the pixel centres)
    assert torch.allclose(reach, 1.5 * bank.psf_pitch_mm.double() * 16.5 / 12.0, rtol=1e-5)
    # distortion mode: 3 / min(H, W) = 3 / 30 everywhere
    dist = _reach("distortion", bank, pixel_grid((30, 40), D), D)
    assert dist.shape == (3, 30, 40) and float(dist.min()) == float(dist.max()) == 0.1
