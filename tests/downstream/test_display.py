"""Tests of ``controlgs_adapter.downstream.display``."""

from __future__ import annotations

import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream import color, display, placement
from controlgs_adapter.downstream.color import srgb_to_linear
from controlgs_adapter.downstream.display import (
    PANEL_COEFFICIENTS,
    DisplayMapping,
    display_mapping,
    display_mapping_with_stats,
    display_power,
    display_power_watts,
)
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError, StateError, StateRangeError

D = torch.float64


@pytest.mark.parametrize("brighten", [True, False])
@pytest.mark.parametrize("rho", [0.0, 0.3])
def test_display_mapping_with_other_coefficients_and_a_smaller_reference_by_hand(brighten, rho):
    """Panel coefficients (0.5, 2, 1), a 2 x 3 reference for a 4 x 5 image: P(X) = sum_c w_c mean(max(X_c, 0)),
    scale = (1 - rho) P(ref) / P(image) (at most 1 without brighten), output clipped to [0, 1]; the stats
    hold the scale, the target, the output's power and the fraction of values clipped."""
    from controlgs_adapter.downstream.display import display_mapping_with_stats

    w = (0.5, 2.0, 1.0)
    g = torch.Generator().manual_seed(4)
    image = torch.rand(3, 4, 5, generator=g, dtype=D) * 1.2 - 0.1  # some values < 0 and > 1
    ref = torch.rand(3, 2, 3, generator=g, dtype=D) * 1.6  # brighter than the image: brighten decides

    def power(x: torch.Tensor) -> float:
        return sum(w[c] * sum(max(v, 0.0) for v in x[c].flatten().tolist()) / x[c].numel() for c in range(3))

    target = (1 - rho) * power(ref)
    scale = target / power(image)
    assert scale > 1.0
    if not brighten:
        scale = min(scale, 1.0)
    dimmed = image * scale
    want = dimmed.clamp(0, 1)
    out, stats = display_mapping_with_stats(image, rho, ref, coefficients=w, brighten=brighten)
    torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    assert float(stats["scale"]) == pytest.approx(scale, rel=1e-12)
    assert float(stats["power_target"]) == pytest.approx(target, rel=1e-12)
    assert float(stats["power"]) == pytest.approx(power(want), rel=1e-12)
    n_clipped = sum(1 for v in dimmed.flatten().tolist() if v < 0 or v > 1)
    assert float(stats["clipped_fraction"]) == pytest.approx(n_clipped / dimmed.numel(), rel=1e-12)


@pytest.mark.parametrize("channel, alpha", [(0, 228.52), (1, 205.66), (2, 567.64)])
def test_display_power_per_channel(channel, alpha):
    """P = mean(alpha R + beta G + gamma B) on linear RGB (DESIGN.md), each primary on its own."""
    img = torch.zeros(3, 4, 6, dtype=torch.float64)
    img[channel, :2] = 0.5  # half the pixels at 0.5: mean 0.25
    assert float(display_power(img)) == pytest.approx(alpha * 0.25, rel=1e-12)
    assert float(display_power_watts(img)) == pytest.approx(alpha * 0.25 * 3e-3, rel=1e-12)
    srgb = torch.zeros(3, 2, 2, dtype=torch.float64)
    srgb[channel] = 0.5  # sRGB 0.5 = linear ((0.5 + 0.055) / 1.055) ** 2.4
    assert float(display_power(srgb, encoding="srgb")) == pytest.approx(alpha * ((0.555 / 1.055) ** 2.4), rel=1e-9)


def test_display_without_reference_detaches_p_ref():
    """No reference: P_ref = P(image) is a constant, so the gradient is that of
    image * (1 - rho) * P(image).detach() / P(image)."""
    g = torch.Generator().manual_seed(1)
    base = torch.rand(2, 3, 5, 7, generator=g, dtype=torch.float64) * 0.8
    weights = torch.rand(2, 3, 5, 7, generator=g, dtype=torch.float64)
    rho = 0.3

    def grad(fn):
        x = base.clone().requires_grad_(True)
        (fn(x) * weights).sum().backward()
        return x.grad

    def by_hand(x):
        p = display_power(x)
        return x * ((1 - rho) * p.detach() / p)[:, None, None, None]

    want = grad(by_hand)
    assert not torch.allclose(want, torch.full_like(want, 1 - rho) * weights)  # the power's gradient is not zero
    stage = DisplayMapping(p_ref="ground_truth")
    ctx = StageContext(native_size=(5, 7))
    assert torch.allclose(grad(lambda x: stage(x, RuntimeState(power_saving=rho), ctx)), want, atol=1e-12, rtol=0)
    assert torch.allclose(grad(lambda x: display_mapping(x, rho)), want, atol=1e-12, rtol=0)


def _power_reference(img: torch.Tensor, coeffs=PANEL_COEFFICIENTS) -> float:
    """Explicit loop over pixels: mean of alpha R + beta G + gamma B (negatives emit nothing)."""
    a, b, c = coeffs
    _, h, w = img.shape
    total = 0.0
    for i in range(h):
        for j in range(w):
            r, g, bl = (max(0.0, float(v)) for v in img[:, i, j])
            total += a * r + b * g + c * bl
    return total / (h * w)


def test_power_model_values():
    white = torch.ones(3, 4, 4, dtype=torch.float64)
    assert float(display_power(white)) == pytest.approx(228.52 + 205.66 + 567.64, rel=1e-12)
    assert float(display_power_watts(white)) == pytest.approx(3.00546, abs=1e-5)  # PowerGS: full white ~3.006 W
    img = torch.rand(3, 5, 6, dtype=torch.float64) * 1.2 - 0.1
    assert float(display_power(img)) == pytest.approx(_power_reference(img), rel=1e-12)
    srgb = torch.rand(2, 3, 4, 4, dtype=torch.float64)
    assert torch.allclose(display_power(srgb, encoding="srgb"), display_power(srgb_to_linear(srgb)))
    custom = (1.0, 0.0, 0.0)
    assert float(display_power(img, custom)) == pytest.approx(_power_reference(img, custom), rel=1e-12)


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


def test_clipping_is_reported():
    img = torch.full((3, 4, 4), 0.25, dtype=torch.float64)
    img[:, 0, 0] = 0.9
    ref = torch.full((3, 4, 4), 0.8, dtype=torch.float64)
    out, stats = display_mapping_with_stats(img, 0.1, ref)
    scale = float(stats["scale"])
    assert scale > 1.0 / 0.9  # brightened so that the 0.9 pixel clips
    assert float(out.max()) == 1.0
    assert float(stats["clipped_fraction"]) == pytest.approx(3 / 48)
    assert float(stats["power"]) < float(stats["power_target"])


@settings(max_examples=20, deadline=None)
@given(st.floats(0.0, 0.999999), st.sampled_from(["black", "no_blue", "negative"]))
def test_degenerate_images_have_no_nan(rho, kind):
    img = torch.rand(3, 4, 4, dtype=torch.float64)
    if kind == "black":
        img = torch.zeros(3, 4, 4, dtype=torch.float64)
    elif kind == "no_blue":
        img[2] = 0
    else:
        img = -img
    img.requires_grad_(True)
    for ref in (None, torch.zeros(3, 4, 4, dtype=torch.float64), torch.rand(3, 4, 4, dtype=torch.float64)):
        out = display_mapping(img, rho, ref)
        (grad,) = torch.autograd.grad(out.sum(), img)
        assert torch.isfinite(out).all() and torch.isfinite(grad).all()
        if kind == "black":
            assert torch.equal(out, img.detach())  # zero power: nothing to scale


def test_black_image_scale_is_one_and_no_reference_scales_by_one_minus_rho():
    _, stats = display_mapping_with_stats(torch.zeros(3, 2, 2), 0.5, torch.rand(3, 2, 2))
    assert float(stats["scale"]) == 1.0
    img = torch.rand(3, 4, 4, dtype=torch.float64) * 0.5
    assert torch.allclose(display_mapping(img, 0.3), img * 0.7)


def test_rho_zero_without_reference_is_identity_and_with_reference_maps_to_p_ref():
    img = torch.rand(3, 4, 4) * 1.5  # not even clipped
    assert display_mapping(img, 0.0) is img
    img = torch.rand(3, 4, 4, dtype=torch.float64) * 0.3
    ref = torch.rand(3, 6, 6, dtype=torch.float64) * 0.5
    out = display_mapping(img, 0.0, ref)  # continuous in rho: same as a tiny rho
    assert torch.allclose(out, display_mapping(img, 1e-12, ref), atol=1e-9)
    assert torch.allclose(display_power(out), display_power(ref), rtol=1e-9)


def test_brighten_false_never_scales_up():
    img = torch.rand(3, 4, 4) * 0.1
    ref = torch.ones(3, 4, 4)
    out = display_mapping(img, 0.2, ref, brighten=False)
    assert torch.equal(out, img)
    assert not torch.equal(display_mapping(img, 0.2, ref), img)


@pytest.mark.parametrize("rho", [1.0, 1.5, -0.1, float("nan"), float("inf"), "x"])
def test_bad_rho_raises(rho):
    with pytest.raises(StateError, match="rho"):
        display_mapping(torch.rand(3, 2, 2), rho)
    if isinstance(rho, float):
        with pytest.raises(StateError, match="power_saving"):
            RuntimeState(power_saving=rho)


def test_bad_input_names_the_argument():
    with pytest.raises(InputValueError, match="reference"):
        display_mapping(torch.rand(3, 2, 2), 0.2, torch.rand(3, 2, 2, dtype=torch.float16))
    with pytest.raises(InputValueError, match="coefficients"):
        display_power(torch.rand(3, 2, 2), (1.0, -1.0, 2.0))
    with pytest.raises(InputValueError, match="encoding"):
        display_power(torch.rand(3, 2, 2), encoding="gamma")


def test_gradcheck_and_gradient_through_the_power():
    img = (torch.rand(2, 3, 3, 4, dtype=torch.float64) * 0.4 + 0.05).requires_grad_(True)
    ref = torch.rand(3, 5, 5, dtype=torch.float64) * 0.3
    assert torch.autograd.gradcheck(lambda x: display_mapping(x, 0.4, ref), (img,))
    (grad,) = torch.autograd.grad(display_mapping(img, 0.4, ref).sum(), img)
    _, stats = display_mapping_with_stats(img.detach(), 0.4, ref)
    grad_fixed_scale = stats["scale"][:, None, None, None].expand_as(img)
    assert not torch.allclose(grad, grad_fixed_scale)  # the scale depends on the image's power


def test_display_stage():
    stage = DisplayMapping()
    assert stage.is_identity(RuntimeState(power_saving=0.0)) and not stage.is_identity(RuntimeState(power_saving=0.2))
    ctx = StageContext(native_size=(4, 4), reference=torch.rand(3, 4, 4))
    assert not stage.is_identity(RuntimeState(power_saving=0.0), ctx)  # maps to P_ref when a reference comes
    img = torch.rand(3, 4, 4, dtype=torch.float64) * 0.2
    gt = torch.rand(3, 8, 8, dtype=torch.float64)
    record: dict = {}
    out = stage(img, RuntimeState(2.0, 0.2), StageContext((8, 8), reference=gt, record=record))
    assert torch.equal(out, display_mapping(img, 0.2, srgb_to_linear(gt)))
    assert {"display.scale", "display.power_target", "display.power", "display.clipped_fraction"} <= set(record)


def test_reference_power_argument_and_stage_cache():
    img = torch.rand(2, 3, 4, 4, dtype=torch.float64) * 0.3
    ref = torch.rand(3, 8, 8, dtype=torch.float64)
    p_ref = display_power(ref)
    assert torch.equal(display_mapping(img, 0.3, reference_power=p_ref), display_mapping(img, 0.3, ref))
    assert torch.allclose(display_mapping(img, 0.3, reference_power=float(p_ref)), display_mapping(img, 0.3, ref))
    with pytest.raises(InputValueError, match="not both"):
        display_mapping(img, 0.3, ref, reference_power=p_ref)
    with pytest.raises(InputValueError, match="reference_power"):
        display_mapping(img, 0.3, reference_power=-1.0)
    stage = DisplayMapping()
    gt = torch.rand(3, 8, 8, dtype=torch.float64)
    first = stage.reference_power(gt, torch.float64)
    assert stage.reference_power(gt, torch.float64) is first  # cached for the same tensor
    assert stage.reference_power(gt.clone(), torch.float64) is not first  # another tensor: recomputed
    gt.mul_(0.5)  # modified in place: recomputed
    assert float(stage.reference_power(gt, torch.float64)) == pytest.approx(float(display_power(gt, encoding="srgb")))


def _analytic_dimming_gradient(x: torch.Tensor, target: float) -> torch.Tensor:
    """d/dx of sum(x * target / P(x)) by hand, for x > 0 with nothing clipped: P(x) = sum_c w_c mean(x_c),
    so d/dx_j = target / P - target * sum(x) / P^2 * w_c(j) / (H W)."""
    w = torch.tensor(PANEL_COEFFICIENTS, dtype=torch.float64)
    hw = x.shape[-1] * x.shape[-2]
    p = float((x.mean(dim=(-2, -1)) * w).sum())
    s = float(x.sum())
    return target / p - target * s / p**2 * (w / hw)[:, None, None].expand_as(x)


def test_dimming_gradient_by_hand_with_and_without_a_reference():
    """Module docstring: "Gradients flow through P(image); the reference is a constant". Without a
    reference P_ref = P(image) taken as a constant too, so the gradient is not simply (1 - rho)."""
    x = (torch.rand(3, 3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.5 + 0.2)
    x.requires_grad_(True)
    rho = 0.4
    p = float(display_power(x.detach()))
    (g,) = torch.autograd.grad(display_mapping(x, rho).sum(), x)
    torch.testing.assert_close(g, _analytic_dimming_gradient(x.detach(), (1 - rho) * p))
    ref = torch.full((3, 2, 2), 0.3, dtype=torch.float64)
    (g,) = torch.autograd.grad(display_mapping(x, rho, ref).sum(), x)
    torch.testing.assert_close(g, _analytic_dimming_gradient(x.detach(), (1 - rho) * float(display_power(ref))))


def test_no_gradient_reaches_the_reference_or_its_power():
    """The reference (or a given reference_power) is a constant of the mapping: no gradient reaches it."""
    x = torch.full((3, 2, 2), 0.3, dtype=torch.float64, requires_grad=True)
    ref = torch.full((3, 2, 2), 0.2, dtype=torch.float64, requires_grad=True)
    g = torch.autograd.grad(display_mapping(x, 0.2, ref).sum(), [x, ref], allow_unused=True)
    assert g[0] is not None and g[1] is None
    p_ref = display_power(ref.detach()).requires_grad_(True)
    g = torch.autograd.grad(display_mapping(x, 0.2, reference_power=p_ref).sum(), [x, p_ref], allow_unused=True)
    assert g[0] is not None and g[1] is None


def test_pixels_exactly_at_the_display_range_ends_are_not_clipped():
    """``clipped_fraction`` counts values outside [0, 1]: an image of exact 0s and 1s mapped at scale 1
    (rho = 0, P_ref = its own power) clips nothing."""
    x = torch.zeros(3, 2, 2, dtype=torch.float64)
    x[:, 0] = 1.0
    out, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert float(stats["scale"]) == 1.0 and torch.equal(out, x)
    assert float(stats["clipped_fraction"]) == 0.0
    x[0, 1, 1] = 1.5                      # one value of 12 above the range
    x[1, 1, 0] = -0.5                     # one below
    _, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert float(stats["clipped_fraction"]) == pytest.approx(2 / 12)


def test_identity_mapping_stats_are_detached():
    """display_mapping_with_stats: the stats are "each [...], detached", also on the rho = 0 shortcut."""
    x = torch.full((3, 2, 2), 0.5, dtype=torch.float64, requires_grad=True)
    out, stats = display_mapping_with_stats(x, 0.0)
    assert out is x
    assert not any(v.requires_grad for v in stats.values())
    assert float(stats["power"]) == pytest.approx(0.5 * sum(PANEL_COEFFICIENTS))


def test_clipped_fraction_is_per_image_of_a_batch():
    """Stats are "each [...]": a batch of two images gets one clipped fraction each (by hand: the first
    has 1 of 12 values above 1 at scale 1, the second none)."""
    x = torch.full((2, 3, 2, 2), 0.5, dtype=torch.float64)
    x[0, 0, 0, 0] = 1.5
    _, stats = display_mapping_with_stats(x, 0.0, reference_power=display_power(x))
    assert stats["clipped_fraction"].tolist() == [pytest.approx(1 / 12), 0.0]


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


def test_display_power_literal_values_and_defaults():
    white = _img([1.0, 1.0, 1.0], 2, 2)
    # 228.52 + 205.66 + 567.64 = 1001.82; 3 / 1000 of it = 3.00546 W
    assert float(display_power(white)) == pytest.approx(1001.82, abs=1e-9)
    assert float(display.display_power_watts(white)) == pytest.approx(3.00546, abs=1e-12)
    # per channel: 0.5 R -> 114.26; 0.25 B -> 141.91; negatives emit nothing; mean over the pixels
    img = _img([0.5, -1.0, 0.25], 2, 2)
    assert float(display_power(img)) == pytest.approx(114.26 + 141.91, abs=1e-9)
    half = _img([0.0, 1.0, 0.0], 2, 2)
    half[1, 0, :] = 0.0  # half of the pixels green at 1 -> 205.66 / 2
    assert float(display_power(half)) == pytest.approx(102.83, abs=1e-9)
    # sRGB encoding decodes first: 0.5 encoded = 0.21404114 linear
    assert float(display_power(_img([0.5, 0.5, 0.5]), encoding="srgb")) == pytest.approx(0.21404114 * 1001.82, rel=1e-7)
    assert float(display_power(_img([1.0, 1.0, 1.0]), (1.0, 2.0, 3.0))) == pytest.approx(6.0)
    watts = display.display_power_watts(_img([0.5, 0.5, 0.5]), encoding="srgb")
    assert float(watts) == pytest.approx(0.21404114 * 1001.82 * 0.003, rel=1e-7)
    # leading dims give one value per image
    batch = torch.stack([_img([1.0, 0.0, 0.0]), _img([0.0, 0.0, 1.0])])
    assert display_power(batch).tolist() == pytest.approx([228.52, 567.64])


@pytest.mark.parametrize("bad", [(1.0, 1.0), (1.0, 1.0, 1.0, 1.0), (-1.0, 1.0, 1.0), (1.0, float("nan"), 1.0),
                                 (1.0, 1.0, float("inf")), (0.0, 0.0, 0.0)])
def test_bad_coefficients_are_refused(bad):
    with pytest.raises(InputValueError, match="coefficients must be 3 finite non-negative"):
        display_power(_img([1.0, 1.0, 1.0]), bad)
    with pytest.raises(InputValueError, match="coefficients"):
        DisplayMapping(coefficients=bad)


def test_a_zero_coefficient_is_allowed():
    assert float(display_power(_img([1.0, 1.0, 1.0]), (0.0, 0.0, 2.0))) == pytest.approx(2.0)


def test_bad_encoding_is_refused():
    with pytest.raises(InputValueError, match="encoding must be 'linear' or 'srgb'"):
        display_power(_img([1.0, 1.0, 1.0]), encoding="gamma")


@pytest.mark.parametrize("rho", ["x", None, float("nan"), float("inf"), -0.01, 1.0, 1.5])
def test_bad_rho_is_a_state_range_error(rho):
    with pytest.raises(StateRangeError, match="rho"):
        display_mapping(_img([0.5, 0.5, 0.5]), rho)


def test_rho_just_below_one_and_zero_are_accepted():
    img = _img([0.5, 0.5, 0.5])
    out = display_mapping(img, 0.99)
    assert out.flatten().tolist() == pytest.approx([0.005] * 3)  # scaled by 1 - 0.99
    assert display_mapping(img, 0.0) is img


def test_rho_zero_without_reference_returns_the_image_and_unit_stats():
    img = _img([2.0, 0.5, -0.5], 2, 2)  # out of range: not clipped at rho = 0 without a reference
    out, stats = display_mapping_with_stats(img, 0.0)
    assert out is img
    p = 2.0 * 228.52 + 0.5 * 205.66
    assert float(stats["scale"]) == 1.0 and float(stats["clipped_fraction"]) == 0.0
    assert float(stats["power"]) == pytest.approx(p) and float(stats["power_target"]) == pytest.approx(p)


def test_mapping_to_a_reference_power_by_hand():
    # image power 0.5 * 1001.82; reference_power 300 at rho 0.25 -> target 225, scale 225 / 500.91
    img = _img([0.5, 0.5, 0.5], 2, 2)
    out, stats = display_mapping_with_stats(img, 0.25, reference_power=300.0)
    scale = 225.0 / (0.5 * 1001.82)
    assert float(stats["scale"]) == pytest.approx(scale)
    assert float(stats["power_target"]) == pytest.approx(225.0)
    assert float(stats["power"]) == pytest.approx(225.0)
    assert out.flatten()[0].item() == pytest.approx(0.5 * scale)
    # a reference image: P_ref of white = 1001.82, rho 0.5 -> target 500.91 = image power: scale 1
    ref = _img([1.0, 1.0, 1.0], 4, 4)
    out2, stats2 = display_mapping_with_stats(img, 0.5, ref)
    assert float(stats2["scale"]) == pytest.approx(1.0)
    assert torch.allclose(out2, img)
    # brighten=False caps the scale at 1; with brighten the image doubles and clips
    out3, stats3 = display_mapping_with_stats(img, 0.0, ref, brighten=False)
    assert float(stats3["scale"]) == 1.0 and torch.equal(out3, img)
    out4, stats4 = display_mapping_with_stats(img, 0.0, ref)
    assert float(stats4["scale"]) == pytest.approx(2.0)
    assert float(out4.max()) == 1.0
    assert torch.equal(display_mapping(img, 0.0, ref), out4)  # brightens by default too
    assert torch.equal(display_mapping(img, 0.0, ref, brighten=False), img)


def test_clipped_fraction_counts_values_below_zero_and_above_one():
    img = _img([0.5, 0.5, 0.5], 2, 2)
    img[0, 0, 0] = -0.2  # 1 of 12 values negative
    img[2, 1, 1] = 3.0  # 1 of 12 values above 1 after scale 1
    out, stats = display_mapping_with_stats(img, 0.0, reference_power=float(display_power(img)))
    assert float(stats["clipped_fraction"]) == pytest.approx(2 / 12)
    assert float(out.min()) == 0.0 and float(out.max()) == 1.0
    # the reported power is the clipped output's: (0.5*3 + 0 + ... ) by hand
    assert float(stats["power"]) == pytest.approx(float(display_power(out)))
    assert float(stats["power"]) < float(stats["power_target"])


def test_black_threshold_is_one_picowatt_unit():
    # power <= 1e-12 is black (scale 1); 1.5e-12 is an image to scale
    for p, black in [(0.5e-12, True), (1.5e-12, False)]:
        img = _img([p / 1001.82] * 3)
        _, stats = display_mapping_with_stats(img, 0.0, reference_power=1.0)
        assert (float(stats["scale"]) == 1.0) is black
    # exactly 1e-12 (red 1e-12 with coefficients (1, 0, 0): no rounding) is still black
    _, at = display_mapping_with_stats(_img([1e-12, 0.0, 0.0]), 0.0, reference_power=1.0, coefficients=(1.0, 0.0, 0.0))
    assert float(at["power"]) == 1e-12 and float(at["scale"]) == 1.0


def test_reference_and_reference_power_refusals():
    img = _img([0.5, 0.5, 0.5])
    with pytest.raises(InputValueError, match="not both"):
        display_mapping(img, 0.1, img, reference_power=1.0)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(InputValueError, match="reference_power must be finite and >= 0"):
            display_mapping(img, 0.1, reference_power=bad)
    display_mapping(img, 0.1, reference_power=0.0)  # 0 is allowed


def test_display_mapping_gradients_flow_through_the_image_power_only():
    # no reference: out = x (1 - rho) P0 / P(x) with P0 = P(x) detached. With coefficients (1, 1, 1) on
    # one pixel P = a + b + c, so d sum(out) / dx_i = s - s (sum_j x_j) / P = 0 (s = 1 - rho)
    x = torch.tensor([0.2, 0.3, 0.4], dtype=D)[:, None, None].requires_grad_(True)
    display_mapping(x, 0.5, coefficients=(1.0, 1.0, 1.0)).sum().backward()
    assert x.grad.abs().max().item() < 1e-12
    # a reference (or a reference power) is a constant: no gradient reaches it, the stats are detached
    x.grad = None
    ref = torch.full((3, 2, 2), 0.5, dtype=D, requires_grad=True)
    out, stats = display_mapping_with_stats(x, 0.2, ref)
    out.sum().backward()
    assert ref.grad is None and x.grad is not None
    assert not any(v.requires_grad for v in stats.values())
    p_ref = torch.tensor(300.0, dtype=D, requires_grad=True)
    display_mapping(x, 0.2, reference_power=p_ref).sum().backward()
    assert p_ref.grad is None
    st = DisplayMapping()
    shown = torch.full((3, 2, 2), 0.5, dtype=D, requires_grad=True)
    rec: dict = {}
    st(x, RuntimeState(power_saving=0.2), StageContext((1, 1), reference=ref, displayed_reference=shown, record=rec)).sum().backward()
    assert shown.grad is None and ref.grad is None and not rec["display.power_ref"].requires_grad
    gt = DisplayMapping(p_ref="ground_truth")
    gt(x, RuntimeState(power_saving=0.2), StageContext((1, 1), reference=ref)).sum().backward()
    assert ref.grad is None


def test_display_stage_reference_cache_follows_dtype_and_edits():
    st = DisplayMapping(p_ref="ground_truth")
    ref = _img([1.0, 1.0, 1.0], 2, 2)
    p64 = st.reference_power(ref, torch.float64)
    assert st.reference_power(ref, torch.float64) is p64
    p32 = st.reference_power(ref, torch.float32)
    assert p32.dtype == torch.float32
    ref.mul_(0.5)  # edited in place: recomputed
    assert float(st.reference_power(ref, torch.float32)) == pytest.approx(0.21404114 * 1001.82, rel=1e-6)


def test_stages_follow_the_image_device():
    # "meta" is a second device on a machine without a GPU: constants must be made on the image's device

    x = torch.ones(3, 4, 4, device="meta")
    assert display_power(x).device.type == "meta"
    assert display_mapping(x, 0.5).device.type == "meta"
    assert area_resample(torch.ones(3, 5, 5, device="meta"), 2.5).device.type == "meta"
    assert color.rgb_to_primaries(x).device.type == "meta"
    assert LensPrewarp(basis="rgb")(x).device.type == "meta"
    assert placement.to_display(torch.ones(2, 2, device="meta"), 9, 16).device.type == "meta"


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
