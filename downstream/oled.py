"""Physical display D_phys: box-filter emission of display pixels (paper Eq. 6, Supp. "Physical Display").

Each display pixel emits a uniform square; on the simulation grid at the native resolution S
this is nearest-neighbour upsampling with the pixel-centre convention: simulation pixel ``i``
(centre ``i + 0.5``) shows display pixel ``floor((i + 0.5) * n / S)`` (``nearest-exact``). For an
integer ratio this repeats each display pixel into a ``k x k`` block.

The other parts of D_phys in the paper (sRGB decode, linear RGB -> monochromatic primaries) are
done by the pipeline's domain conversion (every physical stage works in linear light) and inside
the optics stage (:func:`controlgs_adapter.downstream.color.rgb_to_primaries`).

Domain: linear light (nearest upsampling commutes with any per-pixel transfer function anyway).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from controlgs_adapter.checks import check_image
from controlgs_adapter.errors import ShapeError
from controlgs_adapter.state import RuntimeState

from .stage import Stage, StageContext

__all__ = ["oled_emission", "OLEDEmission"]


def oled_emission(image: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Emit display pixels as boxes sampled on a finer simulation grid.

    Args:
        image: ``[..., 3, h, w]`` display image.
        size: ``(H, W)`` simulation size, ``H >= h`` and ``W >= w``.
    Returns:
        ``[..., 3, H, W]``; ``image`` itself when the sizes match.
    """
    check_image("image", image, finite=False)
    h, w = image.shape[-2:]
    size = (int(size[0]), int(size[1]))
    if (h, w) == size:
        return image
    if size[0] < h or size[1] < w:
        raise ShapeError(f"size must be at least the image size {(h, w)} (box emission only upsamples), got {size}")
    flat = image.reshape(-1, 3, h, w)
    return F.interpolate(flat, size=size, mode="nearest-exact").reshape(*image.shape[:-2], *size)


class OLEDEmission(Stage):
    """D_phys: nearest (box) upsampling from the display resolution back to ``ctx.native_size``."""

    name = "oled"
    domain = "linear"
    order = 40.0

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:  # noqa: D102
        return state.downsample == 1.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        return oled_emission(image, ctx.native_size)
