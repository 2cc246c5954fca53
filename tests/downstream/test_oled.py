"""Tests of ``controlgs_adapter.downstream.oled``."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.oled import OLEDEmission, oled_emission
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError, ShapeError

F64 = torch.float64


def test_box_emission_to_a_non_integer_size_by_hand_and_refusals():
    img = torch.arange(2 * 3, dtype=F64).reshape(1, 2, 3).expand(3, 2, 3)
    out = oled_emission(img, (3, 5))
    # simulation pixel i shows display pixel floor((i + 0.5) n / S): rows 2 -> 3: [0, 1, 1]; cols 3 -> 5: [0, 0, 1, 2, 2]
    want = img[:, [0, 1, 1]][:, :, [0, 0, 1, 2, 2]]
    assert torch.equal(out, want)
    for size in ((2, 2), (1, 3), (1, 2)):  # either side smaller than the image
        with pytest.raises(ShapeError, match="size"):
            oled_emission(img, size)


def test_box_emission_is_nearest_with_pixel_centres():
    img = torch.rand(2, 3, 4, 5, dtype=torch.float64)
    up = oled_emission(img, (8, 15))
    assert torch.equal(up, img.repeat_interleave(2, -2).repeat_interleave(3, -1))
    odd = oled_emission(img, (7, 9))
    rows = [math.floor((i + 0.5) * 4 / 7) for i in range(7)]
    cols = [math.floor((j + 0.5) * 5 / 9) for j in range(9)]
    assert torch.equal(odd, img[..., rows, :][..., cols])
    assert oled_emission(img, (4, 5)) is img


def test_gradcheck_box_emission_and_stage():
    img = torch.rand(3, 3, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: oled_emission(x, (7, 9)), (img,))
    stage = OLEDEmission()
    assert stage.is_identity(RuntimeState(1.0)) and not stage.is_identity(RuntimeState(2.0))
    assert stage(img, RuntimeState(2.0), StageContext((6, 8))).shape == (3, 6, 8)
    with pytest.raises(ShapeError, match="at least"):
        oled_emission(img, (2, 4))
    with pytest.raises(InputValueError, match="image"):
        oled_emission(img.float().half(), (6, 8))


D = torch.float64


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


def test_box_emission_pixel_centre_rule_for_a_non_integer_ratio():
    # 2 -> 3: simulation pixel i shows floor((i + 0.5) * 2 / 3) = 0, 1, 1 ("nearest" would give 0, 0, 1)
    img = torch.tensor([[[1.0, 2.0]]], dtype=D).expand(3, 1, 2).clone()
    out = oled_emission(img, (1, 3))
    assert out[0, 0].tolist() == [1.0, 2.0, 2.0]
    # leading dims are kept
    batch = torch.arange(2 * 5 * 3 * 2 * 2, dtype=D).reshape(2, 5, 3, 2, 2)
    out2 = oled_emission(batch, (4, 4))
    assert out2.shape == (2, 5, 3, 4, 4)
    assert torch.equal(out2[1, 3, 2], batch[1, 3, 2].repeat_interleave(2, 0).repeat_interleave(2, 1))


def test_box_emission_same_size_and_refusals():
    img = _img([0.1, 0.2, 0.3], 2, 3)
    assert oled_emission(img, (2, 3)) is img
    for size in [(1, 3), (2, 2), (4, 2), (1, 6)]:  # either axis smaller is refused
        with pytest.raises(ShapeError, match="size must be at least the image size"):
            oled_emission(img, size)
