"""Where an ``H x W`` image sits on the headset display: the one definition used by the optics
(:meth:`PSFBank.resample_to`), the lens pre-warp built from a bank's chief rays and the per-anchor
condition strengths (``lens``, ``foveation``). Derivation and figure: ``docs/explanation/optics.md``, section
"Images of any aspect on the display".

Placements:

- ``"fit"`` (default): square pixels, the image scaled to fit the display and centred. Pixel pitch
  ``p = min(Dw / W, Dh / H)`` mm; the image covers ``W p x H p`` mm. On the 24 x 24 mm Cardboard
  display a 16:9 landscape image spans the full 24 mm width and 13.5 mm of the height; a square
  image spans the whole display. The rest of the display is black: it emits no light, so only the
  image's region is simulated.
- ``"stretch"``: the display stretched onto the image (pitch ``Dw / W`` by ``Dh / H`` mm,
  anisotropic pixels for an image whose aspect differs from the display's).

Coordinates: display-normalised ``[-1, 1]^2`` about the display centre (the optical axis), x right,
y down; image-normalised ``[-1, 1]^2`` per image axis (pixel centres at ``(2 i + 1) / W - 1``, as
``Camera.normalized_screen``). The image region is ``[-half_x, half_x] x [-half_y, half_y]`` in
display-normalised coordinates, and ``display = image * (half_x, half_y)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from controlgs_adapter.errors import InputValueError

__all__ = ["Placement", "PLACEMENTS", "CARDBOARD_DISPLAY_MM", "ImageRegion", "image_region", "to_display"]

Placement = Literal["fit", "stretch"]
PLACEMENTS: tuple[str, ...] = ("fit", "stretch")
#: (width, height) of the Google-Cardboard display the shipped PSF bank was made for (paper Tbl. S1).
CARDBOARD_DISPLAY_MM: tuple[float, float] = (24.0, 24.0)


@dataclass(frozen=True)
class ImageRegion:
    """The image's region on the display.

    Attributes:
        half_x, half_y: half-extents in display-normalised coordinates (1 = the display's edge).
        pitch_mm: ``(x, y)`` pixel pitch on the display in mm (equal under ``"fit"``).
        size_mm: ``(width, height)`` of the region in mm, centred on the display.
        display_mm: ``(width, height)`` of the display in mm.
    """

    half_x: float
    half_y: float
    pitch_mm: tuple[float, float]
    size_mm: tuple[float, float]
    display_mm: tuple[float, float]

    @property
    def bounds_mm(self) -> tuple[float, float, float, float]:
        """``(x0, x1, y0, y1)`` of the region in mm about the display centre (y down)."""
        w, h = self.size_mm
        return -w / 2, w / 2, -h / 2, h / 2


def image_region(height: int, width: int, display_mm: tuple[float, float] = CARDBOARD_DISPLAY_MM,
                 placement: Placement = "fit") -> ImageRegion:
    """The region of an ``height x width`` image on a ``display_mm`` display (see module docstring).

    A square image on a square display gets exactly ``half_x = half_y = 1`` under both placements.
    """
    if placement not in PLACEMENTS:
        raise InputValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
    if not (isinstance(height, int) and isinstance(width, int)) or height < 1 or width < 1:
        raise InputValueError(f"image size must be ints >= 1, got {height!r} x {width!r}")
    dw, dh = float(display_mm[0]), float(display_mm[1])
    if not (dw > 0 and dh > 0):
        raise InputValueError(f"display_mm must be (width, height) > 0, got {display_mm}")
    if placement == "stretch":
        return ImageRegion(1.0, 1.0, (dw / width, dh / height), (dw, dh), (dw, dh))
    if width * dh >= height * dw:                   # relatively wider than the display: width-limited
        p = dw / width
        return ImageRegion(1.0, (height / width) * (dw / dh), (p, p), (dw, height * p), (dw, dh))
    p = dh / height
    return ImageRegion((width / height) * (dh / dw), 1.0, (p, p), (width * p, dh), (dw, dh))


def to_display(xy: torch.Tensor, height: int, width: int, placement: Placement = "fit",
               display_mm: tuple[float, float] = CARDBOARD_DISPLAY_MM) -> torch.Tensor:
    """Image-normalised positions ``[..., 2]`` (x, y) of an ``height x width`` image -> display-normalised
    positions ``[..., 2]`` (non-finite values stay non-finite)."""
    r = image_region(height, width, display_mm, placement)
    if r.half_x == 1.0 and r.half_y == 1.0:
        return xy
    return xy * torch.tensor([r.half_x, r.half_y], dtype=xy.dtype, device=xy.device)
