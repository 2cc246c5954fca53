"""Tests of ``controlgs_adapter.downstream.oled``: box emission of display pixels on the simulation grid
(nearest with the pixel-centre rule, leading dims kept) and its refusals. The stage contract (identity
at d = 1, gradients, twin) is checked in ``test_stage_contract.py``."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.errors import InputValueError, ShapeError

D = torch.float64


def test_box_emission_is_nearest_with_pixel_centres():
    """Simulation pixel ``i`` (centre ``i + 0.5``) shows display pixel ``floor((i + 0.5) n / S)``: for an
    integer ratio each display pixel is repeated into a block; 2 -> 3 gives rows 0, 1, 1 ("nearest"
    would give 0, 0, 1) and 3 -> 5 columns 0, 0, 1, 2, 2; leading dims are kept; the same size gives the
    image itself."""
    img = torch.rand(2, 3, 4, 5, dtype=D)
    assert torch.equal(oled_emission(img, (8, 15)), img.repeat_interleave(2, -2).repeat_interleave(3, -1))
    rows = [math.floor((i + 0.5) * 4 / 7) for i in range(7)]
    cols = [math.floor((j + 0.5) * 5 / 9) for j in range(9)]
    assert torch.equal(oled_emission(img, (7, 9)), img[..., rows, :][..., cols])
    assert oled_emission(img, (4, 5)) is img
    small = torch.arange(2 * 3, dtype=D).reshape(1, 2, 3).expand(3, 2, 3)
    assert torch.equal(oled_emission(small, (3, 5)), small[:, [0, 1, 1]][:, :, [0, 0, 1, 2, 2]])
    line = torch.tensor([[[1.0, 2.0]]], dtype=D).expand(3, 1, 2).clone()
    assert oled_emission(line, (1, 3))[0, 0].tolist() == [1.0, 2.0, 2.0]
    batch = torch.arange(2 * 5 * 3 * 2 * 2, dtype=D).reshape(2, 5, 3, 2, 2)
    out = oled_emission(batch, (4, 4))
    assert out.shape == (2, 5, 3, 4, 4)
    assert torch.equal(out[1, 3, 2], batch[1, 3, 2].repeat_interleave(2, 0).repeat_interleave(2, 1))


def test_box_emission_refuses_to_shrink_and_non_float_images():
    img = torch.rand(3, 2, 3, dtype=D)
    for size in [(1, 3), (2, 2), (4, 2), (1, 6), (1, 2)]:  # either axis smaller than the image
        with pytest.raises(ShapeError, match=r"size.*\(2, 3\)"):
            oled_emission(img, size)
    with pytest.raises(InputValueError, match="image"):
        oled_emission(img.half(), (6, 8))
