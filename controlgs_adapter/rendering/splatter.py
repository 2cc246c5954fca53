"""Differentiable EWA Gaussian splatter in pure PyTorch (CPU-first, any device).

``rasterize`` renders 3D Gaussians with the conventions of 3D Gaussian Splatting (Kerbl et al. 2023);
``controlgs_adapter/rendering/splatter_reference.py`` holds the brute-force float64 oracle the tests compare against.

Conventions (all shared with the reference; see ``rasterize``'s docstring for the full list):

* camera: OpenCV axes (x right, y down, z forward), ``Camera.world_to_camera`` ``[4, 4]`` and
  ``Camera.intrinsics`` ``[3, 3]`` in pixels; pixel ``(i, j)`` has its centre at ``(i + 0.5, j + 0.5)``.
* Gaussian ``n``: mean ``mu_n`` (world), covariance ``R(q_n) diag(s_n)^2 R(q_n)^T`` with the quaternion
  ``q_n = (w, x, y, z)`` normalised here, opacity ``o_n`` in [0, 1], a colour.

How it is fast (2 CPU cores, no compiled extension; profiler labels ``splatter.*`` in brackets):

1. [project] project only the Gaussians in front of the near plane; drop those whose footprint misses
   the image (``visible``);
2. [bin] sort the rest by depth, bin their candidate rectangles (footprint cut to the box where
   alpha can reach 1/255) into ``tile_size`` x ``tile_size`` tiles, stable-sort the records by tile
   (so (tile, depth) order) and cut the tiles into chunks of fewer than ``2^15`` tile-major pixels, so
   that a chunk's pixel keys and the sort's sentinel fit int16;
3. [expand_pairs] per chunk, in passes over windows of depth rank (at most ``_PAIR_BUDGET`` candidate
   pairs each, so memory is bounded whatever the scene: never a dense [pixels x Gaussians] tensor):
   expand the records into pixel rows, then pixels, the exponent ``log(o G)`` a quadratic in the
   pixel's column per row; give the pairs with alpha < 1/255 the sentinel key and stable-sort by
   pixel with int16 keys (each pixel's run stays in depth order, the dropped pairs last); every
   pair's transmittance comes from one segmented scan of ``log(1 - alpha)`` (float64 prefix sums)
   continued from the earlier passes. Early termination (``transmittance_min``, 3DGS's ``T < 1e-4``):
   the pairs behind each pixel's termination point are dropped here, before anything is accumulated
   or kept for backward; later passes skip the rows whose pixels have all terminated and the tiles
   that have; the first window of a chunk ends at the depth where half of the previous chunk's tiles
   terminated, each next one twice as deep;
4. [accumulate] ``sum_i w_i f_i`` per pixel is one sparse CSR [chunk pixels x chunk records] @
   [records x 5] product per pass (colour, depth, alpha);
5. [backward_pairs] the compositing is a ``torch.autograd.Function`` with a hand-written backward
   (the 3DGS back-to-front suffix sums as a reverse segmented scan per pass, carried across passes
   per pixel); the pairs' terms are summed per record (chunk-local, cache-resident: the conic enters
   through the moments ``sum g dx^2`` etc.) and scattered to the Gaussians once per chunk; a chunk's
   drawn pairs (15 bytes each: record, pixel, alpha, weight, clamp flag; offsets recomputed from the
   pixel) are kept for it while they fit in ``_CACHE_BYTES``, the others are recomputed (as the CUDA
   kernel does).
"""

from __future__ import annotations

import bisect
import math
import warnings
from dataclasses import dataclass
from typing import Any

import torch
from torch.autograd.function import once_differentiable

from controlgs_adapter.checks import check_same_device, check_tensor
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import Camera

__all__ = [
    "RasterOutput",
    "rasterize",
    "project_gaussians",
    "NEAR_PLANE",
    "LOW_PASS",
    "EXTENT_SIGMAS",
    "FRUSTUM_MARGIN",
    "ALPHA_MAX",
    "ALPHA_MIN",
    "TRANSMITTANCE_MIN",
    "MAX_SPREAD",
]

NEAR_PLANE = 0.2  # Gaussians with camera-space z <= this are culled (3DGS ``in_frustum``)
LOW_PASS = 0.3  # px^2 added to the diagonal of every 2D covariance (3DGS anti-aliasing filter)
EXTENT_SIGMAS = 3.0  # footprint half-width, in standard deviations along the major axis
FRUSTUM_MARGIN = 0.15  # the Jacobian's x/z, y/z are clamped to the image +- this fraction of its size
ALPHA_MAX = 0.99  # per-splat alpha clamp
ALPHA_MIN = 1.0 / 255.0  # splats with alpha below this are skipped
TRANSMITTANCE_MIN = 1e-4  # default of rasterize's transmittance_min (early termination, as 3DGS)
# a Gaussian's axis spans at most MAX_SPREAD image sizes (one standard deviation, px) on screen, and at most
# _MAX_SPREAD_PX pixels: a longer axis is shortened to it. Its alpha already varies by less than 2e-8 across the
# image there (the forward is saturated), and its 2D covariance, determinant and their gradients stay finite
# in float32 whatever the scale (1e20 would overflow them and give NaN gradients)
MAX_SPREAD = 1e4
_MAX_SPREAD_PX = 1e9



@dataclass
class RasterOutput:
    """Result of ``rasterize``.

    Attributes:
        color: ``[3, H, W]`` composited colour, background blended in.
        alpha: ``[1, H, W]`` accumulated opacity ``1 - T_final``.
        depth: ``[1, H, W]`` alpha-weighted camera-space depth ``sum_i w_i z_i`` (divide by ``alpha``
            for the expected depth of the drawn surface).
        visible: ``[N]`` bool, Gaussian in front of the near plane with a footprint touching the image.
    """

    color: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    visible: torch.Tensor


# ----------------------------------------------------------------------------- projection


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Quaternions ``[M, 4]`` (w, x, y, z), any non-zero norm -> rotation matrices ``[M, 3, 3]``."""
    w, x, y, z = (q / q.norm(dim=-1, keepdim=True)).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def project_gaussians(
    means_cam: torch.Tensor,  # [M, 3] camera-space means, z > 0
    scales: torch.Tensor,  # [M, 3]
    rotations: torch.Tensor,  # [M, 4] world-space quaternions (w, x, y, z)
    world_to_camera: torch.Tensor,  # [4, 4]
    intrinsics: torch.Tensor,  # [3, 3]
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """EWA projection: means2d ``[M, 2]`` (pixels), 2D covariance ``(a, b, c)`` ``[M, 3]`` (px^2,
    ``[[a, b], [b, c]]``, low-pass included) and its inverse, the conic ``[M, 3]``.

    ``Sigma_2D = J W R S S^T R^T W^T J^T + 0.3 I`` with ``W`` the camera rotation and ``J`` the
    Jacobian of ``(fx x / z + cx, fy y / z + cy)`` at the mean, whose ``x/z`` and ``y/z`` are clamped
    to the image extent widened by ``FRUSTUM_MARGIN`` of its size on each side (3DGS's 1.3 x FoV).
    Each of the ``scales`` is capped where its axis's screen extent reaches ``MAX_SPREAD`` image sizes
    (a saturated forward; finite values and gradients for any finite scale).
    """
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    x, y, z = means_cam.unbind(-1)
    u = fx * x / z + cx
    v = fy * y / z + cy
    lim_x = ((cx + FRUSTUM_MARGIN * width) / fx, (width * (1 + FRUSTUM_MARGIN) - cx) / fx)
    lim_y = ((cy + FRUSTUM_MARGIN * height) / fy, (height * (1 + FRUSTUM_MARGIN) - cy) / fy)
    tx = torch.minimum(torch.maximum(x / z, -lim_x[0]), lim_x[1])  # clamped x / z
    ty = torch.minimum(torch.maximum(y / z, -lim_y[0]), lim_y[1])
    rot = world_to_camera[:3, :3] @ _quat_to_rotmat(rotations)  # [M, 3, 3] camera-space rotation
    # rows of J @ rot: J = [[fx / z, 0, -fx tx / z], [0, fy / z, -fy ty / z]] (tx, ty already / z)
    j0 = (fx / z).unsqueeze(-1) * (rot[:, 0, :] - tx.unsqueeze(-1) * rot[:, 2, :])  # [M, 3]
    j1 = (fy / z).unsqueeze(-1) * (rot[:, 1, :] - ty.unsqueeze(-1) * rot[:, 2, :])
    # cap each local axis's screen std (px per unit length: the column norm of J W R) at the spread limit; the cap
    # is a constant for autograd (an axis at it is saturated), inf for an axis seen end-on (norm 0)
    spread = min(MAX_SPREAD * max(width, height), _MAX_SPREAD_PX)
    scales = torch.minimum(scales, spread / torch.hypot(j0, j1).detach())
    j0, j1 = j0 * scales, j1 * scales  # (J W R S) rows
    a0, c0 = (j0 * j0).sum(-1), (j1 * j1).sum(-1)
    a, b, c = a0 + LOW_PASS, (j0 * j1).sum(-1), c0 + LOW_PASS
    # det = a c - b^2 without cancellation (Lagrange: |j0|^2 |j1|^2 - (j0.j1)^2 = |j0 x j1|^2); the naive
    # product loses all digits for needle-like Gaussians near the camera in float32
    det = (torch.linalg.cross(j0, j1) ** 2).sum(-1) + LOW_PASS * (a0 + c0) + LOW_PASS * LOW_PASS
    cov2d = torch.stack([a, b, c], dim=-1)
    conic = torch.stack([c / det, -b / det, a / det], dim=-1)
    return torch.stack([u, v], dim=-1), cov2d, conic


def _footprints(
    means2d: torch.Tensor, cov2d: torch.Tensor, opacity: torch.Tensor, width: int, height: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-index rectangles ``[M, 4]`` (x0, x1, y0, y1, inclusive, clipped to the image; empty when
    x0 > x1 or y0 > y1), not differentiable (hard supports):

    * the footprint: pixels whose centre lies within ``EXTENT_SIGMAS * sqrt(lambda_max)`` of the mean
      along both axes;
    * the candidates: the footprint cut to the bounding box of the ellipse where
      ``alpha >= ALPHA_MIN`` (``d^T Sigma^-1 d <= 2 ln(255 o)``, half-widths ``sqrt(2 ln(255 o) a)``,
      ``sqrt(2 ln(255 o) c)``); pixels outside it cannot be drawn, so skipping them changes nothing.
    """
    with torch.no_grad():
        a, b, c = cov2d.unbind(-1)
        lam = 0.5 * (a + c) + torch.sqrt(0.25 * (a - c) ** 2 + b * b)  # largest eigenvalue, no cancellation
        r = EXTENT_SIGMAS * torch.sqrt(lam)
        level = 2.0 * torch.log(torch.clamp(opacity / ALPHA_MIN, min=1e-30))  # < 0: never drawn
        slack = 1.0 + 1e-6
        rx = torch.minimum(r, torch.sqrt(torch.clamp(level * a, min=0.0)) * slack)
        ry = torch.minimum(r, torch.sqrt(torch.clamp(level * c, min=0.0)) * slack)
        u, v = means2d.unbind(-1)
        big = float(4 * max(width, height) + 4)  # keep the float -> int conversion in range

        def rect(hx: torch.Tensor, hy: torch.Tensor) -> torch.Tensor:
            out = torch.stack(
                [torch.ceil(u - hx - 0.5), torch.floor(u + hx - 0.5),
                 torch.ceil(v - hy - 0.5), torch.floor(v + hy - 0.5)],
                dim=-1,
            ).clamp(-big, big).long()
            out[:, 0].clamp_(min=0)
            out[:, 1].clamp_(max=width - 1)
            out[:, 2].clamp_(min=0)
            out[:, 3].clamp_(max=height - 1)
            return out

        candidates = rect(rx, ry)
        candidates[level < 0, 1] = -1  # empty
        return rect(r, r), candidates


# ----------------------------------------------------------------------------- tiling


@dataclass
class _Tiling:
    """(tile, Gaussian) records sorted by (tile, depth), each clipped to its tile, and the chunks.

    Pixels are numbered tile-major: pixel ``(x, y)`` of tile ``t`` is ``t * ts^2 + (y % ts) * ts + x % ts``
    (``ts`` the tile size). A chunk is a run of whole tiles ``[t0, t1)`` with fewer than ``_KEY_LIMIT``
    pixels; its pixel keys ``(t - t0) * ts^2 + ...`` and one past them (the sort's sentinel) fit int16.
    """

    gauss: torch.Tensor  # [R] int64 Gaussian (index into the depth-sorted arrays)
    x0: torch.Tensor  # [R] int64 first pixel column of the clipped rectangle
    wx: torch.Tensor  # [R] int64 its width in pixels
    y0: torch.Tensor  # [R] int64 first pixel row
    rows: torch.Tensor  # [R] int64 its height in pixels
    key0: torch.Tensor  # [R] int64 chunk-local key of pixel (x0, y0); (x, y) has key0 + (y - y0) ts + x - x0
    tile: torch.Tensor  # [R] int64 tile index
    rank: torch.Tensor  # [R] int64 depth rank of the record among its tile's records
    chunks: list[tuple[int, int, int, int]]  # (first record, end record, first tile, end tile), non-empty ones
    tile_size: int
    tiles_x: int
    tiles_y: int


_KEY_LIMIT = 1 << 15  # pixels per chunk, sentinel included: int16 sort keys (about 1.4x faster than int32)


def _bin_tiles(rect: torch.Tensor, width: int, height: int, tile_size: int) -> _Tiling:
    """Bin rectangles ``rect`` ``[M, 4]`` (x0, x1, y0, y1 inclusive; Gaussians already in depth order)
    into tiles."""
    dev = rect.device
    ts, tp = tile_size, tile_size * tile_size
    tiles_x, tiles_y = (width + ts - 1) // ts, (height + ts - 1) // ts
    n_tiles = tiles_x * tiles_y
    ids = ((rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])).nonzero().squeeze(1)  # non-empty
    x0, x1, y0, y1 = rect.index_select(0, ids).unbind(-1)
    tx0, ty0 = x0 // ts, y0 // ts
    ntx = x1 // ts - tx0 + 1
    n_rec = ntx * (y1 // ts - ty0 + 1)  # [M'] tiles per rectangle
    owner = torch.repeat_interleave(torch.arange(ids.numel(), device=dev), n_rec)  # [R] in depth order
    local = torch.arange(owner.numel(), device=dev) - torch.repeat_interleave(torch.cumsum(n_rec, 0) - n_rec, n_rec)
    ntx_r = ntx.index_select(0, owner)
    dty = local // ntx_r
    tx = tx0.index_select(0, owner) + local - dty * ntx_r
    ty = ty0.index_select(0, owner) + dty
    tile32, order = torch.sort((ty * tiles_x + tx).int(), stable=True)  # stable: depth order kept per tile
    tile = tile32.long()
    owner, tx, ty = (t.index_select(0, order) for t in (owner, tx, ty))
    rx0 = torch.maximum(x0.index_select(0, owner), tx * ts)
    rx1 = torch.minimum(x1.index_select(0, owner), tx * ts + ts - 1)
    ry0 = torch.maximum(y0.index_select(0, owner), ty * ts)
    ry1 = torch.minimum(y1.index_select(0, owner), ty * ts + ts - 1)
    per_tile = torch.bincount(tile, minlength=n_tiles)
    tile_start = torch.cumsum(per_tile, 0) - per_tile  # [T] first record of each tile
    rank = torch.arange(tile.numel(), device=dev) - tile_start.index_select(0, tile)
    span = max(1, (_KEY_LIMIT - 1) // tp)  # tiles per chunk
    t0 = tile // span * span
    key0 = (tile - t0) * tp + (ry0 - ty * ts) * ts + (rx0 - tx * ts)
    bounds = torch.cat([tile_start[::span], tile_start.new_tensor([tile.numel()])]).tolist()
    chunks = [(bounds[c], bounds[c + 1], c * span, min((c + 1) * span, n_tiles))
              for c in range(len(bounds) - 1) if bounds[c + 1] > bounds[c]]
    return _Tiling(ids.index_select(0, owner), rx0, rx1 - rx0 + 1, ry0, ry1 - ry0 + 1, key0, tile, rank, chunks,
                   ts, tiles_x, tiles_y)


# ----------------------------------------------------------------------------- pairs


@dataclass
class _Pass:
    """The drawn (pixel, Gaussian) pairs of one depth-rank pass over a chunk, sorted by (pixel, depth):
    alpha >= ALPHA_MIN and, with early termination, in front of their pixel's termination point."""

    rec: torch.Tensor  # [P] int32 chunk-local record (index into the chunk's records)
    key: torch.Tensor  # [P] int32 chunk-local tile-major pixel
    alpha: torch.Tensor  # [P] min(ALPHA_MAX, o G)
    w: torch.Tensor  # [P] alpha T_before
    frozen: torch.Tensor  # [P] bool: alpha clamped at ALPHA_MAX (no gradient through it)
    crow: torch.Tensor  # [B + 1] int32 first pair of each of the chunk's B pixels (CSR row pointers)

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in vars(self).values())


_PAIR_BUDGET = 1 << 21  # candidate (pixel, Gaussian) pairs expanded at once (~45 bytes of temporaries each)
_CACHE_BYTES = 512 << 20  # pair data kept from forward for backward; chunks beyond it are recomputed
_PASS_FIRST = 64  # with early termination, the first chunk's first pass takes each tile's records up to this
# depth rank; later chunks start where half of the previous chunk's tiles terminated; each further pass doubles it


@dataclass
class _Geometry:
    """Per-Gaussian coefficients of the exponent, ``log(o G) = A dx^2 + (-b dy) dx + (-c/2 dy^2 + log o)``
    with ``(dx, dy)`` pixel centre - mean (all ``[M]``, working dtype)."""

    u: torch.Tensor
    v: torch.Tensor
    a_half: torch.Tensor  # -a / 2
    b: torch.Tensor
    c_half: torch.Tensor  # -c / 2
    log_o: torch.Tensor

    @staticmethod
    def of(means2d: torch.Tensor, conic: torch.Tensor, opacity: torch.Tensor) -> _Geometry:
        u, v = means2d.detach().unbind(-1)
        a, b, c = conic.detach().unbind(-1)
        return _Geometry(u, v, -0.5 * a, b, -0.5 * c, torch.log(opacity.detach()))

    def take(self, idx: torch.Tensor) -> _Geometry:
        """The coefficients of the Gaussians ``idx``."""
        return _Geometry(*(t.index_select(0, idx) for t in vars(self).values()))


def _candidates(
    tiling: _Tiling, chunk: tuple[int, int, int, int], geo: _Geometry, recs: torch.Tensor, done: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pairs with ``o G >= ALPHA_MIN`` of the chunk's records ``recs`` (ascending chunk-local int64;
    ``geo`` holds the chunk's records' coefficients) whose pixel is not ``done`` (``[B]`` bool or None),
    stably sorted by pixel: chunk-local key (int32), chunk-local record (int32), ``o G`` (unclamped).

    Expanded per pixel row of each record, each row cut to the columns where alpha can reach
    ``ALPHA_MIN`` (the roots of the exponent, a quadratic in the column, with a margin) and to the span
    of its pixel row's live pixels, then per pixel."""
    r0, _, t0, t1 = chunk
    dev, dtype = geo.u.device, geo.u.dtype
    ts = tiling.tile_size
    n_keys = (t1 - t0) * ts * ts
    rows = tiling.rows[r0:].index_select(0, recs)
    n_rows = int(rows.sum())
    row_rec = torch.repeat_interleave(recs, rows, output_size=n_rows)  # [rows] record of each row
    dy_px = torch.arange(n_rows, device=dev).sub_(
        torch.repeat_interleave(torch.cumsum(rows, 0) - rows, rows, output_size=n_rows))
    k0 = tiling.key0[r0:].index_select(0, recs)
    col0 = torch.repeat_interleave(k0 % ts, rows, output_size=n_rows)  # [rows] first column within the tile
    trow = torch.repeat_interleave(k0 // ts, rows, output_size=n_rows).add_(dy_px)  # [rows] pixel row: key // ts
    col1 = tiling.wx[r0:].index_select(0, row_rec).add_(col0).sub_(1)  # [rows] last column
    # per row: log(o G) = (A dx + B) dx + C with dx = ox + the column within the tile
    dy = (tiling.y0[r0:].index_select(0, row_rec) + dy_px).to(dtype).add_(0.5).sub_(geo.v.index_select(0, row_rec))
    a_half = geo.a_half.index_select(0, row_rec)
    b_row = geo.b.index_select(0, row_rec).mul_(dy).neg_()
    c_row = geo.c_half.index_select(0, row_rec).mul_(dy).mul_(dy).add_(geo.log_o.index_select(0, row_rec))
    ox = (tiling.x0[r0:].index_select(0, row_rec) - col0).to(dtype).add_(0.5).sub_(geo.u.index_select(0, row_rec))
    del dy_px, dy
    # columns with (A dx + B) dx + C >= log ALPHA_MIN: dx = (B -+ sqrt(B^2 + 4 A' (C - log ALPHA_MIN))) / (-2 A)
    # (A' = -A > 0), widened by a margin (the exact test below decides)
    inv = a_half.reciprocal().mul_(-0.5)
    root = (c_row - math.log(ALPHA_MIN)).mul_(a_half).mul_(-4).add_(b_row * b_row).clamp_(min=0).sqrt_().mul_(inv)
    mid = (b_row * inv).sub_(ox)
    margin = (mid.abs() + root + ox.abs()).mul_(1e-5).add_(1e-3)
    col0 = torch.maximum(col0, (mid - root - margin).clamp_(-1, ts).ceil_().long())
    col1 = torch.minimum(col1, (mid + root + margin).clamp_(-1, ts).floor_().long())
    del inv, root, mid, margin
    if done is not None:  # cut to the first and last live pixel of the pixel row
        live = (~done).view(-1, ts)
        first = torch.where(live.any(1), live.to(torch.uint8).argmax(1), ts)  # argmax: the first maximum
        last = ts - 1 - live.flip(1).to(torch.uint8).argmax(1)
        col0 = torch.maximum(col0, first.index_select(0, trow))
        col1 = torch.minimum(col1, last.index_select(0, trow))
        del live, first, last
    wx = col1.sub_(col0).add_(1).clamp_(min=0)
    # per pixel
    n = int(wx.sum())
    pr = torch.repeat_interleave(torch.arange(n_rows, device=dev, dtype=torch.int32), wx.int(), output_size=n)
    col = torch.arange(n, device=dev, dtype=torch.int32).sub_((torch.cumsum(wx, 0) - wx - col0).int().index_select(0, pr))
    dx = ox.index_select(0, pr).add_(col)
    raw = torch.exp_(a_half.index_select(0, pr).mul_(dx).add_(b_row.index_select(0, pr)).mul_(dx)
                     .add_(c_row.index_select(0, pr)))
    del dx
    key = trow.mul_(ts).int().index_select(0, pr).add_(col)
    rec = row_rec.int().index_select(0, pr)
    del col, pr
    valid = raw >= ALPHA_MIN
    if done is not None:
        valid &= ~done.index_select(0, key)
    n_valid = int(valid.sum())
    # dropped pairs get the sentinel key n_keys and sort last: no compaction before the sort
    key_dtype = torch.int16 if n_keys < (1 << 15) else torch.int32
    skey, order = torch.sort(key.masked_fill_(~valid, n_keys).to(key_dtype), stable=True)
    order = order[:n_valid]
    return skey[:n_valid].int(), rec.index_select(0, order), raw.index_select(0, order)


def _chunk_passes(
    tiling: _Tiling, chunk: tuple[int, int, int, int], geo: _Geometry, transmittance_min: float, first: int,
) -> tuple[list[_Pass], int]:
    """Expand one chunk's records into their drawn (pixel, Gaussian) pairs, in passes of depth rank.

    Per pass: expand the candidate pairs of the records whose depth rank lies in a window, drop those
    with alpha < 1/255, stable-sort them by pixel (int16 keys; each pixel's run stays in depth order)
    and get every pair's transmittance from one segmented scan of ``log(1 - alpha)`` (float64 prefix
    sums), continued from the pixel's transmittance after the earlier passes. A window holds at most
    ``_PAIR_BUDGET`` candidates; with ``transmittance_min > 0`` the first ends at rank ``first`` and each
    next one at twice the previous end, the pairs behind a pixel's termination point are dropped
    (later passes skip a terminated pixel before its exp), and a tile whose pixels have all terminated
    takes part in no further pass (the 3DGS block's early exit).

    Returns the passes (front to back) and the end rank of the pass after which half of the chunk's
    tiles had terminated (the next chunk's ``first``; the last pass's end when fewer did).
    """
    r0, r1, t0, t1 = chunk
    dev, dtype = geo.u.device, geo.u.dtype
    ts, tp = tiling.tile_size, tiling.tile_size**2
    n_keys = (t1 - t0) * tp
    terminate = transmittance_min > 0
    log_t_min = math.log(transmittance_min) if terminate else -math.inf
    rank = tiling.rank[r0:r1]
    tile = tiling.tile[r0:r1] - t0
    wx, rows = tiling.wx[r0:r1], tiling.rows[r0:r1]
    # candidates with depth rank < r, for the windows' budget
    by_rank = torch.zeros(int(rank.max()) + 2, dtype=torch.float64, device=dev)
    count = (wx * rows).double()
    torch.cumsum(torch.bincount(rank, weights=count), 0, out=by_rank[1:])
    cum = by_rank.tolist()
    max_rank = len(cum) - 2
    done: torch.Tensor | None = None  # [n_keys] bool: pixel terminated or outside every candidate rectangle
    if terminate:  # pixels no record covers (padding included) count as terminated from the start
        lx0, ly0 = tiling.key0[r0:r1] % ts, tiling.key0[r0:r1] % tp // ts
        corner = tile * (ts + 1) ** 2 + ly0 * (ts + 1) + lx0  # rectangle corners in [tiles, ts + 1, ts + 1]
        diff = torch.zeros((t1 - t0) * (ts + 1) ** 2, dtype=torch.int32, device=dev)
        ones = torch.ones_like(corner, dtype=torch.int32)
        for offset, sign in ((0, 1), (wx, -1), (rows * (ts + 1), -1), (rows * (ts + 1) + wx, 1)):
            diff.index_add_(0, corner + offset, ones, alpha=sign)
        cover = diff.view(-1, ts + 1, ts + 1).cumsum(1).cumsum(2)[:, :ts, :ts]
        done = (cover == 0).reshape(-1)
    geo_rec = geo.take(tiling.gauss[r0:r1])
    log_t_pix = torch.zeros(n_keys, dtype=torch.float64, device=dev)  # log T of every pixel after the passes so far
    n_empty = int((torch.bincount(tile, minlength=t1 - t0) == 0).sum())  # tiles without records: done at once
    passes: list[_Pass] = []
    lo, target, half_at = 0, (first if terminate else max_rank + 1), None
    while lo <= max_rank:
        hi = min(target, max(lo + 1, bisect.bisect_right(cum, cum[lo] + _PAIR_BUDGET) - 1))
        if lo == 0 and hi > max_rank and not terminate:
            recs = torch.arange(r1 - r0, device=dev)
        else:
            sel = rank >= lo
            if done is not None:
                sel &= ~done.view(-1, tp).all(1).index_select(0, tile)
            left = float((count * sel).sum())  # candidates of the records left in live tiles
            if left == 0:
                break
            if left <= _PAIR_BUDGET // 4:  # a short tail: one pass (fewer ops beat a tighter window)
                hi = max_rank + 1
            recs = (sel & (rank < hi)).nonzero().squeeze(1)
        key, rec, raw = _candidates(tiling, chunk, geo_rec, recs, done)
        frozen = raw > ALPHA_MAX
        alpha = raw.clamp_(max=ALPHA_MAX)
        # segmented inclusive scan of log(1 - alpha) in float64 (a chunk-wide prefix sum would cancel in float32)
        log_t = torch.log1p(-alpha).double()  # transcendentals in the working dtype (float64 ones are slow)
        log_after = torch.cumsum(log_t, 0)
        crow = torch.zeros(n_keys + 1, dtype=torch.int64, device=dev)
        torch.cumsum(torch.bincount(key, minlength=n_keys), 0, out=crow[1:])
        # per pixel: the prefix before its run, less its log T after the earlier passes
        start = torch.cat([log_after.new_zeros(1), log_after]).index_select(0, crow[:-1]).sub_(log_t_pix)
        log_after.sub_(start.index_select(0, key))
        w = torch.exp((log_after - log_t).to(dtype)).mul_(alpha)
        drawn_crow = crow
        if terminate:
            stop = log_after < log_t_min  # monotone along a pixel's run: a suffix of it
            if bool(stop.any()):  # a pixel stopped iff its run's last pair did: O(pixels), not O(pairs)
                assert done is not None
                done |= stop.index_select(0, (crow[1:] - 1).clamp_(min=0)) & (crow[1:] > crow[:-1])
                drawn = (~stop).nonzero().squeeze(1)
                key, rec, alpha, frozen, w = (t.index_select(0, drawn) for t in (key, rec, alpha, frozen, w))
                drawn_crow = torch.zeros_like(crow)
                torch.cumsum(torch.bincount(key, minlength=n_keys), 0, out=drawn_crow[1:])
        if hi <= max_rank and log_after.numel():  # each pixel's log T after its last drawn pair (the next pass's start)
            n_drawn = drawn_crow[1:] - drawn_crow[:-1]
            last = log_after.index_select(0, (crow[:-1] + n_drawn - 1).clamp_(min=0))
            log_t_pix = torch.where(n_drawn > 0, last, log_t_pix)
        crow = drawn_crow
        if key.numel():
            passes.append(_Pass(rec, key, alpha, w, frozen, crow.int()))
        if done is not None:
            tiles_done = int(done.view(-1, tp).all(1).sum())
            if half_at is None and 2 * (tiles_done - n_empty) >= t1 - t0 - n_empty:
                half_at = hi
            if tiles_done == t1 - t0:
                break
        lo = hi
        if lo >= target:
            target *= 2
    return passes, max(_PASS_FIRST, hi if half_at is None else half_at)


def _to_tiles(img: torch.Tensor, tiling: _Tiling, width: int, height: int) -> torch.Tensor:
    """``[C, H * W]`` row-major pixels -> ``[C, tiles * ts^2]`` tile-major (padding pixels zero)."""
    ts, nx, ny = tiling.tile_size, tiling.tiles_x, tiling.tiles_y
    padded = torch.nn.functional.pad(img.reshape(-1, height, width), (0, nx * ts - width, 0, ny * ts - height))
    return padded.reshape(-1, ny, ts, nx, ts).permute(0, 1, 3, 2, 4).reshape(img.shape[0], -1).contiguous()


def _from_tiles(tm: torch.Tensor, tiling: _Tiling, width: int, height: int) -> torch.Tensor:
    """``[tiles * ts^2, C]`` tile-major -> ``[C, H * W]`` row-major."""
    ts, nx, ny = tiling.tile_size, tiling.tiles_x, tiling.tiles_y
    img = tm.reshape(ny, nx, ts, ts, -1).permute(4, 0, 2, 1, 3).reshape(-1, ny * ts, nx * ts)
    return img[:, :height, :width].reshape(tm.shape[1], -1)


def _pixel_centres(tiling: _Tiling, t0: int, t1: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``[2, (t1 - t0) ts^2]`` x and y of the centres of the tiles ``[t0, t1)``'s pixels, tile-major."""
    ts, tp = tiling.tile_size, tiling.tile_size**2
    cells = torch.arange(t0 * tp, t1 * tp, device=device)
    tile, in_tile = cells // tp, cells % tp
    return torch.stack([(tile % tiling.tiles_x) * ts + in_tile % ts, (tile // tiling.tiles_x) * ts + in_tile // ts]).to(dtype).add_(0.5)


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of per-Gaussian features over the tiled pairs."""

    @staticmethod
    def forward(
        ctx: Any, means2d: torch.Tensor, conic: torch.Tensor, opacity: torch.Tensor,
        feats: torch.Tensor, tiling: _Tiling, width: int, height: int, t_min: float,
    ) -> torch.Tensor:
        """``[M, 2]`` means (px), ``[M, 3]`` conics, ``[M]`` opacities, ``[M, F]`` features -> ``[F, H W]``
        sum over each pixel's drawn pairs of ``w feats``."""
        tp = tiling.tile_size**2
        geo = _Geometry.of(means2d, conic, opacity)
        out = feats.new_zeros(tiling.tiles_x * tiling.tiles_y * tp, feats.shape[1])  # tile-major [T ts^2, F]
        cached: list[list[_Pass] | None] = []
        firsts: list[int] = []
        cache_left = _CACHE_BYTES if any(ctx.needs_input_grad[:4]) else 0
        first = _PASS_FIRST
        for chunk in tiling.chunks:
            r0, r1, t0, t1 = chunk
            firsts.append(first)
            with torch.profiler.record_function("splatter.expand_pairs"):
                passes, first = _chunk_passes(tiling, chunk, geo, t_min, first)
            with torch.profiler.record_function("splatter.accumulate"):
                # out[pixel] += w feats[record's Gaussian]: each pass's pairs are sorted by pixel, a CSR [B, R_c]
                feats_rec = feats.index_select(0, tiling.gauss[r0:r1])
                acc = out[t0 * tp:t1 * tp]
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
                    for p in passes:
                        weights = torch.sparse_csr_tensor(p.crow, p.rec, p.w, (acc.shape[0], r1 - r0),
                                                          check_invariants=False)
                        acc += weights @ feats_rec
            size = sum(p.nbytes() for p in passes)
            keep = size <= cache_left
            cache_left -= size if keep else 0
            cached.append(passes if keep else None)
        ctx.tiling, ctx.width, ctx.height, ctx.cached, ctx.firsts, ctx.t_min = (
            tiling, width, height, cached, firsts, t_min)
        ctx.save_for_backward(means2d, conic, opacity, feats)
        return _from_tiles(out, tiling, width, height)

    @staticmethod
    @once_differentiable
    def backward(
        ctx: Any, grad_out: torch.Tensor,
    ) -> tuple[torch.Tensor | None, ...]:
        """Per pass, back to front: ``dL/dw`` of each pair, the 3DGS suffix sums (a reverse segmented scan
        continued across passes), then per-record sums of the pairs' terms, scattered to the Gaussians
        once per chunk."""
        means2d, conic, opacity, feats = ctx.saved_tensors
        tiling: _Tiling = ctx.tiling
        tp = tiling.tile_size**2
        dtype, dev = feats.dtype, feats.device
        geo = _Geometry.of(means2d, conic, opacity)
        grad_tm = _to_tiles(grad_out, tiling, ctx.width, ctx.height)  # [F, T ts^2]
        feats_t = feats.t().contiguous()
        nf = feats.shape[1]
        # [F + 6, M]: dL/dfeats; then dL/d(u, v, conic a, b, c, opacity)
        grads = feats.new_zeros(nf + 6, feats.shape[0])
        need_uv = ctx.needs_input_grad[0]
        for i, chunk in enumerate(tiling.chunks):
            r0, r1, t0, t1 = chunk
            passes = ctx.cached[i]
            if passes is None:
                with torch.profiler.record_function("splatter.expand_pairs"):
                    passes, _ = _chunk_passes(tiling, chunk, geo, ctx.t_min, ctx.firsts[i])
            with torch.profiler.record_function("splatter.backward_pairs"):
                g_rec = tiling.gauss[r0:r1]
                feats_rec = feats_t.index_select(1, g_rec)  # [F, R_c]
                u_rec, v_rec = geo.u.index_select(0, g_rec), geo.v.index_select(0, g_rec)
                grad_c = grad_tm[:, t0 * tp:t1 * tp]
                centre = _pixel_centres(tiling, t0, t1, dtype, dev)
                # per record: [F] sum of w dL/dout, then sums of g, g dx, g dy, g dx^2, g dx dy, g dy^2 with
                # g = dL/dpower the gradient of the pair's exponent
                acc = feats.new_zeros(nf + 6, r1 - r0)
                behind_pix = torch.zeros(t1 * tp - t0 * tp, dtype=torch.float64, device=dev)  # sum of w f of later passes
                for p in reversed(passes):
                    rec, key, w = p.rec, p.key, p.w
                    f = torch.zeros_like(w)  # dL/dw per pair: feats . grad_out at the pixel
                    for k in range(nf):
                        g_pix = grad_c[k].index_select(0, key)
                        f.addcmul_(feats_rec[k].index_select(0, rec), g_pix)
                        acc[k].index_add_(0, rec, g_pix.mul_(w))
                    # dL/dalpha_k = T_k f_k - (sum_{j > k} w_j f_j) / (1 - alpha_k): reverse segmented scan; then
                    # dL/dpower = alpha dL/dalpha = w f - alpha / (1 - alpha) sum_{j > k} w_j f_j (0 where frozen)
                    wf = f.mul_(w)
                    csum = torch.cumsum(wf.double(), 0)
                    ends = torch.cat([csum.new_zeros(1), csum]).index_select(0, p.crow)  # [B + 1]
                    behind = (ends[1:] + behind_pix).index_select(0, key).sub_(csum).to(dtype)
                    behind_pix += ends[1:] - ends[:-1]
                    g = wf.sub_(behind.mul_(p.alpha).div_(1 - p.alpha)).masked_fill_(p.frozen, 0.0)
                    del f, csum, behind
                    dx = centre[0].index_select(0, key).sub_(u_rec.index_select(0, rec))
                    dy = centre[1].index_select(0, key).sub_(v_rec.index_select(0, rec))
                    gdx, gdy = g * dx, g * dy
                    terms = (g, gdx, gdy, gdx * dx, gdx * dy, gdy * dy)
                    for row in range(6) if need_uv else (0, 3, 4, 5):
                        acc[nf + row].index_add_(0, rec, terms[row])
                # power = A dx^2 - b dx dy - c/2 dy^2 + ..., dx = x - u: d power / d u = a dx + b dy, / d v = c dy + b dx
                a, b, c = conic.detach().index_select(0, g_rec).t()
                s, sx, sy, sxx, sxy, syy = acc[nf:]
                per_rec = torch.stack([a * sx + b * sy, c * sy + b * sx, -0.5 * sxx, -sxy, -0.5 * syy,
                                       s / opacity.detach().index_select(0, g_rec)])
                grads[nf:].index_add_(1, g_rec, per_rec)
                grads[:nf].index_add_(1, g_rec, acc[:nf])
        return (grads[nf:nf + 2].t() if need_uv else None, grads[nf + 2:nf + 5].t(), grads[nf + 5], grads[:nf].t(),
                None, None, None, None)


# ----------------------------------------------------------------------------- public API


def _check_inputs(means, scales, rotations, opacities, colors, camera, background) -> int:
    floats = (torch.float32, torch.float64)
    n = check_tensor("means", means, ["N", 3], dtypes=floats, finite=True)["N"]
    dims = {"N": n}
    check_tensor("scales", scales, ["N", 3], dtypes=(means.dtype,), finite=True, dims=dims)
    check_tensor("rotations", rotations, ["N", 4], dtypes=(means.dtype,), finite=True, dims=dims)
    check_tensor("opacities", opacities, ["N"], dtypes=(means.dtype,), finite=True, dims=dims)
    check_tensor("colors", colors, ["N", 3], dtypes=(means.dtype,), finite=True, dims=dims)
    if not isinstance(camera, Camera):
        raise InputValueError(f"camera must be a controlgs_adapter.state.Camera, got {type(camera).__name__}")
    tensors = dict(means=means, scales=scales, rotations=rotations, opacities=opacities, colors=colors)
    if background is not None:
        check_tensor("background", background, [3], dtypes=(means.dtype,), finite=True)
        tensors["background"] = background
    check_same_device(**tensors)
    if n:
        if bool((scales < 0).any()):
            raise InputValueError(f"scales must be >= 0 (linear, not log), got min {float(scales.min()):.4g}")
        if bool(((opacities < 0) | (opacities > 1)).any()):
            raise InputValueError(
                f"opacities must lie in [0, 1], got range [{float(opacities.min()):.4g}, {float(opacities.max()):.4g}]"
            )
        if bool((rotations.detach().norm(dim=-1) == 0).any()):
            raise InputValueError("rotations must be non-zero quaternions (w, x, y, z), got an all-zero row")
    return n


def rasterize(
    means: torch.Tensor,
    scales: torch.Tensor,
    rotations: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    camera: Camera,
    background: torch.Tensor | None = None,
    *,
    tile_size: int = 16,
    transmittance_min: float = TRANSMITTANCE_MIN,
) -> RasterOutput:
    """Render 3D Gaussians with EWA splatting and front-to-back alpha compositing.

    Args:
        means: ``[N, 3]`` world-space centres.
        scales: ``[N, 3]`` standard deviations along the local axes (linear, >= 0; zero is allowed:
            the low-pass filter keeps the footprint at least ~0.55 px).
        rotations: ``[N, 4]`` quaternions ``(w, x, y, z)``, normalised here (non-zero).
        opacities: ``[N]`` in [0, 1].
        colors: ``[N, 3]`` any finite values (not clamped).
        camera: ``Camera`` (OpenCV axes; ``world_to_camera`` ``[4, 4]``, ``intrinsics`` ``[3, 3]``
            in pixels at ``camera.width`` x ``camera.height``).
        background: ``[3]`` colour behind everything (default black).
        tile_size: tile edge in pixels used to bin the footprints; memory chunks are whole tiles, so a
            tile much larger than 16 raises the peak memory (affects speed and memory only, never the image).
        transmittance_min: early termination (3DGS: 1e-4, the default): a pixel stops compositing at the
            first splat that would take its transmittance below this, and neither that splat nor any
            behind it is drawn (nor costs time in forward or backward). ``0`` composites every splat
            (exact). A terminated pixel's colour, alpha and depth differ from the exact ones by at most
            ``T_stop max|f - f_background|``, with ``T_stop = 1 - alpha`` its remaining transmittance,
            ``< transmittance_min / (1 - ALPHA_MAX)`` (``f`` the colours, depths and 1 of the splats not drawn).

    Returns:
        ``RasterOutput(color [3, H, W], alpha [1, H, W], depth [1, H, W], visible [N] bool)``, with
        ``H, W = camera.height, camera.width``. All tensors share the dtype (float32 or float64) and
        device of ``means``; gradients flow to means, scales, rotations, opacities, colors and background.

    Conventions (3DGS, Kerbl et al. 2023; shared with ``rasterize_reference``):
        * camera-space mean ``p = R_wc mu + t_wc``; depth ``z = p_z``; Gaussians with
          ``z <= NEAR_PLANE`` (0.2, scene units) are culled;
        * projected mean ``(u, v) = (fx p_x / z + cx, fy p_y / z + cy)`` in pixels, pixel ``(i, j)``
          centred at ``(i + 0.5, j + 0.5)``;
        * 3D covariance ``Sigma = R(q) diag(s)^2 R(q)^T``; 2D covariance
          ``J R_wc Sigma R_wc^T J^T + 0.3 I`` (px^2), the Jacobian evaluated at the mean with
          ``p_x / z``, ``p_y / z`` clamped to the image widened by 15 % of its size per side;
        * footprint: the pixels whose centre lies within ``3 sqrt(lambda_max)`` of ``(u, v)`` along
          both axes (``lambda_max`` the largest eigenvalue of the 2D covariance); ``visible`` marks the
          Gaussians with a non-empty footprint in the image;
        * ``alpha_i = min(0.99, o_i exp(-0.5 d^T Sigma_2D^-1 d))``, ``d`` = pixel centre - ``(u, v)``;
          splats with ``alpha_i < 1/255`` are skipped;
        * per pixel, splats in ascending ``z`` (ties: input order); ``T_i = prod_{j<i} (1 - alpha_j)``;
          splat ``i`` is drawn only if ``T_i (1 - alpha_i) >= transmittance_min`` (default 1e-4), and
          nothing behind the first that is not; ``w_i = alpha_i T_i``;
        * ``color = sum_i w_i c_i + T_final background``, ``alpha = 1 - T_final = sum_i w_i``,
          ``depth = sum_i w_i z_i``.
        The cut-offs (near plane, footprint, 1/255, 1e-4, 0.99 clamp) have zero gradient.

    Differences from the 3DGS CUDA rasteriser (all at the level of single low-alpha pixels): the
    footprint test is per pixel, not per 16 px tile (3DGS also draws a splat in the parts of the
    tiles it touches that lie outside its square); ``lambda_max`` is exact (3DGS floors the
    discriminant at 0.1 and rounds the radius up to whole pixels); the 2D determinant is computed
    without cancellation (``|j0 x j1|^2 + ...``), which keeps needle-like Gaussians near the camera
    right in float32.

    Supersampling: render at ``camera`` and area-pool (``downstream.resample.area_resample``), or
    render directly at ``camera.scaled(d)``.
    """
    n = _check_inputs(means, scales, rotations, opacities, colors, camera, background)
    if not (isinstance(tile_size, int) and tile_size >= 1):
        raise InputValueError(f"tile_size must be a positive int, got {tile_size!r}")
    if not (isinstance(transmittance_min, (int, float)) and 0 <= transmittance_min < 1):
        raise InputValueError(f"transmittance_min must be a number in [0, 1), got {transmittance_min!r}")
    width, height = camera.width, camera.height
    dtype, dev = means.dtype, means.device
    w2c = camera.world_to_camera.to(device=dev, dtype=dtype)
    k = camera.intrinsics.to(device=dev, dtype=dtype)
    with torch.profiler.record_function("splatter.project"):
        means_cam = means @ w2c[:3, :3].t() + w2c[:3, 3]  # [N, 3]
        front = (means_cam[:, 2] > NEAR_PLANE).nonzero().squeeze(1)  # [M0]
        means2d, cov2d, conic = project_gaussians(
            means_cam.index_select(0, front), scales.index_select(0, front), rotations.index_select(0, front),
            w2c, k, width, height,
        )
        rect, candidates = _footprints(means2d, cov2d, opacities.index_select(0, front), width, height)
        on_screen = ((rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])).nonzero().squeeze(1)
        idx = front.index_select(0, on_screen)  # [M]
        visible = torch.zeros(n, dtype=torch.bool, device=dev).index_fill_(0, idx, True)
    with torch.profiler.record_function("splatter.bin"):
        z = means_cam[:, 2].index_select(0, idx)  # [M]
        order = torch.argsort(z.detach(), stable=True)  # front to back; ties keep the input order
        sel, idx, z = on_screen.index_select(0, order), idx.index_select(0, order), z.index_select(0, order)
        feats = torch.cat([colors.index_select(0, idx), z.unsqueeze(-1), torch.ones_like(z).unsqueeze(-1)], dim=-1)  # [M, 5]
        tiling = _bin_tiles(candidates.index_select(0, sel), width, height, tile_size)
    out = _Composite.apply(means2d.index_select(0, sel), conic.index_select(0, sel), opacities.index_select(0, idx),
                           feats, tiling, width, height, float(transmittance_min))
    out = out.reshape(5, height, width)
    alpha = out[4:5]
    color = out[:3]
    if background is not None:
        color = color + (1 - alpha) * background.view(3, 1, 1)
    return RasterOutput(color=color, alpha=alpha, depth=out[3:4], visible=visible)
