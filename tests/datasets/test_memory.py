"""Tests of ``controlgs_adapter.datasets.memory``: frames and posed images from in-memory tensors."""

from __future__ import annotations

import pytest
import torch
from helpers.dataset_views import pinhole

from controlgs_adapter.datasets.memory import posed_images, tensor_frames
from controlgs_adapter.errors import InputValueError


def test_tensor_frames_and_posed_images_names_counts_and_background():
    cams = [pinhole(4, 2, 10.0, 12.0)] * 2
    imgs = torch.zeros(2, 3, 2, 4)
    assert [f.name for f in tensor_frames(imgs, cams)] == ["view/0000", "view/0001"]
    assert [f.name for f in tensor_frames(list(imgs), cams, prefix="p")] == ["p/0000", "p/0001"]
    with pytest.raises(InputValueError, match="one camera per image.*2 images and 1 cameras"):
        tensor_frames(imgs, cams[:1])
    default = posed_images(imgs, cams)
    assert default.name == "views" and [f.name for f in default.frames] == ["views/0000", "views/0001"]
    assert default.background.tolist() == [0.0, 0.0, 0.0]
    bg = torch.tensor([0.25, 0.5, 1.0])
    views = posed_images(torch.zeros(1, 4, 2, 4), cams[:1], background=bg, name="mine")
    assert views.name == "mine" and views.frames[0].name == "mine/0000"
    assert views.image(0)[:, 0, 0].tolist() == [0.25, 0.5, 1.0]  # alpha 0: all background
