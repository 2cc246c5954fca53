"""Posed images held in memory: image tensors and their cameras as frames of a dataset (the built-in
scene, tests, data a caller produced itself)."""

from __future__ import annotations

from typing import Sequence

import torch

from ..errors import InputValueError
from ..state import Camera
from .base import Frame, PosedImages

__all__ = ["tensor_frames", "posed_images"]


def tensor_frames(images: torch.Tensor | Sequence[torch.Tensor], cameras: Sequence[Camera], *,
                  prefix: str = "view") -> list[Frame]:
    """One in-memory :class:`Frame` per ``(image, camera)``: images sRGB ``[3 | 4, H, W]`` (a list, or
    a ``[V, C, H, W]`` tensor) at their camera's size; named ``"{prefix}/{i:04d}"``."""
    if len(images) != len(cameras):
        raise InputValueError(f"need one camera per image, got {len(images)} images and {len(cameras)} cameras")
    return [Frame(f"{prefix}/{i:04d}", cam, img) for i, (img, cam) in enumerate(zip(images, cameras))]


def posed_images(images: torch.Tensor | Sequence[torch.Tensor], cameras: Sequence[Camera], *,
                 background: torch.Tensor | None = None, name: str = "views") -> PosedImages:
    """The images with their cameras as a :class:`PosedImages` at full size (no copy, no resampling)."""
    return PosedImages(tensor_frames(images, cameras, prefix=name), background=background, name=name)
