"""Tests of ``controlgs_adapter.downstream.color``."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.downstream import color
from controlgs_adapter.downstream.color import (
    PRIMARY_WAVELENGTHS_NM,
    LinearToSRGB,
    PrimariesToRGB,
    RGBToPrimaries,
    SRGBToLinear,
    convert_domain,
    linear_to_srgb,
    primaries_to_rgb,
    primaries_to_rgb_matrix,
    rgb_to_primaries,
    rgb_to_primaries_matrix,
    srgb_to_linear,
)
from controlgs_adapter.downstream.display import display_mapping, display_power
from controlgs_adapter.downstream.lens import LensPrewarp, lens_prewarp, pixel_grid
from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError

optics_mod = pytest.importorskip("controlgs_adapter.downstream.optics.stage")


STATE = RuntimeState()


# ----------------------------------------------------------------------------- pre-warp then optics
DOTS = ((0.0, 0.0), (0.6, 0.5), (-0.6, -0.5), (0.75, -0.6), (-0.45, 0.7), (0.85, 0.0), (0.0, -0.8))


def _dots(h: int, w: int) -> tuple[torch.Tensor, list[tuple[int, int]]]:
    img = torch.zeros(3, h, w, dtype=torch.float64)
    where = []
    for x, y in DOTS:
        i, j = int((y + 1) / 2 * h), int((x + 1) / 2 * w)
        img[:, i, j] = 1.0
        where.append((i, j))
    return img, where


def _centroids(img: torch.Tensor, where: list[tuple[int, int]], r: int = 4) -> torch.Tensor:
    """``[dots, 3, 2]`` (row, col) light centroid of each primary in a window around each dot."""
    out = []
    for i, j in where:
        win = img[:, max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].clamp_min(0)
        rows = torch.arange(max(i - r, 0), max(i - r, 0) + win.shape[1], dtype=img.dtype)
        cols = torch.arange(max(j - r, 0), max(j - r, 0) + win.shape[2], dtype=img.dtype)
        s = win.sum((1, 2))
        out.append(torch.stack([(win.sum(2) * rows).sum(1) / s, (win.sum(1) * cols).sum(1) / s], -1))
    return torch.stack(out)


@pytest.mark.parametrize("h, w", [(48, 48), (27, 48), (48, 27)])
def test_prewarp_then_optics_lands_dots_where_they_started(h, w):
    """The pipeline's lens (built from the optics' bank for the same region), then the optics'
    chief-ray warp: each white dot is seen where it was rendered, to a fraction of a pixel."""
    p = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": {"mode": "distortion"}}).double()
    target, where = _dots(h, w)
    prim = rgb_to_primaries(target)                 # the optics is separable per primary: warp in that domain
    shown = primaries_to_rgb(p["lens"](prim, STATE, StageContext((h, w))))
    eye = rgb_to_primaries(optics_mod.psf_optics(shown, p["optics"].bank, mode="distortion"))
    plain = rgb_to_primaries(optics_mod.psf_optics(target, p["optics"].bank, mode="distortion"))
    want = torch.tensor(where, dtype=torch.float64)[:, None, :]
    err = (_centroids(eye, where) - want).norm(dim=-1)          # [dots, 3]
    moved = (_centroids(plain, where) - want).norm(dim=-1)
    assert float(err.max()) < 0.25, err                          # the same as for a square image
    assert float(moved.max()) > 0.8                              # without the pre-warp the outer dots move


def test_a_prewarp_for_the_wrong_region_misses():
    """Sensitivity of the dot test: a pre-warp built as if the 27 x 48 image spanned the display
    (stretch) does not land the dots under the "fit" optics."""
    bank = PSFBank.default()
    target, where = _dots(27, 48)
    prim = rgb_to_primaries(target)
    wrong = LensPrewarp.from_psf_bank(bank, placement="stretch").double()
    wrong.basis = "rgb"  # applied to primaries below
    eye = rgb_to_primaries(optics_mod.psf_optics(primaries_to_rgb(wrong(prim, STATE, StageContext((27, 48)))), bank,
                                             mode="distortion"))
    err = (_centroids(eye, where) - torch.tensor(where, dtype=torch.float64)[:, None, :]).norm(dim=-1)
    assert float(err.max()) > 0.3


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


needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


# ----------------------------------------------------------------------------- a perfect render comes back
def _patch(x: torch.Tensor, u: float, v: float, r: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    i, j = int((v + 1) / 2 * h), int((u + 1) / 2 * w)
    return x[..., i - r:i + r, j - r:j + r].mean()


@needs_optics
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_ground_truth_through_the_default_pipeline_comes_back_within_three_percent(mode):
    h = 96
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h, dtype=torch.float64), torch.linspace(-1, 1, h, dtype=torch.float64),
                            indexing="ij")
    smooth = torch.stack([0.5 + 0.2 * torch.cos(2 * xx + yy), 0.45 + 0.2 * torch.sin(xx - 2 * yy), 0.4 + 0.1 * xx * yy])
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True, "optics": {"mode": mode}}).double()
    for gt in (torch.full((3, h, h), 0.6, dtype=torch.float64), smooth):
        eye = srgb_to_linear(pipe(gt, RuntimeState(), reference=gt))
        ref = srgb_to_linear(gt)
        for u, v in ((0.0, 0.0), (0.8, 0.8), (-0.8, -0.8), (0.8, -0.8), (-0.8, 0.8)):
            ratio = float(_patch(eye, u, v, 3) / _patch(ref, u, v, 3))
            assert abs(ratio - 1.0) < 0.03, (u, v, ratio)


CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]


def test_transfer_functions_match_colour_science():
    t = torch.from_numpy(np.linspace(0.0, 1.0, 3 * 27 * 74)).reshape(3, 27, 74)
    ref_dec = colour.cctf_decoding(t.numpy(), function="sRGB")
    ref_enc = colour.cctf_encoding(t.numpy(), function="sRGB")
    assert np.allclose(srgb_to_linear(t).numpy(), ref_dec, atol=1e-12, rtol=0)
    assert np.allclose(linear_to_srgb(t).numpy(), ref_enc, atol=1e-12, rtol=0)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-0.5, 2.0, allow_nan=False), min_size=3, max_size=30))
def test_srgb_round_trip(values):
    n = len(values) // 3 * 3
    x = torch.tensor(values[:n], dtype=torch.float64).reshape(3, 1, -1)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12, rtol=0)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12, rtol=0)
    x32 = x.float()
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x32)), x32, atol=1e-6, rtol=0)


def test_transfer_functions_continuous_and_finite_gradient_at_zero():
    for f, thr in ((srgb_to_linear, 0.04045), (linear_to_srgb, 0.04045 / 12.92)):
        lo = torch.full((3, 1, 1), thr, dtype=torch.float64)
        hi = torch.full((3, 1, 1), thr + 1e-12, dtype=torch.float64)
        assert float((f(hi) - f(lo)).abs().max()) < 1e-7  # IEC thresholds agree to ~1e-8
        z = torch.zeros(3, 2, 2, dtype=torch.float64, requires_grad=True)
        f(z).sum().backward()
        assert torch.isfinite(z.grad).all() and (z.grad > 0).all()


def test_transfer_functions_gradcheck():
    # values away from the thresholds (the piecewise kink is not differentiable)
    x = torch.rand(2, 3, 4, 5, dtype=torch.float64) * 1.2 + 0.05
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(srgb_to_linear, (x,))
    assert torch.autograd.gradcheck(linear_to_srgb, (x,))
    neg = (-torch.rand(3, 2, 2, dtype=torch.float64)).requires_grad_(True)
    assert torch.autograd.gradcheck(srgb_to_linear, (neg,))


def test_primaries_reproduce_spectral_chromaticities():
    """Each primary alone, converted back to linear sRGB and then to XYZ by colour-science, must
    have the chromaticity of the spectral locus at its wavelength."""
    back = primaries_to_rgb_matrix()  # columns: RGB of each unit primary
    for i, wl in enumerate(PRIMARY_WAVELENGTHS_NM):
        xyz = colour.RGB_to_XYZ(back[:, i].numpy(), "sRGB", apply_cctf_decoding=False)
        assert np.allclose(colour.XYZ_to_xy(xyz), colour.XYZ_to_xy(CMFS[wl]), atol=1e-9)


def test_white_drives_all_primaries_equally():
    white = torch.ones(3, 2, 2, dtype=torch.float64)
    assert torch.allclose(rgb_to_primaries(white), white, atol=1e-12)


def test_matrices_are_exact_inverses():
    a, b = rgb_to_primaries_matrix(), primaries_to_rgb_matrix()
    assert torch.allclose(a @ b, torch.eye(3, dtype=torch.float64), atol=1e-13)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=12, max_size=12), st.sampled_from([torch.float32, torch.float64]))
def test_primaries_round_trip_identity(values, dtype):
    rgb = torch.tensor(values, dtype=dtype).reshape(1, 3, 2, 2)
    rgb[..., 0, 0] = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)  # saturated sRGB blue
    s = rgb_to_primaries(rgb)
    assert float(s[0, 1, 0, 0]) < 0  # outside the 656/550/486 triangle: negative 550 nm drive
    assert torch.allclose(primaries_to_rgb(s), rgb, atol=1e-6, rtol=0)


def test_module_twins_and_domain_conversion():
    x = torch.rand(2, 3, 4, 4)
    assert torch.equal(SRGBToLinear()(x), srgb_to_linear(x))
    assert torch.equal(LinearToSRGB()(x), linear_to_srgb(x))
    assert torch.equal(RGBToPrimaries()(x), rgb_to_primaries(x))
    assert torch.equal(PrimariesToRGB()(x), primaries_to_rgb(x))
    assert convert_domain(x, "linear", "linear") is x
    assert torch.equal(convert_domain(x, "srgb", "linear"), srgb_to_linear(x))
    with pytest.raises(ValueError):
        convert_domain(x, "srgb", "xyz")  # type: ignore[arg-type]


def test_bad_input_names_the_argument():
    with pytest.raises(ShapeError, match="image"):
        srgb_to_linear(torch.rand(4, 5, 5))
    with pytest.raises(InputValueError, match="primaries"):
        primaries_to_rgb(torch.rand(3, 5, 5, dtype=torch.float16))
    with pytest.raises(InputValueError, match="image"):
        rgb_to_primaries([[0.0, 0.0, 1.0]])  # type: ignore[arg-type]


def test_primaries_for_other_wavelengths_drive_white_at_one_in_every_primary():
    # the uncached builder (any R, G, B primaries whose gamut holds the sRGB white): each primary's
    # unit is the drive white needs, so linear white (1, 1, 1) -> (1, 1, 1); the second matrix inverts it
    colour = pytest.importorskip("colour")
    from controlgs_adapter.downstream import color

    to_p, to_rgb = color._primaries_matrices_for((638, 532, 465))
    assert to_p @ np.ones(3) == pytest.approx(np.ones(3), abs=1e-12)
    assert to_p @ to_rgb == pytest.approx(np.eye(3), abs=1e-12)
    # the rows are C^-1 M scaled per primary: the primaries' light C diag(u) to_p gives sRGB's XYZ
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    cm = np.stack([np.asarray(cmfs[w]) for w in (638, 532, 465)], axis=1)
    m = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ)
    u = np.linalg.solve(cm, m @ np.ones(3))
    assert np.all(u > 0)
    assert cm @ np.diag(u) @ to_p == pytest.approx(m, abs=1e-12)


D = torch.float64


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


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


def test_functionals_pass_non_finite_values_through_unchecked():
    # the pipeline checks its input once; the stages' functionals accept any value (finite=False)
    from controlgs_adapter.downstream.lens import pixel_grid

    x = _img([0.5, 0.5, 0.5], 2, 2)
    x[0, 0, 0] = float("nan")
    for f in (color.srgb_to_linear, color.linear_to_srgb, color.rgb_to_primaries, color.primaries_to_rgb,
              lambda t: oled_emission(t, (4, 4)), lambda t: area_resample(t, 2.0),
              lambda t: lens_prewarp(t, pixel_grid((2, 2), D)[None].expand(3, -1, -1, -1).contiguous()),
              lambda t: display_power(t)[None, None, None].expand(3, 1, 1), lambda t: display_mapping(t, 0.5)):
        assert bool(torch.isnan(f(x)).any())
    assert bool(torch.isnan(display_mapping(_img([0.5] * 3), 0.5, x)).all())  # a NaN reference power


_CALLS: list[str] = []  # names of the _Scale stages processed, in call order


class _Scale(Stage):
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


def _stage(name: str, order: float, domain: str = "linear", factor: float = 1.0) -> Stage:
    return type(name.title(), (_Scale,), {"name": name, "order": order, "domain": domain})(factor)


def test_pipeline_orders_by_order_then_name_and_skips_identities():
    b, a, c = _stage("b", 1.0, factor=3.0), _stage("a", 1.0, factor=2.0), _stage("c", 0.5, factor=1.0)
    p = Pipeline([b, a, c]).double()
    assert p.names == ["c", "a", "b"]  # c first by order; a before b by name at equal order
    image = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)[:, None, None].expand(3, 2, 2)
    _CALLS.clear()
    eye, rec = p.run_recorded(image)
    assert _CALLS == ["a", "b"] and rec["stages_run"] == ["a", "b"]  # c is the identity: not called
    assert torch.allclose(eye, linear_to_srgb(srgb_to_linear(image) * 6.0), atol=1e-12)
    # no physical stage: post and displayed are the eye image, rendered the input
    assert torch.equal(rec["post"], eye) and torch.equal(rec["displayed"], eye) and torch.equal(rec["rendered"], image)
    assert rec["diagnostics"] == {}
    assert p.active(RuntimeState()) == ["a", "b"]
    assert "a" in p and "z" not in p and p["b"] is b
    with pytest.raises(KeyError, match="no stage 'z'"):
        p["z"]


def test_pipeline_converts_domains_only_around_stages_that_run():
    lin, enc = _stage("lin", 1.0, "linear", 2.0), _stage("enc", 2.0, "srgb", 0.5)
    image = torch.rand(3, 3, 3, dtype=torch.float64)
    out = Pipeline([lin, enc]).double()(image)
    assert torch.allclose(out, linear_to_srgb(srgb_to_linear(image) * 2.0) * 0.5, atol=1e-12)
    only_srgb = Pipeline([_stage("lin", 1.0, "linear", 1.0), enc]).double()(image)
    assert torch.allclose(only_srgb, image * 0.5, atol=1e-15)  # skipped linear stage: no round trip


def test_pipeline_post_is_taken_before_the_first_physical_stage():
    p = Pipeline([_stage("pre", 1.0, factor=0.5), _stage("oled", 40.0, factor=2.0), _stage("optics", 50.0, factor=3.0)]).double()
    image = torch.rand(3, 2, 3, dtype=torch.float64)
    eye, rec = p.run_recorded(image)
    lin = srgb_to_linear(image)
    assert torch.allclose(rec["post"], linear_to_srgb(lin * 0.5), atol=1e-12)
    assert torch.allclose(rec["displayed"], linear_to_srgb(lin * 1.0), atol=1e-12)  # after oled, before optics
    assert torch.allclose(eye, linear_to_srgb(lin * 3.0), atol=1e-12)
    assert rec["stages_run"] == ["pre", "oled", "optics"]


def test_convert_domain_identity_and_refusal():
    x = torch.rand(3, 2, 2, dtype=torch.float64)
    assert convert_domain(x, "linear", "linear") is x and convert_domain(x, "srgb", "srgb") is x
    assert torch.equal(convert_domain(x, "srgb", "linear"), srgb_to_linear(x))
    assert torch.equal(convert_domain(x, "linear", "srgb"), linear_to_srgb(x))
    with pytest.raises(ValueError, match="'srgb' -> 'xyz'"):
        convert_domain(x, "srgb", "xyz")  # type: ignore[arg-type]


def test_lens_prewarp_in_the_primaries_basis_shifts_each_primary():
    """Whole-pixel shifts, a different one per channel: in the primaries basis each display primary
    is shifted (zero fill) and the result converted back to RGB; brute force by slicing."""
    from controlgs_adapter.downstream.color import primaries_to_rgb, rgb_to_primaries

    h, w = 5, 6
    img = torch.rand(2, 3, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    shifts = [(1, 0), (0, -2), (-1, 1)]  # (dy, dx) pixels sampled from: out[y, x] = in[y + dy, x + dx]
    base = pixel_grid((h, w), torch.float64)
    grid = torch.stack([base + torch.tensor([2.0 * dx / w, 2.0 * dy / h], dtype=torch.float64) for dy, dx in shifts])
    gain = torch.tensor([1.0, 0.5, 2.0], dtype=torch.float64)[:, None, None].expand(3, h, w).contiguous()

    def shifted(x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(x)
        for c, (dy, dx) in enumerate(shifts):
            src = torch.nn.functional.pad(x[:, c], (2, 2, 2, 2))
            out[:, c] = src[:, 2 + dy:2 + dy + h, 2 + dx:2 + dx + w] * gain[c, 0, 0]
        return out

    assert torch.allclose(lens_prewarp(img, grid, gain, basis="rgb"), shifted(img), atol=1e-12)
    want = primaries_to_rgb(shifted(rgb_to_primaries(img)))
    assert torch.allclose(lens_prewarp(img, grid, gain, basis="primaries"), want, atol=1e-12)
    assert not torch.allclose(want, shifted(img), atol=1e-3)


def test_primaries_matrix_from_the_iec_srgb_matrix_by_hand():
    """C^-1 M with M the IEC 61966-2-1 sRGB -> XYZ matrix as printed (4 digits) and C the CIE 1931
    2-degree CMFs at 656 / 550 / 486 nm; rows scaled so that white drives every primary at 1."""
    colour = pytest.importorskip("colour")
    import numpy as np

    from controlgs_adapter.downstream.color import primaries_to_rgb_matrix, rgb_to_primaries_matrix

    iec = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    c = np.stack([np.asarray(cmfs[w], dtype=np.float64) for w in (656, 550, 486)], axis=1)
    raw = np.linalg.solve(c, iec)
    want = raw / raw.sum(1, keepdims=True)
    got = rgb_to_primaries_matrix().numpy()
    assert np.allclose(got, want, atol=2e-3)
    assert np.allclose(got.sum(1), 1.0, atol=1e-12)
    assert np.allclose(primaries_to_rgb_matrix().numpy(), np.linalg.inv(want), atol=5e-3)
    assert rgb_to_primaries_matrix(torch.float32).dtype == torch.float32
