"""Mutation-sweep tests of the small downstream stages (colour, display mapping, box emission,
area resampling, placement, the stage base class, foveation): documented defaults, boundaries,
refusals and option branches, each against a number worked out by hand or a float64 brute force."""

from __future__ import annotations


import pytest
import torch

from controlgs_adapter.downstream import color, display, placement
from controlgs_adapter.downstream.display import DisplayMapping, display_mapping, display_mapping_with_stats, display_power
from controlgs_adapter.downstream.foveation import Foveation, foveation
from controlgs_adapter.downstream.oled import OLEDEmission, oled_emission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import AreaResample, area_resample, resampled_size
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError, StateRangeError
from controlgs_adapter.state import RuntimeState

D = torch.float64


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


# ---------------------------------------------------------------- colour


def _iec_decode(v: float) -> float:  # IEC 61966-2-1, written out here independently
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def _iec_encode(v: float) -> float:
    return v * 12.92 if v <= 0.04045 / 12.92 else 1.055 * v ** (1 / 2.4) - 0.055


@pytest.mark.parametrize("v", [-0.5, -0.01, 0.0, 0.02, 0.04, 0.05, 0.5, 1.0, 1.7])
def test_srgb_transfer_functions_match_the_iec_formula(v):
    x = torch.full((3, 1, 1), v, dtype=D)
    assert float(color.srgb_to_linear(x)[0, 0, 0]) == pytest.approx(_iec_decode(v), rel=1e-12, abs=1e-15)
    assert float(color.linear_to_srgb(x)[0, 0, 0]) == pytest.approx(_iec_encode(v), rel=1e-12, abs=1e-15)


def test_srgb_literal_values():
    # 0.5 encoded -> ((0.5 + 0.055) / 1.055) ** 2.4 = 0.21404114 (the textbook mid-grey)
    x = torch.tensor([0.5, 0.02, 1.0], dtype=D)[:, None, None]
    assert color.srgb_to_linear(x).flatten().tolist() == pytest.approx([0.21404114, 0.02 / 12.92, 1.0], rel=1e-7)
    # 0.001 linear -> 0.01292 (linear segment, slope 12.92)
    y = torch.tensor([0.21404114, 0.001, 1.0], dtype=D)[:, None, None]
    assert color.linear_to_srgb(y).flatten().tolist() == pytest.approx([0.5, 0.01292, 1.0], rel=1e-6)


def test_transfer_function_gradients_are_finite_for_negative_and_zero_inputs():
    # the unused power branch sees clamped inputs: (x + 0.055) < 0 or x ** (1/2.4) at 0 would give NaN/inf
    x = torch.tensor([-0.5, -0.06, 0.0, 0.5], dtype=D)[:, None, None, None].expand(4, 3, 1, 1).clone().requires_grad_(True)
    color.srgb_to_linear(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert float(x.grad[0, 0, 0, 0]) == pytest.approx(1 / 12.92)
    x.grad = None
    color.linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all()
    assert float(x.grad[2, 0, 0, 0]) == pytest.approx(12.92)


def test_primaries_matrix_reproduces_srgb_xyz_through_the_cie_cmfs():
    # XYZ of the primaries' light = C (s * white_drive) must equal the sRGB XYZ of the RGB colour;
    # C, M read from colour-science's tables here, not through the library's arithmetic
    import colour
    import numpy as np

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    c = np.stack([np.asarray(cmfs[w]) for w in (656, 550, 486)], axis=1)
    m = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ)
    to_p = color.rgb_to_primaries_matrix().numpy()
    assert to_p @ np.ones(3) == pytest.approx(np.ones(3), abs=1e-12)
    # each primary's unit is the drive that white needs: C diag(u) to_p = M with u > 0 per column
    u = np.linalg.solve(c, m @ np.ones(3))
    assert np.all(u > 0)
    assert c @ np.diag(u) @ to_p == pytest.approx(m, abs=1e-12)
    # primaries_to_rgb is the inverse; the functional forms apply the matrices over the channel axis
    rgb = torch.tensor([0.2, 0.5, 0.9], dtype=D)[:, None, None]
    s = color.rgb_to_primaries(rgb)
    assert s.flatten().numpy() == pytest.approx(to_p @ np.array([0.2, 0.5, 0.9]), abs=1e-12)
    assert color.primaries_to_rgb(s).flatten().tolist() == pytest.approx([0.2, 0.5, 0.9], abs=1e-12)


def test_primaries_white_outside_the_gamut_is_refused():
    # 600 / 550 / 500 nm lie on the yellow-green-cyan part of the spectral locus; D65 white
    # (x 0.3127, y 0.329) is below the 600-500 nm edge (y ~0.457 there), so outside the triangle
    with pytest.raises(RuntimeError, match="outside the gamut"):
        color._primaries_matrices_for((600, 550, 500))


# ---------------------------------------------------------------- display power and mapping


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


def test_display_stage_options_and_records():
    with pytest.raises(InputValueError, match="p_ref must be 'displayed' or 'ground_truth'"):
        DisplayMapping(p_ref="eye")
    st = DisplayMapping()
    assert st.order == 30.0 and st.wants_displayed_reference and st.brighten
    assert not DisplayMapping(p_ref="ground_truth").wants_displayed_reference
    s0 = RuntimeState(power_saving=0.0)
    assert st.is_identity(s0) and st.is_identity(s0, StageContext((2, 2)))
    assert not st.is_identity(s0, StageContext((2, 2), reference=_img([1.0, 1.0, 1.0], 2, 2)))
    assert not st.is_identity(RuntimeState(power_saving=0.1))
    # ground truth as given (sRGB): P_ref of encoded 0.5 grey = 0.21404114 * 1001.82
    gt = DisplayMapping(p_ref="ground_truth", brighten=False)
    img = _img([0.5, 0.5, 0.5], 2, 2)
    rec: dict = {}
    out = gt(img, RuntimeState(power_saving=0.0), StageContext((2, 2), reference=_img([0.5] * 3, 2, 2), record=rec))
    assert float(rec["display.power_ref"]) == pytest.approx(0.21404114 * 1001.82, rel=1e-7)
    assert float(rec["display.scale"]) == pytest.approx(0.21404114 / 0.5, rel=1e-7)
    assert set(rec) == {"display.scale", "display.power_target", "display.power", "display.clipped_fraction",
                        "display.power_ref"}
    assert torch.allclose(out, img * 0.21404114 / 0.5)
    # brighten=False stage: a brighter reference does not scale up
    rec2: dict = {}
    gt(img, RuntimeState(), StageContext((2, 2), reference=_img([1.0] * 3, 2, 2), record=rec2))
    assert float(rec2["display.scale"]) == 1.0
    # displayed reference (linear) wins over the sRGB reference when p_ref="displayed"
    rec3: dict = {}
    ctx = StageContext((2, 2), reference=_img([1.0] * 3, 2, 2), record=rec3, displayed_reference=_img([0.25] * 3, 2, 2))
    st(img, RuntimeState(), ctx)
    assert float(rec3["display.power_ref"]) == pytest.approx(0.25 * 1001.82)
    assert float(rec3["display.scale"]) == pytest.approx(0.5)
    # no reference: no power_ref recorded, scale 1 - rho
    rec4: dict = {}
    st(img, RuntimeState(power_saving=0.2), StageContext((2, 2), record=rec4))
    assert "display.power_ref" not in rec4 and float(rec4["display.scale"]) == pytest.approx(0.8)


def test_display_stage_reference_cache_follows_dtype_and_edits():
    st = DisplayMapping(p_ref="ground_truth")
    ref = _img([1.0, 1.0, 1.0], 2, 2)
    p64 = st.reference_power(ref, torch.float64)
    assert st.reference_power(ref, torch.float64) is p64
    p32 = st.reference_power(ref, torch.float32)
    assert p32.dtype == torch.float32
    ref.mul_(0.5)  # edited in place: recomputed
    assert float(st.reference_power(ref, torch.float32)) == pytest.approx(0.21404114 * 1001.82, rel=1e-6)


# ---------------------------------------------------------------- box emission


def test_box_emission_pixel_centre_rule_for_a_non_integer_ratio():
    # 2 -> 3: simulation pixel i shows floor((i + 0.5) * 2 / 3) = 0, 1, 1 ("nearest" would give 0, 0, 1)
    img = torch.tensor([[[1.0, 2.0]]], dtype=D).expand(3, 1, 2).clone()
    out = oled_emission(img, (1, 3))
    assert out[0, 0].tolist() == [1.0, 2.0, 2.0]
    # leading dims are kept
    batch = torch.arange(2 * 5 * 3 * 2 * 2, dtype=D).reshape(2, 5, 3, 2, 2)
    out2 = oled_emission(batch, (4, 4))
    assert out2.shape == (2, 5, 3, 4, 4)
    assert torch.equal(out2[1, 3, 2], batch[1, 3, 2].repeat_interleave(2, 0).repeat_interleave(2, 1))


def test_box_emission_same_size_and_refusals():
    img = _img([0.1, 0.2, 0.3], 2, 3)
    assert oled_emission(img, (2, 3)) is img
    for size in [(1, 3), (2, 2), (4, 2), (1, 6)]:  # either axis smaller is refused
        with pytest.raises(ShapeError, match="size must be at least the image size"):
            oled_emission(img, size)


def test_oled_stage_runs_only_when_downsampled():
    st = OLEDEmission()
    assert st.order == 40.0 and st.name == "oled"
    assert st.is_identity(RuntimeState(downsample=1.0))
    assert not st.is_identity(RuntimeState(downsample=1.5))
    out = st(_img([0.5, 0.5, 0.5], 1, 1), RuntimeState(downsample=2.0), StageContext((2, 2)))
    assert out.shape == (3, 2, 2)


# ---------------------------------------------------------------- area resampling


def _area_brute(row: list[float], n_out: int) -> list[float]:
    """Exact area average: repeat each input n_out times, average blocks of n_in (float64)."""
    n_in = len(row)
    fine = [v for v in row for _ in range(n_out)]
    return [sum(fine[j * n_in:(j + 1) * n_in]) / n_in for j in range(n_out)]


@pytest.mark.parametrize("n_in, d, n_out", [(5, 2.5, 2), (5, 5 / 3, 3), (7, 7 / 3, 3), (9, 2.0, 4)])
def test_area_resample_rows_match_the_exact_area_average(n_in, d, n_out):
    row = [float(v * v % 7) + 0.25 * v for v in range(n_in)]
    img = torch.tensor(row, dtype=D)[None, None, :].expand(3, 2, n_in).clone()
    out = area_resample(img, d)
    assert out.shape[-1] == n_out
    assert out[1, 0].tolist() == pytest.approx(_area_brute(row, n_out), abs=1e-12)
    # the same along the rows (the transpose path)
    out_t = area_resample(img.transpose(-1, -2).contiguous(), d)
    assert out_t[2, :, 0].tolist() == pytest.approx(_area_brute(row, n_out), abs=1e-12)


def test_area_resample_hand_value_and_unequal_axis_ratios():
    # 5 -> 2: output 0 covers [0, 2.5): (1 + 2 + 0.5 * 3) / 2.5 = 1.8; output 1: (0.5*3 + 4 + 5) / 2.5 = 4.2
    img = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=D)[None, None].expand(3, 1, 5).clone()
    assert area_resample(img, 2.5)[0, 0].tolist() == pytest.approx([1.8, 4.2])
    # 4 x 9 at d = 2.6 -> 2 x 3 (round(1.54), round(3.46)): both divide, but the ratios 2 and 3 differ
    g = torch.Generator().manual_seed(3)
    x = torch.rand(3, 4, 9, generator=g, dtype=D)
    out = area_resample(x, 2.6)
    assert out.shape == (3, 2, 3)
    assert torch.allclose(out, x.reshape(3, 2, 2, 3, 3).mean(dim=(2, 4)), atol=1e-12)
    # 8 x 9 at d = 2 -> 4 x 4 (round(4.5) = 4): rows divide, columns do not
    y = torch.rand(3, 8, 9, generator=g, dtype=D)
    out2 = area_resample(y, 2.0)
    ref = torch.tensor([[_area_brute(r, 4) for r in y[c].reshape(4, 2, 9).mean(1).tolist()] for c in range(3)], dtype=D)
    assert torch.allclose(out2, ref, atol=1e-12)


def test_resampled_size_rounding_and_floor_of_one():
    assert resampled_size((10, 7), 3.0) == (3, 2)
    assert resampled_size((5, 6), 2.0) == (2, 3)  # round(2.5) = 2 (Python's rounding, as Camera.scaled)
    assert resampled_size((2, 2), 8.0) == (1, 1)
    assert resampled_size((16, 9), 1.0) == (16, 9)


@pytest.mark.parametrize("bad", ["two", None, float("nan"), float("inf"), 0.99, 0.0, -2.0])
def test_bad_factors_are_state_range_errors_naming_the_argument(bad):
    with pytest.raises(StateRangeError, match="d must be"):
        area_resample(_img([1.0, 1.0, 1.0], 2, 2), bad)
    with pytest.raises(StateRangeError, match="max_factor must be"):
        AreaResample(max_factor=bad)


def test_resample_stage_bounds_and_sizes():
    st = AreaResample()
    assert st.order == 20.0 and st.max_factor == 8.0
    img = torch.rand(3, 16, 16, dtype=D, generator=torch.Generator().manual_seed(0))
    ctx = StageContext((16, 16))
    assert st(img, RuntimeState(downsample=8.0), ctx).shape == (3, 2, 2)
    with pytest.raises(StateRangeError, match="exceeds this pipeline's max_factor 8.0"):
        st(img, RuntimeState(downsample=8.5), ctx)
    assert AreaResample(max_factor=1.0).max_factor == 1.0
    small = img[:, :8, :8]
    assert st(small, RuntimeState(downsample=2.0), ctx) is small  # already at the display size
    with pytest.raises(ShapeError, match="native size"):
        st(img[:, :12, :12], RuntimeState(downsample=2.0), ctx)
    assert st.is_identity(RuntimeState()) and not st.is_identity(RuntimeState(downsample=1.01))


# ---------------------------------------------------------------- placement


def test_image_region_fit_by_hand():
    r = placement.image_region(9, 16)  # default: fit on the 24 x 24 mm Cardboard display
    assert (r.half_x, r.half_y) == (1.0, 0.5625)  # 9 / 16
    assert r.pitch_mm == (1.5, 1.5) and r.size_mm == (24.0, 13.5) and r.display_mm == (24.0, 24.0)
    assert r.bounds_mm == (-12.0, 12.0, -6.75, 6.75)
    t = placement.image_region(16, 9)
    assert (t.half_x, t.half_y) == (0.5625, 1.0) and t.size_mm == (13.5, 24.0)
    assert t.bounds_mm == (-6.75, 6.75, -12.0, 12.0)
    # a 30 x 20 mm display: a square image is height-limited, pitch 20 / 10 = 2, half_x = 20 / 30
    s = placement.image_region(10, 10, (30.0, 20.0))
    assert s.half_x == pytest.approx(2 / 3) and s.half_y == 1.0 and s.pitch_mm == (2.0, 2.0)
    assert s.size_mm == (20.0, 20.0)
    # a 40 x 10 image on it is width-limited: pitch 30 / 40 = 0.75, height 7.5 mm, half_y = 7.5 / 20
    w = placement.image_region(10, 40, (30.0, 20.0))
    assert w.half_x == 1.0 and w.half_y == pytest.approx(0.375) and w.size_mm == (30.0, 7.5)


def test_image_region_stretch_and_refusals():
    r = placement.image_region(9, 16, placement="stretch")
    assert (r.half_x, r.half_y) == (1.0, 1.0) and r.pitch_mm == (1.5, 24.0 / 9) and r.size_mm == (24.0, 24.0)
    with pytest.raises(InputValueError, match="placement must be one of"):
        placement.image_region(4, 4, placement="fill")
    for h, w in [(0, 4), (4, 0), (4.0, 4), (4, "4")]:
        with pytest.raises(InputValueError, match="image size must be ints >= 1"):
            placement.image_region(h, w)
    for mm in [(0.0, 24.0), (24.0, 0.0), (-1.0, 24.0), (24.0, float("nan"))]:
        with pytest.raises(InputValueError, match="display_mm must be"):
            placement.image_region(4, 4, mm)


def test_to_display_scales_by_the_half_extents():
    xy = torch.tensor([[1.0, 1.0], [-0.5, 0.5]], dtype=D)
    assert placement.to_display(xy, 4, 4) is xy
    out = placement.to_display(xy, 9, 16)
    assert out.tolist() == [[1.0, 0.5625], [-0.5, 0.28125]]
    out_t = placement.to_display(xy, 16, 9)
    assert out_t.tolist() == [[0.5625, 1.0], [-0.28125, 0.5]]
    assert placement.to_display(xy, 9, 16, "stretch") is xy
    assert placement.to_display(xy, 10, 10, display_mm=(30.0, 20.0))[0].tolist() == pytest.approx([2 / 3, 1.0])


# ---------------------------------------------------------------- the stage base class, foveation


class _Probe(Stage):
    name = "probe"

    def process(self, image, state, ctx):
        self.seen = (state, ctx)
        return image * 2


def test_stage_defaults_and_resolve():
    p = _Probe()
    img = torch.ones(2, 3, 4, 5, dtype=D)
    assert torch.equal(p(img), img * 2)
    state, ctx = p.seen
    assert state == RuntimeState() and ctx.native_size == (4, 5) and ctx.reference is None and ctx.record is None
    s = RuntimeState(downsample=2.0)
    c = StageContext((8, 10))
    p(img, s, c)
    assert p.seen == (s, c)
    assert not p.is_identity(s) and p.domain == "linear" and p.after is None and p.before is None
    with pytest.raises(NotImplementedError):
        Stage().process(img, s, c)


def _ordered(order: float) -> Stage:
    return type(f"At{order}".replace(".", "_"), (Stage,), {"name": f"at{order}", "order": order,
                                                         "process": lambda self, i, s, c: i})()


def test_default_orders_of_the_stages():
    # a third-party stage without an order runs after every built-in (order 100 > 50)
    plain = type("Plain", (Stage,), {"name": "plain", "process": lambda self, i, s, c: i})()
    pipe = Pipeline([plain, _ordered(100.1), _ordered(99.9), OLEDEmission(), Foveation(), _ordered(4.9),
                     _ordered(5.1), AreaResample(), DisplayMapping(), _ordered(29.9), _ordered(30.1),
                     _ordered(19.9), _ordered(20.1), _ordered(39.9), _ordered(40.1)])
    assert pipe.names == ["at4.9", "foveation", "at5.1", "at19.9", "resample", "at20.1", "at29.9", "display",
                          "at30.1", "at39.9", "oled", "at40.1", "at99.9", "plain", "at100.1"]


def test_foveation_is_always_the_identity():
    st = Foveation()
    img = torch.rand(3, 2, 2)
    for s in (RuntimeState(), RuntimeState(gaze=(0.5, -0.5), downsample=2.0, power_saving=0.3)):
        assert st.is_identity(s) and st.is_identity(s, StageContext((2, 2), reference=img))
    assert st(img, RuntimeState(gaze=(0.1, 0.1))) is img
    assert foveation(img, None) is img


def test_radial_coefficients_are_checked_as_stored_in_float32():
    from controlgs_adapter.downstream.lens import RadialMap

    with pytest.raises(InputValueError, match="coefficients"):
        RadialMap([[1e39], [0.0], [0.0]])  # finite in float64, inf in the float32 buffer
    assert RadialMap([[1], [0], [0]]).coefficients.dtype == torch.float32  # integers are accepted


def test_functionals_pass_non_finite_values_through_unchecked():
    # the pipeline checks its input once; the stages' functionals accept any value (finite=False)
    from controlgs_adapter.downstream.lens import lens_prewarp, pixel_grid

    x = _img([0.5, 0.5, 0.5], 2, 2)
    x[0, 0, 0] = float("nan")
    for f in (color.srgb_to_linear, color.linear_to_srgb, color.rgb_to_primaries, color.primaries_to_rgb,
              lambda t: oled_emission(t, (4, 4)), lambda t: area_resample(t, 2.0),
              lambda t: lens_prewarp(t, pixel_grid((2, 2), D)[None].expand(3, -1, -1, -1).contiguous()),
              lambda t: display_power(t)[None, None, None].expand(3, 1, 1), lambda t: display_mapping(t, 0.5)):
        assert bool(torch.isnan(f(x)).any())
    assert bool(torch.isnan(display_mapping(_img([0.5] * 3), 0.5, x)).all())  # a NaN reference power


def test_stages_follow_the_image_device():
    # "meta" is a second device on a machine without a GPU: constants must be made on the image's device
    from controlgs_adapter.downstream.lens import LensPrewarp

    x = torch.ones(3, 4, 4, device="meta")
    assert display_power(x).device.type == "meta"
    assert display_mapping(x, 0.5).device.type == "meta"
    assert area_resample(torch.ones(3, 5, 5, device="meta"), 2.5).device.type == "meta"
    assert color.rgb_to_primaries(x).device.type == "meta"
    assert LensPrewarp(basis="rgb")(x).device.type == "meta"
    assert placement.to_display(torch.ones(2, 2, device="meta"), 9, 16).device.type == "meta"


def test_one_pixel_images_are_placed():
    # the bounds are inclusive: 1 x 1 spans the display (pitch 24 mm); 2 x 1 (tall) is height-limited,
    # pitch 24 / 2 = 12 mm, width 12 mm = half_x 0.5; 1 x 2 likewise on its side
    one = placement.image_region(1, 1)
    assert (one.half_x, one.half_y, one.pitch_mm) == (1.0, 1.0, (24.0, 24.0))
    tall = placement.image_region(2, 1)
    assert (tall.half_x, tall.half_y, tall.pitch_mm, tall.size_mm) == (0.5, 1.0, (12.0, 12.0), (12.0, 24.0))
    wide = placement.image_region(1, 2)
    assert (wide.half_x, wide.half_y, wide.size_mm) == (1.0, 0.5, (24.0, 12.0))
