"""Tests of ``controlgs_adapter.downstream.placement``: where an image sits on the display ("fit": square
pixels, scaled to fit and centred; "stretch": the whole display), worked out on square and non-square
displays, the mapping to display coordinates, and the refusals."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from controlgs_adapter.downstream.placement import image_region, to_display
from controlgs_adapter.errors import InputValueError

D = torch.float64
CARDBOARD = (24.0, 24.0)


@pytest.mark.parametrize("h, w, display, half, pitch, size", [
    (1080, 1920, CARDBOARD, (1.0, 0.5625), (0.0125, 0.0125), (24.0, 13.5)),   # 16:9 landscape: full width
    (1920, 1080, CARDBOARD, (0.5625, 1.0), (0.0125, 0.0125), (13.5, 24.0)),   # 9:16 portrait: full height
    (9, 16, CARDBOARD, (1.0, 0.5625), (1.5, 1.5), (24.0, 13.5)),
    (16, 9, CARDBOARD, (0.5625, 1.0), (1.5, 1.5), (13.5, 24.0)),
    (27, 48, CARDBOARD, (1.0, 0.5625), (0.5, 0.5), (24.0, 13.5)),
    (30, 40, CARDBOARD, (1.0, 0.75), (0.6, 0.6), (24.0, 18.0)),
    (4, 8, CARDBOARD, (1.0, 0.5), (3.0, 3.0), (24.0, 12.0)),
    *[(n, n, CARDBOARD, (1.0, 1.0), (24 / n, 24 / n), (24.0, 24.0)) for n in (1, 7, 27, 48, 1000)],  # the whole display
    (2, 1, CARDBOARD, (0.5, 1.0), (12.0, 12.0), (12.0, 24.0)),                 # one pixel wide: height-limited
    (1, 2, CARDBOARD, (1.0, 0.5), (12.0, 12.0), (24.0, 12.0)),
    (10, 10, (30.0, 20.0), (2 / 3, 1.0), (2.0, 2.0), (20.0, 20.0)),           # square image, shorter display side
    (10, 40, (30.0, 20.0), (1.0, 0.375), (0.75, 0.75), (30.0, 7.5)),          # width-limited
    (30, 50, (24.0, 18.0), (1.0, 0.8), (0.48, 0.48), (24.0, 14.4)),
    (50, 20, (24.0, 18.0), (0.3, 1.0), (0.36, 0.36), (7.2, 18.0)),            # height-limited
])
def test_fit_region(h, w, display, half, pitch, size):
    """Square pixels: the longer relative side fills the display; the region in mm and in normalised
    display coordinates agree, centred."""
    r = image_region(h, w, display)
    assert r.display_mm == display
    assert (r.half_x, r.half_y) == pytest.approx(half, abs=1e-15)
    assert r.pitch_mm == pytest.approx(pitch, abs=1e-15) and r.size_mm == pytest.approx(size, abs=1e-12)
    assert r.bounds_mm == pytest.approx((-size[0] / 2, size[0] / 2, -size[1] / 2, size[1] / 2))
    assert (r.size_mm[0] / display[0], r.size_mm[1] / display[1]) == pytest.approx((r.half_x, r.half_y))
    if h == w and display == CARDBOARD:
        assert (r.half_x, r.half_y) == (1.0, 1.0) and r.pitch_mm == (24 / h, 24 / h)   # exactly


@pytest.mark.parametrize("h, w, display, pitch", [(1080, 1920, CARDBOARD, (24 / 1920, 24 / 1080)),
                                                  (9, 16, CARDBOARD, (1.5, 24 / 9)), (30, 50, (24.0, 18.0), (0.48, 0.6))])
def test_stretch_region_is_the_whole_display_with_anisotropic_pixels(h, w, display, pitch):
    s = image_region(h, w, display, placement="stretch")
    assert (s.half_x, s.half_y) == (1.0, 1.0) and s.size_mm == display
    assert s.pitch_mm == pytest.approx(pitch)


def test_to_display_scales_by_the_half_extents():
    """``display = image * (half_x, half_y)``; the same tensor back when the image spans the display."""
    xy = torch.tensor([[1.0, 1.0], [-0.5, 0.5]], dtype=D)
    assert to_display(xy, 4, 4) is xy and to_display(xy, 9, 16, "stretch") is xy
    assert to_display(xy, 9, 16).tolist() == [[1.0, 0.5625], [-0.5, 0.28125]]
    assert to_display(xy, 16, 9).tolist() == [[0.5625, 1.0], [-0.28125, 0.5]]
    assert to_display(xy, 10, 10, display_mm=(30.0, 20.0))[0].tolist() == pytest.approx([2 / 3, 1.0])
    assert torch.equal(to_display(torch.tensor([[1.0, -1.0], [0.5, 0.25]]), 27, 48),
                       torch.tensor([[1.0, -0.5625], [0.5, 0.140625]]))
    xy = torch.tensor([[0.5, -0.5], [-1.0, 1.0]], dtype=D)
    assert torch.equal(to_display(xy, 30, 50, "stretch", (24.0, 18.0)), xy)
    torch.testing.assert_close(to_display(xy, 30, 50, "fit", (24.0, 18.0)), torch.tensor([[0.5, -0.4], [-1.0, 0.8]], dtype=D))
    torch.testing.assert_close(to_display(xy, 50, 20, "fit", (24.0, 18.0)), torch.tensor([[0.15, -0.5], [-0.3, 1.0]], dtype=D))
    assert to_display(torch.ones(2, 2, device="meta"), 9, 16).device.type == "meta"


def test_image_region_is_frozen():
    r = image_region(4, 8)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.half_x = 0.25  # type: ignore[misc]
    assert r.half_x == 1.0


def test_image_region_refusals_name_the_argument():
    for placement in ("crop", "fill"):
        with pytest.raises(InputValueError, match=f"placement must be one of .*'{placement}'"):
            image_region(4, 4, placement=placement)  # type: ignore[arg-type]
    for h, w in [(0, 4), (4, 0), (4.0, 4), (4, "4")]:
        with pytest.raises(InputValueError, match="image size must be ints >= 1"):
            image_region(h, w)
    for mm in [(0.0, 24.0), (24.0, 0.0), (-1.0, 24.0), (24.0, float("nan"))]:
        with pytest.raises(InputValueError, match="display_mm must be"):
            image_region(4, 4, mm)
