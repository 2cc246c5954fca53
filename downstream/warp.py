"""The pre-warp's geometry: normalised pixel grids (``[H, W, 2]``, (x, y) of the pixel centres in
[-1, 1], ``align_corners=False``), bilinear interpolation of maps sampled on a regular grid, the
numerical inverse of a per-channel map ``[3, Gh, Gw, 2]``, and the sampling grid ``[3, H, W, 2]`` and
gain ``[3, H, W]`` that compensate a chief-ray map (:func:`chief_ray_grid`).
"""

from __future__ import annotations

from typing import Literal

import torch

from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import InputValueError, ShapeError

__all__ = ["pixel_grid", "invert_map", "chief_ray_grid"]

_FLOATS = (torch.float32, torch.float64)


def pixel_grid(size: tuple[int, int], dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu") -> torch.Tensor:
    """Normalised (x, y) of the pixel centres of an ``(H, W)`` image, ``[H, W, 2]`` (identity grid)."""
    h, w = int(size[0]), int(size[1])
    ys = (torch.arange(h, dtype=dtype, device=device) + 0.5) * (2.0 / h) - 1.0
    xs = (torch.arange(w, dtype=dtype, device=device) + 0.5) * (2.0 / w) - 1.0
    return torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)


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
    map; arguments as in :meth:`.lens.LensPrewarp.from_chief_ray_map`."""
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
