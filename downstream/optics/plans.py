"""Execution plans of a :class:`~.resampled.ResampledBank`'s operator, built once per (zone, tol,
max_rank): the field PSFs grouped ``zone x zone`` and replaced by truncated-SVD eigen-PSFs, packed into
buckets of equal FFT size (:func:`ladder_len`) and rank: :class:`GatherBucket` (radiance, ``[R, Z, fh,
fw // 2 + 1]`` kernel spectra applied to the warped canvas) and :class:`Bucket` of :class:`Zone` (energy,
splatted display pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from .resampled import ResampledBank

__all__ = ["Zone", "Bucket", "GatherBucket", "fast_len", "ladder_len"]


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
    share FFT sizes and are transformed in one batched call. The ladder starts at 8 (every n <= 8
    gives 8); above that an n is padded by at most 20 % (10 -> 12)."""
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


def _eigen(K: torch.Tensor, m: int, tol: float, max_rank: int | None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Truncated SVD of a group's kernels ``K [nf, k, k]`` (tap ``m`` central): eigen-PSFs
    ``[R, 2 mz + 1, 2 mz + 1]`` cropped to the group's support ``mz``, coefficients ``[nf, R]``
    scaled so that each field's truncated kernel keeps its sum."""
    nzr = K.abs().sum(0) > 0
    rows, cols = nzr.any(1).nonzero().squeeze(1), nzr.any(0).nonzero().squeeze(1)
    mz = int(max((rows - m).abs().max(), (cols - m).abs().max()))
    nf = K.shape[0]
    K = K[:, m - mz:m + mz + 1, m - mz:m + mz + 1].reshape(nf, -1)
    if nf == 1:                       # one field: its kernel is its own (exact) eigen-PSF
        return K.reshape(1, 2 * mz + 1, 2 * mz + 1), K.new_ones(1, 1), mz
    evals, U = torch.linalg.eigh(K @ K.T)
    order = torch.argsort(evals, descending=True)
    evals, U = evals[order].clamp_min(0), U[:, order]
    total = evals.sum()
    resid = (total - torch.cumsum(evals, 0)).clamp_min(0)
    R = int((resid > (tol * tol) * total).sum().item()) + 1
    R = min(R, nf, max_rank or R)
    s = evals[:R].clamp_min(1e-300).sqrt()
    E = (U[:, :R].T @ K) / s[:, None]
    A = U[:, :R] * s
    # keep every field's light: rescale its coefficients so the truncated kernel has its sum
    # (a flat field stays flat in the fast mode too; the factor is exactly 1 at tol = 0)
    have, want = A @ E.sum(1), K.sum(1)
    A = A * torch.where(have.abs() > 1e-12 * want.abs(), want / have, torch.ones_like(have))[:, None]
    return E.reshape(R, 2 * mz + 1, 2 * mz + 1), A, mz


def _rolled(E: torch.Tensor, fh: int, fw: int) -> torch.Tensor:
    """Kernels ``[R, 2mz+1, 2mz+1]`` in an ``fh x fw`` FFT array, tap ``t`` at index ``t mod size``."""
    mz = E.shape[-1] // 2
    Ek = E.new_zeros(E.shape[0], fh, fw)
    Ek[:, :2 * mz + 1, :2 * mz + 1] = E
    return torch.roll(Ek, shifts=(-mz, -mz), dims=(1, 2))


@dataclass
class GatherBucket:
    """Field groups with the same FFT size and rank (radiance): ``out[box] += sum_r a_r . (E_r * C)``,
    ``C`` the warped canvas, transformed in one batched call. Group ``s`` reads the canvas patch of
    its output box ``boxes[s] = (r0, c0, bh, bw, mz)`` (frame rows ``r0 .. r0 + bh``, columns
    ``c0 .. c0 + bw``) widened by its kernel reach ``mz`` into slot ``s`` of the FFT array, and adds
    ``weights[s] * result`` back to the box, by plain slices or by the flat :meth:`tables`."""

    kernel_fft: torch.Tensor    # [R, Z, fh, fw // 2 + 1]
    fft_size: tuple[int, int]
    boxes: list[tuple[int, int, int, int, int]]
    weights: list[torch.Tensor]  # Z x [R, bh, bw] coefficient map a_r on the box (field weight x transmission)
    _tables: tuple[torch.Tensor, ...] | None = field(default=None, repr=False, compare=False)

    def tables(self, m: int, Wc: int, W: int) -> tuple[torch.Tensor, ...]:
        """Every box element as flat indices (built once, cached): ``(in_slot, in_canvas)`` [Min]
        long, the padded boxes' positions in the ``[Z, fh, fw]`` FFT array and in the ``Hc x Wc``
        canvas (margin ``m``, width ``Wc``); ``(out_slot, out_index)`` [Mout] long, the boxes'
        positions in the FFT array and in the ``H x W`` frame (width ``W``); ``out_weight``
        [R, Mout], the weights there."""
        if self._tables is None:
            fh, fw = self.fft_size
            dev = self.kernel_fft.device
            r0, c0, bh, bw, mz = torch.tensor(self.boxes, device=dev).T

            def elements(h: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, ...]:
                n = h * w                                        # box s: rows i, cols j (row-major)
                s = torch.repeat_interleave(torch.arange(len(n), device=dev), n)
                e = torch.arange(int(n.sum()), device=dev) - (torch.cumsum(n, 0) - n)[s]
                return s, e // w[s], e % w[s]

            s, i, j = elements(bh + 2 * mz, bw + 2 * mz)
            in_slot = (s * fh + i) * fw + j
            in_canvas = (r0[s] + m - mz[s] + i) * Wc + c0[s] + m - mz[s] + j
            s, i, j = elements(bh, bw)
            out_slot = (s * fh + mz[s] + i) * fw + mz[s] + j
            out_index = (r0[s] + i) * W + c0[s] + j
            out_weight = torch.cat([w.reshape(w.shape[0], -1) for w in self.weights], 1)
            self._tables = (in_slot, in_canvas, out_slot, out_index, out_weight)
        return self._tables


def _build_gather(rb: "ResampledBank", zone: int, tol: float, max_rank: int | None) -> list[list[GatherBucket]]:
    Gy, Gx = rb.bank.psf.shape[1:3]
    W, N = rb.W, rb.H * rb.W
    nzx, nzy = (Gx + zone - 1) // zone, (Gy + zone - 1) // zone
    cdt = torch.complex64 if rb.dtype == torch.float32 else torch.complex128
    dev = rb.device
    out = []
    for li in range(rb.L):
        boxes = rb.box_matrices(li)
        fidx = rb.out_field_index[li]
        fw_ = rb.out_field_weight[li].double() * rb.transmission[li][fidx]
        live = fw_ > 0
        f_all, v_all = fidx[live], fw_[live]
        q_all = torch.arange(N, device=dev).expand(4, N)[live]
        z_all = (f_all // Gx // zone) * nzx + (f_all % Gx) // zone
        order = torch.argsort(z_all * (Gy * Gx) + f_all)
        f_all, v_all, q_all = f_all[order], v_all[order], q_all[order]
        counts = torch.bincount(z_all, minlength=nzx * nzy).tolist()
        groups: dict[tuple[int, int, int], list] = {}
        for f_g, v_g, q_g in zip(f_all.split(counts), v_all.split(counts), q_all.split(counts)):
            if f_g.numel() == 0:
                continue
            fields, pos = torch.unique(f_g, return_inverse=True)
            E, A, mz = _eigen(*rb.field_kernels(li, fields, boxes), tol, max_rank)
            r, c = q_g // W, q_g % W
            r0, r1, c0, c1 = int(r.min()), int(r.max()) + 1, int(c.min()), int(c.max()) + 1
            bh, bw = r1 - r0, c1 - c0
            Vd = torch.zeros(len(fields), bh * bw, dtype=torch.float64, device=dev)
            Vd.index_put_((pos, (r - r0) * bw + (c - c0)), v_g, accumulate=True)
            coeff = (A.T @ Vd).reshape(-1, bh, bw)                                # [R, bh, bw]
            fh, fwid = ladder_len(bh + 2 * mz), ladder_len(bw + 2 * mz)
            groups.setdefault((fh, fwid, E.shape[0]), []).append((_rolled(E, fh, fwid), (r0, c0, bh, bw, mz), coeff))
        out.append([GatherBucket(kernel_fft=torch.fft.rfft2(torch.stack([z[0] for z in zs], 1)).to(cdt),
                                 fft_size=(fh, fwid), boxes=[z[1] for z in zs],
                                 weights=[z[2].to(rb.dtype) for z in zs])
                    for (fh, fwid, R), zs in sorted(groups.items(), key=lambda kv: kv[0])])
    return out


@dataclass
class Zone:
    """One field group at one wavelength (energy): ``out[box] += sum_r E_r * splat(coeff_r . x[pixels])``."""

    pixels: torch.Tensor        # [n] flat display-pixel indices whose PSF uses a field of the group
    splat_index: torch.Tensor   # [J, n] flat index into the zone's FFT array (fh * fw = dump slot)
    splat_weight: torch.Tensor  # [J, n]
    coeff: torch.Tensor         # [R, n]
    kernels: torch.Tensor       # [R, fh, fw] eigen-PSFs, tap t at index t mod size (float64)
    fft_size: tuple[int, int]
    src: tuple[int, int, int, int]   # rows/cols of the FFT array that reach the frame: r0, r1, c0, c1
    dst: tuple[int, int]             # frame row/col where src (r0, c0) lands


def _build_zones(rb: "ResampledBank", zone: int, tol: float, max_rank: int | None) -> list[list[Bucket]]:
    b = rb.bank
    Gy, Gx = b.psf.shape[1:3]
    fidx, fw_ = rb.field_index, rb.field_weight.double()                   # [4, N]
    nzx = (Gx + zone - 1) // zone
    zid = (fidx // Gx // zone) * nzx + fidx % Gx // zone                   # [4, N] group of each field used
    N = fidx.shape[1]
    pix_all = torch.arange(N, device=fidx.device).expand(4, N)
    key = torch.unique(zid[fw_ > 0] * N + pix_all[fw_ > 0])                # sorted (group, pixel) pairs
    groups = key // N
    counts = torch.bincount(groups, minlength=nzx * ((Gy + zone - 1) // zone)).tolist()
    pixels_of = dict(enumerate(torch.split(key % N, counts)))
    out: list[list[Bucket]] = []
    dump = rb.Hc * rb.Wc
    for li in range(rb.L):
        boxes = rb.box_matrices(li)
        zones_l: list[Zone] = []
        for zy in range(0, Gy, zone):
            for zx in range(0, Gx, zone):
                z = (zy // zone) * nzx + zx // zone
                fields = torch.tensor([fy * Gx + fx for fy in range(zy, min(zy + zone, Gy))
                                       for fx in range(zx, min(zx + zone, Gx))], device=fidx.device)
                pix = pixels_of[z]
                if pix.numel() == 0:
                    continue
                E, A, mz = _eigen(*rb.field_kernels(li, fields, boxes), tol, max_rank)   # [R, kz, kz], [nf, R]
                R = E.shape[0]
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
                Ek = _rolled(E, fh, fwid)
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
    """Field groups with the same FFT size and rank (energy), transformed in one batched call."""

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
