"""Random Gaussian scenes in front of a float64 camera, for the splatter tests (some Gaussians culled, some
drawn, some straddling the image borders)."""

from __future__ import annotations

import math

import torch

from controlgs_adapter.state import Camera

F64 = torch.float64


def _rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)


def make_camera(width: int = 23, height: int = 17, dtype: torch.dtype = F64, yaw: float = 0.3) -> Camera:
    """Posed camera (rotation + translation), fx != fy, off-centre principal point."""
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = _rotation_z(yaw) @ torch.tensor([[1.0, 0, 0], [0, 0.96, -0.28], [0, 0.28, 0.96]], dtype=F64)
    w2c[:3, 3] = torch.tensor([0.2, -0.1, 0.5], dtype=F64)
    k = torch.tensor([[1.1 * width, 0, 0.47 * width], [0, 1.05 * width, 0.53 * height], [0, 0, 1]], dtype=F64)
    return Camera(w2c.to(dtype), k.to(dtype), width, height)


def camera_to_world_points(camera: Camera, pts_cam: torch.Tensor) -> torch.Tensor:
    w2c = camera.world_to_camera.to(pts_cam.dtype)
    return (pts_cam - w2c[:3, 3]) @ w2c[:3, :3]


def random_scene(seed: int, n: int, camera: Camera, dtype: torch.dtype = F64, hard: bool = True):
    """Gaussians placed in camera space (so that most land on screen), then moved to world space.

    ``hard`` mixes in the corner cases: behind the camera, on/near the near plane, huge and tiny scales,
    degenerate (flat, needle, point) covariances, fully transparent and fully opaque ones, off-screen."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=F64)

    z = 1.0 + 4.0 * rand(n)
    xy = (rand(n, 2) * 2 - 1) * 0.6 * z[:, None]
    scales = 0.02 * torch.exp(1.2 * torch.randn(n, 3, generator=g, dtype=F64))
    opac = rand(n)
    if hard:
        kinds = torch.arange(n) % 10
        z = torch.where(kinds == 1, -z, z)  # behind the camera
        z = torch.where(kinds == 2, 0.15 + 0.1 * rand(n), z)  # straddling the near plane (0.2)
        scales = torch.where((kinds == 3)[:, None], 3.0 * scales / scales.amax(-1, keepdim=True), scales)  # huge
        scales = torch.where((kinds == 4)[:, None], 1e-7 * rand(n, 3), scales)  # tiny
        flat = torch.tensor([1.0, 1.0, 0.0], dtype=F64)
        scales = torch.where((kinds == 5)[:, None], scales * flat, scales)  # flat disc
        scales = torch.where((kinds == 6)[:, None], scales * torch.tensor([0.0, 1.0, 0.0], dtype=F64), scales)
        opac = torch.where(kinds == 7, torch.zeros_like(opac), opac)  # fully transparent
        opac = torch.where(kinds == 8, torch.ones_like(opac), opac)  # opaque: alpha clamp at 0.99
        xy = torch.where((kinds == 9)[:, None], xy * 3.0, xy)  # mostly off-screen
    means = camera_to_world_points(camera, torch.cat([xy, z[:, None]], -1))
    rot = torch.randn(n, 4, generator=g, dtype=F64) * (0.5 + rand(n, 1))  # unnormalised
    colors = rand(n, 3)
    return tuple(t.to(dtype) for t in (means, scales, rot, opac, colors))


def gaussian_cloud(n: int = 40, seed: int = 0, device: str = "cpu", max_opacity: float = 0.9):
    """``n`` random Gaussians around the origin and a 48 x 32 camera 3 units away."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g) * 2 - 1
    scales = torch.rand(n, 3, generator=g) * 0.15 + 0.02
    rotations = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g) * max_opacity
    colors = torch.rand(n, 3, generator=g)
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    cam = Camera(w2c, torch.tensor([[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]), 48, 32)
    return [t.to(device) for t in (means, scales, rotations, opacities, colors)], cam
