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

Shapes: ``N = H * W`` pixels (row-major), canvas ``(H + 2m) x (W + 2m)`` with ``m = k // 2`` (the
light that can still reach the frame), flattened with one extra trailing "dump" slot for light that
lands outside it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from controlgs_adapter.errors import InputValueError

if TYPE_CHECKING:
    from .bank import PSFBank

__all__ = ["ResampledBank", "fast_len"]


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

    def __init__(self, bank: "PSFBank", height: int, width: int, *, device: torch.device, dtype: torch.dtype):
        self.bank, self.H, self.W, self.device, self.dtype = bank, height, width, device, dtype
        self.L = bank.num_wavelengths
        px_x, px_y = bank.display_mm[0] / width, bank.display_mm[1] / height
        K = bank.psf.shape[-1]
        reach = float(bank.psf_pitch_mm.max()) * (K // 2 + 0.5) / min(px_x, px_y)
        self.m = int(math.ceil(reach - 0.5 - 1e-9))
        self.k = 2 * self.m + 1
        self.Hc, self.Wc = height + 2 * self.m, width + 2 * self.m
        self._px = (px_x, px_y)
        self._kernels: torch.Tensor | None = None
        self._lowrank: dict[int, tuple[torch.Tensor, torch.Tensor]] = {}
        self.field_index, self.field_weight = self._field_weights()   # [4, N] long, [4, N]
        self.splat_index, self.splat_weight = self._footprints()     # [L, J, N] long, [L, J, N]

    # ----------------------------------------------------------------- per-pixel field blending
    def _field_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        b = self.bank
        Gy, Gx = b.psf.shape[1:3]

        def axis(n_px: int, f: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            u = (2 * torch.arange(n_px, dtype=torch.float64) + 1) / n_px - 1
            f = f.double()
            j = torch.searchsorted(f, u).clamp(1, len(f) - 1) if len(f) > 1 else torch.zeros_like(u, dtype=torch.long)
            if len(f) == 1:
                return j, j, torch.zeros_like(u)
            a = ((u - f[j - 1]) / (f[j] - f[j - 1])).clamp(0, 1)   # constant beyond the outer samples
            return j - 1, j, a

        y0, y1, ay = axis(self.H, b.field_y)
        x0, x1, ax = axis(self.W, b.field_x)
        Y0, X0 = torch.meshgrid(y0, x0, indexing="ij")
        Y1, X1 = torch.meshgrid(y1, x1, indexing="ij")
        AY, AX = torch.meshgrid(ay, ax, indexing="ij")
        idx = torch.stack([Y0 * Gx + X0, Y0 * Gx + X1, Y1 * Gx + X0, Y1 * Gx + X1]).reshape(4, -1)
        w = torch.stack([(1 - AY) * (1 - AX), (1 - AY) * AX, AY * (1 - AX), AY * AX]).reshape(4, -1)
        return idx.to(self.device), w.to(self.device, self.dtype)

    # ----------------------------------------------------------------- chief-ray footprints
    def _chief_at(self, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Chief-ray landing ``[L, *u.shape, 2]`` (normalised) at normalised display points (bilinear)."""
        grid = torch.stack([u, v], -1).double()[None].expand(self.L, *u.shape, 2)
        ch = self.bank.chief.double().permute(0, 3, 1, 2)           # [L, 2, Cy, Cx]
        out = F.grid_sample(ch, grid, mode="bilinear", align_corners=True, padding_mode="border")
        return out.permute(0, 2, 3, 1)

    def _footprints(self) -> tuple[torch.Tensor, torch.Tensor]:
        H, W, m = self.H, self.W, self.m
        ue = 2 * torch.arange(W + 1, dtype=torch.float64) / W - 1     # pixel edges
        uc = (2 * torch.arange(W, dtype=torch.float64) + 1) / W - 1   # pixel centres
        ve = 2 * torch.arange(H + 1, dtype=torch.float64) / H - 1
        vc = (2 * torch.arange(H, dtype=torch.float64) + 1) / H - 1
        Vc, Ue = torch.meshgrid(vc, ue, indexing="ij")                # [H, W+1]
        Ve, Uc = torch.meshgrid(ve, uc, indexing="ij")                # [H+1, W]
        cx = (self._chief_at(Ue, Vc)[..., 0] + 1) * W / 2 + m        # [L, H, W+1] canvas px (edge units)
        cy = (self._chief_at(Uc, Ve)[..., 1] + 1) * H / 2 + m        # [L, H+1, W]
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

    def lowrank(self, rank: int) -> tuple[torch.Tensor, torch.Tensor, tuple[int, int]]:
        """Truncated SVD of the field kernels per wavelength: ``(kernel_fft [L, R, Fh, Fw//2+1],
        coeff [L, R, N], fft_size)``. Coefficients are rescaled per pixel so that every truncated
        pixel kernel keeps unit sum (energy-preserving truncation)."""
        if rank not in self._lowrank:
            kern = self.kernels.double()
            L, G = kern.shape[:2]
            R = min(rank, G, self.k * self.k)
            fh, fw = fast_len(self.Hc), fast_len(self.Wc)
            ffts, coeffs = [], []
            for li in range(L):
                A = kern[li].reshape(G, -1)                                 # [G, k*k]
                evals, U = torch.linalg.eigh(A @ A.T)
                order = torch.argsort(evals, descending=True)[:R]
                s = evals[order].clamp_min(1e-30).sqrt()
                U = U[:, order]                                              # [G, R]
                E = (U.T @ A) / s[:, None]                                   # [R, k*k] orthonormal eigen-PSFs
                a = U * s                                                    # [G, R]
                ap = sum(a[self.field_index[i]] * self.field_weight[i, :, None].double() for i in range(4))  # [N, R]
                total = ap @ E.sum(1)                                         # [N] sum of each truncated kernel
                ap = ap / torch.where(total.abs() > 1e-6, total, torch.ones_like(total))[:, None]
                Ek = torch.zeros(R, fh, fw, dtype=torch.float64, device=E.device)
                Ek[:, : self.k, : self.k] = E.reshape(R, self.k, self.k)
                Ek = torch.roll(Ek, shifts=(-self.m, -self.m), dims=(1, 2))  # tap t at index t mod size
                ffts.append(torch.fft.rfft2(Ek))
                coeffs.append(ap.T)
            cdt = torch.complex64 if self.dtype == torch.float32 else torch.complex128
            self._lowrank[rank] = (torch.stack(ffts).to(self.device, cdt), torch.stack(coeffs).to(self.device, self.dtype),
                                   (fh, fw))
        return self._lowrank[rank]
