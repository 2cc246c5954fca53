"""Foveation: eccentricity-dependent resolution around the gaze, in visual degrees through the lens.

Model (``docs/explanation/foveation.md``): the minimum angle of resolution grows linearly with the
eccentricity ``e`` (degrees) from the gaze, ``omega(e) = omega0 + m e`` (Guenter et al. 2012), so a pixel
needs a local sampling rate ``min(ppd, 1 / omega(e))`` (pixels per degree; ``ppd`` the display's own,
through the lens: :class:`~controlgs_adapter.downstream.optics.visual_angles.VisualAngles`). The blur
scale ``s = ppd / rate >= 1`` (capped at ``max_scale`` for the product levels) sets a continuous mip level
``l = log2(s)``; the output blends a mip pyramid (2 x 2 box prefilter per level, bilinear reconstruction
to full size) per pixel: ``out = L0 + sum_k w_k (L_k - L_{k-1})``, ``w_k = clamp(l - k + 1, 0, 1)`` (computed as
``sum_k (w_k - w_{k+1}) L_k``). Where ``s = 1`` (the foveal plateau, ``1 / omega(e) >= ppd``) ``L0``'s weight is
1, every other 0, and the output is the input exactly. The
operation is linear in the image (differentiable); the gaze only sets the weights.

Presets (slope ``m`` in deg/deg, ``omega0 = 1/60`` deg): ``"guenter-0.022"``, ``"guenter-0.0275"``;
``"level-4x"`` / ``"level-16x"``: the 0.0275 slope with the periphery at most 4x / 16x fewer pixels
(``max_scale`` 2 / 4); ``"off"``. Gaze is ``RuntimeState.gaze`` (azimuth, elevation) in degrees from the
lens axis; with no gaze the stage is the identity unless ``fixed`` (then centred on the lens axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
import torch.nn.functional as F

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import RuntimeState

from .optics.bank import PSFBank
from .optics.visual_angles import VisualAngles, angle_to, direction_vectors
from .placement import PLACEMENTS, Placement
from .stage import Stage, StageContext

__all__ = ["foveation", "Foveation", "FoveationModel", "PRESETS", "sampling_rate", "blur_scale", "pixel_savings"]


@dataclass(frozen=True)
class FoveationModel:
    """A minimum-angle-of-resolution model ``omega(e) = omega0 + slope e`` (degrees).

    Attributes:
        omega0: MAR at the gaze (deg; 1/60: 20/20 acuity).
        slope: MAR growth (deg per deg of eccentricity).
        max_scale: largest blur scale ``s`` (linear; the periphery at most ``max_scale^2`` fewer
            pixels), None: unbounded.
    """

    omega0: float = 1.0 / 60.0
    slope: float = 0.022
    max_scale: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.omega0) and self.omega0 > 0 and math.isfinite(self.slope) and self.slope >= 0):
            raise InputValueError(f"foveation model: omega0 must be > 0 and slope >= 0 (deg), got "
                                  f"{self.omega0!r}, {self.slope!r}")
        if self.max_scale is not None and not (math.isfinite(self.max_scale) and self.max_scale >= 1):
            raise InputValueError(f"foveation model: max_scale must be None or >= 1, got {self.max_scale!r}")


#: the named models; "off" is None
PRESETS: dict[str, FoveationModel | None] = {
    "off": None,
    "guenter-0.022": FoveationModel(slope=0.022),
    "guenter-0.0275": FoveationModel(slope=0.0275),
    "level-4x": FoveationModel(slope=0.0275, max_scale=2.0),
    "level-16x": FoveationModel(slope=0.0275, max_scale=4.0),
}


def _model(preset: str | FoveationModel | None) -> FoveationModel | None:
    if preset is None or isinstance(preset, FoveationModel):
        return preset
    if not isinstance(preset, str) or preset not in PRESETS:
        raise InputValueError(f"foveation preset must be one of {sorted(PRESETS)} or a FoveationModel, got {preset!r}")
    return PRESETS[preset]


def sampling_rate(ecc_deg: torch.Tensor, ppd: torch.Tensor, model: FoveationModel) -> torch.Tensor:
    """Local sampling rate (pixels per degree) ``min(ppd, 1 / omega(e))``; with ``max_scale`` at least
    ``ppd / max_scale``."""
    rate = torch.minimum(ppd, 1.0 / (model.omega0 + model.slope * ecc_deg))
    return rate if model.max_scale is None else torch.maximum(rate, ppd / model.max_scale)


def blur_scale(ecc_deg: torch.Tensor, ppd: torch.Tensor, model: FoveationModel) -> torch.Tensor:
    """Blur scale ``s = ppd / rate >= 1`` (1: full resolution)."""
    return (ppd / sampling_rate(ecc_deg, ppd, model)).clamp_min(1.0)


def pixel_savings(ecc_deg: torch.Tensor, ppd: torch.Tensor, model: FoveationModel) -> float:
    """Fraction of the display's pixels the foveated frame needs: the mean of ``(rate / ppd)^2``."""
    return float((1.0 / blur_scale(ecc_deg, ppd, model) ** 2).mean())


def _levels(image: torch.Tensor, count: int) -> list[torch.Tensor]:
    """``count + 1`` mip levels of ``image`` ``[N, C, H, W]``, each reconstructed at ``H x W``."""
    h, w = image.shape[-2:]
    out, cur = [image], image
    for _ in range(count):
        cur = F.avg_pool2d(cur, 2, ceil_mode=True, count_include_pad=False)
        out.append(F.interpolate(cur, size=(h, w), mode="bilinear", align_corners=False))
    return out


def _blend(image: torch.Tensor, level: torch.Tensor, count: int) -> torch.Tensor:
    """Per-pixel blend of ``image`` ``[..., C, H, W]`` and its first ``count`` mip levels at the continuous
    level ``level`` ``[H, W]`` >= 0 (levels above ``count`` clamp to it): ``sum_k (w_k - w_{k+1}) L_k`` with
    ``w_0 = 1``, ``w_k = clamp(level - k + 1, 0, 1)``."""
    if count == 0:
        return image
    flat = image.reshape(-1, *image.shape[-3:])
    levels = _levels(flat, count)
    w = [torch.ones_like(level)] + [(level - (k - 1)).clamp(0.0, 1.0) for k in range(1, count + 1)]
    w.append(torch.zeros_like(level))
    out = levels[0] * (w[0] - w[1])
    for k in range(1, count + 1):
        out = out.addcmul(levels[k], w[k] - w[k + 1])
    return out.reshape(image.shape)


def foveation(image: torch.Tensor, gaze: tuple[float, float] | None, *, preset: str | FoveationModel | None = "guenter-0.022",
              angles: VisualAngles | None = None, fixed: bool = False, placement: Placement = "fit") -> torch.Tensor:
    """Functional twin of :class:`Foveation`.

    Args:
        image: ``[..., 3, H, W]`` linear light.
        gaze: ``(azimuth, elevation)`` degrees from the lens axis, or None.
        preset: a name of :data:`PRESETS` or a :class:`FoveationModel`; ``"off"``/None: the identity.
        angles: the lens's visual angles; default the shipped Cardboard bank's.
        fixed: with no gaze, foveate about the lens axis (fixed foveation) instead of returning ``image``.
        placement: how the image sits on the display.
    Returns:
        ``image`` itself when off (no gaze and not ``fixed``, or no model), else the foveated image.
    """
    return Foveation(preset, angles=angles, fixed=fixed, placement=placement)(image, RuntimeState(gaze=gaze))


class Foveation(Stage):
    """Gaze-contingent resolution (module docstring). Args as :func:`foveation`; ``bank`` instead of
    ``angles`` gives the lens as a PSF bank."""

    name = "foveation"
    domain = "linear"
    order = 5.0

    def __init__(self, preset: str | FoveationModel | None = "guenter-0.022", *, angles: VisualAngles | None = None,
                 bank: PSFBank | None = None, fixed: bool = False, placement: Placement = "fit") -> None:
        super().__init__()
        if angles is not None and bank is not None:
            raise InputValueError("foveation: give the lens as angles or as bank, not both")
        if angles is not None and not isinstance(angles, VisualAngles):
            raise InputValueError(f"foveation: angles must be a VisualAngles, got {type(angles).__name__}")
        if not isinstance(fixed, bool):
            raise InputValueError(f"foveation: fixed must be a bool, got {fixed!r}")
        if placement not in PLACEMENTS:
            raise InputValueError(f"foveation: placement must be one of {PLACEMENTS}, got {placement!r}")
        self.model = _model(preset)
        self._angles, self._bank = angles, bank
        self.fixed, self.placement = fixed, placement
        self._maps: dict[tuple[int, int, torch.device, torch.dtype], tuple[torch.Tensor, torch.Tensor, int]] = {}

    @property
    def angles(self) -> VisualAngles:
        """The lens's visual-angle map (built from the bank on first use)."""
        if self._angles is None:
            self._angles = VisualAngles.of_bank(self._bank if self._bank is not None else PSFBank.default())
        return self._angles

    def maps(self, height: int, width: int, device: torch.device | str = "cpu",
             dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor, int]:
        """``(unit direction vectors [H, W, 3], ppd [H, W], levels)`` of an ``H x W`` image's pixels (cached per
        size, device and dtype); ``levels``: mip levels enough for any gaze in the field (no host sync per frame)."""
        key = (height, width, torch.device(device), dtype)
        if key not in self._maps:
            directions = self.angles.pixel_directions(height, width, self.placement)
            ppd = self.angles.pixels_per_degree(height, width, self.placement)
            assert self.model is not None
            span = float(torch.rad2deg(torch.atan(self.angles.tangents)).abs().amax()) * 2 * math.sqrt(2)
            top = float(blur_scale(torch.tensor(span, dtype=torch.float64), ppd.max(), self.model))
            levels = min(math.ceil(math.log2(top) - 1e-9), math.floor(math.log2(max(height, width))))
            self._maps[key] = (direction_vectors(directions).to(device, dtype), ppd.to(device, dtype), max(0, levels))
        return self._maps[key]

    def _gaze(self, state: RuntimeState) -> tuple[float, float] | None:
        if self.model is None:
            return None
        return state.gaze if state.gaze is not None else ((0.0, 0.0) if self.fixed else None)

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:  # noqa: D102
        return self._gaze(state) is None

    def level(self, height: int, width: int, gaze: Sequence[float], device: torch.device | str = "cpu",
              dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Continuous mip level ``log2(s)`` ``[H, W]`` for a gaze in degrees (InputValueError outside the field)."""
        if self.model is None:
            raise InputValueError("foveation: the preset is 'off', it has no levels")
        self.angles.check_gaze(gaze)
        unit, ppd, _ = self.maps(height, width, device, dtype)
        return torch.log2(blur_scale(angle_to(unit, gaze), ppd, self.model))

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        gaze = self._gaze(state)
        if gaze is None:
            return image
        h, w = image.shape[-2:]
        level = self.level(h, w, gaze, image.device, image.dtype)
        return _blend(image, level, self.maps(h, w, image.device, image.dtype)[2])
