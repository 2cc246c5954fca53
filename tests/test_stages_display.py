"""Display mapping P_disp: power model and uniform dimming to a power target."""

from __future__ import annotations

import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.color import srgb_to_linear
from controlgs_adapter.downstream.display import (
    PANEL_COEFFICIENTS, DisplayMapping, display_mapping, display_mapping_with_stats, display_power, display_power_watts,
)
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError, StateError
from controlgs_adapter.state import RuntimeState



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
