"""Tests of ``controlgs_adapter.schedules``."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.builtin import controlgs_register_schedules
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


def test_schedule_endpoints_by_hand():
    """clamp((alpha - lo) / (hi - lo), 0, 1) at non-default lo/hi, inverted included."""
    rs = ResampleSchedule(lo=1.0, hi=2.0)
    for d, want in ((2.0, 0.0), (2 ** 1.5, 0.5), (2 ** 1.75, 0.75), (8.0, 1.0), (1.0, 0.0)):
        got = rs.strength(RuntimeState(downsample=d), rows=2, dtype=D)
        assert got.tolist() == pytest.approx([want, want], abs=1e-12), d
    ds = DisplaySchedule(lo=0.2, hi=0.6)
    assert float(ds.strength(RuntimeState(power_saving=0.5), rows=1, dtype=D)) == pytest.approx(0.75)
    inv = DisplaySchedule(lo=0.8, hi=0.0)
    assert float(inv.strength(RuntimeState(power_saving=0.2), rows=1, dtype=D)) == pytest.approx(0.75)
    assert float(inv.strength(RuntimeState(power_saving=0.9), rows=1, dtype=D)) == 0.0
    lens = LensSchedule(lo=0.5, hi=1.0)
    xy = torch.tensor([[0.3, 0.4], [0.45, -0.6], [0.6, 0.8], [3.0, 4.0], [0.1, 0.0], [math.inf, math.inf]], dtype=D)
    assert lens.strength(RuntimeState(), xy, dtype=D).tolist() == pytest.approx([0.0, 0.5, 1.0, 1.0, 0.0, 1.0])
    fov = FoveationSchedule(lo=0.1, hi=0.6)
    xy = torch.tensor([[0.4, 0.2], [0.1, -0.2], [-0.2, -0.6]], dtype=D)  # distances 0.5, 0, 0.5 from the gaze
    assert fov.strength(RuntimeState(gaze=(0.1, -0.2)), xy, dtype=D).tolist() == pytest.approx([0.8, 0.0, 0.8])
    assert fov.strength(RuntimeState(), xy, dtype=D).tolist() == [0.0, 0.0, 0.0]  # no gaze: eccentricity 0
    moved = lens.with_endpoints(hi=2.0)
    assert (moved.lo, moved.hi) == (0.5, 2.0)


states = st.builds(
    RuntimeState,
    downsample=st.floats(1.0, 64.0),  # beyond the supported 8: clamps
    power_saving=st.floats(0.0, 0.999),  # beyond the supported 0.8: clamps
    gaze=st.none() | st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
)


def _clamp01(v: float) -> float:
    return min(max(v, 0.0), 1.0)


def _reference(state: RuntimeState, xy: tuple[float, float], e_lens=(0.0, math.sqrt(2)), e_fov=(0.0, math.sqrt(2))):
    """Eqs. 10-11 with plain Python floats."""
    r = math.hypot(*xy)
    ecc = 0.0 if state.gaze is None else math.hypot(xy[0] - state.gaze[0], xy[1] - state.gaze[1])
    return {
        "lens": _clamp01((r - e_lens[0]) / (e_lens[1] - e_lens[0])),
        "resample": _clamp01(math.log2(state.downsample) / 3.0),
        "display": _clamp01(state.power_saving / 0.8),
        "foveation": _clamp01((ecc - e_fov[0]) / (e_fov[1] - e_fov[0])),
    }


@settings(max_examples=30, deadline=None)
@given(states, st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=1, max_size=6))
def test_builtin_schedules_follow_eqs_10_11(state, points):
    xy = torch.tensor(points, dtype=torch.float64)
    got = {cls.name: cls().strength(state, xy, dtype=torch.float64) for cls in
           (LensSchedule, ResampleSchedule, DisplaySchedule, FoveationSchedule)}
    for i, p in enumerate(points):
        want = _reference(state, p)
        for m, lam in got.items():
            assert 0.0 <= float(lam[i]) <= 1.0
            assert math.isclose(float(lam[i]), want[m], abs_tol=1e-12), (m, p, state)


def test_foveation_without_gaze_injects_nothing_and_inverted_endpoints_invert():
    xy = torch.tensor([[0.5, 0.5], [-1.0, 1.0]])
    assert torch.equal(FoveationSchedule().strength(RuntimeState(), xy), torch.zeros(2))
    inv = LensSchedule(lo=1.0, hi=0.0)  # strongest injection at the centre
    assert torch.allclose(inv.strength(RuntimeState(), torch.tensor([[0.0, 0.0], [0.6, 0.8]])), torch.tensor([1.0, 0.0]))


def test_schedule_argument_errors():
    with pytest.raises(InputValueError, match="differ"):
        ResampleSchedule(lo=2.0, hi=2.0)
    with pytest.raises(InputValueError, match="finite"):
        DisplaySchedule(hi=float("inf"))
    with pytest.raises(InputValueError, match="screen_xy"):
        LensSchedule().strength(RuntimeState())
    for per_anchor in (LensSchedule(), FoveationSchedule()):  # control() called directly, without positions
        with pytest.raises(InputValueError, match="screen_xy"):
            per_anchor.control(RuntimeState(), None)
    assert ResampleSchedule().strength(RuntimeState(downsample=8.0), rows=3).tolist() == [1.0, 1.0, 1.0]


def test_builtin_schedules_are_registered_through_the_hook():
    registered = plugins.schedules()
    for cls in (LensSchedule, ResampleSchedule, DisplaySchedule, FoveationSchedule):
        info = registered[cls.name]
        assert type(info.obj) is cls and info.plugin == "controlgs_adapter.builtin"
        assert (info.obj.lo, info.obj.hi) == (cls.default_lo, cls.default_hi)


def test_schedule_defaults_flags_and_repr():
    table = {LensSchedule: ("lens", True, 0.0, math.sqrt(2.0)), ResampleSchedule: ("resample", False, 0.0, 3.0),
             DisplaySchedule: ("display", False, 0.0, 0.8), FoveationSchedule: ("foveation", True, 0.0, math.sqrt(2.0))}
    for cls, (name, per_anchor, lo, hi) in table.items():
        s = cls()
        assert (s.name, s.per_anchor, s.lo, s.hi) == (name, per_anchor, lo, hi)
        assert s.endpoints() == {"lo": lo, "hi": hi}
    assert BUILTIN_SCHEDULES == tuple(table)
    assert [type(s) for s in controlgs_register_schedules()] == list(table)
    base = StrengthSchedule()
    assert (base.lo, base.hi, base.per_anchor) == (0.0, 1.0, False)
    with pytest.raises(NotImplementedError):
        base.control(RuntimeState(), None)
    assert repr(LensSchedule()) == "LensSchedule(||p||_2: 0 -> 0, 1.41421 -> 1)"
    assert repr(ResampleSchedule(0.5, 2)) == "ResampleSchedule(log2(d): 0.5 -> 0, 2 -> 1)"


def test_schedule_endpoints_and_strength_by_hand():
    s = ResampleSchedule().with_endpoints(hi=2.0)
    assert type(s) is ResampleSchedule and (s.lo, s.hi) == (0.0, 2.0)
    assert (s.with_endpoints(lo=1.0).lo, s.with_endpoints(lo=1.0).hi) == (1.0, 2.0)
    # log2(2) = 1 -> (1 - 0) / (2 - 0) = 0.5; log2(8) = 3 -> 1.5 clamps to 1; d = 1 -> 0
    assert s.strength(RuntimeState(downsample=2.0), rows=2).tolist() == [0.5, 0.5]
    assert s.scalar_strength(3.0) == 1.0 and s.scalar_strength(-1.0) == 0.0 and s.scalar_strength(0.5) == 0.25
    lam = DisplaySchedule().strength(RuntimeState(power_saving=0.2), rows=3, dtype=torch.float64)
    assert lam.dtype == torch.float64 and lam.tolist() == [0.2 / 0.8] * 3  # rho / 0.8
    lam = DisplaySchedule().strength(RuntimeState(power_saving=0.4), torch.zeros(4, 2), dtype=torch.float64)
    assert lam.tolist() == [0.5] * 4  # a global schedule takes its row count from screen_xy
    assert DisplaySchedule().strength(RuntimeState(), rows=2, device="meta").device.type == "meta"
    # device: screen_xy's unless given
    assert LensSchedule().strength(RuntimeState(), torch.zeros(2, 2)).device.type == "cpu"
    assert LensSchedule().strength(RuntimeState(), torch.zeros(2, 2), device="meta").device.type == "meta"
    with pytest.raises(InputValueError, match="strength\\(\\) needs screen_xy or rows"):
        DisplaySchedule().strength(RuntimeState())
    with pytest.raises(ShapeError, match="screen_xy"):
        DisplaySchedule().strength(RuntimeState(), torch.zeros(4, 3))
    with pytest.raises(InputValueError, match="schedule 'foveation' is per anchor and needs screen_xy"):
        FoveationSchedule().strength(RuntimeState(gaze=(0.0, 0.0)), rows=3)
    # lens (lo 0.5, hi 1.5): radius 0 -> clamps to 0, 1 -> 0.5, (3, 4) radius 5 -> clamps to 1
    xy = torch.tensor([[0.0, 0.0], [0.6, 0.8], [3.0, 4.0]], dtype=torch.float64)
    assert LensSchedule(0.5, 1.5).strength(RuntimeState(), xy, dtype=torch.float64).tolist() == [0.0, 0.5, 1.0]
    # foveation about gaze (0.6, 0.8): distances 1, 0, 5 with default (0, sqrt 2)
    got = FoveationSchedule().strength(RuntimeState(gaze=(0.6, 0.8)), xy, dtype=torch.float64)
    assert torch.allclose(got, torch.tensor([1 / math.sqrt(2.0), 0.0, 1.0], dtype=torch.float64), rtol=1e-12, atol=0)
    for lo, hi, word in [("0", 1.0, "finite numbers"), (0.0, float("nan"), "finite numbers"), (1.0, 1, "must differ")]:
        with pytest.raises(InputValueError, match=word):
            LensSchedule(lo, hi)
