"""The lens frame: where each anchor sits in the lens's own coordinates, for the lens condition.

Two modes (``docs/explanation/controlgs.md``, "The lens condition"):

- ``"radius"``: the control value is the radius ``||p - axis||`` of the anchor's display position
  ``p`` about the optical axis; for a centred lens (``axis = (0, 0)``) exactly ``||p||``.
- ``"xy"``: the anchor's position in the lens's frame ``q = G(p) - G(axis)``, with ``G`` the
  reference-wavelength (green) chief-ray map of the lens, display-normalised -> output-normalised,
  sampled on a uniform ``S x S`` grid over ``[-1, 1]^2`` (corners included) and interpolated
  bilinearly; the lens strength is then a signed pair (``LensSchedule.xy_strength``).

A frame is plain data (mode, axis, the sampled map), so an adapter file records it and a loaded
adapter conditions exactly as trained without the PSF bank.
"""

from __future__ import annotations

import math
from typing import Any, Literal

import torch
import torch.nn.functional as F

from .downstream.optics.bank import PSFBank
from .errors import InputValueError

__all__ = ["LensFrame", "LensMode", "LENS_MODES", "FIELD_MAP_SAMPLES", "REFERENCE_CHANNEL"]

LensMode = Literal["radius", "xy"]
LENS_MODES: tuple[str, ...] = ("radius", "xy")
#: S, the side of the field-map grid a frame samples from a bank's chief rays
FIELD_MAP_SAMPLES = 17
#: the bank channel whose chief rays define the frame: green (550 nm) of the 656 / 550 / 486 nm primaries
REFERENCE_CHANNEL = 1
_MAX_SAMPLES = 257


class LensFrame:
    """The lens's frame for the lens condition.

    Args:
        mode: ``"radius"`` or ``"xy"``.
        axis: ``(ax, ay)`` where the optical axis meets the display (display-normalised).
        field_map: ``"xy"`` only: ``[S, S, 2]`` (row = y) the chief-ray landing ``G`` (output-normalised)
            at display positions ``linspace(-1, 1, S)`` per axis; None in ``"radius"`` mode.
    """

    def __init__(self, mode: str = "radius", axis: tuple[float, float] = (0.0, 0.0),
                 field_map: torch.Tensor | None = None) -> None:
        if mode not in LENS_MODES:
            raise InputValueError(f"lens frame mode must be one of {LENS_MODES}, got {mode!r}")
        if (not isinstance(axis, (tuple, list)) or len(axis) != 2 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in axis)):
            raise InputValueError(f"lens frame axis must be two finite numbers, got {axis!r}")
        self.mode: LensMode = "xy" if mode == "xy" else "radius"
        self.axis = (float(axis[0]), float(axis[1]))
        self.field_map: torch.Tensor | None = None
        self._origin = torch.zeros(2, dtype=torch.float64)
        self._on: dict[tuple[torch.device, torch.dtype], tuple[torch.Tensor, torch.Tensor]] = {}
        if mode == "radius":
            if field_map is not None:
                raise InputValueError("lens frame field_map is for mode 'xy' only, got one with mode 'radius'")
            return
        if not isinstance(field_map, torch.Tensor) or not field_map.is_floating_point():
            raise InputValueError(f"lens frame field_map must be a float tensor [S, S, 2], got {type(field_map).__name__}")
        s = field_map.shape[0]
        if field_map.dim() != 3 or tuple(field_map.shape) != (s, s, 2) or not 2 <= s <= _MAX_SAMPLES:
            raise InputValueError(f"lens frame field_map must be [S, S, 2] with 2 <= S <= {_MAX_SAMPLES}, "
                                  f"got {list(field_map.shape)}")
        if not bool(torch.isfinite(field_map).all()):
            raise InputValueError("lens frame field_map holds NaN/Inf values")
        self.field_map = field_map.detach().to("cpu", torch.float64).contiguous()
        self._origin = self._lookup(torch.tensor([self.axis], dtype=torch.float64),
                                    self.field_map.permute(2, 0, 1).unsqueeze(0), self._origin)[0]

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_bank(cls, bank: PSFBank, mode: str | None = None, samples: int = FIELD_MAP_SAMPLES) -> "LensFrame":
        """The frame of ``bank``'s lens: ``mode`` None picks ``"radius"`` for a rotationally symmetric,
        centred lens and ``"xy"`` otherwise; the field map is the reference channel's chief rays sampled
        on ``samples x samples`` display positions."""
        if not isinstance(bank, PSFBank):
            raise InputValueError(f"lens must be a PSFBank or a LensFrame, got {type(bank).__name__}")
        if mode is None:
            mode = "radius" if bank.rotationally_symmetric else "xy"
        if mode not in LENS_MODES:
            raise InputValueError(f"lens_conditioning must be 'radius', 'xy' or None, got {mode!r}")
        if mode == "radius":
            return cls("radius", bank.axis)
        if isinstance(samples, bool) or not isinstance(samples, int) or not 2 <= samples <= _MAX_SAMPLES:
            raise InputValueError(f"samples must be an int in [2, {_MAX_SAMPLES}], got {samples!r}")
        chief = bank.chief[min(REFERENCE_CHANNEL, bank.num_wavelengths - 1)].double()  # [Cy, Cx, 2]
        grid = torch.linspace(-1.0, 1.0, samples, dtype=torch.float64)
        gy, gx = torch.meshgrid(grid, grid, indexing="ij")
        points = torch.stack([gx, gy], -1).reshape(-1, 2)
        table = chief.permute(2, 0, 1).unsqueeze(0)
        return cls("xy", bank.axis, cls._lookup(points, table, torch.zeros(2, dtype=torch.float64)).view(samples, samples, 2))

    @classmethod
    def of(cls, lens: "PSFBank | LensFrame | None", mode: str | None = None) -> "LensFrame":
        """The frame of ``lens`` (a bank, a frame or None: a centred radius frame), in ``mode`` where given
        (a frame in another mode is rebuilt only from ``"xy"`` to ``"radius"``, which drops its map)."""
        if mode is not None and mode not in LENS_MODES:
            raise InputValueError(f"lens_conditioning must be 'radius', 'xy' or None, got {mode!r}")
        if lens is None or isinstance(lens, LensFrame):
            frame = lens or cls()
            if mode is None or mode == frame.mode:
                return frame
            if mode == "radius":
                return cls("radius", frame.axis)
            raise InputValueError("lens_conditioning='xy' needs the lens's field map: pass lens=PSFBank (the optics' "
                                  f"bank) or an 'xy' LensFrame, got {'None' if lens is None else 'a radius LensFrame'}")
        return cls.from_bank(lens, mode)

    # ------------------------------------------------------------------ header
    @property
    def is_default(self) -> bool:
        """True for a centred radius frame: the lens condition of adapters that record no frame."""
        return self.mode == "radius" and self.axis == (0.0, 0.0)

    def header(self) -> dict[str, Any]:
        """The frame as JSON data: ``{"mode", "axis"}`` and, in ``"xy"`` mode, ``"field_map"`` ``S x S x 2``."""
        out: dict[str, Any] = {"mode": self.mode, "axis": list(self.axis)}
        if self.field_map is not None:
            out["field_map"] = self.field_map.tolist()
        return out

    @classmethod
    def from_header(cls, value: Any) -> "LensFrame":
        """The frame recorded by :meth:`header`; :class:`InputValueError` naming the field otherwise."""
        if not isinstance(value, dict):
            raise InputValueError(f"lens_frame: must be an object, got {type(value).__name__}")
        stray = sorted(set(value) - {"mode", "axis", "field_map"})
        if stray:
            raise InputValueError(f"lens_frame: unknown field(s) {stray}")
        mode, axis, raw = value.get("mode"), value.get("axis"), value.get("field_map")
        if mode not in LENS_MODES:
            raise InputValueError(f"lens_frame.mode: must be one of {LENS_MODES}, got {mode!r}")
        if (not isinstance(axis, list) or len(axis) != 2 or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in axis)):
            raise InputValueError(f"lens_frame.axis: must be two finite numbers, got {axis!r}")
        if mode == "radius":
            if raw is not None:
                raise InputValueError("lens_frame.field_map: only mode 'xy' has one")
            return cls("radius", (axis[0], axis[1]))
        if not _numbers(raw, depth=3):
            raise InputValueError("lens_frame.field_map: must be S x S x 2 nested lists of numbers")
        try:
            field_map = torch.tensor(raw, dtype=torch.float64)
        except (TypeError, ValueError) as e:  # ragged lists
            raise InputValueError(f"lens_frame.field_map: must be S x S x 2 nested lists of numbers ({e})") from None
        try:
            return cls("xy", (axis[0], axis[1]), field_map)
        except InputValueError as e:
            raise InputValueError(f"lens_frame.field_map: {str(e).removeprefix('lens frame field_map ')}") from None

    # ------------------------------------------------------------------ the lookup
    def lens_coords(self, screen_xy: torch.Tensor) -> torch.Tensor:
        """``[R, 2]`` positions ``q = G(p) - G(axis)`` in the lens's frame of display positions ``p``
        ``[R, 2]`` (``"xy"`` mode; positions beyond the display take the map's edge value: +inf, for
        an anchor behind the camera, lands on a corner). One ``grid_sample``, no host sync."""
        if self.field_map is None:
            raise InputValueError("lens_coords needs an 'xy' lens frame (a field map), this one is 'radius'")
        return self._lookup(screen_xy, *self._table(screen_xy.device, screen_xy.dtype))

    def _table(self, device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """The field map ``[1, 2, S, S]`` and ``G(axis)`` ``[2]`` on ``device`` in ``dtype`` (copied once)."""
        key = (device, dtype)
        if key not in self._on:
            assert self.field_map is not None
            self._on[key] = (self.field_map.permute(2, 0, 1).unsqueeze(0).to(device, dtype),
                             self._origin.to(device, dtype))
        return self._on[key]

    @staticmethod
    def _lookup(points: torch.Tensor, table: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
        grid = points.clamp(-1.0, 1.0).view(1, 1, -1, 2)
        g = F.grid_sample(table, grid, mode="bilinear", padding_mode="border", align_corners=True)  # [1, 2, 1, R]
        return g[0, :, 0].transpose(0, 1) - origin

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LensFrame):
            return NotImplemented
        maps = (self.field_map is None and other.field_map is None) or (
            self.field_map is not None and other.field_map is not None and torch.equal(self.field_map, other.field_map))
        return self.mode == other.mode and self.axis == other.axis and maps

    __hash__ = None  # type: ignore[assignment]  # mutable tensor inside

    def __repr__(self) -> str:
        size = "" if self.field_map is None else f", field_map={list(self.field_map.shape)}"
        return f"LensFrame(mode={self.mode!r}, axis={self.axis}{size})"


def _numbers(value: Any, depth: int) -> bool:
    """True if ``value`` is ``depth`` levels of lists ending in numbers (no bool, no string)."""
    if depth == 0:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, list) and all(_numbers(v, depth - 1) for v in value)
