"""Tests of ``controlgs_adapter.scene.cameras``: ``look_at`` (pose, intrinsics, the up vector) and the arc of
cameras around the built-in scene (its documented defaults and options)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.scene import look_at
from controlgs_adapter.scene.cameras import arc_cameras

F64 = torch.float64


def _t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def _arc_eye(s: float) -> tuple[float, float, float]:
    """The documented defaults worked out: azimuth in [-32, 32] deg, elevation 8..24 deg with five
    half-periods, radius 5.2 -> 4.2 with three half-periods, target (0, 0.35, 0)."""
    az = math.radians(-32.0 + 64.0 * s)
    el = math.radians(8.0 + 16.0 * (0.5 - 0.5 * math.cos(5.0 * math.pi * s)))
    r = 5.2 - 1.0 * (0.5 - 0.5 * math.cos(3.0 * math.pi * s))
    return (r * math.cos(el) * math.sin(az), 0.35 + r * math.sin(el), r * math.cos(el) * math.cos(az))


def test_look_at_pose_and_intrinsics():
    # eye (0, 0, 5) -> origin, up y: z = (0, 0, -1); x = z x up = (1, 0, 0); y = z x x = (0, -1, 0);
    # t = -R e = (0, 0, 5); fov 90 deg: f = size / (2 tan 45) = size / 2 = 5, c = 5
    cam = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=10, fov_deg=90.0)
    want = torch.tensor([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, 5], [0, 0, 0, 1]], dtype=torch.float32)
    torch.testing.assert_close(cam.world_to_camera, want, atol=1e-6, rtol=0)
    torch.testing.assert_close(cam.intrinsics, torch.tensor([[5.0, 0, 5], [0, 5, 5], [0, 0, 1]]), atol=1e-6, rtol=0)
    assert (cam.width, cam.height) == (10, 10)
    assert cam.world_to_camera.dtype == torch.float32
    # eye (3, 0, 0) -> origin: z = (-1, 0, 0), x = (0, 0, -1), y = (0, -1, 0), t = -R e = (0, 0, 3)
    cam = look_at((3.0, 0.0, 0.0), (0.0, 0.0, 0.0), size=8, fov_deg=60.0)
    want = torch.tensor([[0, 0, -1, 0], [0, -1, 0, 0], [-1, 0, 0, 3], [0, 0, 0, 1]], dtype=torch.float32)
    torch.testing.assert_close(cam.world_to_camera, want, atol=1e-6, rtol=0)
    f = 8 / (2 * math.tan(math.radians(30.0)))  # 6.9282
    torch.testing.assert_close(cam.intrinsics, torch.tensor([[f, 0, 4], [0, f, 4], [0, 0, 1]]), atol=1e-5, rtol=0)
    # an eye off the axes: its centre comes back, the target projects to the image centre
    cam = look_at((1.0, 2.0, 3.0), (0.5, -1.0, 0.25), size=12, fov_deg=40.0)
    torch.testing.assert_close(cam.center, torch.tensor([1.0, 2.0, 3.0]), atol=1e-5, rtol=0)
    p = cam.world_to_camera.double() @ _t(0.5, -1.0, 0.25, 1.0)
    k = cam.intrinsics.double()
    assert abs(float(k[0, 0] * p[0] / p[2] + k[0, 2]) - 6.0) < 1e-4 and abs(float(k[1, 1] * p[1] / p[2] + k[1, 2]) - 6.0) < 1e-4
    # a point above the target (world +y) is above the centre in the image (smaller v)
    cam = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=10, fov_deg=90.0)
    p = cam.world_to_camera.double() @ _t(1.0, 1.0, 0.0, 1.0)  # -> camera (1, -1, 5): u = 6, v = 4
    assert abs(float(5 * p[0] / p[2] + 5) - 6.0) < 1e-6 and abs(float(5 * p[1] / p[2] + 5) - 4.0) < 1e-6
    # the default up is world +y; with up = world x, world +x is the one that appears upward
    cam = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=16, fov_deg=60.0)
    uv, _ = cam.project(torch.tensor([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))
    assert float(uv[0, 1]) < 8.0 and float(uv[0, 0]) == pytest.approx(8.0, abs=1e-5)
    assert float(uv[1, 0]) > 8.0 and float(uv[1, 1]) == pytest.approx(8.0, abs=1e-5)
    cam_x = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), size=16, fov_deg=60.0, up=(1.0, 0.0, 0.0))
    assert float(cam_x.project(torch.tensor([[1.0, 0.0, 0.0]]))[0][0, 1]) < 8.0


def test_look_at_refusals():
    with pytest.raises(InputValueError, match="eye and target must differ"):
        look_at((1.0, 1.0, 1.0), (1.0, 1.0, 1.0), size=8, fov_deg=50.0)
    with pytest.raises(InputValueError, match="parallel to up"):
        look_at((0.0, 3.0, 0.0), (0.0, 0.0, 0.0), size=8, fov_deg=50.0)
    # a custom up: looking down y is fine when up is z
    cam = look_at((0.0, 3.0, 0.0), (0.0, 0.0, 0.0), size=8, fov_deg=50.0, up=(0.0, 0.0, 1.0))
    torch.testing.assert_close(cam.center, torch.tensor([0.0, 3.0, 0.0]), atol=1e-6, rtol=0)


def test_arc_cameras_defaults_are_the_documented_numbers():
    default = arc_cameras(5, size=16)
    explicit = arc_cameras(5, size=16, fov_deg=50.0, radius=(4.2, 5.2), azimuth_deg=32.0, elevation_deg=(8.0, 24.0),
                           target=(0.0, 0.35, 0.0))
    for a, b in zip(default, explicit, strict=True):
        torch.testing.assert_close(a.world_to_camera, b.world_to_camera, rtol=0, atol=0)
        torch.testing.assert_close(a.intrinsics, b.intrinsics, rtol=0, atol=0)
    # fov 50 deg over 16 px: fx = 8 / tan(25 deg); the distance to the target reaches both radius bounds
    assert float(default[0].intrinsics[0, 0]) == pytest.approx(8 / np.tan(np.radians(25.0)), rel=1e-6)
    dist = [float((c.center - torch.tensor([0.0, 0.35, 0.0])).norm()) for c in default]
    assert min(dist) == pytest.approx(4.2, abs=1e-5) and max(dist) == pytest.approx(5.2, abs=1e-5)
    cams = arc_cameras(3, size=20)
    # s = 0: az -32, el 8, r 5.2; s = 0.5: az 0, el 16, r 4.7; s = 1: az 32, el 24, r 4.2
    eyes = [(5.2 * math.cos(math.radians(8)) * math.sin(math.radians(-32)), 0.35 + 5.2 * math.sin(math.radians(8)),
             5.2 * math.cos(math.radians(8)) * math.cos(math.radians(32))),
            (0.0, 0.35 + 4.7 * math.sin(math.radians(16)), 4.7 * math.cos(math.radians(16))),
            (4.2 * math.cos(math.radians(24)) * math.sin(math.radians(32)), 0.35 + 4.2 * math.sin(math.radians(24)),
             4.2 * math.cos(math.radians(24)) * math.cos(math.radians(32)))]
    for cam, eye, s in zip(cams, eyes, (0.0, 0.5, 1.0)):
        torch.testing.assert_close(cam.center.double(), _t(*eye), atol=2e-5, rtol=0)
        torch.testing.assert_close(cam.center.double(), _t(*_arc_eye(s)), atol=2e-5, rtol=0)
        # default fov 50 deg: f = 20 / (2 tan 25) = 21.445
        assert abs(float(cam.intrinsics[0, 0]) - 20 / (2 * math.tan(math.radians(25.0)))) < 1e-4
        assert abs(float(cam.intrinsics[1, 1]) - 21.4451) < 1e-3
        # every camera looks at the target (0, 0.35, 0): it projects to the centre (10, 10)
        p = cam.world_to_camera.double() @ _t(0.0, 0.35, 0.0, 1.0)
        k = cam.intrinsics.double()
        assert abs(float(k[0, 0] * p[0] / p[2] + k[0, 2]) - 10) < 1e-3 and abs(float(k[1, 1] * p[1] / p[2] + k[1, 2]) - 10) < 1e-3
    one = arc_cameras(1, size=8)  # one camera: s = 0
    torch.testing.assert_close(one[0].center.double(), _t(*_arc_eye(0.0)), atol=2e-5, rtol=0)
    five = arc_cameras(5, size=8)
    for i, cam in enumerate(five):
        torch.testing.assert_close(cam.center.double(), _t(*_arc_eye(i / 4)), atol=2e-5, rtol=0)


def test_arc_cameras_options_and_refusal():
    cams = arc_cameras(2, size=10, fov_deg=90.0, radius=(2.0, 3.0), azimuth_deg=45.0, elevation_deg=(0.0, 30.0),
                       target=(1.0, 0.0, -1.0))
    # s = 0: az -45, wobble 0 -> el 0, r = 3 - 1 * 0 = 3; s = 1: az 45, wobble 1 -> el 30, r = 3 - 1 * 1 = 2
    e0 = (1.0 + 3.0 * math.sin(math.radians(-45)), 0.0, -1.0 + 3.0 * math.cos(math.radians(45)))
    e1 = (1.0 + 2.0 * math.cos(math.radians(30)) * math.sin(math.radians(45)), 2.0 * math.sin(math.radians(30)),
          -1.0 + 2.0 * math.cos(math.radians(30)) * math.cos(math.radians(45)))
    torch.testing.assert_close(cams[0].center.double(), _t(*e0), atol=2e-5, rtol=0)
    torch.testing.assert_close(cams[1].center.double(), _t(*e1), atol=2e-5, rtol=0)
    assert abs(float(cams[0].intrinsics[0, 0]) - 5.0) < 1e-5  # fov 90: f = size / 2
    for bad in (0, -2):
        with pytest.raises(InputValueError, match=f"count.*got {bad}$"):
            arc_cameras(bad, size=8)
