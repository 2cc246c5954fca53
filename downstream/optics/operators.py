"""Shift-variant PSF operators on display-primary images (paper Eq. S3), all differentiable.

Every operator maps ``[..., L, H, W]`` primary intensities (L = the bank's wavelengths, linear
light) on the display grid to the virtual image on the same grid (scaled by the reference
magnification), and implements the discretisation in :mod:`.resampled` in the resampled bank's
radiometry (``rb.radiometry``: ``"radiance"``, the default, or the paper's ``"energy"``):

- :func:`psf_reference`: the literal reference, for tests at small sizes. Energy: every display
  pixel splats its intensity through its own blended PSF at its footprint (hand-written gather as
  the exact adjoint). Radiance: every output pixel's own blended PSF applied to the warped canvas
  as a dense per-pixel dot product (autograd). Cost ``N k^2`` per wavelength.
- :func:`psf_exact`: the same operator, exactly, as one FFT convolution per field sample (each
  pixel's PSF is a bilinear blend of 4 field PSFs, so the operator is a sum of field-weighted
  shift-invariant convolutions). The ground truth of the benchmark.
- :func:`psf_distortion`: the chief-ray warp alone (the PSF taken as a delta): the paper's
  approximation for the first 90 % of training, with the same radiometry. Cost ``O(N)``.
- :func:`psf_fast`: per group of ``zone x zone`` field samples, the eigen-PSFs ``E_r`` of the
  group (truncated SVD to relative residual ``tol``) as FFT convolutions, their coefficients
  applied per pixel (energy: ``sum_r E_r * S(a_r . x)``; radiance: ``sum_r a_r . (E_r * S x)``).
  Converges to :func:`psf_exact` as ``tol -> 0`` (exact at 0). Its cost grows with the rank and
  with the group's box plus the kernel margin (docs/explanation/optics.md: 2.4x to 3.8x for k = 129 vs 33).

Pixels that are zero in every channel are skipped in the splats when no gradient is needed
(object scenes on black). With a gradient they cannot be skipped: the gradient there is not zero.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import InputValueError

from .resampled import GatherBucket, ResampledBank

__all__ = ["psf_exact", "psf_reference", "psf_distortion", "psf_fast"]

_FLOATS = (torch.float32, torch.float64)
_CHUNK_ELEMS = 1 << 22


def _prepare(x: torch.Tensor, rb: ResampledBank, name: str = "primaries") -> tuple[torch.Tensor, tuple[int, ...]]:
    check_tensor(name, x, ["*", rb.L, rb.H, rb.W], dtypes=_FLOATS)
    if x.dtype != rb.dtype or x.device != rb.device:
        raise InputValueError(f"{name} is {x.dtype} on {x.device} but the resampled bank is {rb.dtype} on "
                              f"{rb.device}; resample the bank with the image's dtype and device")
    lead = tuple(x.shape[:-3])
    return x.reshape(-1, rb.L, rb.H * rb.W), lead


def _active(x: torch.Tensor) -> torch.Tensor | None:
    """Indices of pixels non-zero in some batch/channel, or None when skipping would not pay."""
    if torch.is_grad_enabled() and x.requires_grad:
        return None
    nz = (x != 0).any(0).any(0)
    count = int(nz.sum())
    return None if count > 0.75 * nz.numel() else nz.nonzero().squeeze(1)


def _splat(values: torch.Tensor, index: torch.Tensor, weight: torch.Tensor, size: int) -> torch.Tensor:
    """``values [B, N]`` -> canvas ``[B, size + 1]`` (last slot = dump) through footprints ``[J, N]``."""
    out = values.new_zeros(values.shape[0], size + 1)
    for j in range(index.shape[0]):
        out.index_add_(1, index[j], values * weight[j])
    return out


def _crop(canvas: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    m = rb.m
    return canvas[..., :-1].reshape(*canvas.shape[:-1], rb.Hc, rb.Wc)[..., m:m + rb.H, m:m + rb.W]


def _canvas(x: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    """``x [B, L, N]`` -> the chief-ray warp on the canvas ``[B, L, Hc Wc + 1]`` (last slot = dump)."""
    act = _active(x)
    outs = []
    for li in range(rb.L):
        idx, w, v = rb.splat_index[li], rb.splat_weight[li], x[:, li]
        if act is not None:
            idx, w, v = idx[:, act], w[:, act], v[:, act]
        outs.append(_splat(v, idx, w, rb.Hc * rb.Wc))
    return torch.stack(outs, 1)


def psf_distortion(primaries: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    """Chief-ray warp per wavelength (display-pixel footprints splatted at their chief rays; for
    radiance times the pupil transmission at each output pixel)."""
    x, lead = _prepare(primaries, rb)
    out = _crop(_canvas(x, rb), rb)
    if rb.radiometry == "radiance":
        out = out * rb.vignetting.reshape(rb.L, rb.H, rb.W)
    return out.reshape(*lead, rb.L, rb.H, rb.W)


def _skip_mask(x: torch.Tensor) -> torch.Tensor | None:
    """``[L, N]`` pixels non-zero in some batch item, or None when a gradient is needed."""
    return None if torch.is_grad_enabled() and x.requires_grad else (x != 0).any(0)


class _ZonesFn(torch.autograd.Function):
    """``sum_r E_r * splat(coeff_r . x)`` per bucket of field groups, forward and its exact adjoint
    (the same FFT convolutions with conjugate kernel spectra, then a gather through the taps)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, rb: ResampledBank, buckets: list, nz: torch.Tensor | None) -> torch.Tensor:
        ctx.rb, ctx.buckets = rb, buckets                                      # x [B, L, N]
        B = x.shape[0]
        out = x.new_zeros(B, rb.L, rb.H * rb.W)
        for li in range(rb.L):
            xl, ol = x[:, li], out[:, li]
            for bk in buckets[li]:
                tp, ti, tw = bk.tap_pixel, bk.tap_index, bk.tap_weight
                if nz is not None:
                    keep = nz[li, tp]
                    n_keep = int(keep.sum())
                    if n_keep == 0:
                        continue
                    if n_keep < 0.75 * keep.numel():
                        tp, ti, tw = tp[keep], ti[keep], tw[:, keep]
                R, Z = bk.kernel_fft.shape[:2]
                fh, fw = bk.fft_size
                arr = x.new_zeros(B * R, Z * fh * fw)
                arr.index_add_(1, ti, (xl[:, tp][:, None, :] * tw).reshape(B * R, -1))
                spec = torch.fft.rfft2(arr.view(B, R, Z, fh, fw)).mul_(bk.kernel_fft)
                res = torch.fft.irfft2(spec.sum(1) if R > 1 else spec[:, 0], s=(fh, fw))   # [B, Z, fh, fw]
                ol.index_add_(1, bk.out_index, res.reshape(B, -1)[:, bk.src_index])
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g: torch.Tensor):  # g [B, L, N]
        rb, buckets = ctx.rb, ctx.buckets
        B = g.shape[0]
        gx = g.new_zeros(B, rb.L, rb.H * rb.W)
        for li in range(rb.L):
            gl, xl = g[:, li], gx[:, li]
            for bk in buckets[li]:
                R, Z = bk.kernel_fft.shape[:2]
                fh, fw = bk.fft_size
                garr = g.new_zeros(B, Z * fh * fw)
                garr[:, bk.src_index] = gl[:, bk.out_index]
                spec = torch.fft.rfft2(garr.view(B, 1, Z, fh, fw))
                spec = spec.mul_(bk.kernel_fft.conj()) if R == 1 else spec * bk.kernel_fft.conj()
                G = torch.fft.irfft2(spec, s=(fh, fw)).reshape(B, R, -1)[..., bk.tap_index]   # [B, R, M]
                xl.index_add_(1, bk.tap_pixel, (G * bk.tap_weight).sum(1) if R > 1 else G[:, 0] * bk.tap_weight[0])
        return gx, None, None, None


_TABLE_MAX_AREA = 4096   # a bucket whose padded boxes average at most this many canvas pixels uses index tables


class _GatherFn(torch.autograd.Function):
    """``sum_r a_r . (E_r * C)`` per bucket of field groups on the warped canvas ``C`` (radiance),
    forward and its exact adjoint (FFT correlation of the weighted gradient, then an add back to
    the canvas). Each group reads and writes rectangular boxes. Size rule: a bucket whose padded
    boxes (output box plus kernel reach) average at most ``_TABLE_MAX_AREA`` pixels moves them all
    in one gather and one ``index_add_`` through its flat :meth:`GatherBucket.tables` (small sizes,
    ~900 boxes per wavelength: one Python step per box would dominate); larger boxes are moved by
    plain slices, which hold no tables in memory (1024^2 exact: all buckets). On a CUDA device every
    bucket uses tables: there a step per box is ~10 kernel launches of host time (1024x576 exact:
    ~5000 launches, 0.2 s per pass on an H100, against ~10 ms of GPU work), and the tables
    (~300 MiB at 1024x576 exact, float32) are cheap in device memory."""

    @staticmethod
    def forward(ctx, C: torch.Tensor, rb: ResampledBank, buckets: list, skip: bool) -> torch.Tensor:
        ctx.rb, ctx.buckets, ctx.size = rb, buckets, C.shape[-1]               # C [B, L, Hc Wc + 1]
        B, m = C.shape[0], rb.m
        Cv = C[..., :-1].view(B, rb.L, rb.Hc, rb.Wc)
        out = C.new_zeros(B, rb.L, rb.H * rb.W)
        ov = out.view(B, rb.L, rb.H, rb.W)
        for li in range(rb.L):
            Cl, ol = Cv[:, li], ov[:, li]
            for bk in buckets[li]:
                R, Z = bk.kernel_fft.shape[:2]
                fh, fw = bk.fft_size
                tab = _use_tables(bk)
                if tab:
                    in_slot, in_canvas, out_slot, out_index, out_weight = bk.tables(m, rb.Wc, rb.W)
                    vals = C[:, li, in_canvas]
                    if skip and not bool(vals.any()):
                        continue
                    arr = C.new_zeros(B, Z, fh, fw)
                    arr.view(B, -1)[:, in_slot] = vals
                else:
                    arr = C.new_zeros(B, Z, fh, fw)
                    for s, (r0, c0, bh, bw, mz) in enumerate(bk.boxes):
                        arr[:, s, :bh + 2 * mz, :bw + 2 * mz] = Cl[:, r0 + m - mz:r0 + m + bh + mz, c0 + m - mz:c0 + m + bw + mz]
                    if skip and not bool(arr.any()):
                        continue
                spec = torch.fft.rfft2(arr.unsqueeze(1))
                spec = spec.mul_(bk.kernel_fft) if R == 1 else spec * bk.kernel_fft
                res = torch.fft.irfft2(spec, s=(fh, fw))                           # [B, R, Z, fh, fw]
                if tab:
                    res = res.reshape(B, R, -1)[..., out_slot]                     # [B, R, M]
                    out[:, li].index_add_(1, out_index, res[:, 0] * out_weight[0] if R == 1 else (res * out_weight).sum(1))
                    continue
                for s, (r0, c0, bh, bw, mz) in enumerate(bk.boxes):
                    piece, wgt = res[:, :, s, mz:mz + bh, mz:mz + bw], bk.weights[s]
                    ol[:, r0:r0 + bh, c0:c0 + bw] += piece[:, 0] * wgt[0] if R == 1 else (piece * wgt).sum(1)
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, g: torch.Tensor):  # g [B, L, N]
        rb, buckets = ctx.rb, ctx.buckets
        B, m = g.shape[0], rb.m
        g4 = g.reshape(B, rb.L, rb.H, rb.W)
        gC = g.new_zeros(B, rb.L, ctx.size)
        gCv = gC[..., :-1].view(B, rb.L, rb.Hc, rb.Wc)
        for li in range(rb.L):
            gl, gcl = g4[:, li], gCv[:, li]
            for bk in buckets[li]:
                R, Z = bk.kernel_fft.shape[:2]
                fh, fw = bk.fft_size
                tab = _use_tables(bk)
                garr = g.new_zeros(B, R, Z, fh, fw)
                if tab:
                    in_slot, in_canvas, out_slot, out_index, out_weight = bk.tables(m, rb.Wc, rb.W)
                    garr.view(B, R, -1)[..., out_slot] = g[:, li, out_index][:, None, :] * out_weight
                else:
                    for s, (r0, c0, bh, bw, mz) in enumerate(bk.boxes):
                        garr[:, :, s, mz:mz + bh, mz:mz + bw] = gl[:, None, r0:r0 + bh, c0:c0 + bw] * bk.weights[s]
                spec = torch.fft.rfft2(garr).mul_(bk.kernel_fft.conj())            # garr already has the R axis
                G = torch.fft.irfft2(spec.sum(1) if R > 1 else spec[:, 0], s=(fh, fw))   # [B, Z, fh, fw]
                if tab:
                    gC[:, li].index_add_(1, in_canvas, G.reshape(B, -1)[:, in_slot])
                    continue
                for s, (r0, c0, bh, bw, mz) in enumerate(bk.boxes):
                    gcl[:, r0 + m - mz:r0 + m + bh + mz, c0 + m - mz:c0 + m + bw + mz] += G[:, s, :bh + 2 * mz, :bw + 2 * mz]
        return gC, None, None, None


def _use_tables(bk: GatherBucket) -> bool:
    """The size rule of :class:`_GatherFn`: index tables on CUDA, elsewhere when the bucket's padded
    boxes are small on average."""
    if bk.kernel_fft.is_cuda:
        return True
    return sum((bh + 2 * mz) * (bw + 2 * mz) for _, _, bh, bw, mz in bk.boxes) <= _TABLE_MAX_AREA * len(bk.boxes)


def _apply_zones(x: torch.Tensor, rb: ResampledBank, buckets: list) -> torch.Tensor:
    if rb.radiometry == "radiance":
        C = _canvas(x, rb)
        skip = not (torch.is_grad_enabled() and C.requires_grad)
        return _GatherFn.apply(C, rb, buckets, skip).reshape(x.shape[0], rb.L, rb.H, rb.W)
    return _ZonesFn.apply(x, rb, buckets, _skip_mask(x)).reshape(x.shape[0], rb.L, rb.H, rb.W)


def psf_fast(primaries: torch.Tensor, rb: ResampledBank, tol: float = 0.02, zone: int = 6,
             max_rank: int | None = None) -> torch.Tensor:
    """Shift-variant PSF as a sum of FFT convolutions: the field grid is split into ``zone x zone``
    groups; in each, the field PSFs are replaced by their truncated SVD (eigen-PSFs) with relative
    Frobenius residual <= ``tol`` (the accuracy knob; ``tol=0`` is exact). Cost grows with the
    number of eigen-PSFs and with each group's FFT box (its pixels plus the kernel margin)."""
    if not (isinstance(tol, (int, float)) and 0 <= tol < 1):
        raise InputValueError(f"tol must be in [0, 1), got {tol!r}")
    if not isinstance(zone, int) or zone < 1:
        raise InputValueError(f"zone must be an int >= 1, got {zone!r}")
    x, lead = _prepare(primaries, rb)
    return _apply_zones(x, rb, rb.zones(zone, tol, max_rank)).reshape(*lead, rb.L, rb.H, rb.W)


def psf_exact(primaries: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    """The operator of :mod:`.resampled`, exactly: since each pixel's PSF is a bilinear blend of
    field PSFs, ``out = sum_f H_f * S(w_f . x)`` (energy) or ``sum_f V_f . (H_f * S x)`` (radiance),
    one FFT convolution per field over the pixels that use it. Equal to :func:`psf_reference` to
    rounding; hand-written backward (the exact adjoint)."""
    x, lead = _prepare(primaries, rb)
    return _apply_zones(x, rb, rb.zones(1, 0.0)).reshape(*lead, rb.L, rb.H, rb.W)


def _tap_chunks(rb: ResampledBank):
    n = max(rb.H * rb.W, rb.Hc * rb.Wc)
    T = max(1, min(rb.k * rb.k, _CHUNK_ELEMS // n))
    for s in range(0, rb.k * rb.k, T):
        yield torch.arange(s, min(s + T, rb.k * rb.k), device=rb.device)


class _ExactPSF(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, rb: ResampledBank) -> torch.Tensor:  # x [B, L, N]
        ctx.rb = rb
        B = x.shape[0]
        H, W, m, k = rb.H, rb.W, rb.m, rb.k
        out = x.new_zeros(B, rb.L, H, W)
        act = _active(x)
        for li in range(rb.L):
            idx, w = rb.splat_index[li], rb.splat_weight[li]
            if act is not None:
                idx, w = idx[:, act], w[:, act]
            for taps in _tap_chunks(rb):
                hk = rb.pixel_kernels(li, taps)                                  # [T, N]
                if act is not None:
                    hk = hk[:, act]
                for b in range(B):
                    xb = x[b, li] if act is None else x[b, li, act]
                    S = _crop_full(_splat(hk * xb, idx, w, rb.Hc * rb.Wc), rb)   # [T, Hc, Wc]
                    for i, t in enumerate(taps.tolist()):
                        ty, tx = divmod(t, k)
                        out[b, li] += S[i, 2 * m - ty:2 * m - ty + H, 2 * m - tx:2 * m - tx + W]
        return out

    @staticmethod
    def backward(ctx, g: torch.Tensor):  # g [B, L, H, W]
        rb = ctx.rb
        H, W, m, k = rb.H, rb.W, rb.m, rb.k
        B = g.shape[0]
        gx = g.new_zeros(B, rb.L, H * W)
        for li in range(rb.L):
            idx, w = rb.splat_index[li], rb.splat_weight[li]
            for taps in _tap_chunks(rb):
                hk = rb.pixel_kernels(li, taps)
                for b in range(B):
                    G = g.new_zeros(len(taps), rb.Hc * rb.Wc + 1)
                    G2 = G[:, :-1].view(len(taps), rb.Hc, rb.Wc)
                    for i, t in enumerate(taps.tolist()):
                        ty, tx = divmod(t, k)
                        G2[i, 2 * m - ty:2 * m - ty + H, 2 * m - tx:2 * m - tx + W] = g[b, li]
                    gathered = sum(G[:, idx[j]] * w[j] for j in range(idx.shape[0]))   # [T, N]
                    gx[b, li] += (hk * gathered).sum(0)
        return gx, None


def _crop_full(canvas: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    return canvas[..., :-1].reshape(*canvas.shape[:-1], rb.Hc, rb.Wc)


def _gather_reference(x: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    """Radiance, literally: ``out[q] = sum_t h_q[t] C[q - t]`` with every output pixel's own blended
    PSF ``h_q`` (dense ``[N, k^2]``) and the warped canvas ``C``; autograd backward."""
    C = _crop_full(_canvas(x, rb), rb)                                         # [B, L, Hc, Wc]
    taps = torch.arange(rb.k * rb.k, device=rb.device)
    outs = []
    for li in range(rb.L):
        patches = torch.nn.functional.unfold(C[:, li, None], rb.k)            # [B, k^2, N]: C[q + a - m]
        outs.append((patches * rb.pixel_kernels(li, taps).flip(0)).sum(1))  # tap t = m - a
    return torch.stack(outs, 1)


def psf_reference(primaries: torch.Tensor, rb: ResampledBank) -> torch.Tensor:
    """Brute-force form of the operator, the independent reference for tests (``N k^2``). Energy:
    every display pixel's blended PSF splatted tap by tap through its footprint, hand-written
    gather backward (the exact adjoint). Radiance: every output pixel's blended PSF dotted with
    its window of the warped canvas (autograd)."""
    x, lead = _prepare(primaries, rb)
    if rb.radiometry == "radiance":
        return _gather_reference(x, rb).reshape(*lead, rb.L, rb.H, rb.W)
    return _ExactPSF.apply(x, rb).reshape(*lead, rb.L, rb.H, rb.W)
