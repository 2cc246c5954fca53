"""Tests of ``controlgs_adapter.downstream.placement``."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from controlgs_adapter.downstream import placement
from controlgs_adapter.downstream.placement import image_region, to_display
from controlgs_adapter.errors import InputValueError


# ----------------------------------------------------------------------------- the region, by hand
@pytest.mark.parametrize("h, w, half, pitch, size", [
    (1080, 1920, (1.0, 0.5625), (0.0125, 0.0125), (24.0, 13.5)),      # 16:9 landscape: full width
    (1920, 1080, (0.5625, 1.0), (0.0125, 0.0125), (13.5, 24.0)),      # 9:16 portrait: full height
    (27, 48, (1.0, 0.5625), (0.5, 0.5), (24.0, 13.5)),
    (48, 48, (1.0, 1.0), (0.5, 0.5), (24.0, 24.0)),                    # square: the whole display
    (30, 40, (1.0, 0.75), (0.6, 0.6), (24.0, 18.0)),
])
def test_fit_region_by_hand(h, w, half, pitch, size):
    r = image_region(h, w)
    assert (r.half_x, r.half_y) == pytest.approx(half, abs=1e-15)
    assert r.pitch_mm == pytest.approx(pitch, abs=1e-15) and r.size_mm == pytest.approx(size, abs=1e-12)
    assert r.bounds_mm == pytest.approx((-size[0] / 2, size[0] / 2, -size[1] / 2, size[1] / 2))
    # the region in mm and in normalised display coordinates agree (display half-width 12 mm)
    assert (r.size_mm[0] / 24, r.size_mm[1] / 24) == pytest.approx((r.half_x, r.half_y))


def test_square_images_span_the_display_exactly_and_stretch_is_anisotropic():
    for n in (7, 27, 48, 1000):
        r = image_region(n, n)
        assert (r.half_x, r.half_y) == (1.0, 1.0) and r.pitch_mm == (24 / n, 24 / n)
    s = image_region(1080, 1920, placement="stretch")
    assert (s.half_x, s.half_y) == (1.0, 1.0) and s.pitch_mm == pytest.approx((24 / 1920, 24 / 1080))
    # a non-square display: a square image is limited by the shorter side (30 x 20 mm: pitch 2 mm)
    r = image_region(10, 10, (30.0, 20.0))
    assert r.pitch_mm == (2.0, 2.0) and (r.half_x, r.half_y) == pytest.approx((20 / 30, 1.0))
    xy = torch.tensor([[1.0, -1.0], [0.5, 0.25]])
    assert torch.equal(to_display(xy, 27, 48), torch.tensor([[1.0, -0.5625], [0.5, 0.140625]]))
    with pytest.raises(InputValueError, match="placement"):
        image_region(4, 4, placement="crop")  # type: ignore[arg-type]


D = torch.float64


def test_stretch_and_fit_placement_by_hand():
    """A 30 x 50 image on a 24 x 18 mm display. 'stretch': the whole display, pitch 24/50 by 18/30 mm,
    positions unchanged. 'fit': width-limited, pitch 0.48 mm both ways, 14.4 mm tall = 0.8 of the display."""
    s = image_region(30, 50, (24.0, 18.0), "stretch")
    assert (s.half_x, s.half_y, s.size_mm) == (1.0, 1.0, (24.0, 18.0))
    assert s.pitch_mm == pytest.approx((0.48, 0.6))
    f = image_region(30, 50, (24.0, 18.0), "fit")
    assert (f.half_x, f.half_y) == pytest.approx((1.0, 0.8)) and f.pitch_mm == pytest.approx((0.48, 0.48))
    assert f.size_mm == pytest.approx((24.0, 14.4)) and f.bounds_mm == pytest.approx((-12.0, 12.0, -7.2, 7.2))
    tall = image_region(50, 20, (24.0, 18.0), "fit")  # height-limited: pitch 18/50, 7.2 mm wide = 0.3 of the display
    assert (tall.half_x, tall.half_y) == pytest.approx((0.3, 1.0)) and tall.pitch_mm == pytest.approx((0.36, 0.36))
    xy = torch.tensor([[0.5, -0.5], [-1.0, 1.0]], dtype=D)
    assert torch.equal(to_display(xy, 30, 50, "stretch", (24.0, 18.0)), xy)
    torch.testing.assert_close(to_display(xy, 30, 50, "fit", (24.0, 18.0)), torch.tensor([[0.5, -0.4], [-1.0, 0.8]], dtype=D))
    torch.testing.assert_close(to_display(xy, 50, 20, "fit", (24.0, 18.0)), torch.tensor([[0.15, -0.5], [-0.3, 1.0]], dtype=D))


def test_image_region_is_frozen():
    r = image_region(4, 8)  # fit on the 24 x 24 mm display: the width fills it, half_y = 4 / 8
    assert (r.half_x, r.half_y) == (1.0, 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.half_x = 0.25  # type: ignore[misc]
    assert r.half_x == 1.0


def test_image_region_fit_by_hand():
    r = placement.image_region(9, 16)  # default: fit on the 24 x 24 mm Cardboard display
    assert (r.half_x, r.half_y) == (1.0, 0.5625)  # 9 / 16
    assert r.pitch_mm == (1.5, 1.5) and r.size_mm == (24.0, 13.5) and r.display_mm == (24.0, 24.0)
    assert r.bounds_mm == (-12.0, 12.0, -6.75, 6.75)
    t = placement.image_region(16, 9)
    assert (t.half_x, t.half_y) == (0.5625, 1.0) and t.size_mm == (13.5, 24.0)
    assert t.bounds_mm == (-6.75, 6.75, -12.0, 12.0)
    # a 30 x 20 mm display: a square image is height-limited, pitch 20 / 10 = 2, half_x = 20 / 30
    s = placement.image_region(10, 10, (30.0, 20.0))
    assert s.half_x == pytest.approx(2 / 3) and s.half_y == 1.0 and s.pitch_mm == (2.0, 2.0)
    assert s.size_mm == (20.0, 20.0)
    # a 40 x 10 image on it is width-limited: pitch 30 / 40 = 0.75, height 7.5 mm, half_y = 7.5 / 20
    w = placement.image_region(10, 40, (30.0, 20.0))
    assert w.half_x == 1.0 and w.half_y == pytest.approx(0.375) and w.size_mm == (30.0, 7.5)


def test_image_region_stretch_and_refusals():
    r = placement.image_region(9, 16, placement="stretch")
    assert (r.half_x, r.half_y) == (1.0, 1.0) and r.pitch_mm == (1.5, 24.0 / 9) and r.size_mm == (24.0, 24.0)
    with pytest.raises(InputValueError, match="placement must be one of"):
        placement.image_region(4, 4, placement="fill")
    for h, w in [(0, 4), (4, 0), (4.0, 4), (4, "4")]:
        with pytest.raises(InputValueError, match="image size must be ints >= 1"):
            placement.image_region(h, w)
    for mm in [(0.0, 24.0), (24.0, 0.0), (-1.0, 24.0), (24.0, float("nan"))]:
        with pytest.raises(InputValueError, match="display_mm must be"):
            placement.image_region(4, 4, mm)


def test_to_display_scales_by_the_half_extents():
    xy = torch.tensor([[1.0, 1.0], [-0.5, 0.5]], dtype=D)
    assert placement.to_display(xy, 4, 4) is xy
    out = placement.to_display(xy, 9, 16)
    assert out.tolist() == [[1.0, 0.5625], [-0.5, 0.28125]]
    out_t = placement.to_display(xy, 16, 9)
    assert out_t.tolist() == [[0.5625, 1.0], [-0.28125, 0.5]]
    assert placement.to_display(xy, 9, 16, "stretch") is xy
    assert placement.to_display(xy, 10, 10, display_mm=(30.0, 20.0))[0].tolist() == pytest.approx([2 / 3, 1.0])


def test_one_pixel_images_are_placed():
    # the bounds are inclusive: 1 x 1 spans the display (pitch 24 mm); 2 x 1 (tall) is height-limited,
    # pitch 24 / 2 = 12 mm, width 12 mm = half_x 0.5; 1 x 2 likewise on its side
    one = placement.image_region(1, 1)
    assert (one.half_x, one.half_y, one.pitch_mm) == (1.0, 1.0, (24.0, 24.0))
    tall = placement.image_region(2, 1)
    assert (tall.half_x, tall.half_y, tall.pitch_mm, tall.size_mm) == (0.5, 1.0, (12.0, 12.0), (12.0, 24.0))
    wide = placement.image_region(1, 2)
    assert (wide.half_x, wide.half_y, wide.size_mm) == (1.0, 0.5, (24.0, 12.0))
