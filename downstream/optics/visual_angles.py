"""Visual angles through the lens: where each display pixel is seen, in degrees from the lens axis.

A lens model is a PSF bank's chief rays (:class:`~controlgs_adapter.downstream.optics.bank.PSFBank`,
green primary): ``chief`` gives, on a uniform grid of display-normalised positions, the landing on the
virtual image plane in normalised output coordinates. Seen from the eye pupil on the lens axis, a
landing ``(X, Y)`` (mm on the virtual image plane at distance ``D``, measured from the axis's own
landing) has the direction

    azimuth = atan(X / D),   elevation = atan(Y / D)     (degrees; x right, y down as the display)

i.e. the direction vector ``(tan azimuth, tan elevation, 1)``. The tangents ``(X / D, Y / D)`` are
``chief * scale`` per axis:

- a traced bank (``meta["prescription"]``, ``meta["figures"]["reference_magnification"]``):
  ``scale = display half-extent (mm) * reference magnification / virtual_image_distance_mm``;
- a bank from a distortion profile: ``meta["lens"]["deg_per_output_unit"]`` (``scale_x =
  radians(deg_per_output_unit)``, ``scale_y = scale_x * display height / width``), else
  ``meta["lens"]["half_fov_deg"]`` (the landing at half the display width from the axis is seen at
  that angle).

Pixels per degree come from the Jacobian of the pixel -> (azimuth, elevation) map (central
differences of the interpolated chief-ray map, one pixel apart): ``ppd = 1 / sqrt(|det J|)``, the
areal sampling density, so ``sum over pixels of (rate / ppd)^2`` counts the pixels a frame at a
local ``rate`` needs. Eccentricity is the angle between two directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Sequence

import torch
import torch.nn.functional as F

from controlgs_adapter.errors import InputValueError

from ..placement import Placement, image_region
from .bank import PSFBank

__all__ = ["VisualAngles", "eccentricity", "angle_to", "direction_vectors", "REFERENCE_CHANNEL", "HEADER_SAMPLES"]

#: the bank channel whose chief rays define the directions: green (550 nm)
REFERENCE_CHANNEL = 1
#: the most samples per axis :meth:`VisualAngles.header` records (the shipped Cardboard bank's chief-ray grid)
HEADER_SAMPLES = 65
_D = torch.float64


def direction_vectors(angles_deg: torch.Tensor) -> torch.Tensor:
    """``(azimuth, elevation)`` ``[..., 2]`` degrees -> unit direction vectors ``[..., 3]``."""
    t = torch.tan(torch.deg2rad(angles_deg))
    v = torch.cat([t, torch.ones_like(t[..., :1])], dim=-1)
    return v / torch.linalg.vector_norm(v, dim=-1, keepdim=True)


def eccentricity(angles_deg: torch.Tensor, gaze_deg: Sequence[float] | torch.Tensor) -> torch.Tensor:
    """Angle in degrees ``[...]`` between directions ``angles_deg`` ``[..., 2]`` and the gaze
    direction ``(azimuth, elevation)`` in degrees (``atan2(|u x v|, u . v)``: accurate near 0)."""
    return angle_to(direction_vectors(angles_deg), gaze_deg)


def angle_to(unit: torch.Tensor, gaze_deg: Sequence[float] | torch.Tensor) -> torch.Tensor:
    """Degrees ``[...]`` between unit direction vectors ``unit`` ``[..., 3]`` (:func:`direction_vectors`) and
    the gaze direction ``(azimuth, elevation)`` in degrees."""
    g = torch.as_tensor(gaze_deg, dtype=unit.dtype, device=unit.device)
    v = direction_vectors(g)
    cross = torch.linalg.vector_norm(torch.linalg.cross(unit, v.expand_as(unit), dim=-1), dim=-1)
    return torch.rad2deg(torch.atan2(cross, unit @ v))


@dataclass(frozen=True)
class VisualAngles:
    """The visual-angle map of a lens.

    Attributes:
        tangents: ``[Sy, Sx, 2]`` float64 ``(X / D, Y / D)`` of the chief rays, relative to the axis's
            landing, at display positions ``grid_x`` ``[Sx]``, ``grid_y`` ``[Sy]`` (uniform, -1 .. 1).
        display_mm: ``(width, height)`` of the display in mm.
        axis: display-normalised position of the lens axis (:attr:`PSFBank.axis`), where the tangents are 0.
    """

    tangents: torch.Tensor
    grid_x: torch.Tensor
    grid_y: torch.Tensor
    display_mm: tuple[float, float]
    axis: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def of_bank(cls, bank: PSFBank) -> "VisualAngles":
        """The map of ``bank``'s green chief rays (module docstring for the scale per lens kind); made once
        per bank (kept in its cache)."""
        if not isinstance(bank, PSFBank):
            raise InputValueError(f"bank must be a PSFBank, got {type(bank).__name__}")
        if "visual_angles" not in bank._cache:
            bank._cache["visual_angles"] = cls._trace(bank)
        return bank._cache["visual_angles"]

    @classmethod
    def _trace(cls, bank: PSFBank) -> "VisualAngles":
        ch = min(REFERENCE_CHANNEL, bank.chief.shape[0] - 1)
        chief = bank.chief[ch].double()
        gx, gy = bank.chief_x.double(), bank.chief_y.double()
        origin = _bilinear(chief, gx, gy, torch.tensor([bank.axis], dtype=_D))[0]
        w, h = bank.display_mm
        lens, meta = bank.lens, bank.meta
        pres, figs = meta.get("prescription"), meta.get("figures")
        if isinstance(pres, dict) and isinstance(figs, dict) and "reference_magnification" in figs:
            dist, mag = pres.get("virtual_image_distance_mm"), figs["reference_magnification"]
            if not (isinstance(dist, (int, float)) and dist > 0 and isinstance(mag, (int, float)) and mag > 0):
                raise InputValueError(f"PSF bank: meta.prescription.virtual_image_distance_mm and "
                                      f"meta.figures.reference_magnification must be > 0, got {dist!r}, {mag!r}")
            scale = (w / 2 * mag / dist, h / 2 * mag / dist)
        elif isinstance(lens.get("deg_per_output_unit"), (int, float)) and lens["deg_per_output_unit"] > 0:
            sx = math.radians(float(lens["deg_per_output_unit"]))
            scale = (sx, sx * h / w)
        elif isinstance(lens.get("half_fov_deg"), (int, float)) and 0 < lens["half_fov_deg"] < 90:
            edge = _bilinear(chief, gx, gy, torch.tensor([[bank.axis[0] + 1.0, bank.axis[1]]], dtype=_D))[0]
            q = float(torch.hypot(edge[0] - origin[0], (edge[1] - origin[1]) * h / w))
            sx = math.tan(math.radians(float(lens["half_fov_deg"]))) / q
            scale = (sx, sx * h / w)
        else:
            raise InputValueError("PSF bank: no visual angles: it needs meta.prescription.virtual_image_distance_mm "
                                  "with meta.figures.reference_magnification, or meta.lens.deg_per_output_unit "
                                  "or meta.lens.half_fov_deg")
        tangents = (chief - origin) * torch.tensor(scale, dtype=_D)
        return cls(tangents, gx, gy, (float(w), float(h)), bank.axis)

    # ------------------------------------------------------------------ header
    def header(self) -> dict[str, Any]:
        """The map as JSON data: ``{"tangents": Sy x Sx x 2, "display_mm": [w, h], "axis": [ax, ay]}``. An axis
        of more than :data:`HEADER_SAMPLES` samples is resampled (bilinearly) onto ``HEADER_SAMPLES``."""
        sy, sx = (min(n, HEADER_SAMPLES) for n in self.tangents.shape[:2])
        tangents = self.tangents
        if (sy, sx) != tuple(tangents.shape[:2]):
            gy, gx = torch.meshgrid(torch.linspace(-1, 1, sy, dtype=_D), torch.linspace(-1, 1, sx, dtype=_D),
                                    indexing="ij")
            points = torch.stack([gx, gy], -1).reshape(-1, 2)
            tangents = _bilinear(tangents.double(), self.grid_x.double(), self.grid_y.double(), points).view(sy, sx, 2)
        return {"tangents": tangents.double().tolist(), "display_mm": list(self.display_mm), "axis": list(self.axis)}

    @classmethod
    def from_header(cls, value: Any) -> "VisualAngles":
        """The map recorded by :meth:`header` (tangents at ``linspace(-1, 1, S)`` per axis);
        :class:`InputValueError` naming the field otherwise."""
        if not isinstance(value, dict):
            raise InputValueError(f"visual_angles: must be an object, got {type(value).__name__}")
        stray = sorted(set(value) - {"tangents", "display_mm", "axis"})
        if stray:
            raise InputValueError(f"visual_angles: unknown field(s) {stray}")
        raw: Any = value.get("tangents")
        display_mm: Any = value.get("display_mm")
        axis: Any = value.get("axis")
        if not _finite_pair(display_mm) or not min(display_mm) > 0:
            raise InputValueError(f"visual_angles.display_mm: must be two finite numbers > 0, got {display_mm!r}")
        if not _finite_pair(axis):
            raise InputValueError(f"visual_angles.axis: must be two finite numbers, got {axis!r}")
        if not _numbers(raw, depth=3):
            raise InputValueError("visual_angles.tangents: must be Sy x Sx x 2 nested lists of numbers")
        try:
            tangents = torch.tensor(raw, dtype=_D)
        except (TypeError, ValueError) as e:  # ragged lists
            raise InputValueError(f"visual_angles.tangents: must be Sy x Sx x 2 nested lists of numbers ({e})") from None
        if tangents.dim() != 3 or tangents.shape[-1] != 2 or not all(2 <= n <= HEADER_SAMPLES for n in tangents.shape[:2]):
            raise InputValueError(f"visual_angles.tangents: must be [Sy, Sx, 2] with 2 <= Sy, Sx <= {HEADER_SAMPLES}, "
                                  f"got {list(tangents.shape)}")
        if not bool(torch.isfinite(tangents).all()):
            raise InputValueError("visual_angles.tangents: holds NaN/Inf values")
        sy, sx = tangents.shape[:2]
        return cls(tangents, torch.linspace(-1, 1, sx, dtype=_D), torch.linspace(-1, 1, sy, dtype=_D),
                   (float(display_mm[0]), float(display_mm[1])), (float(axis[0]), float(axis[1])))

    # ------------------------------------------------------------------ positions -> directions
    def directions(self, xy: torch.Tensor) -> torch.Tensor:
        """Display-normalised positions ``[..., 2]`` -> ``(azimuth, elevation)`` ``[..., 2]`` in degrees
        (bilinear in the chief-ray map; clamped to the display's edge outside it), in ``xy``'s dtype."""
        t = _bilinear(self.tangents.to(xy.device), self.grid_x.to(xy.device), self.grid_y.to(xy.device),
                      xy.reshape(-1, 2).to(_D))
        return torch.rad2deg(torch.atan(t)).reshape(xy.shape).to(xy.dtype)

    def pixel_positions(self, height: int, width: int, placement: Placement = "fit", *,
                        offset: tuple[float, float] = (0.0, 0.0)) -> torch.Tensor:
        """Display-normalised centres ``[H, W, 2]`` (float64) of an ``H x W`` image's pixels, placed on
        the display (:mod:`~controlgs_adapter.downstream.placement`), shifted by ``offset`` pixels."""
        r = image_region(height, width, self.display_mm, placement)
        x = ((2 * torch.arange(width, dtype=_D) + 1 + 2 * offset[0]) / width - 1) * r.half_x
        y = ((2 * torch.arange(height, dtype=_D) + 1 + 2 * offset[1]) / height - 1) * r.half_y
        yy, xx = torch.meshgrid(y, x, indexing="ij")
        return torch.stack([xx, yy], dim=-1)

    def pixel_directions(self, height: int, width: int, placement: Placement = "fit") -> torch.Tensor:
        """``(azimuth, elevation)`` ``[H, W, 2]`` degrees (float64) of each pixel of an ``H x W`` image."""
        return self.directions(self.pixel_positions(height, width, placement))

    def pixels_per_degree(self, height: int, width: int, placement: Placement = "fit") -> torch.Tensor:
        """Local sampling density ``[H, W]`` (float64) in pixels per degree: ``1 / sqrt(|det J|)``, ``J`` the
        Jacobian (degrees per pixel) of pixel -> direction by central differences one pixel apart."""
        def at(dx: float, dy: float) -> torch.Tensor:
            return self.directions(self.pixel_positions(height, width, placement, offset=(dx, dy)))
        jx = at(0.5, 0.0) - at(-0.5, 0.0)   # d(az, el) / d column
        jy = at(0.0, 0.5) - at(0.0, -0.5)   # d(az, el) / d row
        det = (jx[..., 0] * jy[..., 1] - jx[..., 1] * jy[..., 0]).abs()
        return det.rsqrt()

    def axis_pixels_per_degree(self, height: int, width: int, placement: Placement = "fit") -> float:
        """Pixels per degree on the lens axis (:meth:`pixels_per_degree`'s Jacobian there): a pixel
        centred on the axis subtends ``2 atan(M p / 2 D)`` per side for pitch p on a distortion-free
        lens; the headset's ppd that ColorVideoVDP is given."""
        r = image_region(height, width, self.display_mm, placement)
        step = torch.tensor([[r.half_x / width, 0.0], [0.0, r.half_y / height]], dtype=_D)  # half a pixel per axis
        axis = torch.tensor(self.axis, dtype=_D)
        d = self.directions(torch.stack([axis + step[0], axis - step[0], axis + step[1], axis - step[1]]))
        jx, jy = d[0] - d[1], d[2] - d[3]
        return float((jx[0] * jy[1] - jx[1] * jy[0]).abs().rsqrt())

    # ------------------------------------------------------------------ the field
    def in_field(self, gaze_deg: Sequence[float]) -> bool:
        """Whether the direction ``(azimuth, elevation)`` degrees is seen on the display (inside the
        outline of the display's edge mapped through the lens)."""
        t = torch.tan(torch.deg2rad(torch.tensor([float(gaze_deg[0]), float(gaze_deg[1])], dtype=_D)))
        g = self.tangents
        ring = torch.cat([g[0, :], g[1:, -1], g.flip(1)[-1, 1:], g.flip(0)[1:-1, 0]], dim=0)  # closed outline
        x0, y0 = ring[:, 0], ring[:, 1]
        x1, y1 = ring.roll(-1, 0)[:, 0], ring.roll(-1, 0)[:, 1]
        crosses = (y0 > t[1]) != (y1 > t[1])
        x_at = x0 + (t[1] - y0) * (x1 - x0) / torch.where(y1 == y0, torch.ones_like(y0), y1 - y0)
        return bool((crosses & (t[0] < x_at)).sum() % 2 == 1)

    def check_gaze(self, gaze_deg: Sequence[float]) -> None:
        """InputValueError unless the gaze direction lies in the lens's field."""
        if not self.in_field(gaze_deg):
            az = torch.rad2deg(torch.atan(self.tangents[..., 0]))
            el = torch.rad2deg(torch.atan(self.tangents[..., 1]))
            raise InputValueError(
                f"gaze ({gaze_deg[0]:g}, {gaze_deg[1]:g}) deg is outside the lens's field (azimuth "
                f"{float(az.min()):.1f} .. {float(az.max()):.1f}, elevation {float(el.min()):.1f} .. "
                f"{float(el.max()):.1f} deg at the display's edge)")


def _numbers(value: Any, depth: int) -> bool:
    """True if ``value`` is ``depth`` levels of lists ending in numbers (no bool, no string)."""
    if depth == 0:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, list) and all(_numbers(v, depth - 1) for v in value)


def _finite_pair(value: Any) -> bool:
    """True if ``value`` is a list of two finite numbers."""
    return isinstance(value, list) and len(value) == 2 and _numbers(value, 1) and all(math.isfinite(v) for v in value)


def _bilinear(grid: torch.Tensor, gx: torch.Tensor, gy: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Bilinear interpolation of ``grid`` ``[Sy, Sx, C]`` (samples at ``gx``, ``gy``, uniform) at
    ``xy`` ``[N, 2]`` -> ``[N, C]``; clamped to the grid's border."""
    nx = (xy[:, 0] - gx[0]) / (gx[-1] - gx[0]) * 2 - 1
    ny = (xy[:, 1] - gy[0]) / (gy[-1] - gy[0]) * 2 - 1
    pts = torch.stack([nx, ny], dim=-1).to(grid.dtype).view(1, 1, -1, 2)
    out = F.grid_sample(grid.permute(2, 0, 1).unsqueeze(0), pts, mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out[0, :, 0].transpose(0, 1)
