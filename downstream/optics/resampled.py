"""A :class:`PSFBank` at one simulation resolution: everything the operators need, computed once.

Discretisation of paper Eq. S3 used by every operator (so they converge to the same thing):

    out[q] = sum_p x[p] * sum_t h_p[t] * B_p(q - t)

- ``h_p`` ``[k, k]`` is the PSF of display pixel p on the output pixel grid: the four surrounding
  field PSFs, each box-resampled to the output pitch (energy-exact), blended bilinearly;
- ``B_p`` is the footprint of display pixel p (a box whose edges are the chief-ray images of the
  pixel's edges, per wavelength) integrated over output pixels: the display pixel's box filter
  (paper S2) and the output pixel's box, with the local magnification of the distortion. Footprints
  of neighbouring pixels tile, so a flat field stays seam-free; for a distortion-free bank B_p is a
  single output pixel and the operator is exactly a convolution.

Placement (``region``, :func:`controlgs_adapter.downstream.placement.image_region`): image pixel
centre ``u`` (image-normalised) sits at display-normalised ``u * (half_x, half_y)``, where the bank's
field PSFs and chief rays are sampled; landing points are divided by the same factors, so the output
is the virtual image (at the reference magnification) on the image's own pixel grid, with the
image's pixel pitch ``region.pitch_mm`` converting the PSFs' millimetres to pixels.

Shapes: ``N = H * W`` pixels (row-major), canvas ``(H + 2m) x (W + 2m)`` with ``m = k // 2`` (the
light that can still reach the frame), flattened with one extra trailing "dump" slot for light that
lands outside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from controlgs_adapter.errors import InputValueError

if TYPE_CHECKING:
    from ..placement import ImageRegion
    from .bank import PSFBank

__all__ = ["ResampledBank", "Zone", "Bucket", "fast_len", "ladder_len"]


def fast_len(n: int) -> int:
    """Smallest m >= n whose prime factors are 2, 3, 5, 7 (fast FFT sizes)."""
    m = n
    while True:
        r = m
        for p in (2, 3, 5, 7):
            while r % p == 0:
                r //= p
        if r == 1:
            return m
        m += 1


_LADDER: list[int] = []


def ladder_len(n: int) -> int:
    """Round ``n`` up to a coarse ladder of fast FFT sizes (steps of ~12 %), so that field groups
    share FFT sizes and are transformed in one batched call."""
    if not _LADDER:
        v = 8.0
        while v < 1 << 16:
            m = fast_len(int(math.ceil(v)))
            if not _LADDER or m > _LADDER[-1]:
                _LADDER.append(m)
            v *= 1.12
    for m in _LADDER:
        if m >= n:
            return m
    return fast_len(n)


def _box_matrix(pitch_px: torch.Tensor, K: int, m: int) -> torch.Tensor:
    """``[G, 2m+1, K]``: fraction of stored cell i (width ``pitch_px``) that falls in output tap t."""
    c = K // 2
    i = torch.arange(K, dtype=torch.float64) - c
    a = (i - 0.5)[None, :] * pitch_px[:, None]                  # [G, K] cell edges in output px
    b = (i + 0.5)[None, :] * pitch_px[:, None]
    t = torch.arange(-m, m + 1, dtype=torch.float64)
    lo = torch.maximum(a[:, None, :], (t - 0.5)[None, :, None])
    hi = torch.minimum(b[:, None, :], (t + 0.5)[None, :, None])
    return (hi - lo).clamp_min(0) / pitch_px[:, None, None]


class ResampledBank:
    """Per-resolution tables (see module docstring). Build through :meth:`PSFBank.resample_to`."""

    def __init__(self, bank: "PSFBank", height: int, width: int, region: "ImageRegion", *, device: torch.device,
                 dtype: torch.dtype):
        self.bank, self.H, self.W, self.device, self.dtype = bank, height, width, device, dtype
        self.region = region
        self.L = bank.num_wavelengths
        px_x, px_y = region.pitch_mm
        K = bank.psf.shape[-1]
        reach = float(bank.psf_pitch_mm.max()) * (K // 2 + 0.5) / min(px_x, px_y)
        self.m = int(math.ceil(reach - 0.5 - 1e-9))
        self.k = 2 * self.m + 1
        self.Hc, self.Wc = height + 2 * self.m, width + 2 * self.m
        self._px = (px_x, px_y)
        self._kernels: torch.Tensor | None = None
        self._zones: dict = {}
        self.field_index, self.field_weight = self._field_weights()   # [4, N] long, [4, N]
        self.splat_index, self.splat_weight = self._footprints()     # [L, J, N] long, [L, J, N]

    # ----------------------------------------------------------------- per-pixel field blending
    def _field_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        b = self.bank
        Gy, Gx = b.psf.shape[1:3]

        def axis(n_px: int, f: torch.Tensor, half: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            u = ((2 * torch.arange(n_px, dtype=torch.float64) + 1) / n_px - 1) * half   # display-normalised
            f = f.double()
            j = torch.searchsorted(f, u).clamp(1, len(f) - 1) if len(f) > 1 else torch.zeros_like(u, dtype=torch.long)
            if len(f) == 1:
                return j, j, torch.zeros_like(u)
            a = ((u - f[j - 1]) / (f[j] - f[j - 1])).clamp(0, 1)   # constant beyond the outer samples
            return j - 1, j, a

        y0, y1, ay = axis(self.H, b.field_y, self.region.half_y)
        x0, x1, ax = axis(self.W, b.field_x, self.region.half_x)
        Y0, X0 = torch.meshgrid(y0, x0, indexing="ij")
        Y1, X1 = torch.meshgrid(y1, x1, indexing="ij")
        AY, AX = torch.meshgrid(ay, ax, indexing="ij")
        idx = torch.stack([Y0 * Gx + X0, Y0 * Gx + X1, Y1 * Gx + X0, Y1 * Gx + X1]).reshape(4, -1)
        w = torch.stack([(1 - AY) * (1 - AX), (1 - AY) * AX, AY * (1 - AX), AY * AX]).reshape(4, -1)
        return idx.to(self.device), w.to(self.device, self.dtype)

    # ----------------------------------------------------------------- chief-ray footprints
    def _chief_at(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Chief-ray landing ``[L, *u.shape, 2]`` (normalised) at normalised display points.

        Separable Keys cubic convolution (a = -1/2: reproduces quadratics, C1), so the derivative,
        the local magnification, is continuous and a flat field shows no steps at grid lines.
        The grid is extended by one sample each side by quadratic extrapolation."""
        ch = self.bank.chief.double()                                           # [L, Cy, Cx, 2]
        ch = torch.cat([3 * ch[:, :1] - 3 * ch[:, 1:2] + ch[:, 2:3], ch, 3 * ch[:, -1:] - 3 * ch[:, -2:-1] + ch[:, -3:-2]], 1)
        ch = torch.cat([3 * ch[:, :, :1] - 3 * ch[:, :, 1:2] + ch[:, :, 2:3], ch,
                        3 * ch[:, :, -1:] - 3 * ch[:, :, -2:-1] + ch[:, :, -3:-2]], 2)
        Cy, Cx = self.bank.chief.shape[1:3]

        def taps(t: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
            g = (t.double() + 1) / 2 * (n - 1)                                 # grid units, 0..n-1
            i = torch.floor(g).clamp(0, n - 2)
            f = g - i
            w = torch.stack([((-0.5 * f + 1.0) * f - 0.5) * f, (1.5 * f - 2.5) * f * f + 1.0,
                             ((-1.5 * f + 2.0) * f + 0.5) * f, (0.5 * f - 0.5) * f * f], -1)
            idx = i.long()[..., None] + torch.arange(4)                         # padded grid index
            return idx, w

        iy, wy = taps(v, Cy)
        ix, wx = taps(u, Cx)
        out = 0
        for a in range(4):
            for b in range(4):
                out = out + ch[:, iy[..., a], ix[..., b]] * (wy[..., a] * wx[..., b])[None, ..., None]
        return out

    def _footprints(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Chief rays at the image pixels' display positions (image-normalised ``u`` times the
        region's half-extent), landing points back in the image's frame (divided by it: the virtual
        image at the reference magnification, on the image's own pixel grid)."""
        H, W, m = self.H, self.W, self.m
        sx, sy = self.region.half_x, self.region.half_y
        ue = 2 * torch.arange(W + 1, dtype=torch.float64) / W - 1     # pixel edges
        uc = (2 * torch.arange(W, dtype=torch.float64) + 1) / W - 1   # pixel centres
        ve = 2 * torch.arange(H + 1, dtype=torch.float64) / H - 1
        vc = (2 * torch.arange(H, dtype=torch.float64) + 1) / H - 1
        Vc, Ue = torch.meshgrid(vc, ue, indexing="ij")                # [H, W+1]
        Ve, Uc = torch.meshgrid(ve, uc, indexing="ij")                # [H+1, W]
        cx = (self._chief_at(Ue * sx, Vc * sy)[..., 0] / sx + 1) * W / 2 + m   # [L, H, W+1] canvas px (edge units)
        cy = (self._chief_at(Uc * sx, Ve * sy)[..., 1] / sy + 1) * H / 2 + m   # [L, H+1, W]
        ax, bx = cx[..., :-1], cx[..., 1:]
        ay, by = cy[:, :-1, :], cy[:, 1:, :]
        if (bx <= ax).any() or (by <= ay).any():
            raise InputValueError("PSF bank: the chief-ray map folds over (not monotonic) at this resolution")
        jx = int(torch.ceil((bx - ax).max()).item()) + 1
        jy = int(torch.ceil((by - ay).max()).item()) + 1
        idx, wts = [], []
        x0, y0 = torch.floor(ax), torch.floor(ay)
        for oy in range(jy):
            py = y0 + oy
            wy = (torch.minimum(by, py + 1) - torch.maximum(ay, py)).clamp_min(0) / (by - ay)
            for ox in range(jx):
                pxl = x0 + ox
                wx = (torch.minimum(bx, pxl + 1) - torch.maximum(ax, pxl)).clamp_min(0) / (bx - ax)
                inside = (pxl >= 0) & (pxl < self.Wc) & (py >= 0) & (py < self.Hc)
                flat = torch.where(inside, py * self.Wc + pxl, torch.full_like(pxl, self.Hc * self.Wc))
                idx.append(flat.long().reshape(self.L, -1))
                wts.append(torch.where(inside, wx * wy, torch.zeros_like(wx)).reshape(self.L, -1))
        return torch.stack(idx, 1).to(self.device), torch.stack(wts, 1).to(self.device, self.dtype)

    # ----------------------------------------------------------------- kernels
    @property
    def kernels(self) -> torch.Tensor:
        """``[L, G, k, k]`` field PSFs on the output pixel grid (unit sum, tap ``m`` on the chief ray)."""
        if self._kernels is None:
            b = self.bank
            L, Gy, Gx, K, _ = b.psf.shape
            out = torch.empty(L, Gy * Gx, self.k, self.k, dtype=torch.float64)
            for li in range(L):
                p = b.psf_pitch_mm[li].reshape(-1).double()
                wx = _box_matrix(p / self._px[0], K, self.m)          # [G, k, K]
                wy = _box_matrix(p / self._px[1], K, self.m)
                out[li] = torch.einsum("gtk,gkl,gsl->gts", wy, b.psf[li].reshape(-1, K, K).double(), wx)
            self._kernels = out.to(self.device, self.dtype)
        return self._kernels

    def pixel_kernels(self, li: int, taps: torch.Tensor) -> torch.Tensor:
        """``[T, N]``: value of tap ``taps`` (flat index into ``k x k``) of every pixel's blended PSF."""
        kf = self.kernels[li].reshape(self.kernels.shape[1], -1)[:, taps]   # [G, T]
        out = kf[self.field_index[0]] * self.field_weight[0, :, None]
        for i in range(1, 4):
            out = out + kf[self.field_index[i]] * self.field_weight[i, :, None]
        return out.T

    def zones(self, zone: int, tol: float, max_rank: int | None = None) -> list["Zone"]:
        """Field-group decomposition of the operator (cached): the fields are split into groups of
        ``zone x zone``; within a group, the kernels are replaced by their truncated SVD with the
        smallest rank whose relative Frobenius residual is <= ``tol`` (capped by ``max_rank``).
        Because each pixel's PSF is a bilinear blend of field PSFs, ``zone=1`` (any tol) and
        ``tol=0`` are exact."""
        key = (zone, float(tol), max_rank)
        if key not in self._zones:
            self._zones[key] = _build_zones(self, zone, float(tol), max_rank)
        return self._zones[key]


@dataclass
class Zone:
    """One field group at one wavelength: ``out[box] += sum_r E_r * splat(coeff_r . x[pixels])``."""

    pixels: torch.Tensor        # [n] flat display-pixel indices whose PSF uses a field of the group
    splat_index: torch.Tensor   # [J, n] flat index into the zone's FFT array (fh * fw = dump slot)
    splat_weight: torch.Tensor  # [J, n]
    coeff: torch.Tensor         # [R, n]
    kernels: torch.Tensor       # [R, fh, fw] eigen-PSFs, tap t at index t mod size (float64)
    fft_size: tuple[int, int]
    src: tuple[int, int, int, int]   # rows/cols of the FFT array that reach the frame: r0, r1, c0, c1
    dst: tuple[int, int]             # frame row/col where src (r0, c0) lands


def _build_zones(rb: "ResampledBank", zone: int, tol: float, max_rank: int | None) -> list[list[Zone]]:
    b = rb.bank
    Gy, Gx = b.psf.shape[1:3]
    kern = rb.kernels.double()                                             # [L, G, k, k]
    fidx, fw_ = rb.field_index, rb.field_weight.double()                   # [4, N]
    nzx = (Gx + zone - 1) // zone
    zid = (fidx // Gx // zone) * nzx + fidx % Gx // zone                   # [4, N] group of each field used
    N = fidx.shape[1]
    pix_all = torch.arange(N, device=fidx.device).expand(4, N)
    key = torch.unique(zid[fw_ > 0] * N + pix_all[fw_ > 0])                # sorted (group, pixel) pairs
    groups = key // N
    counts = torch.bincount(groups, minlength=nzx * ((Gy + zone - 1) // zone)).tolist()
    pixels_of = dict(enumerate(torch.split(key % N, counts)))
    out: list[list[Zone]] = []
    dump = rb.Hc * rb.Wc
    for li in range(rb.L):
        zones_l: list[Zone] = []
        for zy in range(0, Gy, zone):
            for zx in range(0, Gx, zone):
                z = (zy // zone) * nzx + zx // zone
                fields = torch.tensor([fy * Gx + fx for fy in range(zy, min(zy + zone, Gy))
                                       for fx in range(zx, min(zx + zone, Gx))], device=fidx.device)
                pix = pixels_of[z]
                if pix.numel() == 0:
                    continue
                K = kern[li, fields]                                           # [nf, k, k]
                nzr = (K.abs().sum(0) > 0)
                rows, cols = nzr.any(1).nonzero().squeeze(1), nzr.any(0).nonzero().squeeze(1)
                mz = int(max((rows - rb.m).abs().max(), (cols - rb.m).abs().max()))
                K = K[:, rb.m - mz:rb.m + mz + 1, rb.m - mz:rb.m + mz + 1].reshape(len(fields), -1)
                evals, U = torch.linalg.eigh(K @ K.T)
                order = torch.argsort(evals, descending=True)
                evals, U = evals[order].clamp_min(0), U[:, order]
                total = evals.sum()
                resid = (total - torch.cumsum(evals, 0)).clamp_min(0)
                R = int((resid > (tol * tol) * total).sum().item()) + 1
                R = min(R, len(fields), max_rank or R)
                s = evals[:R].clamp_min(1e-300).sqrt()
                E = (U[:, :R].T @ K) / s[:, None]                                # [R, kz*kz]
                A = U[:, :R] * s                                                 # [nf, R] per-field coefficients
                # per-pixel coefficients: sum of the pixel's bilinear weights on this group's fields
                pos = torch.full((Gy * Gx,), -1, dtype=torch.long, device=fidx.device)
                pos[fields] = torch.arange(len(fields), device=fidx.device)
                coeff = torch.zeros(pix.numel(), R, dtype=torch.float64, device=fidx.device)
                for i in range(4):
                    pi = pos[fidx[i, pix]]
                    ok = pi >= 0
                    coeff[ok] += fw_[i, pix[ok], None] * A[pi[ok]]
                # landing box of the group's pixels on the canvas
                idx, w = rb.splat_index[li][:, pix], rb.splat_weight[li][:, pix]
                live = (w > 0) & (idx < dump)
                if not live.any():
                    continue
                flat = idx[live]
                r, c = flat // rb.Wc, flat % rb.Wc
                r0, r1, c0, c1 = int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1
                fh, fwid = ladder_len(r1 - r0 + 2 * mz), ladder_len(c1 - c0 + 2 * mz)
                lr, lc = idx // rb.Wc - r0 + mz, idx % rb.Wc - c0 + mz
                local = torch.where(live, lr * fwid + lc, torch.full_like(idx, fh * fwid))
                Ek = torch.zeros(R, fh, fwid, dtype=torch.float64, device=fidx.device)
                Ek[:, :2 * mz + 1, :2 * mz + 1] = E.reshape(R, 2 * mz + 1, 2 * mz + 1)
                Ek = torch.roll(Ek, shifts=(-mz, -mz), dims=(1, 2))
                # array (i, j) is canvas (i - mz + r0, j - mz + c0); frame = canvas - m
                fr0, fc0 = r0 - mz - rb.m, c0 - mz - rb.m
                a0, b0 = max(0, -fr0), max(0, -fc0)
                a1, b1 = min(r1 - r0 + 2 * mz, rb.H - fr0), min(c1 - c0 + 2 * mz, rb.W - fc0)
                if a1 <= a0 or b1 <= b0:
                    continue
                zones_l.append(Zone(pixels=pix, splat_index=local, splat_weight=w.to(rb.dtype),
                                    coeff=coeff.T.contiguous().to(rb.dtype), kernels=Ek,
                                    fft_size=(fh, fwid), src=(a0, a1, b0, b1), dst=(fr0 + a0, fc0 + b0)))
        out.append(_bucketize(zones_l, rb))
    return out


@dataclass
class Bucket:
    """Field groups with the same FFT size and rank, transformed in one batched call."""

    tap_pixel: torch.Tensor     # [M] display pixel of each splat tap (non-zero footprint entries only)
    tap_index: torch.Tensor     # [M] flat index into [Z, fh, fw] where the tap lands
    tap_weight: torch.Tensor    # [R, M] footprint weight x the pixel's coefficient of eigen-PSF r
    kernel_fft: torch.Tensor    # [R, Z, fh, fw // 2 + 1]
    fft_size: tuple[int, int]
    num_groups: int
    out_index: torch.Tensor     # [M] flat frame index receiving ...
    src_index: torch.Tensor     # [M] ... this flat index of the [Z, fh, fw] result


def _bucketize(zones: list[Zone], rb: "ResampledBank") -> list[Bucket]:
    keys: dict[tuple[int, int, int], list[Zone]] = {}
    for z in zones:
        keys.setdefault((*z.fft_size, z.coeff.shape[0]), []).append(z)
    buckets = []
    cdt = torch.complex64 if rb.dtype == torch.float32 else torch.complex128
    for (fh, fw, R), zs in sorted(keys.items()):
        area = fh * fw
        tpix, tidx, twt, outs, srcs = [], [], [], [], []
        for slot, z in enumerate(zs):
            live = (z.splat_weight > 0) & (z.splat_index < area)                 # [J, n]
            i, j = live.T.nonzero(as_tuple=True)                                 # pixel-major
            tpix.append(z.pixels[i])
            tidx.append(z.splat_index[j, i] + slot * area)
            twt.append(z.coeff[:, i] * z.splat_weight[j, i])
            a0, a1, b0, b1 = z.src
            r, c = z.dst
            ii, jj = torch.meshgrid(torch.arange(a0, a1), torch.arange(b0, b1), indexing="ij")
            srcs.append((slot * area + ii * fw + jj).reshape(-1))
            outs.append(((ii - a0 + r) * rb.W + (jj - b0 + c)).reshape(-1))
        buckets.append(Bucket(tap_pixel=torch.cat(tpix), tap_index=torch.cat(tidx), tap_weight=torch.cat(twt, 1),
                              kernel_fft=torch.fft.rfft2(torch.stack([z.kernels for z in zs], 1)).to(cdt), fft_size=(fh, fw),
                              num_groups=len(zs), out_index=torch.cat(outs).to(rb.device),
                              src_index=torch.cat(srcs).to(rb.device)))
    return buckets
