"""Stand-ins for the render protocol tests: a small pinhole camera and a model that renders itself, recording
what its render was given."""

from __future__ import annotations

from typing import Any

import torch

from controlgs_adapter.state import Camera


def small_camera(width: int = 4, height: int = 3) -> Camera:
    """A ``width x height`` camera at the origin (f = 4, principal point at the image centre)."""
    k = torch.tensor([[4.0, 0.0, width / 2], [0.0, 4.0, height / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, width, height)


class Renders:
    """Brings its own visible_anchors / render; render returns ``self.out`` (whatever a test sets) and records the
    visible anchors and background it was given."""

    def __init__(self, out: Any) -> None:
        self.out = out
        self.seen: list[Any] = []

    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        return torch.tensor([True, False, True])

    def render(self, camera: Camera, visible: Any, background: Any = None) -> Any:
        self.seen.append((visible, background))
        return self.out
