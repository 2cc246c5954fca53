"""Distortion profiles as a lens model: the distortion (and lateral colour) a headset runtime ships,
read from a small JSON file and turned into a chief-ray-only :class:`~.bank.PSFBank`.

A profile gives distortion and lateral colour only, no PSF: :func:`bank_from_profile` stores every
PSF as a unit impulse (``meta["lens"]["psf"] = False``), and the optics stage then runs the
chief-ray warp in every mode (``"fast"`` and ``"exact"`` reduce to ``"distortion"``, at its cost).

Every form is converted to the map a bank stores: display point -> virtual-image landing, in
normalised output coordinates at the reference magnification (the green primary's paraxial
magnification at the distortion centre), so a distortion-free lens maps every point to itself.
Coordinates: display-normalised ``[-1, 1]`` about the display centre (x right, y down); the
distortion centre ``c`` may lie off the display centre (an off-centre eye: asymmetric distortion).

The file (JSON; a profile is data, loading it runs no code), common fields:

- ``kind``: ``"opencv"``, ``"polynomial"`` or ``"radial_table"``;
- ``display_px``: ``[width, height]`` pixels; ``display_mm``: ``[width, height]`` millimetres;
- ``centre_px`` (continuous display pixels from the top-left corner) or ``centre_norm``
  (normalised display coordinates), at most one; default the display centre;
- ``channel_scales``: ``[R, G, B]`` factors on the landing radius about the centre, applied after the
  form's map (chromatic scales, e.g. Oculus DK1: 0.996, 1, 1.014); default ones;
- ``name``, ``source``, ``licence``: optional strings (provenance).

Forms (``direction``: ``"display_to_eye"`` maps a display point to where the eye sees it,
``"eye_to_display"`` the other way; the latter is inverted numerically):

- ``"opencv"``: ``k1`` (required), ``k2``, ``k3``, ``p1``, ``p2`` (each a number or ``[R, G, B]``),
  ``radius_px`` (the length, in display pixels, that counts as radius 1; default 1: coefficients
  in pixel units, as Monado's Windows Mixed Reality ``distortion3K``), optional ``fov_deg`` (twice
  the field angle at half the display width from the centre). With ``u = (p - c) / radius_px``
  (pixels), ``u' = u (1 + k1 r^2 + k2 r^4 + k3 r^6) + (2 p1 x y + p2 (r^2 + 2 x^2),
  p1 (r^2 + 2 y^2) + 2 p2 x y)``. Default direction ``"display_to_eye"`` (what the WMR and Oculus
  SDK distortion meshes compute: the rendered-image point a display pixel shows); ``"eye_to_display"``
  is OpenCV's camera convention (undistorted -> distorted).
- ``"polynomial"``: ``coefficients`` ``{"R": [k1, k3, k5, k7, k9], "G": ..., "B": ...}`` (1 to 5
  odd-power coefficients per primary, as SimulaVR's profiles), ``half_fov_deg``, ``radius_mm``
  (the display radius that is ``rho = 1``; default half the display width). ``"display_to_eye"``
  (default): field angle ``theta = half_fov_deg * P(rho)``; ``"eye_to_display"``:
  ``rho = P(theta / half_fov_deg)``.
- ``"radial_table"``: ``samples`` ``[[field_angle_deg, display_radius], ...]`` starting at
  ``[0, 0]``, both strictly increasing: the eye -> display direction (a field angle and the display
  radius that shows it), inverted numerically; ``radius_unit`` ``"percent"`` (of ``radius_mm``,
  default half the display width) or ``"mm"``; ``interpolation`` ``"linear"`` or
  ``"monotone_cubic"`` (Fritsch-Carlson, as SciPy's PCHIP); beyond the last sample the landing
  (``tan theta``) goes on linearly with its end slope, so display corners past the table's field
  stay finite (and are usually outside the lens's visible circle). (MeganeX 8K's published profile reads this way: its angles reach 48.31 deg
  at 100 %; read the other way round it would put 100 deg at 48 % of the radius, past any flat
  virtual image.)

Radial forms become landings through the flat virtual image: a display point at radius ``r`` from
``c`` is seen at field angle ``theta(r)`` and lands at ``tan(theta) / G`` display-equivalent
millimetres from ``c``, ``G = d tan(theta_G) / dr`` at ``r = 0`` (green).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Callable

import torch

from controlgs_adapter.errors import FileFormatError, InputValueError

from .bank import PSFBank

__all__ = ["DistortionProfile", "PROFILE_KINDS", "is_profile", "load_profile", "parse_profile", "bank_from_profile"]

PROFILE_KINDS = ("opencv", "polynomial", "radial_table")
DIRECTIONS = ("display_to_eye", "eye_to_display")
#: nominal primaries of a profile bank (a profile names none; its chromatic terms are per primary)
PROFILE_WAVELENGTHS_NM = (656.0, 550.0, 486.0)
CHANNELS = ("R", "G", "B")
MAX_FILE_BYTES = 1 << 20
_COMMON = {"kind", "display_px", "display_mm", "centre_px", "centre_norm", "channel_scales", "name", "source",
           "licence"}
_FIELDS = {"opencv": {"k1", "k2", "k3", "p1", "p2", "radius_px", "fov_deg", "direction"},
           "polynomial": {"coefficients", "half_fov_deg", "radius_mm", "direction"},
           "radial_table": {"samples", "radius_unit", "radius_mm", "interpolation"}}
_D = torch.float64


class _Invalid(Exception):
    """One invalid field: ``(field, what is wrong)``."""


@dataclass(frozen=True)
class DistortionProfile:
    """A parsed, validated profile (see the module docstring for the file).

    Attributes:
        kind: the form; fields: its parsed fields (per-primary coefficients as 3-tuples).
        display_px, display_mm: ``(width, height)``; centre: distortion centre, normalised display coordinates.
        channel_scales: ``(R, G, B)`` landing-radius factors; source: the file (or name) it came from.
    """

    kind: str
    display_px: tuple[int, int]
    display_mm: tuple[float, float]
    centre: tuple[float, float]
    channel_scales: tuple[float, float, float]
    fields: dict[str, Any]
    source: str = "<profile>"

    # ------------------------------------------------------------------ the map
    @property
    def half_mm(self) -> tuple[float, float]:
        return self.display_mm[0] / 2, self.display_mm[1] / 2

    @property
    def tangential(self) -> bool:
        return self.kind == "opencv" and any(v != 0 for k in ("p1", "p2") for v in self.fields[k])

    def landing(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """``[3, *x.shape, 2]`` float64: where display points ``(x, y)`` (normalised display
        coordinates) land, in normalised output coordinates, per primary (R, G, B)."""
        x, y = torch.as_tensor(x, dtype=_D), torch.as_tensor(y, dtype=_D)
        hx, hy = self.half_mm
        cx, cy = self.centre
        dx, dy = (x - cx) * hx, (y - cy) * hy                       # mm from the centre
        outs = []
        for ci in range(3):
            if self.kind == "opencv":
                qx, qy = self._opencv(dx, dy, ci)
            else:
                r = torch.hypot(dx, dy)
                gain = self._radial_gain(r, ci)                     # landing radius / display radius
                qx, qy = dx * gain, dy * gain
            s = self.channel_scales[ci]
            outs.append(torch.stack([cx + s * qx / hx, cy + s * qy / hy], -1))
        return torch.stack(outs)

    def field_angle_deg(self, r_mm: torch.Tensor, channel: int = 1) -> torch.Tensor:
        """Field angle (deg) of a display point ``r_mm`` from the centre (radial forms)."""
        return torch.rad2deg(self._theta(torch.as_tensor(r_mm, dtype=_D), channel))

    # opencv ----------------------------------------------------------------
    def _brown(self, u: torch.Tensor, v: torch.Tensor, ci: int) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.fields
        k1, k2, k3, p1, p2 = (f[k][ci] for k in ("k1", "k2", "k3", "p1", "p2"))
        r2 = u * u + v * v
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        return (u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u),
                v * radial + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v)

    def _opencv(self, dx: torch.Tensor, dy: torch.Tensor, ci: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Landing offset (mm from the centre) of display offsets ``dx, dy`` (mm)."""
        ppx = self.display_px[0] / self.display_mm[0]
        ppy = self.display_px[1] / self.display_mm[1]
        rad = self.fields["radius_px"]
        u, v = dx * ppx / rad, dy * ppy / rad
        if self.fields["direction"] == "display_to_eye":
            qu, qv = self._brown(u, v, ci)
        else:
            qu, qv = _invert_2d(lambda a, b: self._brown(a, b, ci), u, v, f"{self.source}: opencv map")
        return qu * rad / ppx, qv * rad / ppy

    # radial forms -----------------------------------------------------------
    def _theta(self, r: torch.Tensor, ci: int) -> torch.Tensor:
        """Field angle (rad) at display radius ``r`` (mm), primary ``ci``, before ``channel_scales``."""
        f = self.fields
        if self.kind == "polynomial":
            th, R = math.radians(f["half_fov_deg"]), f["radius_mm"]
            coef = f["coefficients"][ci]
            if f["direction"] == "display_to_eye":
                return th * _odd_poly(coef, r / R)
            t = _invert_increasing(lambda s: _odd_poly(coef, s), r / R, math.pi / 2 / th, f"{self.source}: coefficients")
            return th * t
        deg, rad, slopes = self._table
        deg_end, r_end = float(deg[-1]), float(rad[-1])
        inside = _invert_increasing(lambda t: _interp_table(deg, rad, slopes, t), r.clamp_max(r_end), deg_end + 1e-9,
                                    f"{self.source}: samples")
        th_end = math.radians(deg_end)                     # beyond the table: tan(theta) linear in r, its end slope
        slope = math.radians(1.0) / self._table_slope(-1) / math.cos(th_end) ** 2
        return torch.where(r > r_end, torch.atan(math.tan(th_end) + slope * (r - r_end)), torch.deg2rad(inside))

    @cached_property
    def _table(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The table: field angles (deg), display radii (mm) and, for the monotone cubic, node slopes."""
        f = self.fields
        unit = f["radius_mm"] / 100 if f["radius_unit"] == "percent" else 1.0
        deg = torch.tensor([s[0] for s in f["samples"]], dtype=_D)
        rad = torch.tensor([s[1] for s in f["samples"]], dtype=_D) * unit
        return deg, rad, _pchip_slopes(deg, rad) if f["interpolation"] == "monotone_cubic" else None

    def _table_slope(self, end: int) -> float:
        """d r / d theta (mm per deg) of the table at its first (``end`` 0) or last (-1) sample."""
        deg, rad, slopes = self._table
        if slopes is not None:
            return float(slopes[end])
        i = 0 if end == 0 else len(deg) - 2
        return float((rad[i + 1] - rad[i]) / (deg[i + 1] - deg[i]))

    def axis_slope(self) -> float:
        """``G``: d tan(theta) / dr at the centre for green (rad per mm), radial forms."""
        f = self.fields
        if self.kind == "polynomial":
            th, R, k1 = math.radians(f["half_fov_deg"]), f["radius_mm"], f["coefficients"][1][0]
            return th * k1 / R if f["direction"] == "display_to_eye" else th / (k1 * R)
        return math.radians(1.0) / self._table_slope(0)

    def _radial_gain(self, r: torch.Tensor, ci: int) -> torch.Tensor:
        """Landing radius over display radius at display radius ``r`` (mm); its limit 1 (green) at 0."""
        G = self.axis_slope()
        safe = torch.where(r > 0, r, torch.ones_like(r))
        gain = torch.tan(self._theta(safe, ci)) / (G * safe)
        tiny = torch.full_like(r, 1e-9)
        g0 = torch.tan(self._theta(tiny, ci)) / (G * tiny)
        return torch.where(r > 0, gain, g0)

    # ------------------------------------------------------------------ figures
    def half_fov_deg(self) -> float | None:
        """Field angle (deg, green) at half the display width from the centre, if the profile defines angles."""
        if self.kind == "opencv":
            fov = self.fields.get("fov_deg")
            return None if fov is None else fov / 2
        return float(self.field_angle_deg(torch.tensor(self.half_mm[0], dtype=_D)))

    def deg_per_output_unit(self) -> float | None:
        """Visual degrees per unit of normalised output x near the axis (along y: times height / width)."""
        if self.kind != "opencv":
            return math.degrees(self.axis_slope() * self.half_mm[0])     # d theta / d q = G near the axis
        half = self.half_fov_deg()
        if half is None:
            return None
        cx, cy = self.centre
        edge = self.landing(torch.tensor(cx + 1.0), torch.tensor(cy))[1]   # half the width from the centre, +x
        q_mm = float(torch.hypot(edge[0] - cx, (edge[1] - cy) * self.half_mm[1] / self.half_mm[0])) * self.half_mm[0]
        return math.degrees(math.tan(math.radians(half)) / q_mm * self.half_mm[0])

    def to_json(self) -> dict[str, Any]:
        """The parsed profile as plain JSON data (per-primary values as 3-lists)."""
        out: dict[str, Any] = {"kind": self.kind, "display_px": list(self.display_px),
                               "display_mm": list(self.display_mm), "centre_norm": list(self.centre),
                               "channel_scales": list(self.channel_scales), "source": self.source}
        for k, v in self.fields.items():
            out[k] = [list(c) for c in v] if k == "coefficients" else (list(v) if isinstance(v, tuple) else v)
        return out


# ---------------------------------------------------------------------- numerics
def _odd_poly(coef: tuple[float, ...], s: torch.Tensor) -> torch.Tensor:
    """``k1 s + k3 s^3 + ...`` (Horner in ``s^2``)."""
    s2 = s * s
    acc = torch.zeros_like(s)
    for k in reversed(coef):
        acc = acc * s2 + k
    return acc * s


def _invert_increasing(fn: Callable[[torch.Tensor], torch.Tensor], target: torch.Tensor, hi: float,
                       what: str) -> torch.Tensor:
    """``t`` in ``[0, hi)`` with ``fn(t) = target`` for an increasing ``fn`` (bisection, 80 steps, float64);
    :class:`InputValueError` if a target lies beyond ``fn(hi)`` (past a right angle)."""
    target = torch.as_tensor(target, dtype=_D)
    top = float(fn(torch.tensor(hi, dtype=_D)))
    if bool((target >= top).any()):
        raise InputValueError(f"{what}: a display point beyond the field angle of 90 deg (display radius "
                              f"{float(target.max()):.4g} >= {top:.4g}); the profile does not cover this display")
    lo, up = torch.zeros_like(target), torch.full_like(target, hi)
    for _ in range(80):
        mid = (lo + up) / 2
        below = fn(mid) < target
        lo, up = torch.where(below, mid, lo), torch.where(below, up, mid)
    return (lo + up) / 2


def _invert_2d(fn: Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
               u: torch.Tensor, v: torch.Tensor, what: str) -> tuple[torch.Tensor, torch.Tensor]:
    """``(a, b)`` with ``fn(a, b) = (u, v)``: Newton with a central-difference Jacobian from ``(u, v)``."""
    a, b = u.clone(), v.clone()
    h = 1e-6 * (1 + torch.maximum(u.abs(), v.abs()))
    for _ in range(50):
        fu, fv = fn(a, b)
        ru, rv = u - fu, v - fv
        if _max_abs(ru, rv) < 1e-13:
            break
        (pa, qa), (ma, na) = fn(a + h, b), fn(a - h, b)
        (pb, qb), (mb, nb) = fn(a, b + h), fn(a, b - h)
        j11, j21, j12, j22 = (pa - ma) / (2 * h), (qa - na) / (2 * h), (pb - mb) / (2 * h), (qb - nb) / (2 * h)
        det = j11 * j22 - j12 * j21
        a, b = a + (j22 * ru - j12 * rv) / det, b + (j11 * rv - j21 * ru) / det
    fu, fv = fn(a, b)
    err = _max_abs(u - fu, v - fv)
    if not err < 1e-9:
        raise InputValueError(f"{what}: cannot be inverted over the display (residual {err:.3g}; the map folds over)")
    return a, b


def _max_abs(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.maximum(a.abs(), b.abs()).max()) if a.numel() else 0.0


def _pchip_slopes(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Fritsch-Carlson monotone cubic node slopes (SciPy's PCHIP: weighted harmonic mean inside,
    the shape-preserving three-point formula at the ends)."""
    h, d = x.diff(), y.diff() / x.diff()
    n = len(x)
    m = torch.zeros(n, dtype=_D)
    if n == 2:
        return torch.full((2,), float(d[0]), dtype=_D)
    w1, w2 = 2 * h[1:] + h[:-1], h[1:] + 2 * h[:-1]
    same = (d[:-1] * d[1:]) > 0
    hm = (w1 + w2) / (w1 / torch.where(same, d[:-1], 1.0) + w2 / torch.where(same, d[1:], 1.0))
    m[1:-1] = torch.where(same, hm, torch.zeros_like(hm))

    def edge(h0: float, h1: float, d0: float, d1: float) -> float:
        s = ((2 * h0 + h1) * d0 - h0 * d1) / (h0 + h1)
        if math.copysign(1, s) != math.copysign(1, d0):
            return 0.0
        if math.copysign(1, d0) != math.copysign(1, d1) and abs(s) > abs(3 * d0):
            return 3 * d0
        return s

    m[0] = edge(float(h[0]), float(h[1]), float(d[0]), float(d[1]))
    m[-1] = edge(float(h[-1]), float(h[-2]), float(d[-1]), float(d[-2]))
    return m


def _interp_table(x: torch.Tensor, y: torch.Tensor, slopes: torch.Tensor | None, t: torch.Tensor) -> torch.Tensor:
    """The table ``y(x)`` at ``t >= 0``: linear, or cubic Hermite with node ``slopes``; beyond the last
    sample linear with the end slope (the last segment's, or the last node's)."""
    t = torch.as_tensor(t, dtype=_D)
    i = torch.searchsorted(x, t.contiguous(), right=True).clamp(1, len(x) - 1) - 1
    x0, x1, y0, y1 = x[i], x[i + 1], y[i], y[i + 1]
    h = x1 - x0
    s = (t - x0) / h
    if slopes is None:
        inside = y0 + s * (y1 - y0)
        end = (y[-1] - y[-2]) / (x[-1] - x[-2])
    else:
        m0, m1 = slopes[i], slopes[i + 1]
        s2, s3 = s * s, s * s * s
        inside = (2 * s3 - 3 * s2 + 1) * y0 + (s3 - 2 * s2 + s) * h * m0 + (-2 * s3 + 3 * s2) * y1 + (s3 - s2) * h * m1
        end = slopes[-1]
    return torch.where(t > x[-1], y[-1] + end * (t - x[-1]), inside)


# ---------------------------------------------------------------------- parsing
def is_profile(obj: Mapping) -> bool:
    """True if a parsed JSON object is a distortion profile (its ``kind`` is one of :data:`PROFILE_KINDS`)."""
    return isinstance(obj, Mapping) and obj.get("kind") in PROFILE_KINDS


def load_profile(path: str | os.PathLike) -> DistortionProfile:
    """Read and validate a profile JSON file; :class:`FileFormatError` naming the file and the field."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_FILE_BYTES:
            raise FileFormatError(f"{p}: a profile is at most {MAX_FILE_BYTES} bytes, this file has {size}")
        obj = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as e:
        raise FileFormatError(f"{p}: cannot read the profile ({e})") from None
    except json.JSONDecodeError as e:
        raise FileFormatError(f"{p}: not JSON ({e})") from None
    return _parse(obj, str(p), FileFormatError)


def parse_profile(obj: Mapping, source: str = "<profile>") -> DistortionProfile:
    """Validate a profile given as a mapping; :class:`InputValueError` naming ``source`` and the field."""
    return _parse(obj, source, InputValueError)


def _parse(obj: Any, source: str, error: type[Exception]) -> DistortionProfile:
    try:
        return _build(obj, source)
    except _Invalid as e:
        name, what = e.args
        raise error(f"{source}: field {name!r} {what}") from None


def _number(obj: Mapping, name: str, *, default: float | None = None, positive: bool = False,
            below: float | None = None) -> float:
    if name not in obj:
        if default is None:
            raise _Invalid(name, "is missing")
        return default
    return _value(obj[name], name, positive=positive, below=below)


def _value(v: Any, name: str, *, positive: bool = False, below: float | None = None) -> float:
    """``v`` as a finite float (positive, below ``below`` if asked), else the field ``name`` is invalid."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise _Invalid(name, f"must be a finite number, got {v!r}")
    if positive and not v > 0:
        raise _Invalid(name, f"must be positive, got {v!r}")
    if below is not None and not v < below:
        raise _Invalid(name, f"must be below {below}, got {v!r}")
    return float(v)


def _pair(obj: Mapping, name: str, *, positive: bool, integer: bool = False) -> tuple[float, float]:
    v = obj.get(name)
    if v is None:
        raise _Invalid(name, "is missing")
    kind = "integers" if integer else "numbers"
    if not isinstance(v, list) or len(v) != 2 or not all(
            isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in v):
        raise _Invalid(name, f"must be two finite {kind}, got {v!r}")
    if integer and not all(float(a).is_integer() for a in v):
        raise _Invalid(name, f"must be two integers, got {v!r}")
    if positive and not all(a > 0 for a in v):
        raise _Invalid(name, f"must be positive, got {v!r}")
    return float(v[0]), float(v[1])


def _per_primary(obj: Mapping, name: str, default: float | None) -> tuple[float, float, float]:
    """A number or ``[R, G, B]`` numbers."""
    if name not in obj and default is not None:
        return (default,) * 3
    v = obj.get(name)
    if isinstance(v, list):
        if len(v) != 3:
            raise _Invalid(name, f"must be a number or [R, G, B], got {len(v)} values")
        vals = [_value(a, name) for a in v]
        return vals[0], vals[1], vals[2]
    x = _number(obj, name)
    return x, x, x


def _choice(obj: Mapping, name: str, options: tuple[str, ...], default: str) -> str:
    v = obj.get(name, default)
    if v not in options:
        raise _Invalid(name, f"must be one of {list(options)}, got {v!r}")
    return str(v)


def _build(obj: Any, source: str) -> DistortionProfile:
    if not isinstance(obj, Mapping):
        raise _Invalid("kind", f"is missing: a profile is a JSON object, got {type(obj).__name__}")
    kind = obj.get("kind")
    if kind not in PROFILE_KINDS:
        raise _Invalid("kind", f"must be one of {list(PROFILE_KINDS)}, got {kind!r}")
    unknown = sorted(set(obj) - _COMMON - _FIELDS[kind])
    if unknown:
        raise _Invalid(unknown[0], f"is not a field of a {kind!r} profile (fields: {sorted(_COMMON | _FIELDS[kind])})")
    for name in ("name", "source", "licence"):
        if name in obj and not isinstance(obj[name], str):
            raise _Invalid(name, f"must be a string, got {obj[name]!r}")
    w_px, h_px = _pair(obj, "display_px", positive=True, integer=True)
    display_mm = _pair(obj, "display_mm", positive=True)
    if "centre_px" in obj and "centre_norm" in obj:
        raise _Invalid("centre_norm", "cannot be given with 'centre_px' (give one)")
    if "centre_px" in obj:
        px = _pair(obj, "centre_px", positive=False)
        centre = (2 * px[0] / w_px - 1, 2 * px[1] / h_px - 1)
        name = "centre_px"
    else:
        centre = _pair(obj, "centre_norm", positive=False) if "centre_norm" in obj else (0.0, 0.0)
        name = "centre_norm"
    if not all(abs(c) < 1 for c in centre):
        raise _Invalid(name, f"must lie inside the display, got normalised {list(centre)}")
    scales = _per_primary(obj, "channel_scales", 1.0)
    if not all(s > 0 for s in scales) or not isinstance(obj.get("channel_scales", []), list):
        raise _Invalid("channel_scales", f"must be three positive numbers [R, G, B], got {obj.get('channel_scales')!r}")
    fields: dict[str, Any] = {}
    half_w = display_mm[0] / 2
    if kind == "opencv":
        fields["k1"] = _per_primary(obj, "k1", None)
        for k in ("k2", "k3", "p1", "p2"):
            fields[k] = _per_primary(obj, k, 0.0)
        fields["radius_px"] = _number(obj, "radius_px", default=1.0, positive=True)
        if "fov_deg" in obj:
            fields["fov_deg"] = _number(obj, "fov_deg", positive=True, below=180.0)
        fields["direction"] = _choice(obj, "direction", DIRECTIONS, "display_to_eye")
    elif kind == "polynomial":
        fields["coefficients"] = _coefficients(obj.get("coefficients"))
        fields["half_fov_deg"] = _number(obj, "half_fov_deg", positive=True, below=90.0)
        fields["radius_mm"] = _number(obj, "radius_mm", default=half_w, positive=True)
        fields["direction"] = _choice(obj, "direction", DIRECTIONS, "display_to_eye")
    else:
        fields["samples"] = _samples(obj.get("samples"))
        fields["radius_unit"] = _choice(obj, "radius_unit", ("percent", "mm"), "percent")
        fields["radius_mm"] = _number(obj, "radius_mm", default=half_w, positive=True)
        fields["interpolation"] = _choice(obj, "interpolation", ("linear", "monotone_cubic"), "monotone_cubic")
    profile = DistortionProfile(kind=kind, display_px=(int(w_px), int(h_px)), display_mm=display_mm, centre=centre,
                                channel_scales=scales, fields=fields, source=source)
    _check_monotone(profile)
    return profile


def _coefficients(v: Any) -> tuple[tuple[float, ...], ...]:
    name = "coefficients"
    if not isinstance(v, Mapping) or set(v) != set(CHANNELS):
        raise _Invalid(name, f"must be an object with lists 'R', 'G', 'B' of k1, k3, k5, k7, k9, got {v!r}")
    out = []
    for c in CHANNELS:
        k = v[c]
        if not isinstance(k, list) or not 1 <= len(k) <= 5:
            raise _Invalid(name, f"{c} must be a list of 1 to 5 numbers (k1, k3, k5, k7, k9), got {k!r}")
        vals = tuple(_value(a, f"{name}.{c}") for a in k)
        if not vals[0] > 0:
            raise _Invalid(f"{name}.{c}", f"k1 must be positive (the map's slope on the axis), got {vals[0]!r}")
        out.append(vals)
    return tuple(out)


def _samples(v: Any) -> tuple[tuple[float, float], ...]:
    name = "samples"
    if not isinstance(v, list) or len(v) < 2:
        raise _Invalid(name, f"must be a list of at least 2 [field_angle_deg, display_radius] pairs, got {v!r}")
    pts = []
    for i, s in enumerate(v):
        if not isinstance(s, list) or len(s) != 2:
            raise _Invalid(name, f"entry {i} must be a pair [field_angle_deg, display_radius], got {s!r}")
        pts.append((_value(s[0], f"{name}[{i}][0]"), _value(s[1], f"{name}[{i}][1]")))
    if pts[0] != (0.0, 0.0):
        raise _Invalid(name, f"must start at [0, 0] (the axis), got {list(pts[0])}")
    for i in range(1, len(pts)):
        if not (pts[i][0] > pts[i - 1][0] and pts[i][1] > pts[i - 1][1]):
            raise _Invalid(name, f"must increase strictly in both columns: entry {i} {list(pts[i])} after "
                        f"{list(pts[i - 1])}")
    if not pts[-1][0] < 90:
        raise _Invalid(name, f"field angles must stay below 90 deg, got {pts[-1][0]}")
    return tuple(pts)


def _check_monotone(profile: DistortionProfile) -> None:
    """The radial map must increase out to the display's farthest corner from the centre."""
    hx, hy = profile.half_mm
    cx, cy = profile.centre
    r_max = math.hypot((1 + abs(cx)) * hx, (1 + abs(cy)) * hy)
    r = torch.linspace(0, r_max, 257, dtype=_D)
    if profile.kind == "opencv":
        ppx = profile.display_px[0] / profile.display_mm[0]
        rad = profile.fields["radius_px"]
        u = r * ppx / rad
        for ci in range(3):
            out = profile._brown(u, torch.zeros_like(u), ci)[0]
            if not bool((out.diff() > 0).all()):
                raise _Invalid("k1", f"gives a radial map that folds over inside the display (primary {CHANNELS[ci]})")
        return
    if profile.kind == "polynomial":
        f = profile.fields
        s = torch.linspace(0, 1, 257, dtype=_D) * (r_max / f["radius_mm"] if f["direction"] == "display_to_eye"
                                                    else math.pi / 2 / math.radians(f["half_fov_deg"]))
        for ci in range(3):
            vals = _odd_poly(f["coefficients"][ci], s)
            bad = not bool((vals.diff() > 0).all())
            if f["direction"] == "display_to_eye":
                bad = bad or float(vals[-1]) * f["half_fov_deg"] >= 90
            if bad:
                raise _Invalid("coefficients", f"{CHANNELS[ci]} must increase (and stay below 90 deg) out to the "
                            f"display corner ({r_max:.4g} mm from the centre)")
    try:
        profile._theta(torch.tensor([r_max], dtype=_D), 1)
    except InputValueError:
        raise _Invalid("samples" if profile.kind == "radial_table" else "coefficients",
                    f"do not reach the display corner ({r_max:.4g} mm from the centre) below 90 deg") from None


# ---------------------------------------------------------------------- the bank
def bank_from_profile(profile: DistortionProfile, grid: tuple[int, int] = (65, 65)) -> PSFBank:
    """A chief-ray-only :class:`PSFBank` for a profile: chief rays ``[3, Cy, Cx, 2]`` on a uniform
    ``grid`` (``Cy x Cx``, display edges included) from :meth:`DistortionProfile.landing`; PSFs unit
    impulses (``K = 1``) on a 2 x 2 field grid; ``meta["lens"]`` holds the lens frame (``axis`` =
    the distortion centre, ``psf`` False, ``kind`` ``"profile"``, ``half_fov_deg`` and
    ``deg_per_output_unit`` where defined), ``meta["profile"]`` the parsed profile and
    ``meta["figures"]`` the corner distortion per primary."""
    cy_n, cx_n = grid
    if not all(isinstance(n, int) and n >= 5 for n in grid):
        raise InputValueError(f"grid must be two ints >= 5, got {grid!r}")
    cx, cy = torch.linspace(-1, 1, cx_n, dtype=_D), torch.linspace(-1, 1, cy_n, dtype=_D)
    Y, X = torch.meshgrid(cy, cx, indexing="ij")
    chief = profile.landing(X, Y)                                     # [3, Cy, Cx, 2]
    jac = (chief[:, 1:, 1:, 0] - chief[:, 1:, :-1, 0]) * (chief[:, 1:, 1:, 1] - chief[:, :-1, 1:, 1]) - \
        (chief[:, 1:, 1:, 1] - chief[:, 1:, :-1, 1]) * (chief[:, 1:, 1:, 0] - chief[:, :-1, 1:, 0])
    if not bool((jac > 0).all()):
        raise InputValueError(f"{profile.source}: the profile's map folds over inside the display")
    pitch = 1e-4 * min(m / p for m, p in zip(profile.display_mm, profile.display_px))
    f = torch.tensor([-0.5, 0.5], dtype=_D)
    lens: dict[str, Any] = {"axis": list(profile.centre), "psf": False, "kind": "profile",
                            "rotationally_symmetric": profile.centre == (0.0, 0.0) and not profile.tangential}
    half = profile.half_fov_deg()
    if half is not None:
        lens["half_fov_deg"] = half
        lens["deg_per_output_unit"] = profile.deg_per_output_unit()
    corner = profile.landing(torch.tensor(1.0), torch.tensor(1.0))   # [3, 2]
    a = torch.tensor(profile.centre, dtype=_D)
    ref = float((torch.tensor([1.0, 1.0], dtype=_D) - a).norm())
    distortion = [100 * (float((corner[c] - a).norm()) / ref - 1) for c in range(3)]
    figures = {"corner_distortion_pct": distortion,
               "corner_lateral_colour_px": float(((corner[2] - corner[0]) * torch.tensor(profile.display_px, dtype=_D)
                                                  / 2).norm())}
    meta = {"lens": lens, "profile": profile.to_json(), "figures": figures,
            "assumptions": "a distortion profile gives distortion and lateral colour only, no PSF: every PSF is "
                           "a unit impulse; primaries nominal 656/550/486 nm"}
    return PSFBank(psf=torch.ones(3, 2, 2, 1, 1, dtype=_D), psf_pitch_mm=torch.full((3, 2, 2), pitch, dtype=_D),
                   field_x=f, field_y=f.clone(), chief=chief, chief_x=cx, chief_y=cy,
                   wavelengths_nm=PROFILE_WAVELENGTHS_NM, display_mm=profile.display_mm, meta=meta)
