"""Tests of ``controlgs_adapter.datasets.memory``."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.datasets.base import Frame, SceneData
from controlgs_adapter.datasets.memory import posed_images, tensor_frames
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import Camera


def _cam(w: int, h: int, fx: float = 10.0, fy: float = 12.0, cx: float | None = None, cy: float | None = None) -> Camera:
    k = torch.tensor([[fx, 0.0, w / 2.0 if cx is None else cx], [0.0, fy, h / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, w, h)


def test_tensor_frames_names_and_counts():
    frames = tensor_frames([torch.zeros(3, 2, 4)] * 2, [_cam(4, 2)] * 2, prefix="p")
    assert [f.name for f in frames] == ["p/0000", "p/0001"]
    with pytest.raises(InputValueError, match="need one camera per image, got 2 images and 1 cameras"):
        tensor_frames(torch.zeros(2, 3, 2, 4), [_cam(4, 2)])
    bg = torch.tensor([0.25, 0.5, 1.0])
    views = posed_images(torch.zeros(1, 4, 2, 4), [_cam(4, 2)], background=bg, name="mine")
    assert views.name == "mine" and views.frames[0].name == "mine/0000"
    assert views.image(0)[:, 0, 0].tolist() == [0.25, 0.5, 1.0]  # alpha 0: all background


def _two_cameras() -> SceneData:
    """Two 8 x 6 cameras at the origin (f = 4, centre (4, 3)): v0 looks down +z, v1 down -z."""
    frames = []
    for i, flip in enumerate((1.0, -1.0)):
        w2c = torch.eye(4)
        w2c[:3, :3] = torch.diag(torch.tensor([1.0, flip, flip]))
        k = torch.tensor([[4.0, 0, 4], [0, 4.0, 3], [0, 0, 1]])
        frames.append(Frame(f"v{i}", Camera(w2c, k, 8, 6), torch.zeros(3, 6, 8)))
    return SceneData({"train": frames}, source="src")


def test_memory_frames_default_names():
    from controlgs_adapter.datasets.memory import posed_images, tensor_frames

    cams = [_two_cameras().splits["train"][0].camera] * 2
    imgs = torch.zeros(2, 3, 6, 8)
    assert [f.name for f in tensor_frames(imgs, cams)] == ["view/0000", "view/0001"]
    assert [f.name for f in tensor_frames(imgs, cams, prefix="p")] == ["p/0000", "p/0001"]
    p = posed_images(imgs, cams)
    assert p.name == "views" and [f.name for f in p.frames] == ["views/0000", "views/0001"]
    assert p.background.tolist() == [0.0, 0.0, 0.0]
