"""The strength schedules (Eqs. 10-11): each built-in schedule's control value, endpoints, clamping,
row count, dtype and device, their registration through the plug-in hook, and their refusals."""

from __future__ import annotations

import json
import math

import pytest
import torch
from helpers.banks import radial_lens_bank
from helpers.strength_oracle import STATES, reference_strengths
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.builtin import controlgs_register_schedules
from controlgs_adapter.downstream.optics.visual_angles import HEADER_SAMPLES, VisualAngles
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.schedules import (
    BUILTIN_SCHEDULES,
    DisplaySchedule,
    FoveationSchedule,
    LensSchedule,
    ResampleSchedule,
    StrengthSchedule,
)

D = torch.float64


def test_schedule_strengths_by_hand():
    """clamp((alpha - lo) / (hi - lo), 0, 1) of each schedule's control value alpha, at default and
    other endpoints, inverted ones included."""
    rs = ResampleSchedule(lo=1.0, hi=2.0)  # alpha = log2(d)
    for d, want in ((2.0, 0.0), (2 ** 1.5, 0.5), (2 ** 1.75, 0.75), (8.0, 1.0), (1.0, 0.0)):
        got = rs.strength(RuntimeState(downsample=d), rows=2, dtype=D)
        assert got.tolist() == pytest.approx([want, want], abs=1e-12), d
    s = ResampleSchedule().with_endpoints(hi=2.0)
    assert type(s) is ResampleSchedule and (s.lo, s.hi) == (0.0, 2.0)
    assert (s.with_endpoints(lo=1.0).lo, s.with_endpoints(lo=1.0).hi) == (1.0, 2.0)
    assert s.strength(RuntimeState(downsample=2.0), rows=2).tolist() == [0.5, 0.5]  # log2(2) / 2
    assert s.scalar_strength(3.0) == 1.0 and s.scalar_strength(-1.0) == 0.0 and s.scalar_strength(0.5) == 0.25
    assert ResampleSchedule().strength(RuntimeState(downsample=8.0), rows=3).tolist() == [1.0, 1.0, 1.0]

    lam = DisplaySchedule().strength(RuntimeState(power_saving=0.2), rows=3, dtype=D)  # alpha = rho, hi 0.8
    assert lam.dtype == D and lam.tolist() == [0.2 / 0.8] * 3
    assert float(DisplaySchedule(lo=0.2, hi=0.6).strength(RuntimeState(power_saving=0.5), rows=1, dtype=D)) == \
        pytest.approx(0.75)
    inv = DisplaySchedule(lo=0.8, hi=0.0)
    assert float(inv.strength(RuntimeState(power_saving=0.2), rows=1, dtype=D)) == pytest.approx(0.75)
    assert float(inv.strength(RuntimeState(power_saving=0.9), rows=1, dtype=D)) == 0.0
    lam = DisplaySchedule().strength(RuntimeState(power_saving=0.4), torch.zeros(4, 2), dtype=D)
    assert lam.tolist() == [0.5] * 4  # a global schedule takes its row count from screen_xy

    lens = LensSchedule(lo=0.5, hi=1.0)  # alpha = |p|
    xy = torch.tensor([[0.3, 0.4], [0.45, -0.6], [0.6, 0.8], [3.0, 4.0], [0.1, 0.0], [math.inf, math.inf]], dtype=D)
    assert lens.strength(RuntimeState(), xy, dtype=D).tolist() == pytest.approx([0.0, 0.5, 1.0, 1.0, 0.0, 1.0])
    xy = torch.tensor([[0.0, 0.0], [0.6, 0.8], [3.0, 4.0]], dtype=D)
    assert LensSchedule(0.5, 1.5).strength(RuntimeState(), xy, dtype=D).tolist() == [0.0, 0.5, 1.0]
    moved = lens.with_endpoints(hi=2.0)
    assert (moved.lo, moved.hi) == (0.5, 2.0)
    inverted = LensSchedule(lo=1.0, hi=0.0)  # strongest injection at the centre
    assert torch.allclose(inverted.strength(RuntimeState(), torch.tensor([[0.0, 0.0], [0.6, 0.8]])), torch.tensor([1.0, 0.0]))

    # foveation: alpha = the angle in degrees between the gaze and the direction p is seen in, here
    # through a distortion-free lens with tan(angle) = 0.3 q (default endpoints 0 .. 30 degrees)
    flat = VisualAngles.of_bank(radial_lens_bank(0.0, C=9))
    fov = FoveationSchedule(angles=flat)
    got = fov.strength(RuntimeState(gaze=(0.0, 0.0)), xy, dtype=D)  # (3, 4) is clamped to the corner (1, 1)
    want = [0.0, math.degrees(math.atan(0.3)) / 30, math.degrees(math.atan(0.3 * math.sqrt(2))) / 30]
    assert torch.allclose(got, torch.tensor(want, dtype=D), rtol=0, atol=1e-12)
    horizon = torch.tensor([[0.2, 0.0], [-0.5, 0.0], [1.0, 0.0]], dtype=D)  # on the horizon angles subtract
    fov = FoveationSchedule(lo=2.0, hi=12.0, angles=flat)
    got = fov.strength(RuntimeState(gaze=(10.0, 0.0)), horizon, dtype=D)
    want = [min(max((abs(math.degrees(math.atan(0.3 * q)) - 10.0) - 2.0) / 10.0, 0.0), 1.0) for q in (0.2, -0.5, 1.0)]
    assert torch.allclose(got, torch.tensor(want, dtype=D), rtol=0, atol=1e-12)
    assert fov.strength(RuntimeState(), horizon, dtype=D).tolist() == [0.0, 0.0, 0.0]  # no gaze: eccentricity 0
    assert fov.with_endpoints(hi=20.0).angles is flat
    behind = fov.strength(RuntimeState(gaze=(0.0, 0.0)), torch.tensor([[math.inf, math.inf]], dtype=D))
    assert behind.tolist() == [1.0]  # an anchor behind the camera is far from the gaze
    with pytest.raises(InputValueError, match=r"^gaze \(17, 0\) deg is outside the lens's field"):
        fov.strength(RuntimeState(gaze=(17.0, 0.0)), horizon)  # atan(0.3) = 16.7 deg at the edge
    assert torch.equal(FoveationSchedule().strength(RuntimeState(), torch.tensor([[0.5, 0.5], [-1.0, 1.0]])),
                       torch.zeros(2))


def test_foveation_lens_angles_are_the_map_given():
    """``lens_angles`` is what an adapter file records: the map given, None for the Cardboard lens even once it is built."""
    default = FoveationSchedule()
    default.strength(RuntimeState(gaze=(1.0, 0.0)), torch.zeros(1, 2))  # builds the Cardboard map
    assert default.lens_angles is None and default.with_endpoints(hi=20.0).lens_angles is None
    flat = VisualAngles.of_bank(radial_lens_bank(0.0, C=9))
    assert default.for_lens(flat).with_endpoints(lo=1.0).lens_angles is flat


@pytest.mark.parametrize("k, C, tol_deg", [(0.2, 9, 0.0), (0.0, 257, 1e-12), (0.2, 257, 0.005)])
def test_visual_angles_header_round_trip(k, C, tol_deg):
    """A map of at most HEADER_SAMPLES per axis is recorded on its own grid (exact); a finer one is resampled onto
    65 x 65 (exact for a linear map; for the cubic radial map within ``tol_deg`` of the analytic directions, where
    the 257-grid map itself is within 0.0002 deg)."""
    angles = VisualAngles.of_bank(radial_lens_bank(k, C=C))
    back = VisualAngles.from_header(json.loads(json.dumps(angles.header())))
    assert back.tangents.shape == (min(C, HEADER_SAMPLES), min(C, HEADER_SAMPLES), 2)
    assert (back.display_mm, back.axis) == (angles.display_mm, angles.axis)
    xy = torch.rand(4000, 2, generator=torch.Generator().manual_seed(0), dtype=D) * 2 - 1
    if C <= HEADER_SAMPLES:
        assert torch.equal(back.tangents, angles.tangents) and torch.equal(back.directions(xy), angles.directions(xy))
        return
    q = xy * (1 + k * (xy ** 2).sum(-1, keepdim=True))
    analytic = torch.rad2deg(torch.atan(q * 12 * 15 / 600))  # the bank's 12 mm half display, magnification 15, 600 mm
    assert (back.directions(xy) - analytic).abs().max() <= tol_deg + 1e-9


def test_lens_xy_strength_is_signed_q_over_hi_clamped():
    """(lambda_x, lambda_y) = clamp(q / hi, -1, 1): signed, lo unused, saturating per axis."""
    q = torch.tensor([[0.0, 0.0], [0.3, -0.6], [-2.0, 0.9], [math.inf, -math.inf]], dtype=D)
    got = LensSchedule(lo=0.5, hi=1.2).xy_strength(q)
    want = torch.tensor([[0, 0], [0.25, -0.5], [-1, 0.75], [1, -1]], dtype=D)
    assert got.dtype == D and torch.allclose(got, want, rtol=0, atol=1e-12)
    with pytest.raises(ShapeError, match="q"):
        LensSchedule().xy_strength(torch.zeros(3))


def test_strength_device_follows_screen_xy_unless_given():
    assert DisplaySchedule().strength(RuntimeState(), rows=2, device="meta").device.type == "meta"
    assert LensSchedule().strength(RuntimeState(), torch.zeros(2, 2)).device.type == "cpu"
    assert LensSchedule().strength(RuntimeState(), torch.zeros(2, 2), device="meta").device.type == "meta"


@settings(max_examples=30, deadline=None)
@given(STATES, st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=1, max_size=6))
def test_builtin_schedules_follow_eqs_10_11(state, points):
    xy = torch.tensor(points, dtype=D)
    got = {cls.name: cls().strength(state, xy, dtype=D) for cls in
           (LensSchedule, ResampleSchedule, DisplaySchedule, FoveationSchedule)}
    for i, p in enumerate(points):
        want = reference_strengths(state, p)
        for m, lam in got.items():
            assert 0.0 <= float(lam[i]) <= 1.0
            assert math.isclose(float(lam[i]), want[m], abs_tol=1e-12), (m, p, state)


def test_schedule_refusals_name_the_argument():
    for lo, hi, pattern in [(2.0, 2.0, "differ.*lo = hi = 2.0"), (1.0, 1, "differ.*lo = hi = 1"),
                            (0.0, float("inf"), "finite.*hi=inf"), ("0", 1.0, "finite.*lo='0'"),
                            (0.0, float("nan"), "finite.*hi=nan")]:
        for cls in (LensSchedule, ResampleSchedule, DisplaySchedule):
            with pytest.raises(InputValueError, match=f"'{cls.name}'.*{pattern}"):
                cls(lo, hi)
    with pytest.raises(InputValueError, match="'lens'.*screen_xy.*None"):
        LensSchedule().strength(RuntimeState())
    for per_anchor in (LensSchedule(), FoveationSchedule()):  # control() called directly, without positions
        with pytest.raises(InputValueError, match=f"'{per_anchor.name}'.*screen_xy.*None"):
            per_anchor.control(RuntimeState(), None)
    with pytest.raises(InputValueError, match=r"strength\(\).*screen_xy.*rows"):
        DisplaySchedule().strength(RuntimeState())
    with pytest.raises(ShapeError, match=r"screen_xy.*\[4, 3\]"):
        DisplaySchedule().strength(RuntimeState(), torch.zeros(4, 3))
    with pytest.raises(InputValueError, match="'foveation'.*screen_xy"):
        FoveationSchedule().strength(RuntimeState(gaze=(0.0, 0.0)), rows=3)


def test_schedule_defaults_registration_and_repr():
    table = {LensSchedule: ("lens", True, 0.0, math.sqrt(2.0)), ResampleSchedule: ("resample", False, 0.0, 3.0),
             DisplaySchedule: ("display", False, 0.0, 0.8), FoveationSchedule: ("foveation", True, 0.0, 30.0)}
    registered = plugins.schedules()
    for cls, (name, per_anchor, lo, hi) in table.items():
        s = cls()
        assert (s.name, s.per_anchor, s.lo, s.hi) == (name, per_anchor, lo, hi)
        assert (cls.default_lo, cls.default_hi) == (lo, hi) and s.endpoints() == {"lo": lo, "hi": hi}
        info = registered[name]  # registered through the hook, like a plug-in's
        assert type(info.obj) is cls and info.plugin == "controlgs_adapter.builtin"
        assert (info.obj.lo, info.obj.hi) == (lo, hi)
    assert BUILTIN_SCHEDULES == tuple(table)
    assert [type(s) for s in controlgs_register_schedules()] == list(table)
    base = StrengthSchedule()
    assert (base.lo, base.hi, base.per_anchor) == (0.0, 1.0, False)
    with pytest.raises(NotImplementedError):
        base.control(RuntimeState(), None)
    assert repr(LensSchedule()) == "LensSchedule(||p||_2: 0 -> 0, 1.41421 -> 1)"
    assert repr(ResampleSchedule(0.5, 2)) == "ResampleSchedule(log2(d): 0.5 -> 0, 2 -> 1)"
