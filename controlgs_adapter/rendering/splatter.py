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
   (so (tile, depth) order), and cut the tiles into chunks of about ``_PAIR_BUDGET`` candidate
   (pixel, Gaussian) pairs and at most ``2^15`` pixels, so that memory is bounded whatever the scene
   (never a dense [pixels x Gaussians] tensor) and a chunk's pixels, numbered tile-major, fit int16;
3. [expand_pairs] per chunk, expand the records into their (pixel, Gaussian) pairs, drop those with
   alpha < 1/255, stable-sort them by pixel with int16 keys (each pixel's run stays in depth order)
   and get every pair's transmittance from one segmented scan of ``log(1 - alpha)`` (float64 prefix
   sums); per-chunk work is proportional to the chunk's pairs and pixels, never to the image. Early
   termination (``transmittance_min``, 3DGS's ``T < 1e-4``): the records are taken in passes of
   doubling depth rank per tile, the pairs behind each pixel's termination point are dropped here,
   before anything is accumulated or kept for backward, terminated pixels are skipped before the
   exp of later passes and terminated tiles expand no further records;
4. [accumulate] ``sum_i w_i f_i`` per pixel is one sparse CSR [chunk pixels x Gaussians] @
   [Gaussians x 5] product (colour, depth, alpha);
5. [backward_pairs] the compositing is a ``torch.autograd.Function`` with a hand-written backward
   (the 3DGS back-to-front suffix sums as a reverse segmented scan, then scatter-adds to the
   Gaussians); a chunk's drawn pairs (17 bytes each: Gaussian, pixel, alpha, weight, clamp flag; offsets
   recomputed from the pixel) are kept for it while they fit in ``_CACHE_BYTES``, the others are
   recomputed (as the CUDA kernel does).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

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
]

NEAR_PLANE = 0.2  # Gaussians with camera-space z <= this are culled (3DGS ``in_frustum``)
LOW_PASS = 0.3  # px^2 added to the diagonal of every 2D covariance (3DGS anti-aliasing filter)
EXTENT_SIGMAS = 3.0  # footprint half-width, in standard deviations along the major axis
FRUSTUM_MARGIN = 0.15  # the Jacobian's x/z, y/z are clamped to the image +- this fraction of its size
ALPHA_MAX = 0.99  # per-splat alpha clamp
ALPHA_MIN = 1.0 / 255.0  # splats with alpha below this are skipped
TRANSMITTANCE_MIN = 1e-4  # default of rasterize's transmittance_min (early termination, as 3DGS)

_PAIR_BUDGET = 1 << 20  # candidate (pixel, Gaussian) pairs expanded at once (~50 bytes of temporaries each)
_CACHE_BYTES = 512 << 20  # pair data kept from forward for backward; chunks beyond it are recomputed


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
    (``ts`` the tile size); a chunk is a run of whole tiles ``[t0, t1)``, its pairs' keys
    ``(t - t0) * ts^2 + ...`` fit in int16 (fast stable sort) whenever ``(t1 - t0) ts^2 <= 2^15``.
    """

    gauss: torch.Tensor  # [R] int64 Gaussian (index into depth-sorted arrays)
    x0: torch.Tensor  # [R] int64 first pixel column of the clipped rectangle
    x1: torch.Tensor  # [R] int64 last pixel column
    y0: torch.Tensor  # [R] int64 first pixel row
    rows: torch.Tensor  # [R] int64 pixel rows of the rectangle
    key_base: torch.Tensor  # [R] int64 key of pixel (x, y) in its chunk = key_base + y * ts + x
    tile: torch.Tensor  # [R] int64 tile index
    rank: torch.Tensor  # [R] int64 depth rank of the record among its tile's records
    chunks: list[tuple[int, int, int, int]]  # (first record, end record, first tile, end tile)
    tile_size: int
    tiles_x: int
    tiles_y: int


_KEY_LIMIT = 1 << 15  # pixels per chunk for int16 sort keys


def _bin_tiles(rect: torch.Tensor, width: int, height: int, tile_size: int) -> _Tiling:
    """Bin rectangles ``rect`` ``[M, 4]`` (Gaussians already in depth order) into tiles."""
    dev = rect.device
    ts, tp = tile_size, tile_size * tile_size
    tiles_x, tiles_y = (width + ts - 1) // ts, (height + ts - 1) // ts
    ids = ((rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])).nonzero().squeeze(1)  # non-empty
    rect = rect.index_select(0, ids)
    x0, x1, y0, y1 = rect.unbind(-1)
    tx0, tx1, ty0, ty1 = x0 // ts, x1 // ts, y0 // ts, y1 // ts
    ntx = tx1 - tx0 + 1
    n_rec = ntx * (ty1 - ty0 + 1)  # [M']
    owner = torch.repeat_interleave(torch.arange(rect.shape[0], device=dev), n_rec)  # [R] in depth order
    local = torch.arange(owner.numel(), device=dev) - torch.repeat_interleave(torch.cumsum(n_rec, 0) - n_rec, n_rec)
    ntx_r = ntx[owner]
    tx = tx0[owner] + local % ntx_r
    ty = ty0[owner] + local // ntx_r
    tile, order = torch.sort((ty * tiles_x + tx).int(), stable=True)  # stable: depth order kept per tile
    tile = tile.long()
    owner, tx, ty = owner[order], tx[order], ty[order]
    rx0 = torch.maximum(x0[owner], tx * ts)
    rx1 = torch.minimum(x1[owner], tx * ts + ts - 1)
    ry0 = torch.maximum(y0[owner], ty * ts)
    ry1 = torch.minimum(y1[owner], ty * ts + ts - 1)
    count = (rx1 - rx0 + 1) * (ry1 - ry0 + 1)  # candidate pixels, the chunks' cost estimate
    # chunks: runs of whole tiles with about _PAIR_BUDGET candidate pairs and at most max_span tiles each
    tile_first = torch.ones_like(tile, dtype=torch.bool)
    tile_first[1:] = tile[1:] != tile[:-1]
    first_idx = tile_first.nonzero().squeeze(1)  # record index where each tile begins
    before = (torch.cumsum(count, 0) - count)[first_idx]
    starts, tiles, before = first_idx.tolist(), tile.index_select(0, first_idx).tolist(), before.tolist()
    n_tiles, total = len(starts), int(count.sum()) if count.numel() else 0
    starts.append(owner.numel())
    before.append(total)
    max_span = max(1, _KEY_LIMIT // tp)
    chunks: list[tuple[int, int, int, int]] = []
    c = 0
    for i in range(1, n_tiles + 1):
        if i == n_tiles or tiles[i] - tiles[c] >= max_span or before[i + 1] - before[c] > _PAIR_BUDGET:
            chunks.append((starts[c], starts[i], tiles[c], tiles[i - 1] + 1))
            c = i
    # key of (x, y) in its chunk: (tile - t0) * tp + (y - ty * ts) * ts + (x - tx * ts)
    t0_rec = torch.zeros_like(tile)
    if chunks:
        bounds = torch.tensor([ch[0] for ch in chunks], device=dev)
        t0s = torch.tensor([ch[2] for ch in chunks], device=dev)
        t0_rec = t0s.index_select(0, torch.searchsorted(bounds, torch.arange(tile.numel(), device=dev), right=True) - 1)
    key_base = (tile - t0_rec) * tp - ty * ts * ts - tx * ts
    rank = torch.arange(tile.numel(), device=dev) - first_idx.index_select(0, torch.cumsum(tile_first, 0) - 1)
    return _Tiling(ids.index_select(0, owner), rx0, rx1, ry0, ry1 - ry0 + 1, key_base, tile, rank, chunks, ts,
                   tiles_x, tiles_y)


@dataclass
class _Pairs:
    """The drawn (pixel, Gaussian) pairs of one chunk, sorted by (pixel, depth): alpha >= ALPHA_MIN and,
    with early termination, only those in front of their pixel's termination point."""

    gauss: torch.Tensor  # [P] int32
    key: torch.Tensor  # [P] int32 chunk-local tile-major pixel
    alpha: torch.Tensor  # [P] min(ALPHA_MAX, o G)
    w: torch.Tensor  # [P] alpha T_before
    frozen: torch.Tensor  # [P] bool: alpha clamped at ALPHA_MAX (no gradient through it)
    crow: torch.Tensor  # [B + 1] int32 first pair of each of the chunk's B pixels (CSR row pointers)

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in vars(self).values())


_PASS_FIRST = 64  # with early termination, a chunk's first pass takes each tile's first records up to this depth
# rank, each further pass twice as many


def _record_pairs(
    tiling: _Tiling, recs: slice | torch.Tensor, means2d: torch.Tensor, conic: torch.Tensor, opacity: torch.Tensor,
    done: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pairs with ``o G >= ALPHA_MIN`` of the records ``recs`` (a slice or ascending int64 indices)
    whose pixel is not ``done`` (``[chunk pixels]`` bool or None), record-major: chunk-local key (int32),
    Gaussian (int32), ``o G`` (unclamped)."""
    take = (lambda t: t[recs]) if isinstance(recs, slice) else (lambda t: t.index_select(0, recs))
    dev, dtype = means2d.device, means2d.dtype
    ts = tiling.tile_size
    g_rec = take(tiling.gauss)
    x0, y0 = take(tiling.x0), take(tiling.y0)
    wx = take(tiling.x1) - x0 + 1
    count = wx * take(tiling.rows)
    n = int(count.sum())
    # per record: offsets of its first pixel centre from the mean, key of its first pixel, conic, opacity
    ox = (x0.to(dtype) + 0.5 - means2d[:, 0].index_select(0, g_rec))
    oy = (y0.to(dtype) + 0.5 - means2d[:, 1].index_select(0, g_rec))
    key0 = (take(tiling.key_base) + y0 * ts + x0).int()
    ca, cb, cc = (row.index_select(0, g_rec) for row in conic.t())
    o = opacity.index_select(0, g_rec)
    count, wx = count.int(), wx.int()
    # pairs, record-major (gathers by the record index are monotone, hence cache-friendly)
    rec = torch.repeat_interleave(torch.arange(g_rec.numel(), device=dev, dtype=torch.int32), count, output_size=n)
    local = torch.arange(n, device=dev, dtype=torch.int32).sub_((torch.cumsum(count, 0, dtype=torch.int32) - count).index_select(0, rec))
    wx_p = wx.index_select(0, rec)
    ly = local // wx_p
    lx = local.sub_(ly * wx_p)
    del wx_p
    key = key0.index_select(0, rec).add_(ly * ts).add_(lx)
    if done is not None:  # terminated pixels: no offsets, no exp
        live = (~done).index_select(0, key).nonzero().squeeze(1)
        rec, key, lx, ly = (t.index_select(0, live) for t in (rec, key, lx, ly))
        del live
    dx = ox.index_select(0, rec).add_(lx)
    dy = oy.index_select(0, rec).add_(ly)
    del lx, ly
    raw = (ca.index_select(0, rec) * dx).mul_(dx).addcmul_(cc.index_select(0, rec) * dy, dy).mul_(-0.5)
    raw = torch.exp_(raw.sub_(cb.index_select(0, rec).mul_(dx).mul_(dy))).mul_(o.index_select(0, rec))
    del dx, dy
    keep = (raw >= ALPHA_MIN).nonzero().squeeze(1)
    gauss = g_rec.int().index_select(0, rec.index_select(0, keep))
    return key.index_select(0, keep), gauss, raw.index_select(0, keep)


def _sort_by_pixel(key: torch.Tensor, n_keys: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Stable sort of chunk-local keys (int16 when they fit: about 2x faster) -> (int32 keys, order)."""
    key, order = torch.sort(key.to(torch.int16) if n_keys <= _KEY_LIMIT else key, stable=True)
    return key.int(), order


def _expand_pairs(
    tiling: _Tiling, chunk: tuple[int, int, int, int], means2d: torch.Tensor, conic: torch.Tensor,
    opacity: torch.Tensor, transmittance_min: float,
) -> _Pairs:
    """Expand one chunk's records into their drawn (pixel, Gaussian) pairs sorted by (pixel, depth).

    Per pass: expand the pairs, drop those with alpha < 1/255, stable-sort them by pixel (int16 keys;
    each pixel's run stays in depth order) and get every pair's transmittance from one segmented scan
    of ``log(1 - alpha)`` (float64 prefix sums), continuing the pixel's transmittance from the earlier
    passes. With ``transmittance_min > 0`` each tile's records are taken in passes of increasing depth
    rank (``_PASS_FIRST``, then doubling); the pairs behind a pixel's termination point are dropped
    (later passes skip a terminated pixel before its exp), and a tile whose pixels have all terminated
    expands none of its later records (the 3DGS block's early exit).
    """
    r0, r1, t0, t1 = chunk
    dtype = means2d.dtype
    tp = tiling.tile_size**2
    n_keys = (t1 - t0) * tp
    log_t_min = math.log(transmittance_min) if transmittance_min > 0 else -math.inf
    log_t_pix: torch.Tensor | None = None  # [n_keys] float64 log T of every pixel after the passes so far
    done: torch.Tensor | None = None  # [n_keys] bool: pixel terminated
    parts: list[tuple[torch.Tensor, ...]] = []
    rank = tiling.rank[r0:r1]
    max_rank = int(rank.max())
    lo, hi = 0, (_PASS_FIRST if transmittance_min > 0 else max_rank + 1)
    while lo <= max_rank:
        last = hi > max_rank
        if lo == 0 and last:
            recs: slice | torch.Tensor = slice(r0, r1)
        else:
            sel = (rank >= lo) & (rank < hi)
            if done is not None:
                sel &= ~done.view(-1, tp).all(1).index_select(0, tiling.tile[r0:r1] - t0)
            recs = sel.nonzero().squeeze(1).add_(r0)
        key, gauss, raw = _record_pairs(tiling, recs, means2d, conic, opacity, done)
        key, order = _sort_by_pixel(key, n_keys)
        gauss, raw = gauss.index_select(0, order), raw.index_select(0, order)
        del order
        frozen = raw > ALPHA_MAX
        alpha = raw.clamp_(max=ALPHA_MAX)
        # segmented exclusive scan of log(1 - alpha) in float64 (a chunk-wide prefix sum would cancel in float32)
        first = torch.zeros(n_keys + 1, dtype=torch.int64, device=key.device)
        torch.cumsum(torch.bincount(key, minlength=n_keys), 0, out=first[1:])
        log_t = torch.log1p(-alpha).double()  # transcendentals in the working dtype (float64 ones are slow)
        log_before = torch.cumsum(log_t, 0).sub_(log_t)
        log_before.sub_(log_before.index_select(0, first.index_select(0, key)))
        if log_t_pix is not None:
            log_before.add_(log_t_pix.index_select(0, key))
        if transmittance_min > 0:
            stop = (log_before + log_t) < log_t_min  # monotone along a pixel's run: a suffix of it
            if bool(stop.any()):  # a pixel stopped iff its run's last pair did; O(pixels), not O(pairs)
                last_stop = stop.index_select(0, (first[1:] - 1).clamp_(min=0)) & (first[1:] > first[:-1])
                done = last_stop if done is None else done.logical_or_(last_stop)
                drawn = (~stop).nonzero().squeeze(1)
                key, gauss, alpha, frozen, log_before, log_t = (
                    t.index_select(0, drawn) for t in (key, gauss, alpha, frozen, log_before, log_t))
            if not last:
                log_t_pix = log_t.new_zeros(n_keys) if log_t_pix is None else log_t_pix
                log_t_pix.index_add_(0, key, log_t)
        del first
        parts.append((key, gauss, alpha, frozen, log_before))
        if done is not None and bool(done.all()):
            break
        lo, hi = hi, 2 * hi
    key, gauss, alpha, frozen, log_before = (torch.cat(t) for t in zip(*parts)) if len(parts) > 1 else parts[0]
    if len(parts) > 1:  # each pass's pairs lie behind the earlier passes' ones: a stable sort merges them
        key, order = _sort_by_pixel(key, n_keys)
        gauss, alpha, frozen, log_before = (t.index_select(0, order) for t in (gauss, alpha, frozen, log_before))
    crow = torch.zeros(n_keys + 1, dtype=torch.int32, device=key.device)
    torch.cumsum(torch.bincount(key, minlength=n_keys), 0, out=crow[1:])
    w = torch.exp(log_before.to(dtype)).mul_(alpha)
    return _Pairs(gauss, key, alpha, w, frozen, crow)


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


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of per-Gaussian features over the tiled pairs."""

    @staticmethod
    def forward(ctx, means2d, conic, opacity, feats, tiling, width, height, t_min):  # type: ignore[override]
        tp = tiling.tile_size**2
        out = feats.new_zeros(tiling.tiles_x * tiling.tiles_y * tp, feats.shape[1])  # tile-major [T ts^2, F]
        cached: list[_Pairs | None] = []
        cache_left = _CACHE_BYTES if any(ctx.needs_input_grad[:4]) else 0
        for chunk in tiling.chunks:
            with torch.profiler.record_function("splatter.expand_pairs"):
                p = _expand_pairs(tiling, chunk, means2d, conic, opacity, t_min)
            with torch.profiler.record_function("splatter.accumulate"):
                # out[pixel] += w feats[gauss]: the pairs are sorted by pixel, i.e. a CSR matrix [B, M]
                n_keys = p.crow.numel() - 1
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # "sparse CSR support is in beta"
                    weights = torch.sparse_csr_tensor(p.crow, p.gauss, p.w, (n_keys, feats.shape[0]), check_invariants=False)
                    out[chunk[2] * tp:chunk[3] * tp] = weights @ feats
            keep = p.nbytes() <= cache_left
            cache_left -= p.nbytes() if keep else 0
            cached.append(p if keep else None)
        ctx.tiling, ctx.width, ctx.height, ctx.cached, ctx.t_min = tiling, width, height, cached, t_min
        ctx.save_for_backward(means2d, conic, opacity, feats)
        return _from_tiles(out, tiling, width, height)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):  # type: ignore[override]
        means2d, conic, opacity, feats = ctx.saved_tensors
        tiling, width, height, t_min = ctx.tiling, ctx.width, ctx.height, ctx.t_min
        tp, ts = tiling.tile_size**2, tiling.tile_size
        nf = feats.shape[1]
        grad_tm = _to_tiles(grad_out, tiling, width, height)  # [F, T ts^2]
        feats_t = feats.t().contiguous()
        g_feats = torch.zeros_like(feats_t)  # [F, M]
        need_uv = ctx.needs_input_grad[0]
        g_geo = means2d.new_zeros(6, means2d.shape[0])  # u, v, conic a, b, c, opacity
        geo_t = torch.cat([means2d.t(), conic.t()]).contiguous()  # [5, M]
        for i, chunk in enumerate(tiling.chunks):
            p = ctx.cached[i]
            if p is None:
                with torch.profiler.record_function("splatter.expand_pairs"):
                    p = _expand_pairs(tiling, chunk, means2d, conic, opacity, t_min)
            with torch.profiler.record_function("splatter.backward_pairs"):
                t0, t1 = chunk[2], chunk[3]
                grad_c = grad_tm[:, t0 * tp:t1 * tp]
                gauss, key, w = p.gauss, p.key, p.w
                f = torch.zeros_like(w)  # dL/dw per pair: feats . grad_out at the pixel
                for k in range(nf):
                    g_pix = grad_c[k].index_select(0, key)
                    f.addcmul_(feats_t[k].index_select(0, gauss), g_pix)
                    g_feats[k].index_add_(0, gauss, g_pix.mul_(w))
                # dL/dalpha_k = T_k f_k - (sum_{j > k} w_j f_j) / (1 - alpha_k): reverse segmented scan; then
                # dL/dpower = alpha dL/dalpha = w f - alpha / (1 - alpha) sum_{j > k} w_j f_j (0 where frozen)
                wf = f.mul_(w)
                csum = torch.cumsum(wf.double(), 0)
                csum_end = csum.index_select(0, (p.crow[1:] - 1).clamp_(min=0))  # [B] per pixel
                behind = csum_end.index_select(0, key).sub_(csum).to(w.dtype)
                g_pow = wf.sub_(behind.mul_(p.alpha).div_(1 - p.alpha)).masked_fill_(p.frozen, 0.0)
                del f, csum, csum_end, behind
                # pixel centre - mean, the centres from a table over the chunk's pixels
                cells = torch.arange(t0 * tp, t1 * tp, device=key.device)
                tile, in_tile = cells // tp, cells % tp
                xc = ((tile % tiling.tiles_x) * ts + in_tile % ts).to(w.dtype).add_(0.5)
                yc = ((tile // tiling.tiles_x) * ts + in_tile // ts).to(w.dtype).add_(0.5)
                gu, gv, ca, cb, cc = (row.index_select(0, gauss) for row in geo_t)
                dx, dy = xc.index_select(0, key).sub_(gu), yc.index_select(0, key).sub_(gv)
                del cells, tile, in_tile, xc, yc, gu, gv
                if need_uv:  # d power / d u = -d power / d dx
                    g_geo[0].index_add_(0, gauss, (ca * dx).addcmul_(cb, dy).mul_(g_pow))
                    g_geo[1].index_add_(0, gauss, (cc * dy).addcmul_(cb, dx).mul_(g_pow))
                g_geo[2].index_add_(0, gauss, dx * dx * g_pow, alpha=-0.5)
                g_geo[3].index_add_(0, gauss, dx * dy * g_pow, alpha=-1.0)
                g_geo[4].index_add_(0, gauss, dy * dy * g_pow, alpha=-0.5)
                # alpha = o G  ->  d alpha / d o = G = alpha / o (o > 0 where alpha >= 1/255)
                g_geo[5].index_add_(0, gauss, g_pow.div_(opacity.index_select(0, gauss)))
        g_means2d = g_geo[:2].t() if need_uv else None
        g_conic = g_geo[2:5].t()
        return g_means2d, g_conic, g_geo[5], g_feats.t(), None, None, None, None


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
            means_cam[front], scales[front], rotations[front], w2c, k, width, height
        )
        rect, candidates = _footprints(means2d, cov2d, opacities[front], width, height)
        on_screen = ((rect[:, 0] <= rect[:, 1]) & (rect[:, 2] <= rect[:, 3])).nonzero().squeeze(1)
        idx = front[on_screen]  # [M]
        visible = torch.zeros(n, dtype=torch.bool, device=dev)
        visible[idx] = True
    with torch.profiler.record_function("splatter.bin"):
        z = means_cam[idx, 2]  # [M]
        order = torch.argsort(z.detach(), stable=True)  # front to back; ties keep the input order
        sel, idx = on_screen[order], idx[order]
        z = z[order]
        feats = torch.cat([colors[idx], z.unsqueeze(-1), torch.ones_like(z).unsqueeze(-1)], dim=-1)  # [M, 5]
        tiling = _bin_tiles(candidates[sel], width, height, tile_size)
    out = _Composite.apply(means2d[sel], conic[sel], opacities[idx], feats, tiling, width, height,
                           float(transmittance_min))
    out = out.reshape(5, height, width)
    alpha = out[4:5]
    color = out[:3]
    if background is not None:
        color = color + (1 - alpha) * background.view(3, 1, 1)
    return RasterOutput(color=color, alpha=alpha, depth=out[3:4], visible=visible)
