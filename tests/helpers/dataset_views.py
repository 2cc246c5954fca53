"""Pinhole cameras and in-memory frames for the dataset tests: cameras at the origin (OpenCV axes) that look
down +z, or turned round to look down -z."""

from __future__ import annotations

import torch

from controlgs_adapter.datasets.base import Frame
from controlgs_adapter.state import Camera

#: world-to-camera of a camera at the origin looking down +z, and of one turned round (looking down -z)
FRONT = torch.eye(4)
BACK = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


def pinhole(w: int, h: int, fx: float = 10.0, fy: float | None = None, cx: float | None = None,
            cy: float | None = None, w2c: torch.Tensor = FRONT) -> Camera:
    """A ``w x h`` camera with pose ``w2c``; ``fy`` defaults to ``fx``, the principal point to the image centre."""
    k = torch.tensor([[fx, 0.0, w / 2.0 if cx is None else cx],
                      [0.0, fx if fy is None else fy, h / 2.0 if cy is None else cy],
                      [0.0, 0.0, 1.0]])
    return Camera(w2c.clone(), k, w, h)


def looking(n: int, flipped: int = 0, f: float = 4.0) -> list[Frame]:
    """``n`` black 8 x 6 frames ``v0 .. v{n-1}`` with cameras at the origin (focal ``f``, centre (4, 3)) looking
    down +z; the last ``flipped`` look down -z."""
    return [Frame(f"v{i}", pinhole(8, 6, f, w2c=BACK if i >= n - flipped else FRONT), torch.zeros(3, 6, 8))
            for i in range(n)]
