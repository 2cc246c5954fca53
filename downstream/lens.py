"""Lens correction by pre-warping, P_lens (paper Eq. 2, Supp. "Lens Correction Through Pre-Warping").

The headset lens maps a display point ``p`` to the virtual-image point ``D_c(p)`` (its chief ray,
per colour channel c; pincushion for a magnifier). To make the eye see the rendered image ``I``
the display must show ``J_c(p) = I_c(D_c(p))``: as a map of points the pre-warp is ``D_c^-1``
("inverse distortion"), and applied by backward sampling it reads ``I`` at ``D_c(p)``. The stage
therefore holds, per channel, a *sampling grid* ``[3, H, W, 2]``: for every display pixel the
(x, y) position in the rendered image to sample, in normalised coordinates ([-1, 1], pixel
centres, ``align_corners=False``), plus a per-pixel, per-channel gain ``[3, H, W]`` that corrects
colour shifts of the display-optics path. Sampling is bilinear; outside the image is black.

Sources of the grid (all :class:`PrewarpMap` modules, evaluated at any image size):
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

import hashlib
import os
import weakref
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, Mapping, Sequence, TypeGuard, cast

import torch
import torch.nn.functional as F
from torch import nn

from controlgs_adapter.checks import check_image, check_same_device, check_tensor
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError, warn_user
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors
from controlgs_adapter.state import RuntimeState

from .color import primaries_to_rgb, rgb_to_primaries
from .placement import CARDBOARD_DISPLAY_MM, PLACEMENTS, Placement, image_region
from .stage import Stage, StageContext

if TYPE_CHECKING:  # pragma: no cover
    from .optics.bank import PSFBank

__all__ = [
    "CARDBOARD_RADIAL", "pixel_grid", "lens_prewarp", "invert_map", "chief_ray_grid", "PrewarpMap", "RadialMap",
    "LUTMap", "BankMap", "DisplayLUTMap", "MLPMap", "LensPrewarp", "bank_fingerprint", "BASES", "DEFAULT_PREWARP_FILE",
]

#: Radial coefficients k1 per channel (R, G, B) fitted to the Cardboard lens's chief rays (the
#: display corner of a 1024 px, 24 mm display lands at 606.5 / 611.8 / 617.1 px from the centre
#: for 656 / 550 / 486 nm, docs/explanation/optics.md): ``1 + 2 k1 = landing / 512`` at the corner (r^2 = 2).
CARDBOARD_RADIAL: tuple[tuple[float], tuple[float], tuple[float]] = (
    (0.5 * (606.5 / 512.0 - 1.0),), (0.5 * (611.8 / 512.0 - 1.0),), (0.5 * (617.1 / 512.0 - 1.0),),
)

_FLOATS = (torch.float32, torch.float64)
Basis = Literal["primaries", "rgb"]
#: colour bases of the warp: the display primaries (default) or the RGB channels (the paper's)
BASES: tuple[str, ...] = ("primaries", "rgb")
LUT_KIND = "controlgs-prewarp-lut"
LUT_FORMAT_VERSION = 1
DISPLAY_LUT_KIND = "controlgs-prewarp-display-lut"
DISPLAY_LUT_FORMAT_VERSION = 1
_LUT_MODES = ("distortion", "exact", "fast")
#: the fitted pre-warp shipped for the shipped Cardboard bank (``controlgs optics fit-prewarp``)
DEFAULT_PREWARP_FILE = "cardboard_prewarp_lut.safetensors"


def pixel_grid(size: tuple[int, int], dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """Normalised (x, y) of the pixel centres of an ``(H, W)`` image, ``[H, W, 2]`` (identity grid)."""
    h, w = int(size[0]), int(size[1])
    ys = (torch.arange(h, dtype=dtype, device=device) + 0.5) * (2.0 / h) - 1.0
    xs = (torch.arange(w, dtype=dtype, device=device) + 0.5) * (2.0 / w) - 1.0
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)


def lens_prewarp(image: torch.Tensor, grid: torch.Tensor, gain: torch.Tensor | None = None,
                 basis: Basis = "rgb") -> torch.Tensor:
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
    Returns:
        ``[..., 3, Ho, Wo]``, ``out_c = gain_c * image_c(grid_c)`` in the chosen basis.
    """
    check_image("image", image, finite=False)
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
    warped = F.grid_sample(per_channel, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    if gain is not None:
        warped = warped * gain[:, None]
    out = warped.transpose(0, 1).reshape(*lead, 3, b["Ho"], b["Wo"])
    return primaries_to_rgb(out) if basis == "primaries" else out


Span = tuple[float, float]


def _cell_centres(n: int) -> Span:
    return -1.0 + 1.0 / n, 1.0 - 1.0 / n


def _sample_span(name: str, coords: torch.Tensor | None, n: int) -> Span:
    """(first, last) normalised coordinate of ``n`` uniform samples; None: cell centres of [-1, 1]."""
    if coords is None:
        return _cell_centres(n)
    check_tensor(name, coords, [n], dtypes=_FLOATS, finite=True)
    c = coords.detach().double().cpu()
    step = c[1:] - c[:-1]
    if not bool((step > 0).all()) or float((step - step.mean()).abs().max()) > 1e-6 * float(step.mean()) + 1e-12:
        raise InputValueError(f"{name} must be uniformly spaced and increasing, got {c.tolist()[:4]}...")
    return float(c[0]), float(c[-1])


def _interp_regular(values: torch.Tensor, points: torch.Tensor, xs: Span | None = None, ys: Span | None = None) -> torch.Tensor:
    """Bilinear interpolation, linear extrapolation outside, of ``values`` ``[C, Gh, Gw, D]`` sampled
    on a regular grid whose x samples run uniformly from ``xs[0]`` to ``xs[1]`` (likewise y; default:
    the cell centres of [-1, 1], pixel-centre convention), at normalised (x, y) ``points``
    ``[C, ..., 2]`` -> ``[C, ..., D]``. Needs Gh, Gw >= 2."""
    c, gh, gw, d = values.shape
    xs = xs or _cell_centres(gw)
    ys = ys or _cell_centres(gh)
    pts = points.reshape(c, -1, 2)
    fx = (pts[..., 0] - xs[0]) * ((gw - 1) / (xs[1] - xs[0]))  # continuous sample index
    fy = (pts[..., 1] - ys[0]) * ((gh - 1) / (ys[1] - ys[0]))
    x0 = fx.detach().floor().clamp(0, gw - 2).long()
    y0 = fy.detach().floor().clamp(0, gh - 2).long()
    tx, ty = (fx - x0)[..., None], (fy - y0)[..., None]
    ci = torch.arange(c, device=values.device)[:, None]

    def at(yy: torch.Tensor, xx: torch.Tensor) -> torch.Tensor:
        return values[ci, yy, xx]  # [C, P, D]

    out = ((1 - ty) * ((1 - tx) * at(y0, x0) + tx * at(y0, x0 + 1))
           + ty * ((1 - tx) * at(y0 + 1, x0) + tx * at(y0 + 1, x0 + 1)))
    return out.reshape(*points.shape[:-1], d)


def invert_map(
    forward_map: torch.Tensor,
    size: tuple[int, int],
    *,
    sample_x: torch.Tensor | None = None,
    sample_y: torch.Tensor | None = None,
    iterations: int = 30,
    tol: float = 1e-9,
) -> torch.Tensor:
    """Numerically invert per-channel 2-D maps given on a regular grid.

    Args:
        forward_map: ``[3, Gh, Gw, 2]``: ``F_c`` sampled on a regular grid of normalised (x, y)
            positions, bilinearly interpolated and linearly extrapolated in between; must be
            locally invertible.
        size: ``(H, W)`` of the output grid.
        sample_x, sample_y: ``[Gw]``, ``[Gh]`` uniform sample coordinates; default: the cell
            centres of [-1, 1] (pixel-centre convention).
    Returns:
        ``[3, H, W, 2]`` grid ``G_c`` with ``F_c(G_c(q)) = q`` at the pixel centres q (Newton's method
        in float64, no gradient through it).
    """
    check_tensor("forward_map", forward_map, [3, "Gh", "Gw", 2], dtypes=_FLOATS, finite=True)
    if min(forward_map.shape[1:3]) < 2:
        raise ShapeError(f"forward_map needs at least 2x2 samples, got {list(forward_map.shape)}")
    xs = _sample_span("sample_x", sample_x, forward_map.shape[2])
    ys = _sample_span("sample_y", sample_y, forward_map.shape[1])
    with torch.no_grad():
        fmap = forward_map.detach().double()
        target = pixel_grid(size, torch.float64, fmap.device).expand(3, -1, -1, -1)
        g = 2.0 * target - _interp_regular(fmap, target, xs, ys)  # first-order inverse as the start
        eps = 1e-6
        ex = torch.tensor([eps, 0.0], dtype=torch.float64, device=fmap.device)
        ey = torch.tensor([0.0, eps], dtype=torch.float64, device=fmap.device)
        for _ in range(iterations):
            r = _interp_regular(fmap, g, xs, ys) - target  # [3, H, W, 2]
            if float(r.abs().max()) < tol:
                break
            jx = (_interp_regular(fmap, g + ex, xs, ys) - _interp_regular(fmap, g - ex, xs, ys)) / (2 * eps)  # dF/dx
            jy = (_interp_regular(fmap, g + ey, xs, ys) - _interp_regular(fmap, g - ey, xs, ys)) / (2 * eps)  # dF/dy
            det = jx[..., 0] * jy[..., 1] - jy[..., 0] * jx[..., 1]
            if bool((det.abs() < 1e-12).any()):
                raise InputValueError("forward_map is not invertible (its Jacobian vanishes somewhere)")
            dx = (jy[..., 1] * r[..., 0] - jy[..., 0] * r[..., 1]) / det
            dy = (jx[..., 0] * r[..., 1] - jx[..., 1] * r[..., 0]) / det
            g = g - torch.stack([dx, dy], dim=-1)
    return g.to(forward_map.dtype)


def _area_magnification(grid: torch.Tensor) -> torch.Tensor:
    """``|det d grid / dp|`` of a sampling grid ``[3, H, W, 2]`` over normalised pixel centres
    (central differences, one-sided at the border) -> ``[3, H, W]``."""
    h, w = grid.shape[1:3]
    dgx_dy, dgx_dx = torch.gradient(grid[..., 0], spacing=(2.0 / h, 2.0 / w), dim=(1, 2))
    dgy_dy, dgy_dx = torch.gradient(grid[..., 1], spacing=(2.0 / h, 2.0 / w), dim=(1, 2))
    return (dgx_dx * dgy_dy - dgx_dy * dgy_dx).abs()


def chief_ray_grid(
    chief_ray_map: torch.Tensor,
    size: tuple[int, int],
    *,
    direction: Literal["display_to_eye", "eye_to_display"] = "display_to_eye",
    sample_x: torch.Tensor | None = None,
    sample_y: torch.Tensor | None = None,
    gain: torch.Tensor | Literal["jacobian"] | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The sampling grid ``[3, H, W, 2]`` and gain ``[3, H, W]`` (or None) that compensate a chief-ray
    map; arguments as in :meth:`LensPrewarp.from_chief_ray_map`."""
    check_tensor("chief_ray_map", chief_ray_map, [3, "Gh", "Gw", 2], dtypes=_FLOATS, finite=True)
    if min(chief_ray_map.shape[1:3]) < 2:
        raise ShapeError(f"chief_ray_map needs at least 2x2 samples, got {list(chief_ray_map.shape)}")
    xs = _sample_span("sample_x", sample_x, chief_ray_map.shape[2])
    ys = _sample_span("sample_y", sample_y, chief_ray_map.shape[1])
    if direction == "display_to_eye":
        p = pixel_grid(size, chief_ray_map.dtype, chief_ray_map.device).expand(3, -1, -1, -1)
        grid = _interp_regular(chief_ray_map.detach(), p, xs, ys)
    elif direction == "eye_to_display":
        grid = invert_map(chief_ray_map, size, sample_x=sample_x, sample_y=sample_y)
    else:
        raise InputValueError(f"direction must be 'display_to_eye' or 'eye_to_display', got {direction!r}")
    if isinstance(gain, str):
        if gain != "jacobian":
            raise InputValueError(f"gain must be a tensor, 'jacobian' or None, got {gain!r}")
        gain = _area_magnification(grid)
    return grid, gain


class PrewarpMap(nn.Module):
    """Source of the pre-warp: ``forward(size, dtype, device) -> (grid [3, H, W, 2], gain [3, H, W] | None)``."""

    def is_identity(self) -> bool:
        """True if the map is the identity (grid = pixel centres, gain = 1)."""
        raise NotImplementedError

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor | None]:  # noqa: D102
        raise NotImplementedError


class RadialMap(PrewarpMap):
    """``grid_c(p) = p * (1 + sum_k coefficients[c, k] r^(2k+2))`` (aspect-corrected r), gain 1.

    Args:
        coefficients: ``[3, K]`` radial coefficients per channel (R, G, B).
        learnable: make the coefficients a trainable parameter.
    """

    def __init__(self, coefficients: Sequence[Sequence[float]] | torch.Tensor = CARDBOARD_RADIAL, learnable: bool = False) -> None:
        super().__init__()
        k = torch.as_tensor(coefficients, dtype=torch.float64).float()  # checked as stored: 1e39 is inf in float32
        check_tensor("coefficients", k, [3, "K"], finite=True)
        if learnable:
            self.coefficients = nn.Parameter(k)
        else:
            self.register_buffer("coefficients", k)

        self._cache: dict[tuple, torch.Tensor] = {}  # fixed coefficients: grid per (size, dtype, device, version)

    def is_identity(self) -> bool:  # noqa: D102
        return not bool(self.coefficients.detach().any())

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, None]:  # noqa: D102
        if self.coefficients.requires_grad and torch.is_grad_enabled():
            return self._grid(size, dtype, device), None
        k = self.coefficients
        key = (tuple(size), dtype, torch.device(device), k.device, k.data_ptr(), k._version)
        if key not in self._cache:
            self._cache.clear()
            with torch.no_grad():
                self._cache[key] = self._grid(size, dtype, device)
        return self._cache[key], None

    def _grid(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> torch.Tensor:
        p = pixel_grid(size, dtype, device)  # [H, W, 2]
        region = image_region(int(size[0]), int(size[1]), CARDBOARD_DISPLAY_MM, "fit")
        aspect = torch.tensor([region.half_x, region.half_y], dtype=dtype, device=device)
        r2 = ((p * aspect) ** 2).sum(-1)  # [H, W] squared display-normalised radius
        k = self.coefficients.to(device=device, dtype=dtype)  # [3, K]
        powers = r2[None] ** torch.arange(1, k.shape[1] + 1, device=device, dtype=dtype)[:, None, None]  # [K, H, W]
        factor = 1.0 + torch.einsum("ck,khw->chw", k, powers)  # [3, H, W]
        return p[None] * factor[..., None]


class LUTMap(PrewarpMap):
    """A lookup table: grid ``[3, Hl, Wl, 2]`` and gain ``[3, Hl, Wl]`` (None: 1) at pixel centres
    of an ``Hl x Wl`` image; for another size the displacement and gain are interpolated bilinearly
    (linearly extrapolated at the border)."""

    displacement: torch.Tensor  # [3, Hl, Wl, 2] buffer: grid minus the pixel centres
    gain: torch.Tensor  # [3, Hl, Wl] buffer

    def __init__(self, grid: torch.Tensor, gain: torch.Tensor | None = None) -> None:
        super().__init__()
        b = check_tensor("grid", grid, [3, "H", "W", 2], dtypes=_FLOATS, finite=True)
        if min(b["H"], b["W"]) < 2:
            raise ShapeError(f"grid needs at least 2x2 pixels, got {list(grid.shape)}")
        if gain is None:
            gain = torch.ones(3, b["H"], b["W"], dtype=grid.dtype, device=grid.device)
        check_tensor("gain", gain, [3, "H", "W"], dtypes=_FLOATS, dims=b, finite=True)
        ident = pixel_grid((b["H"], b["W"]), grid.dtype, grid.device)
        self.register_buffer("displacement", (grid.detach() - ident).float())  # [3, Hl, Wl, 2]
        self.register_buffer("gain", gain.detach().float())  # [3, Hl, Wl]
        self._identity: tuple[tuple, bool] | None = None  # (buffer versions, answer)
        self._evaluated: tuple[tuple, tuple[torch.Tensor, torch.Tensor]] | None = None  # last (key, (grid, gain))

    def _version_key(self) -> tuple:
        return tuple((t.data_ptr(), t._version) for t in (self.displacement, self.gain))

    def is_identity(self) -> bool:  # noqa: D102
        key = self._version_key()
        if self._identity is None or self._identity[0] != key:  # O(N) scan only after a change
            self._identity = (key, not bool(self.displacement.any()) and bool((self.gain == 1).all()))
        return self._identity[1]

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: D102
        key = (tuple(size), dtype, torch.device(device), self._version_key())
        if self._evaluated is None or self._evaluated[0] != key:  # the table is fixed: evaluate once per size
            disp, gain = self.displacement.to(device=device, dtype=dtype), self.gain.to(device=device, dtype=dtype)
            p = pixel_grid(size, dtype, device)
            if tuple(size) != tuple(disp.shape[1:3]):
                table = torch.cat([disp, gain[..., None]], dim=-1)  # [3, Hl, Wl, 3]
                table = _interp_regular(table, p.expand(3, -1, -1, -1))
                disp, gain = table[..., :2], table[..., 2]
            self._evaluated = (key, (p[None] + disp, gain))
        return self._evaluated[1]


def _bank_in_image_frame(bank: "PSFBank", size: tuple[int, int],
                         placement: Placement) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A bank's chief rays in the normalised frame of an ``(H, W)`` image placed on its display:
    ``(chief [3, Cy, Cx, 2], sample_x [Cx], sample_y [Cy])``, display coordinates divided by the
    image region's half-extents (the frame the optics uses, ``ResampledBank``)."""
    region = image_region(int(size[0]), int(size[1]), bank.display_mm, placement)
    half = torch.tensor([region.half_x, region.half_y], dtype=bank.chief.dtype, device=bank.chief.device)
    return bank.chief / half, bank.chief_x / region.half_x, bank.chief_y / region.half_y


class BankMap(PrewarpMap):
    """The pre-warp that compensates a PSF bank's lens (distortion and lateral colour, one map per
    primary) for an image placed on the bank's display with ``placement``; the grid (and the
    ``"jacobian"`` gain, see :meth:`LensPrewarp.from_chief_ray_map`) is evaluated at each image
    size, so every aspect gets the region the optics simulates. Fixed (no parameters)."""

    def __init__(self, bank: "PSFBank", placement: Placement = "fit", gain: Literal["jacobian"] | None = None) -> None:
        super().__init__()
        if bank.chief.shape[0] != 3:
            raise InputValueError(f"bank must have 3 wavelengths (R, G, B primaries), got {bank.wavelengths_nm}")
        if placement not in PLACEMENTS:
            raise InputValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
        if gain not in (None, "jacobian"):
            raise InputValueError(f"gain must be 'jacobian' or None, got {gain!r}")
        self.bank, self.placement, self.gain = bank, placement, gain
        ident = torch.stack(torch.meshgrid(bank.chief_x.float(), bank.chief_y.float(), indexing="xy"), -1)
        self._identity = gain is None and bool((bank.chief == ident).all())
        self._evaluated: tuple[tuple, tuple[torch.Tensor, torch.Tensor | None]] | None = None

    def is_identity(self) -> bool:  # noqa: D102
        return self._identity

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor | None]:  # noqa: D102
        key = (tuple(size), dtype, torch.device(device))
        if self._evaluated is None or self._evaluated[0] != key:
            chief, sx, sy = _bank_in_image_frame(self.bank, size, self.placement)
            grid, gain = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain=self.gain)
            self._evaluated = (key, (grid.to(device, dtype), None if gain is None else gain.to(device, dtype)))
        return self._evaluated[1]

    def extra_repr(self) -> str:
        return f"placement={self.placement!r}, gain={self.gain!r}"


def bank_fingerprint(bank: "PSFBank") -> str:
    """A short hash of a bank's optics (PSFs, pitches, chief rays, wavelengths, display size): a
    fitted LUT names the bank it was fitted for."""
    h = hashlib.sha256()
    for t in (bank.psf, bank.psf_pitch_mm, bank.field_x, bank.field_y, bank.chief, bank.chief_x, bank.chief_y):
        h.update(t.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    h.update(repr((tuple(float(w) for w in bank.wavelengths_nm), tuple(float(d) for d in bank.display_mm))).encode())
    return h.hexdigest()[:16]


class DisplayLUTMap(PrewarpMap):
    """A fitted pre-warp tabulated in display coordinates over the whole display (one table per
    optics mode), sampled for the region an image occupies on the display (:mod:`.placement`), so
    one table serves images of any aspect.

    A table holds, at the pixel centres of an ``Hd x Wd`` grid over the display (display-normalised
    coordinates, ``align_corners=False``), per primary: ``displacement`` ``[3, Hd, Wd, 2]``, the
    display-normalised eye position of the display point minus the point (what the pre-warp samples
    there), and ``gain`` ``[3, Hd, Wd]``. For an ``H x W`` image with half-extents
    ``(hx, hy)`` the grid at image point ``u`` is ``(u h + displacement(u h)) / h`` (bilinear in the
    table, linear extrapolation at its border). The grid and gain are evaluated once per (size,
    dtype, device, table in use) and the same tensors returned again; an in-place change of a table
    is seen at the next call.

    Args:
        tables: optics mode (``"distortion"``, ``"exact"``; ``"fast"`` uses ``"exact"``) ->
            ``(displacement, gain)``.
        display_mm: ``(width, height)`` of the display the tables cover.
        placement: where images sit on the display (``"fit"`` or ``"stretch"``).
        mode: the table to use; None: the mode of the optics stage given to :meth:`follow`, else
            the first table.
        meta: provenance (bank fingerprint, fit settings, residuals), saved with the tables.
    """

    def __init__(self, tables: Mapping[str, tuple[torch.Tensor, torch.Tensor]], display_mm: tuple[float, float] = CARDBOARD_DISPLAY_MM,
                 placement: Placement = "fit", mode: str | None = None, meta: Mapping[str, Any] | None = None) -> None:
        super().__init__()
        if not tables:
            raise InputValueError("tables must hold at least one optics mode")
        if placement not in PLACEMENTS:
            raise InputValueError(f"placement must be one of {PLACEMENTS}, got {placement!r}")
        self.modes = tuple(tables)
        for m, (disp, gain) in tables.items():
            if m not in _LUT_MODES:
                raise InputValueError(f"table modes must be among {_LUT_MODES}, got {m!r}")
            b = check_tensor(f"displacement[{m!r}]", disp, [3, "H", "W", 2], dtypes=_FLOATS, finite=True)
            check_tensor(f"gain[{m!r}]", gain, [3, "H", "W"], dtypes=_FLOATS, dims=b, finite=True)
            if min(b["H"], b["W"]) < 2:
                raise ShapeError(f"table {m!r} needs at least 2x2 samples, got {list(disp.shape)}")
            self.register_buffer(f"displacement_{m}", disp.detach().float())
            self.register_buffer(f"gain_{m}", gain.detach().float())
        self.display_mm = (float(display_mm[0]), float(display_mm[1]))
        self.placement = placement
        self.mode = mode
        self.meta = dict(meta or {})
        self._optics: weakref.ref | None = None
        self._evaluated: tuple[tuple, tuple[torch.Tensor, torch.Tensor]] | None = None

    def follow(self, optics: nn.Module) -> "DisplayLUTMap":
        """Use the table of ``optics.mode`` at every call (weakly referenced, not a submodule)."""
        self._optics = weakref.ref(optics)
        return self

    def table_mode(self) -> str:
        """The table in use (see the class docstring)."""
        optics = self._optics() if self._optics is not None else None
        want = self.mode if self.mode is not None else getattr(optics, "mode", None)
        if want is None:
            return self.modes[0]
        if want not in self.modes and want == "fast" and "exact" in self.modes:
            return "exact"
        if want not in self.modes:
            raise InputValueError(f"this pre-warp LUT has tables for {self.modes}, not for optics mode {want!r}")
        return want

    def is_identity(self) -> bool:  # noqa: D102
        return False

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: D102
        m = self.table_mode()
        disp, gain = getattr(self, f"displacement_{m}"), getattr(self, f"gain_{m}")
        key = (tuple(size), dtype, torch.device(device), m, disp.data_ptr(), disp._version, gain._version)
        if self._evaluated is None or self._evaluated[0] != key:
            region = image_region(int(size[0]), int(size[1]), self.display_mm, self.placement)
            half = torch.tensor([region.half_x, region.half_y], dtype=dtype, device=device)
            p = pixel_grid(size, dtype, device) * half  # [H, W, 2] display-normalised
            table = torch.cat([disp, gain[..., None]], dim=-1).to(device=device, dtype=dtype)  # [3, Hd, Wd, 3]
            val = _interp_regular(table, p.expand(3, -1, -1, -1))
            self._evaluated = (key, ((p + val[..., :2]) / half, val[..., 2]))
        return self._evaluated[1]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the tables (safetensors, atomic; kind ``controlgs-prewarp-display-lut``)."""
        tensors = {}
        for m in self.modes:
            tensors[f"displacement_{m}"] = getattr(self, f"displacement_{m}")
            tensors[f"gain_{m}"] = getattr(self, f"gain_{m}")
        header = {"modes": list(self.modes), "display_mm": list(self.display_mm), "meta": self.meta,
                  "units": {"displacement": "display-normalised (x, y) eye position minus display position",
                            "gain": "factor per primary (656, 550, 486 nm)"}}
        return save_tensors(path, tensors, header, kind=DISPLAY_LUT_KIND, format_version=DISPLAY_LUT_FORMAT_VERSION)

    @classmethod
    def load(cls, path: str | os.PathLike, placement: Placement = "fit") -> "DisplayLUTMap":
        """Read a file written by :meth:`save`."""
        tensors, header = load_tensors(path, kind=DISPLAY_LUT_KIND, max_version=DISPLAY_LUT_FORMAT_VERSION)
        modes = header.get("modes")
        if not isinstance(modes, list) or not modes:
            raise FileFormatError(f"{path}: display LUT header lacks its modes")
        missing = [k for m in modes for k in (f"displacement_{m}", f"gain_{m}") if k not in tensors]
        if missing:
            raise FileFormatError(f"{path}: display LUT lacks {missing}")
        display_mm = header.get("display_mm", list(CARDBOARD_DISPLAY_MM))
        try:
            return cls({m: (tensors[f"displacement_{m}"], tensors[f"gain_{m}"]) for m in modes},
                       (float(display_mm[0]), float(display_mm[1])), placement, meta=header.get("meta") or {})
        except (InputValueError, ShapeError) as e:
            raise FileFormatError(f"{path}: {e}") from None

    def extra_repr(self) -> str:
        return f"modes={self.modes}, placement={self.placement!r}, display_mm={self.display_mm}"


class MLPMap(PrewarpMap):
    """Learned map: an MLP from normalised (x, y) to 3 x (dx, dy, log gain), zero-initialised last
    layer (identity at init); :meth:`LensPrewarp.bake` tabulates it.

    Args:
        hidden: width of the hidden layers.
        layers: number of hidden layers.
        frequencies: number of Fourier-feature octaves of (x, y) fed to the MLP (0: raw x, y).
    """

    def __init__(self, hidden: int = 64, layers: int = 2, frequencies: int = 4) -> None:
        super().__init__()
        if hidden < 1 or layers < 1 or frequencies < 0:
            raise InputValueError(f"hidden, layers must be >= 1 and frequencies >= 0, got {hidden}, {layers}, {frequencies}")
        self.frequencies = int(frequencies)
        width_in = 2 + 4 * self.frequencies
        mods: list[nn.Module] = []
        for i in range(layers):
            mods += [nn.Linear(width_in if i == 0 else hidden, hidden), nn.SiLU()]
        last = nn.Linear(hidden, 9)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.mlp = nn.Sequential(*mods, last)

    def _last(self) -> nn.Linear:
        """The output layer (9 = 3 x (dx, dy, log gain))."""
        # nn.Sequential's stubs type its items as Module; __init__ ends it with this Linear
        return cast(nn.Linear, self.mlp[-1])

    def is_identity(self) -> bool:  # noqa: D102
        last = self._last()
        return not bool(last.weight.detach().any()) and not bool(last.bias.detach().any())

    def _encode(self, p: torch.Tensor) -> torch.Tensor:
        if self.frequencies == 0:
            return p
        scales = torch.pi * 2.0 ** torch.arange(self.frequencies, dtype=p.dtype, device=p.device)  # [F]
        angles = (p[..., None] * scales).flatten(-2)  # [..., 2F]
        return torch.cat([p, torch.sin(angles), torch.cos(angles)], dim=-1)

    def forward(self, size: tuple[int, int], dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:  # noqa: D102
        p = pixel_grid(size, dtype, device)  # [H, W, 2]
        mlp_dtype = self._last().weight.dtype
        out = self.mlp(self._encode(p.to(mlp_dtype))).to(dtype)  # [H, W, 9]
        out = out.reshape(*p.shape[:2], 3, 3).permute(2, 0, 1, 3)  # [3, H, W, (dx, dy, log gain)]
        return p[None] + out[..., :2], torch.exp(out[..., 2])


def _optics_bank(optics: nn.Module) -> PSFBank:
    """The PSF bank (``optics.bank``) of an optics stage such as
    :class:`~.optics.stage.PSFOptics`; :class:`InputValueError` if it has none."""
    from .optics.bank import PSFBank

    bank = getattr(optics, "bank", None)
    if not isinstance(bank, PSFBank):
        raise InputValueError(f"optics must be an optics stage with a PSFBank as its bank, got a {type(optics).__name__} "
                              f"whose bank is a {type(bank).__name__}")
    return bank


def _is_placement(value: object) -> TypeGuard[Placement]:
    return value in PLACEMENTS


def _optics_placement(optics: nn.Module) -> Placement:
    """Where an optics stage places images on its display (``optics.placement``; ``"fit"`` if it
    has none); :class:`InputValueError` for another value."""
    placement = getattr(optics, "placement", "fit")
    if not _is_placement(placement):
        raise InputValueError(f"optics.placement must be one of {PLACEMENTS}, got {placement!r}")
    return placement


class LensPrewarp(Stage):
    """P_lens: per-channel pre-warp and gain from a :class:`PrewarpMap` (default: Cardboard radial).

    A map with trainable parameters is never skipped in training mode (even while it is still
    the identity, so that it receives gradients).

    Args:
        prewarp_map: the map; default ``RadialMap(coefficients)``.
        coefficients: ``[3, K]`` radial coefficients, only when ``prewarp_map`` is None.
        basis: ``"primaries"`` (default: each display primary warped with its own map, see
            :func:`lens_prewarp`) or ``"rgb"`` (the paper's per-RGB-channel warp).
    """

    name = "lens"
    domain = "linear"
    order = 10.0

    def __init__(self, prewarp_map: PrewarpMap | None = None, *, coefficients: Sequence[Sequence[float]] | torch.Tensor | None = None,
                 basis: Basis = "primaries") -> None:
        super().__init__()
        if prewarp_map is not None and coefficients is not None:
            raise InputValueError("give either prewarp_map or coefficients, not both")
        if basis not in BASES:
            raise InputValueError(f"basis must be one of {BASES}, got {basis!r}")
        self.map = prewarp_map if prewarp_map is not None else RadialMap(CARDBOARD_RADIAL if coefficients is None else coefficients)
        self.basis = basis

    @classmethod
    def for_optics(
        cls, optics: nn.Module, *, source: Literal["fitted", "chief_rays"] = "fitted", basis: Basis = "primaries",
        lut: str | os.PathLike | None = None, gain: Literal["jacobian"] | None = None,
    ) -> "LensPrewarp":
        """The pre-warp that compensates an optics stage (its ``bank``, ``placement`` and, for a
        fitted LUT, its current ``mode``).

        Args:
            optics: the pipeline's optics stage (:class:`~.optics.stage.PSFOptics`).
            source: ``"fitted"``: map and gain fitted through the optics
                (:func:`.prewarp_fit.fit_bank_prewarp`), read from ``lut`` (default: the LUT shipped
                for the shipped Cardboard bank; for another bank without a LUT this falls back to
                ``"chief_rays"`` with a warning); ``"chief_rays"``: the bank's chief rays
                (:class:`BankMap`, gain ``gain``).
            basis: see :class:`LensPrewarp`.
            lut: a file written by :meth:`DisplayLUTMap.save` (``controlgs optics fit-prewarp``).
        """
        bank = _optics_bank(optics)
        placement = _optics_placement(optics)
        if source == "chief_rays":
            return cls(BankMap(bank, placement, gain), basis=basis)
        if source != "fitted":
            raise InputValueError(f"source must be 'fitted' or 'chief_rays', got {source!r}")
        if gain is not None:
            raise InputValueError("gain applies to source='chief_rays'; a fitted LUT brings its own gain")
        if lut is None:
            with resources.as_file(resources.files("controlgs_adapter.data").joinpath(DEFAULT_PREWARP_FILE)) as path:
                fitted = DisplayLUTMap.load(path, placement) if path.is_file() else None
            radiometry = getattr(optics, "radiometry", None)
            if fitted is None or fitted.meta.get("bank") != bank_fingerprint(bank) or fitted.meta.get("radiometry") != radiometry:
                fallback: Literal["jacobian"] | None = "jacobian" if radiometry == "energy" else None
                warn_user(f"no fitted pre-warp LUT for this PSF bank and radiometry {radiometry!r}: using its chief "
                          f"rays (gain {fallback}); make one with `controlgs optics fit-prewarp --bank BANK --out LUT` "
                          "and pass it as {'lens': {'lut': LUT}}", UserWarning)
                return cls(BankMap(bank, placement, fallback), basis=basis)
        else:
            fitted = DisplayLUTMap.load(lut, placement)
            if fitted.meta.get("bank") != bank_fingerprint(bank):
                raise InputValueError(f"{lut}: this pre-warp LUT was fitted for another PSF bank "
                                      f"({fitted.meta.get('bank')!r}, the optics' bank is {bank_fingerprint(bank)!r})")
            if fitted.meta.get("radiometry") != getattr(optics, "radiometry", None):
                raise InputValueError(f"{lut}: this pre-warp LUT was fitted for radiometry {fitted.meta.get('radiometry')!r}, "
                                      f"the optics use {getattr(optics, 'radiometry', None)!r}")
        return cls(fitted.follow(optics), basis=basis)

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
        return lens_prewarp(image, grid, gain, self.basis)

    def extra_repr(self) -> str:
        return f"basis={self.basis!r}"
