import math

import pytest
import torch
from hypothesis import given, strategies as st

from controlgs_adapter import Camera, RuntimeState
from controlgs_adapter.errors import StateError


@pytest.mark.parametrize("kw", [dict(downsample=0.5), dict(downsample=float("nan")), dict(power_saving=1.0),
                                dict(power_saving=-0.1), dict(gaze=(2.0, 0.0))])
def test_runtime_state_rejects_out_of_range(kw):
    with pytest.raises(StateError) as e:
        RuntimeState(**kw)
    assert next(iter(kw)) in str(e.value)


@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.5, 20))
def test_normalized_screen_matches_pixel_convention(x, y, z):
    k = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(torch.eye(4, dtype=torch.float64), k, 64, 48)
    p = cam.normalized_screen(torch.tensor([[x, y, z]], dtype=torch.float64))[0]
    u, v = 50 * x / z + 32, 50 * y / z + 24
    assert math.isclose(float(p[0]), 2 * u / 64 - 1, abs_tol=1e-9)
    assert math.isclose(float(p[1]), 2 * v / 48 - 1, abs_tol=1e-9)


def test_normalized_screen_puts_points_at_and_behind_the_camera_plane_at_inf():
    # depth exactly 0 (the camera centre itself, and a point beside it) and depth < 0: +inf, never nan or -inf
    k = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(torch.eye(4, dtype=torch.float64), k, 64, 48)
    pts = torch.tensor([[0.0, 0.0, 0.0], [-1.0, 0.5, 0.0], [0.3, -0.2, -2.0], [0.3, -0.2, 2.0]], dtype=torch.float64)
    p = cam.normalized_screen(pts)
    assert torch.equal(p[:3], torch.full((3, 2), float("inf"), dtype=torch.float64))
    assert torch.allclose(p[3], torch.tensor([2 * (50 * 0.15 + 32) / 64 - 1, 2 * (50 * -0.1 + 24) / 48 - 1],
                                             dtype=torch.float64))



def test_fov_per_axis_by_hand_and_from_scaffold_round_trip():
    """fov = (2 atan(W / 2fx), 2 atan(H / 2fy)) with fx != fy (by hand), and Camera.from_scaffold's FoVx,
    FoVy come back out (3DGS's cameras carry the two angles)."""
    import types

    cam = Camera(torch.eye(4), torch.tensor([[40.0, 0, 32.0], [0, 20.0, 24.0], [0, 0, 1]]), 64, 48)
    fx, fy = cam.fov
    assert math.isclose(fx, 2 * math.atan(0.8), rel_tol=1e-7) and math.isclose(fy, 2 * math.atan(1.2), rel_tol=1e-7)
    vc = types.SimpleNamespace(world_view_transform=torch.eye(4), image_width=80, image_height=45, FoVx=1.2, FoVy=0.7)
    got = Camera.from_scaffold(vc).fov
    assert math.isclose(got[0], 1.2, rel_tol=1e-6) and math.isclose(got[1], 0.7, rel_tol=1e-6)
