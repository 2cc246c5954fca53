"""Tests of ``controlgs_adapter.downstream.optics.visual_angles``: directions, pixels per degree and
eccentricity on an analytic lens (chief rays ``q = d (1 + k |d|^2)``) against a hand computation."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.banks import radial_lens_bank, tiny_bank
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.visual_angles import VisualAngles, eccentricity
from controlgs_adapter.errors import InputValueError

K, DIST, MAG = 0.2, 600.0, 15.0
S = 12.0 * MAG / DIST  # tan(angle) per unit of normalised output


def _hand(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions (deg) and pixels per degree of the analytic lens, by hand (square image: the display)."""
    x = (2 * torch.arange(width, dtype=torch.float64) + 1) / width - 1
    y = (2 * torch.arange(height, dtype=torch.float64) + 1) / height - 1
    py, px = torch.meshgrid(y, x, indexing="ij")
    r2 = px ** 2 + py ** 2
    qx, qy = px * (1 + K * r2), py * (1 + K * r2)
    directions = torch.stack([torch.atan(S * qx), torch.atan(S * qy)], -1).rad2deg()
    # d angle / d q per axis, |det dq/dp| = (1 + k r^2)(1 + 3 k r^2), dp/dpixel = 2 / W
    ax = math.degrees(1) * S / (1 + (S * qx) ** 2)
    ay = math.degrees(1) * S / (1 + (S * qy) ** 2)
    det = ax * ay * (1 + K * r2) * (1 + 3 * K * r2) * (2 / width) * (2 / height)
    return directions, det.rsqrt()


def test_directions_and_pixels_per_degree_match_the_hand_computation():
    va = VisualAngles.of_bank(radial_lens_bank(K))
    for h, w in ((32, 32), (64, 64)):
        want_dir, want_ppd = _hand(h, w)
        assert torch.allclose(va.pixel_directions(h, w), want_dir, atol=2e-4, rtol=0)
        assert torch.allclose(va.pixels_per_degree(h, w), want_ppd, rtol=2e-3, atol=0)
    # the Jacobian is the lens's: without the distortion term the corner would have 1.5x the density
    flat = VisualAngles.of_bank(radial_lens_bank(0.0)).pixels_per_degree(64, 64)
    assert float(flat[0, 0] / va.pixels_per_degree(64, 64)[0, 0]) > 1.5


def test_placement_of_a_wide_image():
    """A 16 x 32 image under "fit" spans the display's width and half its height: its directions are the
    square image's rows of the middle half (display y in [-0.5, 0.5])."""
    va = VisualAngles.of_bank(radial_lens_bank(K))
    wide, square = va.pixel_directions(16, 32), va.pixel_directions(32, 32)
    assert torch.allclose(wide, square[8:24], atol=1e-12)


def test_eccentricity_against_closed_forms():
    d = torch.tensor([[0.0, 12.5], [-20.0, 0.0], [7.0, -3.0]], dtype=torch.float64)
    e = eccentricity(d, (0.0, 0.0))
    assert e[:2].tolist() == pytest.approx([12.5, 20.0], abs=1e-12)
    # along the horizon, angles add: (30, 0) from (-20, 0) is 50 degrees
    assert float(eccentricity(torch.tensor([30.0, 0.0], dtype=torch.float64), (-20.0, 0.0))) == pytest.approx(50.0, abs=1e-12)
    u = torch.tensor([math.tan(math.radians(7.0)), math.tan(math.radians(-3.0)), 1.0], dtype=torch.float64)
    assert float(e[2]) == pytest.approx(math.degrees(math.acos(1 / float(u.norm()))), abs=1e-10)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-60, 60), min_size=6, max_size=6))
def test_eccentricity_is_a_metric_on_directions(v):
    a, b, c = (torch.tensor(v[i:i + 2], dtype=torch.float64) for i in (0, 2, 4))
    ab, ba = float(eccentricity(a, b)), float(eccentricity(b, a))
    assert ab == pytest.approx(ba, abs=1e-9) and ab >= 0 and float(eccentricity(a, a)) == pytest.approx(0.0, abs=1e-6)
    assert float(eccentricity(a, c)) <= ab + float(eccentricity(b, c)) + 1e-9


def test_profile_banks_by_degrees_per_output_unit_or_half_field():
    dpu = VisualAngles.of_bank(radial_lens_bank(0.0, C=9, lens={"deg_per_output_unit": 40.0}))
    d = dpu.directions(torch.tensor([[0.5, -0.25]], dtype=torch.float64))[0]
    assert d.tolist() == pytest.approx([math.degrees(math.atan(math.radians(40.0) * q)) for q in (0.5, -0.25)], abs=1e-9)
    half = VisualAngles.of_bank(radial_lens_bank(K, C=65, lens={"half_fov_deg": 45.0}))
    assert float(half.directions(torch.tensor([[1.0, 0.0]], dtype=torch.float64))[0, 0]) == pytest.approx(45.0, abs=1e-9)
    with pytest.raises(InputValueError, match=r"^PSF bank: no visual angles: .*deg_per_output_unit"):
        VisualAngles.of_bank(tiny_bank())


def test_the_field_and_a_gaze_outside_it():
    va = VisualAngles.of_bank(PSFBank.default())
    edge = float(va.directions(torch.tensor([[1.0, 0.0]], dtype=torch.float64))[0, 0])  # ~15.3 deg on Cardboard
    assert va.in_field((0.0, 0.0)) and va.in_field((edge - 0.2, 0.0)) and not va.in_field((edge + 0.2, 0.0))
    corner = va.directions(torch.tensor([[0.98, 0.98]], dtype=torch.float64))[0].tolist()
    assert va.in_field(corner) and not va.in_field((-edge - 0.2, 0.0))
    with pytest.raises(InputValueError, match=r"^gaze \(20, 0\) deg is outside the lens's field \(azimuth -1"):
        va.check_gaze((20.0, 0.0))
