"""A 3DGS / Scaffold-GS viewpoint camera built the way its ``Camera`` class builds one (for ``Camera.from_scaffold``)."""

from __future__ import annotations

import math
import types

import torch


def scaffold_camera(w: int, h: int, fovx: float, fovy: float, uid: int | None = 3) -> types.SimpleNamespace:
    """A 3DGS/Scaffold-GS camera as its ``Camera`` class builds it: ``world_view_transform`` the
    transposed world-to-camera, ``full_proj_transform`` = view @ projection (row-vector convention)."""
    angle = 0.3
    r = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
                     dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = r, torch.tensor([0.2, -0.1, 3.0], dtype=torch.float64)
    znear, zfar = 0.01, 100.0
    top, right = math.tan(fovy / 2) * znear, math.tan(fovx / 2) * znear
    p = torch.zeros(4, 4, dtype=torch.float64)  # 3DGS getProjectionMatrix (symmetric frustum)
    p[0, 0], p[1, 1] = 2 * znear / (2 * right), 2 * znear / (2 * top)
    p[3, 2], p[2, 2], p[2, 3] = 1.0, zfar / (zfar - znear), -(zfar * znear) / (zfar - znear)
    view = w2c.T
    cam = types.SimpleNamespace(world_view_transform=view.float(), full_proj_transform=(view @ p.T),
                                image_width=w, image_height=h, FoVx=fovx, FoVy=fovy)
    if uid is not None:
        cam.uid = uid
    return cam
