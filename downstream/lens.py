"""Lens correction by pre-warping, P_lens (paper Eq. 2, Supp. "Lens Correction Through Pre-Warping").

The headset lens maps a display point ``p`` to the virtual-image point ``D_c(p)`` (its chief ray,
per colour channel c; pincushion for a magnifier). To make the eye see the rendered image ``I``
the display must show ``J_c(p) = I_c(D_c(p))``: as a map of points the pre-warp is ``D_c^-1``
("inverse distortion"), and applied by backward sampling it reads ``I`` at ``D_c(p)``. The stage
therefore holds, per channel, a *sampling grid* ``[3, H, W, 2]``: for every display pixel the
(x, y) position in the rendered image to sample, in normalised coordinates ([-1, 1], pixel
centres, ``align_corners=False``), plus a per-pixel, per-channel gain ``[3, H, W]`` that corrects
colour shifts of the display-optics path. Sampling is bilinear; outside the image is black.

This module holds the stage (:class:`LensPrewarp`) and its functional twin (:func:`lens_prewarp`);
the grid geometry lives in :mod:`.warp`, the maps in :mod:`.lens_maps` and :mod:`.bank_maps`
(re-exported here). Sources of the grid (all :class:`PrewarpMap` modules, evaluated at any image size):
- :class:`RadialMap`: ``grid_c(p) = p (1 + k_c1 r^2 + k_c2 r^4 + ...)``, r the radius in
  display-normalised coordinates of the image placed on the square Cardboard display with
  ``"fit"`` (the longer image axis spans [-1, 1]; the same frame as the optics). Default: a one-term fit to the chief
  rays of the Google-Cardboard lens (``CARDBOARD_RADIAL``), for tests and users without a bank.
- :class:`LUTMap`: a lookup table (grid + gain), e.g. from chief rays with
  :meth:`LensPrewarp.from_chief_ray_map`, or baked from a learned map. A LUT holds for images of
  the aspect it was made at.
- :class:`BankMap`: a PSF bank's chief rays for an image placed on the bank's display
  (:mod:`.placement`, default ``"fit"``), evaluated at each image size:
  :meth:`LensPrewarp.from_psf_bank`.
- :class:`MLPMap`: a small MLP (x, y) -> per-channel displacement and log-gain, zero-initialised
  (identity), trained end to end through the optics; :meth:`LensPrewarp.bake` turns it into a LUT.

Domain: linear light (bilinear sampling interpolates emitted light, like a compositor sampling an
sRGB texture).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from controlgs_adapter.checks import check_image, check_same_device, check_tensor
from controlgs_adapter.errors import FileFormatError, InputValueError, warn_user
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors
from controlgs_adapter.state import RuntimeState

from .bank_maps import DISPLAY_LUT_FORMAT_VERSION as DISPLAY_LUT_FORMAT_VERSION  # re-exported: the file format's old home
from .bank_maps import DISPLAY_LUT_KIND as DISPLAY_LUT_KIND
from .bank_maps import (
    DEFAULT_PREWARP_FILE, BankMap, DisplayLUTMap, _bank_in_image_frame, _optics_bank, _optics_placement, bank_fingerprint,
)
from .color import primaries_to_rgb, rgb_to_primaries
from .lens_maps import CARDBOARD_RADIAL, LUTMap, MLPMap, PrewarpMap, RadialMap
from .placement import Placement
from .stage import Stage, StageContext
from .warp import chief_ray_grid, invert_map, pixel_grid

if TYPE_CHECKING:  # pragma: no cover
    from .optics.bank import PSFBank

__all__ = [
    "CARDBOARD_RADIAL", "pixel_grid", "lens_prewarp", "invert_map", "chief_ray_grid", "PrewarpMap", "RadialMap",
    "LUTMap", "BankMap", "DisplayLUTMap", "MLPMap", "LensPrewarp", "bank_fingerprint", "BASES", "DEFAULT_PREWARP_FILE",
]

Basis = Literal["primaries", "rgb"]
#: colour bases of the warp: the display primaries (default) or the RGB channels (the paper's)
BASES: tuple[str, ...] = ("primaries", "rgb")
#: samples per display pixel along each axis of the fitted pre-warp (:meth:`LensPrewarp.for_optics`)
FITTED_SUPERSAMPLE = 2
LUT_KIND = "controlgs-prewarp-lut"
LUT_FORMAT_VERSION = 1


def lens_prewarp(image: torch.Tensor, grid: torch.Tensor, gain: torch.Tensor | None = None,
                 basis: Basis = "rgb", supersample: int = 1) -> torch.Tensor:
    """Per-channel bilinear warp and gain.

    Args:
        image: ``[..., 3, H, W]`` rendered image (linear light).
        grid: ``[3, Ho, Wo, 2]`` per channel, for every output pixel, the normalised (x, y)
            position in ``image`` to sample (``align_corners=False``; outside -> 0).
        gain: ``[3, Ho, Wo]`` per-pixel, per-channel factor, or None (1).
        basis: ``"rgb"``: the channels are the RGB channels (the paper's per-channel warp);
            ``"primaries"``: the image is converted to the display primaries (656 / 550 / 486 nm,
            :func:`.color.rgb_to_primaries`), each primary is warped with its own grid and gain,
            and the result converted back to linear RGB (what the panel's subpixels emit).
        supersample: ``n``: each output pixel averages ``n x n`` bilinear samples spread over its
            footprint in ``image`` (the grid's steps to the neighbouring output pixels): an area
            sample where the warp minifies, so a detail finer than an output pixel is not aliased
            (1: one sample at the grid point).
    Returns:
        ``[..., 3, Ho, Wo]``, ``out_c = gain_c * image_c(grid_c)`` in the chosen basis.
    """
    check_image("image", image, finite=False)
    if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
        raise InputValueError(f"supersample must be an int >= 1, got {supersample!r}")
    b = check_tensor("grid", grid, [3, "Ho", "Wo", 2], dtypes=(image.dtype,))
    check_same_device(image=image, grid=grid)
    if gain is not None:
        check_tensor("gain", gain, [3, "Ho", "Wo"], dtypes=(image.dtype,), dims=b)
        check_same_device(image=image, gain=gain)
    if basis not in BASES:
        raise InputValueError(f"basis must be one of {BASES}, got {basis!r}")
    if basis == "primaries":
        image = rgb_to_primaries(image)
    h, w = image.shape[-2:]
    lead = image.shape[:-3]
    per_channel = image.reshape(-1, 3, h, w).transpose(0, 1)  # [3, B, H, W]: channels as the batch
    warped = _area_sample(per_channel, grid, supersample)
    if gain is not None:
        warped = warped * gain[:, None]
    out = warped.transpose(0, 1).reshape(*lead, 3, b["Ho"], b["Wo"])
    return primaries_to_rgb(out) if basis == "primaries" else out


def _area_sample(channels: torch.Tensor, grid: torch.Tensor, n: int) -> torch.Tensor:
    """``[3, B, Ho, Wo]``: the mean of ``n x n`` bilinear samples of ``channels`` ``[3, B, H, W]``
    over each output pixel's footprint (the parallelogram of the grid's central differences)."""
    if n == 1:
        return F.grid_sample(channels, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    steps = [torch.gradient(grid, dim=d)[0] if grid.shape[d] > 1 else torch.zeros_like(grid) for d in (2, 1)]
    offsets = [((i + 0.5) / n - 0.5, (j + 0.5) / n - 0.5) for i in range(n) for j in range(n)]
    total = channels.new_zeros(channels.shape[:2] + grid.shape[1:3])
    for oy, ox in offsets:
        total = total + F.grid_sample(channels, grid + ox * steps[0] + oy * steps[1], mode="bilinear",
                                      padding_mode="zeros", align_corners=False)
    return total / (n * n)


class LensPrewarp(Stage):
    """P_lens: per-channel pre-warp and gain from a :class:`PrewarpMap` (default: Cardboard radial).

    A map with trainable parameters is never skipped in training mode (even while it is still
    the identity, so that it receives gradients).

    Args:
        prewarp_map: the map; default ``RadialMap(coefficients)``.
        coefficients: ``[3, K]`` radial coefficients, only when ``prewarp_map`` is None.
        basis: ``"primaries"`` (default: each display primary warped with its own map, see
            :func:`lens_prewarp`) or ``"rgb"`` (the paper's per-RGB-channel warp).
        supersample: samples per output pixel along each axis (:func:`lens_prewarp`; 1: one).
    """

    name = "lens"
    domain = "linear"
    order = 10.0

    def __init__(self, prewarp_map: PrewarpMap | None = None, *, coefficients: Sequence[Sequence[float]] | torch.Tensor | None = None,
                 basis: Basis = "primaries", supersample: int = 1) -> None:
        super().__init__()
        if isinstance(supersample, bool) or not isinstance(supersample, int) or supersample < 1:
            raise InputValueError(f"supersample must be an int >= 1, got {supersample!r}")
        if prewarp_map is not None and coefficients is not None:
            raise InputValueError("give either prewarp_map or coefficients, not both")
        if basis not in BASES:
            raise InputValueError(f"basis must be one of {BASES}, got {basis!r}")
        self.map = prewarp_map if prewarp_map is not None else RadialMap(CARDBOARD_RADIAL if coefficients is None else coefficients)
        self.basis = basis
        self.supersample = supersample

    @classmethod
    def for_optics(
        cls, optics: nn.Module, *, source: Literal["fitted", "chief_rays"] = "fitted", basis: Basis = "primaries",
        lut: str | os.PathLike | None = None, gain: Literal["jacobian"] | None = None, supersample: int | None = None,
    ) -> "LensPrewarp":
        """The pre-warp that compensates an optics stage (its ``bank``, ``placement`` and, for a
        fitted LUT, its current ``mode``).

        Args:
            optics: the pipeline's optics stage (:class:`~.optics.stage.PSFOptics`).
            source: ``"fitted"``: map and gain fitted through the optics
                (:func:`.prewarp_fit.fit_bank_prewarp`), read from ``lut`` (default: a shipped lens's LUT
                fitted for this bank, found by its fingerprint, :func:`.optics.lenses.prewarp_for_bank`;
                for another bank without a LUT this falls back to ``"chief_rays"`` with a warning, without one for a
                bank without PSFs, whose chief rays are its whole optics); ``"chief_rays"``: the bank's chief rays
                (:class:`BankMap`, gain ``gain``).
            basis: see :class:`LensPrewarp`.
            lut: a file written by :meth:`DisplayLUTMap.save` (``controlgs optics fit-prewarp``).
            supersample: see :class:`LensPrewarp`; None: :data:`FITTED_SUPERSAMPLE` for a fitted LUT (the
                fit places each primary of a dot within 0.1 px with it), 1 for the chief rays.
        """
        bank = _optics_bank(optics)
        placement = _optics_placement(optics)
        if source == "chief_rays":
            return cls(BankMap(bank, placement, gain), basis=basis, supersample=supersample or 1)
        if source != "fitted":
            raise InputValueError(f"source must be 'fitted' or 'chief_rays', got {source!r}")
        if gain is not None:
            raise InputValueError("gain applies to source='chief_rays'; a fitted LUT brings its own gain")
        if lut is None:
            from .optics.lenses import prewarp_for_bank

            shipped = prewarp_for_bank(bank)
            fitted = None if shipped is None else DisplayLUTMap.load(shipped, placement)
            radiometry = getattr(optics, "radiometry", None)
            if fitted is None or fitted.meta.get("radiometry") != radiometry:
                fallback: Literal["jacobian"] | None = "jacobian" if radiometry == "energy" else None
                if not bank.has_psf:  # a distortion profile: its chief rays are the whole optics, nothing to fit
                    return cls(BankMap(bank, placement, fallback), basis=basis,
                               supersample=FITTED_SUPERSAMPLE if supersample is None else supersample)
                warn_user(f"no fitted pre-warp LUT for this PSF bank and radiometry {radiometry!r}: using its chief "
                          f"rays (gain {fallback}); make one with `controlgs optics fit-prewarp --lens BANK --out LUT` "
                          "and pass it as {'lens': {'lut': LUT}}", UserWarning)
                return cls(BankMap(bank, placement, fallback), basis=basis, supersample=supersample or 1)
        else:
            fitted = DisplayLUTMap.load(lut, placement)
            if fitted.meta.get("bank") != bank_fingerprint(bank):
                raise InputValueError(f"{lut}: this pre-warp LUT was fitted for another PSF bank "
                                      f"({fitted.meta.get('bank')!r}, the optics' bank is {bank_fingerprint(bank)!r})")
            if fitted.meta.get("radiometry") != getattr(optics, "radiometry", None):
                raise InputValueError(f"{lut}: this pre-warp LUT was fitted for radiometry {fitted.meta.get('radiometry')!r}, "
                                      f"the optics use {getattr(optics, 'radiometry', None)!r}")
        return cls(fitted.follow(optics), basis=basis, supersample=FITTED_SUPERSAMPLE if supersample is None else supersample)

    @classmethod
    def radial(cls, coefficients: Sequence[Sequence[float]] | torch.Tensor, learnable: bool = False) -> "LensPrewarp":
        """Analytic radial polynomial map, ``coefficients`` ``[3, K]``."""
        return cls(RadialMap(coefficients, learnable=learnable))

    @classmethod
    def from_lut(cls, grid: torch.Tensor, gain: torch.Tensor | None = None) -> "LensPrewarp":
        """From a sampling grid ``[3, H, W, 2]`` and gain ``[3, H, W]`` (see :class:`LUTMap`)."""
        return cls(LUTMap(grid, gain))

    @classmethod
    def learned(cls, hidden: int = 64, layers: int = 2, frequencies: int = 4) -> "LensPrewarp":
        """A trainable :class:`MLPMap` (identity at init)."""
        return cls(MLPMap(hidden, layers, frequencies))

    @classmethod
    def from_chief_ray_map(
        cls,
        chief_ray_map: torch.Tensor,
        size: tuple[int, int],
        *,
        direction: Literal["display_to_eye", "eye_to_display"] = "display_to_eye",
        sample_x: torch.Tensor | None = None,
        sample_y: torch.Tensor | None = None,
        gain: torch.Tensor | Literal["jacobian"] | None = None,
    ) -> "LensPrewarp":
        """Build the LUT that compensates the lens's chief-ray mapping.

        Args:
            chief_ray_map: ``[3, Gh, Gw, 2]`` per channel (R, G, B primaries), sampled on a regular
                ``Gh x Gw`` grid of normalised (x, y) positions (``sample_x``, ``sample_y``):
                - ``"display_to_eye"`` (what a PSF bank stores: a chief ray per display field
                  point): the virtual-image position, in the normalised frame of the rendered
                  image, where the display point is seen. The grid is this map at the display
                  pixel centres (interpolated).
                - ``"eye_to_display"`` (rays traced from the eye): the display position that shows
                  the virtual-image point; it is inverted numerically (:func:`invert_map`).
            size: ``(H, W)`` of the LUT (the display/native resolution).
            sample_x, sample_y: ``[Gw]``, ``[Gh]`` uniform coordinates of the samples; default:
                the cell centres of [-1, 1] (pixel-centre convention).
            gain: ``[3, H, W]`` per-channel gain; ``"jacobian"``: the area magnification
                ``|det dD_c/dp|`` of the map at each display pixel, which undoes the brightness
                fall-off of an energy-conserving lens (a display pixel's light spreads over that
                area); it exceeds 1 off axis, so the display clips there unless the image is dimmer;
                None: 1.
        """
        return cls(LUTMap(*chief_ray_grid(chief_ray_map, size, direction=direction, sample_x=sample_x,
                                          sample_y=sample_y, gain=gain)))

    @classmethod
    def from_psf_bank(
        cls, bank: "PSFBank | None", size: tuple[int, int] | None = None, *,
        gain: torch.Tensor | Literal["jacobian"] | None = None, placement: Placement = "fit",
    ) -> "LensPrewarp":
        """Compensate the distortion and lateral colour of a PSF bank's lens (None: the shipped
        Google-Cardboard bank): its chief rays (display -> eye, one map per primary) for an image
        placed on the bank's display with ``placement`` (as the optics stage places it).

        Args:
            size: None: a :class:`BankMap`, evaluated at each image's size (any aspect); ``(H, W)``:
                a :class:`LUTMap` at that size (valid for images of that aspect).
            gain: as in :meth:`from_chief_ray_map` (a tensor needs ``size``).
            placement: ``"fit"`` or ``"stretch"``, :mod:`controlgs_adapter.downstream.placement`.
        """
        from .optics.bank import PSFBank

        bank = bank if bank is not None else PSFBank.default()
        if size is None:
            if isinstance(gain, torch.Tensor):
                raise InputValueError("a gain tensor needs a LUT size: pass size=(H, W)")
            return cls(BankMap(bank, placement, gain))
        if bank.chief.shape[0] != 3:
            raise InputValueError(f"bank must have 3 wavelengths (R, G, B primaries), got {bank.wavelengths_nm}")
        chief, sx, sy = _bank_in_image_frame(bank, size, placement)
        return cls(LUTMap(*chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain=gain)))

    def save_lut(self, path: str | os.PathLike, size: tuple[int, int] | None = None) -> Path:
        """Write the map as a LUT (safetensors, atomic): the LUT itself, or the map baked at
        ``size`` (required unless the map is a :class:`LUTMap`). Returns the path."""
        if size is None:
            if not isinstance(self.map, LUTMap):
                raise InputValueError(f"size is required to save a {type(self.map).__name__} as a LUT")
            lut = self.map
        else:
            lut = self._baked(size)
        grid = (lut.displacement + pixel_grid((lut.gain.shape[1], lut.gain.shape[2]), lut.gain.dtype, lut.gain.device)).float()
        header = {"size": list(lut.gain.shape[1:]), "source": type(self.map).__name__,
                  "units": {"grid": "normalised (x, y) sampling positions, align_corners=False", "gain": "factor"}}
        return save_tensors(path, {"grid": grid, "gain": lut.gain.float()}, header, kind=LUT_KIND,
                            format_version=LUT_FORMAT_VERSION)

    @classmethod
    def load_lut(cls, path: str | os.PathLike) -> "LensPrewarp":
        """Read a LUT written by :meth:`save_lut`."""
        tensors, _ = load_tensors(path, kind=LUT_KIND, max_version=LUT_FORMAT_VERSION)
        missing = {"grid", "gain"} - set(tensors)
        if missing:
            raise FileFormatError(f"{path}: pre-warp LUT lacks {sorted(missing)}")
        return cls.from_lut(tensors["grid"], tensors["gain"])

    def bake(self, size: tuple[int, int]) -> "LensPrewarp":
        """A LUT copy of this stage's map at ``(H, W)`` (fixed, cheap at inference)."""
        return LensPrewarp(self._baked(size), basis=self.basis)

    def _baked(self, size: tuple[int, int]) -> LUTMap:
        """This stage's map tabulated at ``(H, W)``."""
        tensors = [*self.map.parameters(), *self.map.buffers()]
        device = tensors[0].device if tensors else torch.device("cpu")
        with torch.no_grad():
            grid, gain = self.map(size, torch.float32, device)
            return LUTMap(grid, gain)

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:  # noqa: D102
        if self.training and any(p.requires_grad for p in self.map.parameters()):
            return False
        return self.map.is_identity()

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        grid, gain = self.map(tuple(image.shape[-2:]), image.dtype, image.device)
        return lens_prewarp(image, grid, gain, self.basis, self.supersample)

    def extra_repr(self) -> str:
        return f"basis={self.basis!r}, supersample={self.supersample}"
