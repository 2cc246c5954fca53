"""Pinhole cameras on an arc around the diorama (OpenCV axes: x right, y down, z forward)."""

from __future__ import annotations

import math

import torch

from ..errors import InputValueError
from ..state import Camera

__all__ = ["look_at", "arc_cameras"]


def look_at(eye: tuple[float, float, float], target: tuple[float, float, float], *, size: int, fov_deg: float,
            up: tuple[float, float, float] = (0.0, 1.0, 0.0)) -> Camera:
    """A square ``size x size`` camera at ``eye`` looking at ``target`` with a ``fov_deg`` field of view
    (world ``up`` appears upward in the image)."""
    e, t, u = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = t - e
    if float(z.norm()) == 0.0:
        raise InputValueError("look_at: eye and target must differ")
    z = z / z.norm()
    x = torch.linalg.cross(z, u)
    if float(x.norm()) < 1e-9:
        raise InputValueError("look_at: viewing direction is parallel to up")
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.stack([x, y, z])
    w2c[:3, 3] = -(w2c[:3, :3] @ e)
    f = size / (2.0 * math.tan(math.radians(fov_deg) / 2.0))
    k = torch.tensor([[f, 0.0, size / 2.0], [0.0, f, size / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(w2c.float(), k.float(), size, size)


def arc_cameras(count: int, *, size: int, fov_deg: float = 50.0, radius: tuple[float, float] = (4.2, 5.2),
                azimuth_deg: float = 32.0, elevation_deg: tuple[float, float] = (8.0, 24.0),
                target: tuple[float, float, float] = (0.0, 0.35, 0.0)) -> list[Camera]:
    """``count`` cameras on an arc in front of the scene (the +z side), azimuth evenly in
    ``[-azimuth_deg, azimuth_deg]``; elevation and distance oscillate between their bounds so that
    neighbouring views differ in height and scale."""
    if count < 1:
        raise InputValueError(f"count must be >= 1, got {count!r}")
    cams = []
    for i in range(count):
        s = i / max(count - 1, 1)
        az = math.radians(-azimuth_deg + 2.0 * azimuth_deg * s)
        wobble = 0.5 - 0.5 * math.cos(2.0 * math.pi * 2.5 * s)  # 0..1, five half-periods over the arc
        el = math.radians(elevation_deg[0] + (elevation_deg[1] - elevation_deg[0]) * wobble)
        r = radius[1] - (radius[1] - radius[0]) * (0.5 - 0.5 * math.cos(2.0 * math.pi * 1.5 * s))
        eye = (target[0] + r * math.cos(el) * math.sin(az), target[1] + r * math.sin(el), target[2] + r * math.cos(el) * math.cos(az))
        cams.append(look_at(eye, target, size=size, fov_deg=fov_deg))
    return cams
