"""Tests of ``controlgs_adapter.downstream.color``: the sRGB transfer functions (against the IEC formula
and colour-science, invertible, finite gradients everywhere), the linear RGB <-> display primaries
matrices (from the CIE colour-matching functions, white at one in every primary), the domain conversion
of stages, and the refusals. The module twins keep the stage contract (``test_stage_contract.py``)."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream import color
from controlgs_adapter.downstream.color import (
    PRIMARY_WAVELENGTHS_NM,
    convert_domain,
    linear_to_srgb,
    primaries_to_rgb,
    primaries_to_rgb_matrix,
    rgb_to_primaries,
    rgb_to_primaries_matrix,
    srgb_to_linear,
)
from controlgs_adapter.errors import InputValueError, ShapeError

D = torch.float64
CMFS = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
SRGB_TO_XYZ = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ)


def _iec_decode(v: float) -> float:  # IEC 61966-2-1, written out here independently
    return v / 12.92 if v <= 0.04045 else ((v + 0.055) / 1.055) ** 2.4


def _iec_encode(v: float) -> float:
    return v * 12.92 if v <= 0.04045 / 12.92 else 1.055 * v ** (1 / 2.4) - 0.055


# ----------------------------------------------------------------------------- transfer functions
def test_srgb_transfer_functions_match_the_iec_formula_and_colour_science():
    """Elementwise IEC 61966-2-1 on the whole real line (negatives on the linear segment, values above 1 on
    the power branch); colour-science's sRGB CCTFs on [0, 1]; worked out: 0.5 encoded is the textbook mid-grey
    0.21404114, 0.001 linear encodes to 0.01292."""
    for v in (-0.5, -0.01, 0.0, 0.02, 0.04, 0.05, 0.5, 1.0, 1.7):
        x = torch.full((3, 1, 1), v, dtype=D)
        assert float(srgb_to_linear(x)[0, 0, 0]) == pytest.approx(_iec_decode(v), rel=1e-12, abs=1e-15)
        assert float(linear_to_srgb(x)[0, 0, 0]) == pytest.approx(_iec_encode(v), rel=1e-12, abs=1e-15)
    t = torch.from_numpy(np.linspace(0.0, 1.0, 3 * 27 * 74)).reshape(3, 27, 74)
    assert np.allclose(srgb_to_linear(t).numpy(), colour.cctf_decoding(t.numpy(), function="sRGB"), atol=1e-12, rtol=0)
    assert np.allclose(linear_to_srgb(t).numpy(), colour.cctf_encoding(t.numpy(), function="sRGB"), atol=1e-12, rtol=0)
    x = torch.tensor([0.5, 0.02, 1.0], dtype=D)[:, None, None]
    assert srgb_to_linear(x).flatten().tolist() == pytest.approx([0.21404114, 0.02 / 12.92, 1.0], rel=1e-7)
    y = torch.tensor([0.21404114, 0.001, 1.0], dtype=D)[:, None, None]
    assert linear_to_srgb(y).flatten().tolist() == pytest.approx([0.5, 0.01292, 1.0], rel=1e-6)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-0.5, 2.0, allow_nan=False), min_size=3, max_size=30))
def test_srgb_round_trip(values):
    n = len(values) // 3 * 3
    x = torch.tensor(values[:n], dtype=D).reshape(3, 1, -1)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x)), x, atol=1e-12, rtol=0)
    assert torch.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12, rtol=0)
    x32 = x.float()
    assert torch.allclose(linear_to_srgb(srgb_to_linear(x32)), x32, atol=1e-6, rtol=0)


def test_transfer_functions_are_continuous_with_finite_gradients_everywhere():
    """The branches meet at the thresholds (to 1e-7 across 1e-12); the unused power branch sees clamped
    inputs, so negative and zero inputs have finite gradients: the linear segment's slopes 1/12.92 and
    12.92; gradcheck away from the kinks, negatives and values above 1 included."""
    for f, thr in ((srgb_to_linear, 0.04045), (linear_to_srgb, 0.04045 / 12.92)):
        lo = torch.full((3, 1, 1), thr, dtype=D)
        hi = torch.full((3, 1, 1), thr + 1e-12, dtype=D)
        assert float((f(hi) - f(lo)).abs().max()) < 1e-7
        z = torch.zeros(3, 2, 2, dtype=D, requires_grad=True)
        f(z).sum().backward()
        assert torch.isfinite(z.grad).all() and (z.grad > 0).all()
    x = torch.tensor([-0.5, -0.06, 0.0, 0.5], dtype=D)[:, None, None, None].expand(4, 3, 1, 1).clone().requires_grad_(True)
    srgb_to_linear(x).sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad[0, 0, 0, 0]) == pytest.approx(1 / 12.92)
    x.grad = None
    linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all() and float(x.grad[2, 0, 0, 0]) == pytest.approx(12.92)
    pos = (torch.rand(2, 3, 4, 5, dtype=D) * 1.2 + 0.05).requires_grad_(True)
    assert torch.autograd.gradcheck(srgb_to_linear, (pos,)) and torch.autograd.gradcheck(linear_to_srgb, (pos,))
    neg = (-torch.rand(3, 2, 2, dtype=D)).requires_grad_(True)
    assert torch.autograd.gradcheck(srgb_to_linear, (neg,))


# ----------------------------------------------------------------------------- display primaries
@pytest.mark.parametrize("wavelengths", [PRIMARY_WAVELENGTHS_NM, (638, 532, 465)])
def test_primaries_matrices_from_the_cie_colour_matching_functions(wavelengths):
    """Rows C^-1 M (C the CIE 1931 2-degree CMFs at the primaries, M sRGB -> XYZ, both read from
    colour-science here), each primary scaled by the drive white needs: linear white (1, 1, 1) -> (1, 1, 1),
    the primaries' light C diag(u) to_p is sRGB's XYZ with u > 0, and the second matrix is the exact inverse.
    The library's matrices are those of 656 / 550 / 486 nm, and the functional forms apply them over the
    channel axis."""
    to_p, to_rgb = color._primaries_matrices_for(tuple(wavelengths))
    c = np.stack([np.asarray(CMFS[w], dtype=np.float64) for w in wavelengths], axis=1)
    u = np.linalg.solve(c, SRGB_TO_XYZ @ np.ones(3))
    assert np.all(u > 0)
    assert c @ np.diag(u) @ to_p == pytest.approx(SRGB_TO_XYZ, abs=1e-12)
    assert to_p @ np.ones(3) == pytest.approx(np.ones(3), abs=1e-12)
    assert to_p @ to_rgb == pytest.approx(np.eye(3), abs=1e-12)
    if tuple(wavelengths) == PRIMARY_WAVELENGTHS_NM:
        a, b = rgb_to_primaries_matrix(), primaries_to_rgb_matrix()
        assert a.numpy() == pytest.approx(to_p, abs=0) and b.numpy() == pytest.approx(to_rgb, abs=0)
        assert torch.allclose(a @ b, torch.eye(3, dtype=D), atol=1e-13)
        assert rgb_to_primaries_matrix(torch.float32).dtype == torch.float32
        rgb = torch.tensor([0.2, 0.5, 0.9], dtype=D)[:, None, None]
        s = rgb_to_primaries(rgb)
        assert s.flatten().numpy() == pytest.approx(to_p @ np.array([0.2, 0.5, 0.9]), abs=1e-12)
        assert primaries_to_rgb(s).flatten().tolist() == pytest.approx([0.2, 0.5, 0.9], abs=1e-12)
        white = torch.ones(3, 2, 2, dtype=D)
        assert torch.allclose(rgb_to_primaries(white), white, atol=1e-12)


def test_primaries_matrix_from_the_printed_iec_srgb_matrix():
    """C^-1 M with M the IEC 61966-2-1 sRGB -> XYZ matrix as printed (4 digits): the library's matrix to
    2e-3, its rows summing to 1 (white at one), and its inverse to 5e-3."""
    iec = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    c = np.stack([np.asarray(CMFS[w], dtype=np.float64) for w in (656, 550, 486)], axis=1)
    raw = np.linalg.solve(c, iec)
    want = raw / raw.sum(1, keepdims=True)
    got = rgb_to_primaries_matrix().numpy()
    assert np.allclose(got, want, atol=2e-3)
    assert np.allclose(got.sum(1), 1.0, atol=1e-12)
    assert np.allclose(primaries_to_rgb_matrix().numpy(), np.linalg.inv(want), atol=5e-3)


def test_primaries_reproduce_spectral_chromaticities():
    """Each primary alone, converted back to linear sRGB and then to XYZ by colour-science, has the
    chromaticity of the spectral locus at its wavelength."""
    back = primaries_to_rgb_matrix()  # columns: RGB of each unit primary
    for i, wl in enumerate(PRIMARY_WAVELENGTHS_NM):
        xyz = colour.RGB_to_XYZ(back[:, i].numpy(), "sRGB", apply_cctf_decoding=False)
        assert np.allclose(colour.XYZ_to_xy(xyz), colour.XYZ_to_xy(CMFS[wl]), atol=1e-9)


def test_primaries_whose_gamut_misses_white_are_refused():
    """600 / 550 / 500 nm lie on the yellow-green-cyan part of the spectral locus; D65 white (x 0.3127,
    y 0.329) is below the 600-500 nm edge (y ~0.457 there), so outside the triangle."""
    with pytest.raises(RuntimeError, match=r"gamut.*\(600, 550, 500\)"):
        color._primaries_matrices_for((600, 550, 500))


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=12, max_size=12), st.sampled_from([torch.float32, torch.float64]))
def test_primaries_round_trip_with_negative_drives_outside_the_gamut(values, dtype):
    rgb = torch.tensor(values, dtype=dtype).reshape(1, 3, 2, 2)
    rgb[..., 0, 0] = torch.tensor([0.0, 0.0, 1.0], dtype=dtype)  # saturated sRGB blue
    s = rgb_to_primaries(rgb)
    assert float(s[0, 1, 0, 0]) < 0  # outside the 656/550/486 triangle: negative 550 nm drive
    assert torch.allclose(primaries_to_rgb(s), rgb, atol=1e-6, rtol=0)


# ----------------------------------------------------------------------------- domains and refusals
def test_convert_domain_between_stages():
    x = torch.rand(3, 2, 2, dtype=D)
    assert convert_domain(x, "linear", "linear") is x and convert_domain(x, "srgb", "srgb") is x
    assert torch.equal(convert_domain(x, "srgb", "linear"), srgb_to_linear(x))
    assert torch.equal(convert_domain(x, "linear", "srgb"), linear_to_srgb(x))
    with pytest.raises(ValueError, match="'srgb' -> 'xyz'"):
        convert_domain(x, "srgb", "xyz")  # type: ignore[arg-type]


def test_bad_input_names_the_argument():
    with pytest.raises(ShapeError, match="image"):
        srgb_to_linear(torch.rand(4, 5, 5))
    with pytest.raises(InputValueError, match="primaries"):
        primaries_to_rgb(torch.rand(3, 5, 5, dtype=torch.float16))
    with pytest.raises(InputValueError, match="image"):
        rgb_to_primaries([[0.0, 0.0, 1.0]])  # type: ignore[arg-type]
