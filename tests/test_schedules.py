"""Strength schedules (paper Eqs. 10-11): lambda follows the formulas exactly and clamps to [0, 1]."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings, strategies as st

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter import plugins
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.schedules import DisplaySchedule, FoveationSchedule, LensSchedule, ResampleSchedule

from scaffold_standin import ScaffoldStandIn, make_camera

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


_model = ScaffoldStandIn(num_anchors=25, seed=3)
with torch.no_grad():  # spread anchors so some project outside the image (lens radius > sqrt 2 -> clamps)
    _model._anchor.mul_(torch.tensor([4.0, 4.0, 1.0]))


@settings(max_examples=20, deadline=None)
@given(states, st.floats(0.0, 0.5), st.floats(0.6, 2.0), st.integers(0, 2**31 - 1))
def test_controlgs_strengths_project_each_anchor_with_the_camera(state, lo, hi, seed):
    cam = make_camera(width=40, height=30)
    cgs = ControlGS.wrap(_model, modules=("lens", "resample", "display", "foveation"),
                         endpoints={"lens": (lo, hi), "foveation": (lo, hi)})
    try:
        ids = torch.randperm(25, generator=torch.Generator().manual_seed(seed))[:10]
        got = cgs.strengths(state, cam, ids)
        # independent pinhole projection in float64
        pts = _model._anchor.detach().double()[ids]
        k = cam.intrinsics.double()
        z = pts[:, 2] + float(cam.world_to_camera[2, 3])
        u = k[0, 0] * pts[:, 0] / z + k[0, 2]
        v = k[1, 1] * pts[:, 1] / z + k[1, 2]
        xy = torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], dim=1)
        assert bool((xy.abs() > 1).any())  # some anchors are off screen
        # anchors and gaze on the display ("fit" placement: the 40 px width spans it, the height 30/40)
        xy = xy * torch.tensor([1.0, 30 / 40], dtype=torch.float64)
        if state.gaze is not None:
            state = RuntimeState(state.downsample, state.power_saving, (state.gaze[0], state.gaze[1] * 30 / 40))
        for i in range(len(ids)):
            want = _reference(state, (float(xy[i, 0]), float(xy[i, 1])), (lo, hi), (lo, hi))
            for m in want:
                assert math.isclose(float(got[m][i]), want[m], abs_tol=2e-6), (m, i)
    finally:
        cgs.unwrap()


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
