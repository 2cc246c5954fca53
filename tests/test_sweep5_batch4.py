"""Mutation sweep 5, batch 4: behaviours that a plausible one-line bug changed and no test observed
(``Camera.project`` divides by the signed depth behind the camera, as its docstring says). See
docs/testing.md."""

from __future__ import annotations

import torch

from controlgs_adapter.state import Camera

F64 = torch.float64


def test_project_divides_by_the_signed_depth_behind_the_camera():
    """``Camera.project`` docstring: a point at camera coordinates ``(x, y, -z)`` lands where ``(x, y, z)``
    does, mirrored through the principal point; only ``|depth| < 1e-12`` is clamped to ``1e-12``.
    By hand with fx = 50, fy = 40, cx = 32, cy = 24 (identity pose: world = camera coordinates)."""
    k = torch.tensor([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, 64, 48, {})
    pts = torch.tensor([[1.0, 3.0, -2.0], [1.0, 3.0, 2.0], [-4.0, 2.0, -0.5]], dtype=F64)
    uv, z = cam.project(pts)
    assert z.tolist() == [-2.0, 2.0, -0.5]
    # (1, 3, -2): u = 50 * 1 / -2 + 32 = 7, v = 40 * 3 / -2 + 24 = -36; its mirror (1, 3, 2): (57, 84)
    # (-4, 2, -0.5): u = 50 * -4 / -0.5 + 32 = 432, v = 40 * 2 / -0.5 + 24 = -136
    assert uv.tolist() == [[7.0, -36.0], [57.0, 84.0], [432.0, -136.0]]
    centre = torch.tensor([32.0, 24.0], dtype=F64)
    assert torch.equal(uv[0] - centre, -(uv[1] - centre))
    # a depth below 1e-12 in magnitude, on either side, is divided as +1e-12
    uv0, _ = cam.project(torch.tensor([[1e-12, 0.0, -1e-13], [1e-12, 0.0, 1e-13]], dtype=F64))
    assert torch.allclose(uv0, torch.tensor([[82.0, 24.0], [82.0, 24.0]], dtype=F64), rtol=1e-12, atol=0)
