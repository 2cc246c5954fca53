"""Colour conversions: sRGB transfer functions and the three monochromatic display primaries."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.color import (
    PRIMARY_WAVELENGTHS_NM, LinearToSRGB, PrimariesToRGB, RGBToPrimaries, SRGBToLinear, convert_domain,
    linear_to_srgb, primaries_to_rgb, primaries_to_rgb_matrix, rgb_to_primaries, rgb_to_primaries_matrix,
    srgb_to_linear,
)
from controlgs_adapter.errors import InputValueError, ShapeError

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
