"""Colour conversions of the display path (paper Supp. "Physical Display", Eqs. S1 and S3).

- sRGB transfer functions, exact IEC 61966-2-1 piecewise form. Values below the linear-segment
  threshold (negatives included) stay on the linear segment, so both directions are defined on
  the whole real line, invertible, and have finite gradients everywhere (slope 1/12.92 and 12.92
  at 0). Values above 1 follow the power branch (no clamping here; the display clips).
- Linear RGB <-> intensities of three monochromatic display primaries at 656 / 550 / 486 nm.
  A primary of unit intensity at wavelength l emits the CIE 1931 2-degree tristimulus
  ``cmf(l) = (xbar, ybar, zbar)(l)``; so for primaries ``s``, ``XYZ = C s`` with
  ``C = [cmf(656) | cmf(550) | cmf(486)]``, and for linear sRGB ``XYZ = M rgb`` (IEC sRGB -> XYZ
  matrix, D65). Hence ``s = C^-1 M rgb``. Each primary is then scaled so that linear-RGB white
  (1, 1, 1) drives all three primaries at 1 (a per-channel unit that cancels in the round trip and
  keeps primary images in the range of the RGB image). Saturated colours outside the triangle of
  the three primaries get negative intensities; they are kept (the optics is linear).
  The matrices come from colour-science (no hand-typed tables), are computed once in float64 and
  cached per dtype/device; the inverse is the float64 matrix inverse.

Shapes: images ``[..., 3, H, W]`` (channels-first, any leading dims), float32/float64.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Literal

import numpy as np
import torch
from torch import nn

from controlgs_adapter.checks import check_image

__all__ = [
    "PRIMARY_WAVELENGTHS_NM", "srgb_to_linear", "linear_to_srgb", "convert_domain",
    "rgb_to_primaries", "primaries_to_rgb", "rgb_to_primaries_matrix", "primaries_to_rgb_matrix",
    "SRGBToLinear", "LinearToSRGB", "RGBToPrimaries", "PrimariesToRGB",
]

#: Wavelengths of the red, green and blue display primaries (paper Eq. S1), nanometres.
PRIMARY_WAVELENGTHS_NM: tuple[int, int, int] = (656, 550, 486)

# IEC 61966-2-1 constants
_A = 0.055
_GAMMA = 2.4
_SLOPE = 12.92
_DECODE_THRESHOLD = 0.04045  # encoded value where the power branch starts
# linear value where the power branch starts: IEC writes 0.0031308; 0.04045 / 12.92 = 0.00313080495...
# (5e-12 away) makes the linear segments map exactly onto each other, so the pair is exactly inverse
_ENCODE_THRESHOLD = _DECODE_THRESHOLD / _SLOPE


def srgb_to_linear(image: torch.Tensor) -> torch.Tensor:
    """sRGB-encoded -> linear light (IEC 61966-2-1 EOTF), elementwise.

    Args:
        image: ``[..., 3, H, W]`` encoded values (any real value is accepted).
    Returns:
        ``[..., 3, H, W]`` linear values, same dtype.
    """
    check_image("image", image, finite=False)
    return _srgb_to_linear(image)


def _srgb_to_linear(image: torch.Tensor) -> torch.Tensor:
    power_in = image.clamp(min=_DECODE_THRESHOLD)  # the unused branch never sees x <= threshold (no NaN grads)
    power = ((power_in + _A) / (1.0 + _A)) ** _GAMMA
    return torch.where(image <= _DECODE_THRESHOLD, image / _SLOPE, power)


def linear_to_srgb(image: torch.Tensor) -> torch.Tensor:
    """Linear light -> sRGB-encoded (inverse of :func:`srgb_to_linear`), elementwise.

    Args:
        image: ``[..., 3, H, W]`` linear values (any real value is accepted).
    Returns:
        ``[..., 3, H, W]`` encoded values, same dtype.
    """
    check_image("image", image, finite=False)
    return _linear_to_srgb(image)


def _linear_to_srgb(image: torch.Tensor) -> torch.Tensor:
    power_in = image.clamp(min=_ENCODE_THRESHOLD)  # x ** (1/2.4) has an infinite slope at 0
    power = (1.0 + _A) * power_in ** (1.0 / _GAMMA) - _A
    return torch.where(image <= _ENCODE_THRESHOLD, image * _SLOPE, power)


Domain = Literal["srgb", "linear"]


def convert_domain(image: torch.Tensor, src: Domain, dst: Domain) -> torch.Tensor:
    """Convert ``image`` ``[..., 3, H, W]`` between the colour domains of stages; a no-op if equal.

    Unchecked (the pipeline validates its input once); use the public functions for user data.
    """
    if src == dst:
        return image
    if (src, dst) == ("srgb", "linear"):
        return _srgb_to_linear(image)
    if (src, dst) == ("linear", "srgb"):
        return _linear_to_srgb(image)
    raise ValueError(f"unknown colour domain conversion {src!r} -> {dst!r} (expected 'srgb' or 'linear')")


@lru_cache(maxsize=1)
def _primaries_matrices_f64() -> tuple[np.ndarray, np.ndarray]:
    """(rgb->primaries, primaries->rgb) as float64 ``[3, 3]`` numpy arrays, built from colour-science."""
    return _primaries_matrices_for(PRIMARY_WAVELENGTHS_NM)


def _primaries_matrices_for(wavelengths_nm: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_primaries_matrices_f64` for primaries at ``wavelengths_nm`` (R, G, B), uncached;
    :class:`RuntimeError` if the sRGB white lies outside their gamut."""
    import colour  # heavy import, done once and only when the primaries are used

    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    c = np.stack([np.asarray(cmfs[w], dtype=np.float64) for w in wavelengths_nm], axis=1)  # [3 XYZ, 3 primaries]
    m = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, dtype=np.float64)  # [3 XYZ, 3 RGB]
    raw = np.linalg.solve(c, m)  # C^-1 M: linear RGB -> primary intensities (unit: one CMF emission)
    white = raw @ np.ones(3)
    if not np.all(white > 0):  # the sRGB white point must lie inside the primaries' triangle
        raise RuntimeError(f"sRGB white is outside the gamut of the {wavelengths_nm} nm primaries: {white}")
    to_primaries = raw / white[:, None]  # white (1, 1, 1) -> (1, 1, 1)
    return to_primaries, np.linalg.inv(to_primaries)


@lru_cache(maxsize=16)
def _matrix(which: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(_primaries_matrices_f64()[which], dtype=dtype, device=device)


def rgb_to_primaries_matrix(dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
    """``[3, 3]`` matrix M_RGB->lambda (rows: 656, 550, 486 nm primaries; columns: linear R, G, B)."""
    return _matrix(0, dtype, torch.device(device)).clone()


def primaries_to_rgb_matrix(dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu") -> torch.Tensor:
    """``[3, 3]`` matrix M_lambda->RGB, the exact inverse of :func:`rgb_to_primaries_matrix`."""
    return _matrix(1, dtype, torch.device(device)).clone()


def _apply_channel_matrix(image: torch.Tensor, matrix: torch.Tensor) -> torch.Tensor:
    return torch.einsum("ij,...jhw->...ihw", matrix, image)


def rgb_to_primaries(image: torch.Tensor) -> torch.Tensor:
    """Linear RGB ``[..., 3, H, W]`` -> primary intensities ``[..., 3, H, W]`` (656, 550, 486 nm).

    Linear, so negative intensities appear for colours outside the primaries' gamut.
    """
    check_image("image", image, finite=False)
    return _apply_channel_matrix(image, _matrix(0, image.dtype, image.device))


def primaries_to_rgb(primaries: torch.Tensor) -> torch.Tensor:
    """Primary intensities ``[..., 3, H, W]`` (656, 550, 486 nm) -> linear RGB ``[..., 3, H, W]``."""
    check_image("primaries", primaries, finite=False)
    return _apply_channel_matrix(primaries, _matrix(1, primaries.dtype, primaries.device))


class SRGBToLinear(nn.Module):
    """Module twin of :func:`srgb_to_linear`."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return srgb_to_linear(image)


class LinearToSRGB(nn.Module):
    """Module twin of :func:`linear_to_srgb`."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return linear_to_srgb(image)


class RGBToPrimaries(nn.Module):
    """Module twin of :func:`rgb_to_primaries`."""

    def forward(self, image: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return rgb_to_primaries(image)


class PrimariesToRGB(nn.Module):
    """Module twin of :func:`primaries_to_rgb`."""

    def forward(self, primaries: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return primaries_to_rgb(primaries)
