"""Tests of ``controlgs_adapter.downstream.display``: the OLED power model (worked-out values and a pixel
loop), uniform dimming to a power target with clipping (worked-out values, brute force, the stats it reports),
its conventions at rho = 0 and for black images, its gradients (through the image's power only), the
stage's reference power and records, and the refusals. The stage contract is checked in
``test_stage_contract.py``."""

from __future__ import annotations

import re

import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.color import srgb_to_linear
from controlgs_adapter.downstream.display import (
    PANEL_COEFFICIENTS,
    WATTS_PER_UNIT,
    DisplayMapping,
    display_mapping,
    display_mapping_with_stats,
    display_power,
    display_power_watts,
)
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError, StateError, StateRangeError

D = torch.float64
WHITE = 228.52 + 205.66 + 567.64  # 1001.82
MID_GREY = 0.21404114             # sRGB 0.5 in linear light: ((0.5 + 0.055) / 1.055) ** 2.4


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


def _power_loop(img: torch.Tensor, coeffs=PANEL_COEFFICIENTS) -> float:
    """Explicit loop over the pixels of a [3, H, W] image: mean of alpha R + beta G + gamma B, negatives
    emitting nothing."""
    a, b, c = coeffs
    _, h, w = img.shape
    total = 0.0
    for i in range(h):
        for j in range(w):
            r, g, bl = (max(0.0, float(v)) for v in img[:, i, j])
            total += a * r + b * g + c * bl
    return total / (h * w)


# ----------------------------------------------------------------------------- the power model
def test_display_power_literal_values_and_units():
    """P = mean(alpha R + beta G + gamma B) on linear RGB with (228.52, 205.66, 567.64): white 1001.82,
    3.00546 W (PowerGS: 3 / 1000 W per unit); each channel alone; negatives emit nothing; sRGB input is
    decoded first; other (or zero) coefficients; one value per image of a batch."""
    white = _img([1.0, 1.0, 1.0], 2, 2)
    assert float(display_power(white)) == pytest.approx(WHITE, abs=1e-9)
    assert float(display_power_watts(white)) == pytest.approx(3.00546, abs=1e-12) and WATTS_PER_UNIT == 3e-3
    for channel, alpha in enumerate(PANEL_COEFFICIENTS):
        img = torch.zeros(3, 4, 6, dtype=D)
        img[channel, :2] = 0.5  # half the pixels at 0.5: mean 0.25
        assert float(display_power(img)) == pytest.approx(alpha * 0.25, rel=1e-12)
        assert float(display_power_watts(img)) == pytest.approx(alpha * 0.25 * 3e-3, rel=1e-12)
        srgb = torch.zeros(3, 2, 2, dtype=D)
        srgb[channel] = 0.5
        assert float(display_power(srgb, encoding="srgb")) == pytest.approx(alpha * ((0.555 / 1.055) ** 2.4), rel=1e-9)
    assert float(display_power(_img([0.5, -1.0, 0.25], 2, 2))) == pytest.approx(114.26 + 141.91, abs=1e-9)
    half = _img([0.0, 1.0, 0.0], 2, 2)
    half[1, 0, :] = 0.0  # half of the pixels green at 1 -> 205.66 / 2
    assert float(display_power(half)) == pytest.approx(102.83, abs=1e-9)
    assert float(display_power(_img([0.5, 0.5, 0.5]), encoding="srgb")) == pytest.approx(MID_GREY * WHITE, rel=1e-7)
    watts = display_power_watts(_img([0.5, 0.5, 0.5]), encoding="srgb")
    assert float(watts) == pytest.approx(MID_GREY * WHITE * 0.003, rel=1e-7)
    assert float(display_power(_img([1.0, 1.0, 1.0]), (1.0, 2.0, 3.0))) == pytest.approx(6.0)
    assert float(display_power(_img([1.0, 1.0, 1.0]), (0.0, 0.0, 2.0))) == pytest.approx(2.0)  # a zero coefficient
    batch = torch.stack([_img([1.0, 0.0, 0.0]), _img([0.0, 0.0, 1.0])])
    assert display_power(batch).tolist() == pytest.approx([228.52, 567.64])


def test_display_power_matches_a_pixel_loop():
    img = torch.rand(3, 5, 6, dtype=D) * 1.2 - 0.1
    for coeffs in (PANEL_COEFFICIENTS, (1.0, 0.0, 0.0), (0.5, 2.0, 1.0)):
        assert float(display_power(img, coeffs)) == pytest.approx(_power_loop(img, coeffs), rel=1e-12)
    srgb = torch.rand(2, 3, 4, 4, dtype=D)
    assert torch.allclose(display_power(srgb, encoding="srgb"), display_power(srgb_to_linear(srgb)))


# ----------------------------------------------------------------------------- the mapping
@pytest.mark.parametrize("brighten", [True, False])
@pytest.mark.parametrize("rho", [0.0, 0.3])
def test_display_mapping_with_other_coefficients_and_a_smaller_reference(brighten, rho):
    """Panel coefficients (0.5, 2, 1), a 2 x 3 reference for a 4 x 5 image: scale = (1 - rho) P(ref) /
    P(image) (at most 1 without brighten), output clipped to [0, 1]; the stats hold the scale, the target,
    the output's power and the fraction of values clipped."""
    w = (0.5, 2.0, 1.0)
    g = torch.Generator().manual_seed(4)
    image = torch.rand(3, 4, 5, generator=g, dtype=D) * 1.2 - 0.1  # some values < 0 and > 1
    ref = torch.rand(3, 2, 3, generator=g, dtype=D) * 1.6  # brighter than the image: brighten decides
    target = (1 - rho) * _power_loop(ref, w)
    scale = target / _power_loop(image, w)
    assert scale > 1.0
    if not brighten:
        scale = min(scale, 1.0)
    dimmed = image * scale
    want = dimmed.clamp(0, 1)
    out, stats = display_mapping_with_stats(image, rho, ref, coefficients=w, brighten=brighten)
    torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    assert float(stats["scale"]) == pytest.approx(scale, rel=1e-12)
    assert float(stats["power_target"]) == pytest.approx(target, rel=1e-12)
    assert float(stats["power"]) == pytest.approx(_power_loop(want, w), rel=1e-12)
    n_clipped = sum(1 for v in dimmed.flatten().tolist() if v < 0 or v > 1)
    assert float(stats["clipped_fraction"]) == pytest.approx(n_clipped / dimmed.numel(), rel=1e-12)


def test_mapping_to_a_reference_power():
    """Image power 0.5 * 1001.82; reference_power 300 at rho 0.25 -> target 225, scale 225 / 500.91. A white
    reference at rho 0.5 -> target 500.91 = the image's power: scale 1; at rho 0 the image doubles and clips,
    unless brighten=False caps the scale at 1 (a dim image against a bright reference is left as it is). A
    reference power given as a tensor or a number equals the reference it comes from."""
    img = _img([0.5, 0.5, 0.5], 2, 2)
    out, stats = display_mapping_with_stats(img, 0.25, reference_power=300.0)
    scale = 225.0 / (0.5 * WHITE)
    assert float(stats["scale"]) == pytest.approx(scale)
    assert float(stats["power_target"]) == pytest.approx(225.0) and float(stats["power"]) == pytest.approx(225.0)
    assert out.flatten()[0].item() == pytest.approx(0.5 * scale)
    ref = _img([1.0, 1.0, 1.0], 4, 4)
    out2, stats2 = display_mapping_with_stats(img, 0.5, ref)
    assert float(stats2["scale"]) == pytest.approx(1.0) and torch.allclose(out2, img)
    out3, stats3 = display_mapping_with_stats(img, 0.0, ref, brighten=False)
    assert float(stats3["scale"]) == 1.0 and torch.equal(out3, img)
    out4, stats4 = display_mapping_with_stats(img, 0.0, ref)
    assert float(stats4["scale"]) == pytest.approx(2.0) and float(out4.max()) == 1.0
    assert torch.equal(display_mapping(img, 0.0, ref), out4)  # brightens by default too
    assert torch.equal(display_mapping(img, 0.0, ref, brighten=False), img)
    dim = torch.rand(3, 4, 4) * 0.1
    assert torch.equal(display_mapping(dim, 0.2, torch.ones(3, 4, 4), brighten=False), dim)
    assert not torch.equal(display_mapping(dim, 0.2, torch.ones(3, 4, 4)), dim)
    x = torch.rand(2, 3, 4, 4, dtype=D) * 0.3
    gt = torch.rand(3, 8, 8, dtype=D)
    p_ref = display_power(gt)
    assert torch.equal(display_mapping(x, 0.3, reference_power=p_ref), display_mapping(x, 0.3, gt))
    assert torch.allclose(display_mapping(x, 0.3, reference_power=float(p_ref)), display_mapping(x, 0.3, gt))


def test_rho_zero_and_no_reference_conventions():
    """Without a reference P_ref = P(image): the image is scaled by 1 - rho (0.99 gives 0.005), and at rho = 0
    it is returned itself, not clipped, with unit stats (detached). With a reference, rho = 0 still maps the
    image to P_ref (continuous in rho: the same as a tiny rho)."""
    img = _img([2.0, 0.5, -0.5], 2, 2)  # out of range: not clipped at rho = 0 without a reference
    out, stats = display_mapping_with_stats(img, 0.0)
    assert out is img and display_mapping(img, 0.0) is img
    p = 2.0 * 228.52 + 0.5 * 205.66
    assert float(stats["scale"]) == 1.0 and float(stats["clipped_fraction"]) == 0.0
    assert float(stats["power"]) == pytest.approx(p) and float(stats["power_target"]) == pytest.approx(p)
    x = torch.full((3, 2, 2), 0.5, dtype=D, requires_grad=True)
    out, stats = display_mapping_with_stats(x, 0.0)
    assert out is x and not any(v.requires_grad for v in stats.values())
    assert float(stats["power"]) == pytest.approx(0.5 * WHITE)
    assert display_mapping(_img([0.5, 0.5, 0.5]), 0.99).flatten().tolist() == pytest.approx([0.005] * 3)
    img = torch.rand(3, 4, 4, dtype=D) * 0.5
    assert torch.allclose(display_mapping(img, 0.3), img * 0.7)
    img = torch.rand(3, 4, 4, dtype=D) * 0.3
    ref = torch.rand(3, 6, 6, dtype=D) * 0.5
    out = display_mapping(img, 0.0, ref)
    assert torch.allclose(out, display_mapping(img, 1e-12, ref), atol=1e-9)
    assert torch.allclose(display_power(out), display_power(ref), rtol=1e-9)


@settings(max_examples=30, deadline=None)
@given(
    st.floats(1e-6, 0.99), st.floats(0.05, 1.0), st.floats(0.05, 1.0), st.integers(0, 2**31 - 1),
    st.sampled_from([torch.float32, torch.float64]),
)
def test_power_after_dimming_equals_target(rho, img_level, ref_level, seed, dtype):
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(2, 3, 6, 5, generator=g, dtype=dtype) * img_level
    ref = torch.rand(3, 9, 8, generator=g, dtype=dtype) * ref_level  # at S, image at S/d: mean power compares
    out, stats = display_mapping_with_stats(img, rho, ref)
    assume(bool((stats["clipped_fraction"] == 0).all()))
    target = (1 - rho) * display_power(ref)
    assert torch.allclose(display_power(out), target.expand(2), rtol=1e-5, atol=0)
    assert torch.allclose(stats["power"], stats["power_target"], rtol=1e-5, atol=0)


def test_clipped_fraction_counts_values_outside_the_display_range_per_image():
    """Values below 0 or above 1 after scaling are clipped and counted (exact 0 and 1 are not), one fraction
    per image of a batch; the reported power is the clipped output's, below the target."""
    x = torch.zeros(3, 2, 2, dtype=D)
    x[:, 0] = 1.0
    out, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert float(stats["scale"]) == 1.0 and torch.equal(out, x) and float(stats["clipped_fraction"]) == 0.0
    img = _img([0.5, 0.5, 0.5], 2, 2)
    img[0, 0, 0] = -0.2  # 1 of 12 values negative
    img[2, 1, 1] = 3.0  # 1 of 12 values above 1 at scale 1
    out, stats = display_mapping_with_stats(img, 0.0, reference_power=float(display_power(img)))
    assert float(stats["clipped_fraction"]) == pytest.approx(2 / 12)
    assert float(out.min()) == 0.0 and float(out.max()) == 1.0
    assert float(stats["power"]) == pytest.approx(float(display_power(out)))
    assert float(stats["power"]) < float(stats["power_target"])
    img = torch.full((3, 4, 4), 0.25, dtype=D)
    img[:, 0, 0] = 0.9
    out, stats = display_mapping_with_stats(img, 0.1, torch.full((3, 4, 4), 0.8, dtype=D))
    assert float(stats["scale"]) > 1.0 / 0.9  # brightened so that the 0.9 pixel clips
    assert float(out.max()) == 1.0 and float(stats["clipped_fraction"]) == pytest.approx(3 / 48)
    assert float(stats["power"]) < float(stats["power_target"])
    batch = torch.full((2, 3, 2, 2), 0.5, dtype=D)
    batch[0, 0, 0, 0] = 1.5
    _, stats = display_mapping_with_stats(batch, 0.0, reference_power=display_power(batch))
    assert stats["clipped_fraction"].tolist() == [pytest.approx(1 / 12), 0.0]


def test_black_images_are_not_scaled():
    """An image of power at most 1e-12 is black: scale 1 (1.5e-12 is scaled; exactly 1e-12 is black)."""
    _, stats = display_mapping_with_stats(torch.zeros(3, 2, 2), 0.5, torch.rand(3, 2, 2))
    assert float(stats["scale"]) == 1.0
    for p, black in [(0.5e-12, True), (1.5e-12, False)]:
        _, stats = display_mapping_with_stats(_img([p / WHITE] * 3), 0.0, reference_power=1.0)
        assert (float(stats["scale"]) == 1.0) is black
    _, at = display_mapping_with_stats(_img([1e-12, 0.0, 0.0]), 0.0, reference_power=1.0, coefficients=(1.0, 0.0, 0.0))
    assert float(at["power"]) == 1e-12 and float(at["scale"]) == 1.0


@settings(max_examples=20, deadline=None)
@given(st.floats(0.0, 0.999999), st.sampled_from(["black", "no_blue", "negative"]))
def test_degenerate_images_have_no_nan(rho, kind):
    img = torch.rand(3, 4, 4, dtype=D)
    if kind == "black":
        img = torch.zeros(3, 4, 4, dtype=D)
    elif kind == "no_blue":
        img[2] = 0
    else:
        img = -img
    img.requires_grad_(True)
    for ref in (None, torch.zeros(3, 4, 4, dtype=D), torch.rand(3, 4, 4, dtype=D)):
        out = display_mapping(img, rho, ref)
        (grad,) = torch.autograd.grad(out.sum(), img)
        assert torch.isfinite(out).all() and torch.isfinite(grad).all()
        if kind == "black":
            assert torch.equal(out, img.detach())  # zero power: nothing to scale


# ----------------------------------------------------------------------------- gradients
def _analytic_dimming_gradient(x: torch.Tensor, target: float, w=PANEL_COEFFICIENTS) -> torch.Tensor:
    """d/dx of sum(x * target / P(x)) written out, for x > 0 with nothing clipped: P(x) = sum_c w_c mean(x_c),
    so d/dx_j = target / P - target * sum(x) / P^2 * w_c(j) / (H W)."""
    w = torch.tensor(w, dtype=D)
    hw = x.shape[-1] * x.shape[-2]
    p = float((x.mean(dim=(-2, -1)) * w).sum())
    return target / p - target * float(x.sum()) / p**2 * (w / hw)[:, None, None].expand_as(x)


def test_dimming_gradient_is_the_analytic_one():
    """Gradients flow through P(image); the reference is a constant, and without one P_ref = P(image) is
    taken as a constant too, so the gradient is not simply (1 - rho): the functional and the stage
    (without a reference) against the analytic gradient; on one pixel with coefficients (1, 1, 1) it
    vanishes; gradcheck with a reference."""
    x = torch.rand(3, 3, 4, dtype=D, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.2
    rho = 0.4
    p = float(display_power(x))
    want = _analytic_dimming_gradient(x, (1 - rho) * p)
    assert not torch.allclose(want, torch.full_like(want, 1 - rho))
    stage = DisplayMapping(p_ref="ground_truth")
    for f in (lambda t: display_mapping(t, rho), lambda t: stage(t, RuntimeState(power_saving=rho), StageContext((3, 4)))):
        xr = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(f(xr).sum(), xr)
        torch.testing.assert_close(g, want)
    ref = torch.full((3, 2, 2), 0.3, dtype=D)
    xr = x.clone().requires_grad_(True)
    (g,) = torch.autograd.grad(display_mapping(xr, rho, ref).sum(), xr)
    torch.testing.assert_close(g, _analytic_dimming_gradient(x, (1 - rho) * float(display_power(ref))))
    one = torch.tensor([0.2, 0.3, 0.4], dtype=D)[:, None, None].requires_grad_(True)
    display_mapping(one, 0.5, coefficients=(1.0, 1.0, 1.0)).sum().backward()
    assert one.grad.abs().max().item() < 1e-12
    img = (torch.rand(2, 3, 3, 4, dtype=D) * 0.4 + 0.05).requires_grad_(True)
    gt = torch.rand(3, 5, 5, dtype=D) * 0.3
    assert torch.autograd.gradcheck(lambda t: display_mapping(t, 0.4, gt), (img,))


def test_no_gradient_reaches_the_reference_or_its_power():
    """The reference, a given reference power and the displayed reference are constants of the mapping: no
    gradient reaches them, in the functional or the stage (either p_ref); the stats and the recorded
    reference power are detached."""
    x = torch.full((3, 2, 2), 0.3, dtype=D, requires_grad=True)
    ref = torch.full((3, 2, 2), 0.2, dtype=D, requires_grad=True)
    out, stats = display_mapping_with_stats(x, 0.2, ref)
    g = torch.autograd.grad(out.sum(), [x, ref], allow_unused=True)
    assert g[0] is not None and g[1] is None
    assert not any(v.requires_grad for v in stats.values())
    p_ref = display_power(ref.detach()).requires_grad_(True)
    g = torch.autograd.grad(display_mapping(x, 0.2, reference_power=p_ref).sum(), [x, p_ref], allow_unused=True)
    assert g[0] is not None and g[1] is None
    shown = torch.full((3, 2, 2), 0.5, dtype=D, requires_grad=True)
    rec: dict = {}
    ctx = StageContext((2, 2), reference=ref, displayed_reference=shown, record=rec)
    DisplayMapping()(x, RuntimeState(power_saving=0.2), ctx).sum().backward()
    assert shown.grad is None and ref.grad is None and not rec["display.power_ref"].requires_grad
    DisplayMapping(p_ref="ground_truth")(x, RuntimeState(power_saving=0.2), StageContext((2, 2), reference=ref)).sum().backward()
    assert ref.grad is None and x.grad is not None


# ----------------------------------------------------------------------------- the stage
def test_display_stage_reference_power_and_records():
    """Order 30; the identity only at rho = 0 without a reference. With ``p_ref="ground_truth"`` the
    reference power is that of the sRGB ground truth (encoded 0.5 grey: 0.21404114 x 1001.82), with
    ``"displayed"`` (default) that of the displayed reference when the pipeline gives one, else of the
    ground truth; without a reference the scale is 1 - rho and no reference power is recorded. The
    stage records scale, targets, power and clipped fraction."""
    with pytest.raises(InputValueError, match="p_ref.*'eye'"):
        DisplayMapping(p_ref="eye")  # type: ignore[arg-type]
    st = DisplayMapping()
    assert st.order == 30.0 and st.wants_displayed_reference and st.brighten
    assert not DisplayMapping(p_ref="ground_truth").wants_displayed_reference
    s0 = RuntimeState(power_saving=0.0)
    assert st.is_identity(s0) and st.is_identity(s0, StageContext((2, 2)))
    assert not st.is_identity(s0, StageContext((2, 2), reference=_img([1.0, 1.0, 1.0], 2, 2)))
    assert not st.is_identity(RuntimeState(power_saving=0.1))
    gt_stage = DisplayMapping(p_ref="ground_truth", brighten=False)
    img = _img([0.5, 0.5, 0.5], 2, 2)
    rec: dict = {}
    out = gt_stage(img, s0, StageContext((2, 2), reference=_img([0.5] * 3, 2, 2), record=rec))
    assert float(rec["display.power_ref"]) == pytest.approx(MID_GREY * WHITE, rel=1e-7)
    assert float(rec["display.scale"]) == pytest.approx(MID_GREY / 0.5, rel=1e-7)
    assert set(rec) == {"display.scale", "display.power_target", "display.power", "display.clipped_fraction",
                        "display.power_ref"}
    assert torch.allclose(out, img * MID_GREY / 0.5)
    rec = {}
    gt_stage(img, RuntimeState(), StageContext((2, 2), reference=_img([1.0] * 3, 2, 2), record=rec))
    assert float(rec["display.scale"]) == 1.0  # brighten=False: a brighter reference does not scale up
    rec = {}
    ctx = StageContext((2, 2), reference=_img([1.0] * 3, 2, 2), record=rec, displayed_reference=_img([0.25] * 3, 2, 2))
    st(img, RuntimeState(), ctx)
    assert float(rec["display.power_ref"]) == pytest.approx(0.25 * WHITE) and float(rec["display.scale"]) == pytest.approx(0.5)
    rec = {}
    st(img, RuntimeState(power_saving=0.2), StageContext((2, 2), record=rec))
    assert "display.power_ref" not in rec and float(rec["display.scale"]) == pytest.approx(0.8)
    small = torch.rand(3, 4, 4, dtype=D) * 0.2
    gt = torch.rand(3, 8, 8, dtype=D)
    rec = {}
    assert torch.equal(st(small, RuntimeState(2.0, 0.2), StageContext((8, 8), reference=gt, record=rec)),
                       display_mapping(small, 0.2, srgb_to_linear(gt)))
    assert {"display.scale", "display.power_target", "display.power", "display.clipped_fraction"} <= set(rec)


def test_display_stage_caches_the_reference_power_per_tensor_version_and_dtype():
    """The ground truth's power is reused while the same tensor comes back unmodified in the same dtype;
    another tensor, an in-place edit or another dtype computes it again."""
    stage = DisplayMapping(p_ref="ground_truth")
    gt = torch.rand(3, 8, 8, dtype=D)
    first = stage.reference_power(gt, D)
    assert stage.reference_power(gt, D) is first
    assert stage.reference_power(gt.clone(), D) is not first
    gt.mul_(0.5)
    assert float(stage.reference_power(gt, D)) == pytest.approx(float(display_power(gt, encoding="srgb")))
    ref = _img([1.0, 1.0, 1.0], 2, 2)
    p64 = stage.reference_power(ref, D)
    assert stage.reference_power(ref, D) is p64
    assert stage.reference_power(ref, torch.float32).dtype == torch.float32
    ref.mul_(0.5)
    assert float(stage.reference_power(ref, torch.float32)) == pytest.approx(MID_GREY * WHITE, rel=1e-6)


def test_the_power_model_follows_the_image_device():
    """Constants are made on the image's device ("meta" stands in for a second device)."""
    x = torch.ones(3, 4, 4, device="meta")
    assert display_power(x).device.type == "meta"
    assert display_mapping(x, 0.5).device.type == "meta"


# ----------------------------------------------------------------------------- refusals
@pytest.mark.parametrize("rho", [1.0, 1.5, -0.1, -0.01, float("nan"), float("inf"), "x", None])
def test_bad_rho_is_a_state_range_error_naming_it(rho):
    with pytest.raises(StateRangeError, match=rf"rho \(power saving\) must be .*got {rho!r}"):
        display_mapping(_img([0.5, 0.5, 0.5]), rho)
    if isinstance(rho, float):
        with pytest.raises(StateError, match="power_saving"):
            RuntimeState(power_saving=rho)


@pytest.mark.parametrize("bad", [(1.0, 1.0), (1.0, 1.0, 1.0, 1.0), (-1.0, 1.0, 1.0), (1.0, float("nan"), 1.0),
                                 (1.0, 1.0, float("inf")), (0.0, 0.0, 0.0)])
def test_bad_coefficients_are_refused(bad):
    with pytest.raises(InputValueError, match=rf"coefficients.*{re.escape(repr(bad))}"):
        display_power(_img([1.0, 1.0, 1.0]), bad)
    with pytest.raises(InputValueError, match="coefficients"):
        DisplayMapping(coefficients=bad)


def test_display_refusals_name_the_argument():
    img = _img([0.5, 0.5, 0.5])
    with pytest.raises(InputValueError, match="encoding.*'gamma'"):
        display_power(img, encoding="gamma")
    with pytest.raises(InputValueError, match="reference"):
        display_mapping(torch.rand(3, 2, 2), 0.2, torch.rand(3, 2, 2, dtype=torch.float16))
    with pytest.raises(InputValueError, match="reference="):
        display_mapping(torch.rand(3, 8, 8), 0.3, torch.rand(3, 8, 8, device="meta"))
    with pytest.raises(InputValueError, match="reference or reference_power, not both"):
        display_mapping(img, 0.1, img, reference_power=1.0)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(InputValueError, match=rf"reference_power.*{bad!r}"):
            display_mapping(img, 0.1, reference_power=bad)
    display_mapping(img, 0.1, reference_power=0.0)  # 0 is allowed
