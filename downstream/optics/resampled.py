"""A :class:`PSFBank` at one simulation resolution: everything the operators need, computed once
(the execution plans built from it, its field groups and FFT buckets, are in :mod:`.plans`, re-exported here).

Two radiometries (``radiometry``), one geometry. Display pixel ``p`` is a square; its image under
the chief-ray map (per wavelength) is the quadrilateral ``Q_p`` spanned by the chief-ray images of
its four corners (adjacent pixels share edges, so the quads tile the virtual image exactly).
``a_p(q)`` is the exact area of ``Q_p`` inside output pixel ``q`` (in output-pixel units) and
``A_p = sum_q a_p(q)`` its area, the local area magnification of the chief-ray map.

- ``"radiance"`` (default): a lossless lens conserves radiance, so the eye sees a uniform display
  as uniform, whatever the distortion and aberrations; only rays the lens aperture blocks are lost
  (the bank's traced pupil transmission ``T``). Discretised as a gather over output pixels:

      C[q]   = sum_p x[p] a_p(q)                                  (the chief-ray warp, radiance)
      out[q] = sum_f V_f(q) (H_f * C)[q],  V_f(q) = T_f b_f(d(q))

  ``H_f`` the field PSFs on the output grid, ``d(q)`` the display point whose chief ray lands on
  output pixel ``q`` (the inverse chief-ray map) and ``b_f`` the bilinear weights of the field
  samples there. Each output pixel sees a bilinear blend of field PSFs, as in the paper, but the
  blend is indexed by where the light arrives, so a flat field gives ``sum_f V_f(q) = T(q)``
  exactly: no seams on the field-sample lines, whatever the interpolant.
- ``"energy"`` (paper Eq. S3 as written): every display pixel's energy is kept and scattered
  through its own blended PSF, ``out[q] = sum_p x[p] sum_t h_p[t] a_p(q - t) / A_p``; a flat
  display falls off as ``1 / A_p`` (0.80 at mid-edge, 0.60 in the corner of the Cardboard lens).

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
from typing import TYPE_CHECKING, Literal, overload

import torch

from controlgs_adapter.errors import InputValueError

from .plans import Bucket, GatherBucket, Zone, _build_gather, _build_zones, fast_len, ladder_len

if TYPE_CHECKING:
    from ..placement import ImageRegion
    from .bank import PSFBank

__all__ = ["ResampledBank", "Zone", "Bucket", "GatherBucket", "fast_len", "ladder_len", "RADIOMETRIES",
           "Radiometry"]

Radiometry = Literal["radiance", "energy"]
RADIOMETRIES: tuple[str, ...] = ("radiance", "energy")


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


def _mean_relu(g0: torch.Tensor, g1: torch.Tensor) -> torch.Tensor:
    """Mean of ``max(g, 0)`` over a linear ``g`` from ``g0`` to ``g1`` (elementwise, stable)."""
    lo, hi = torch.minimum(g0, g1), torch.maximum(g0, g1)
    mixed = hi * hi / (2 * (hi - lo)).clamp_min(1e-300)
    return torch.where(lo >= 0, 0.5 * (lo + hi), torch.where(hi <= 0, torch.zeros_like(hi), mixed))


def quad_overlap(qx: torch.Tensor, qy: torch.Tensor, a: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Exact area of polygons inside unit pixels ``[a, a + 1] x [c, c + 1]``.

    ``qx, qy [V, ...]``: vertices in order, positive shoelace orientation (the order (x0,y0),
    (x1,y0), (x1,y1), (x0,y1) of a box with x1 > x0, y1 > y0); ``a, c [...]``. Green's theorem:
    ``-sum_edges int clamp(y - c, 0, 1) dx`` over each edge's x clipped to ``[a, a + 1]`` (the
    clipping's vertical edges add nothing). Neighbouring polygons share edges, so their overlaps
    with any pixel add up to the area of their union inside it."""
    total = torch.zeros_like(qx[0])
    V = qx.shape[0]
    for e in range(V):
        x0, y0, x1, y1 = qx[e], qy[e], qx[(e + 1) % V], qy[(e + 1) % V]
        dx = x1 - x0
        u0 = torch.maximum(torch.minimum(x0, x1), a)
        u1 = torch.minimum(torch.maximum(x0, x1), a + 1)
        slope = (y1 - y0) / torch.where(dx == 0, torch.ones_like(dx), dx)
        g0, g1 = y0 + slope * (u0 - x0) - c, y0 + slope * (u1 - x0) - c
        inner = _mean_relu(g0, g1) - _mean_relu(g0 - 1, g1 - 1)
        total = total - torch.sign(dx) * (u1 - u0).clamp_min(0) * inner
    return total


def quad_overlaps(qx: torch.Tensor, qy: torch.Tensor, x0: torch.Tensor, y0: torch.Tensor, jx: int, jy: int
                  ) -> torch.Tensor:
    """``[jy, jx, ...]``: :func:`quad_overlap` of the polygons ``qx, qy [V, ...]`` with the unit
    pixels ``[x0 + i, x0 + i + 1] x [y0 + j, y0 + j + 1]`` for all ``j < jy, i < jx`` at once. Per
    edge, the clipped x-interval and its end heights are shared by a column of pixels, and the
    band integral ``int clamp(y - c, 0, 1)`` is the difference of the half-plane integrals
    ``int max(y - c, 0)`` at ``c`` and ``c + 1``, shared by vertically adjacent pixels."""
    dt = qx.dtype
    ax = x0 + torch.arange(jx, dtype=dt).reshape(jx, *([1] * x0.dim()))            # [jx, ...] pixel left edges
    cy = y0 + torch.arange(jy + 1, dtype=dt).reshape(jy + 1, 1, *([1] * y0.dim()))   # [jy + 1, 1, ...]
    total = torch.zeros(jy, jx, *qx.shape[1:], dtype=dt)
    V = qx.shape[0]
    for e in range(V):
        x0e, y0e, x1e, y1e = qx[e], qy[e], qx[(e + 1) % V], qy[(e + 1) % V]
        dx = x1e - x0e
        u0 = torch.maximum(torch.minimum(x0e, x1e), ax)
        u1 = torch.minimum(torch.maximum(x0e, x1e), ax + 1)
        slope = (y1e - y0e) / torch.where(dx == 0, torch.ones_like(dx), dx)
        ya, yb = y0e + slope * (u0 - x0e), y0e + slope * (u1 - x0e)            # [jx, ...]
        half = _mean_relu(ya - cy, yb - cy)                                     # [jy + 1, jx, ...]
        total -= (torch.sign(dx) * (u1 - u0).clamp_min(0)) * (half[:-1] - half[1:])
    return total


def _bilinear_axis(f: torch.Tensor, u: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Lower/upper sample index and fraction of ``u`` on the increasing samples ``f`` (constant beyond)."""
    f = f.double().to(u.device)
    if len(f) == 1:
        z = torch.zeros_like(u, dtype=torch.long)
        return z, z, torch.zeros_like(u)
    j = torch.searchsorted(f, u.contiguous()).clamp(1, len(f) - 1)
    a = ((u - f[j - 1]) / (f[j] - f[j - 1])).clamp(0, 1)
    return j - 1, j, a


def _bilinear_fields(fx: torch.Tensor, fy: torch.Tensor, x: torch.Tensor, y: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """``[4, *x.shape]`` flat field indices and bilinear weights at display points ``(x, y)``."""
    x0, x1, ax = _bilinear_axis(fx, x)
    y0, y1, ay = _bilinear_axis(fy, y)
    Gx = len(fx)
    idx = torch.stack([y0 * Gx + x0, y0 * Gx + x1, y1 * Gx + x0, y1 * Gx + x1])
    w = torch.stack([(1 - ay) * (1 - ax), (1 - ay) * ax, ay * (1 - ax), ay * ax])
    return idx, w


#: quads per chunk of the footprint computation (temporaries of this many float64 stay in cache)
_FOOTPRINT_CHUNK = 1 << 12

#: landing-point grid (per side) on which the inverse chief-ray map is solved before interpolation
INVERSE_GRID = 129


def _keys(f: torch.Tensor) -> torch.Tensor:
    """``[..., 4]`` Keys cubic convolution weights (a = -1/2) of the samples ``i - 1 .. i + 2`` at fraction ``f``."""
    return torch.stack([((-0.5 * f + 1.0) * f - 0.5) * f, (1.5 * f - 2.5) * f * f + 1.0,
                        ((-1.5 * f + 2.0) * f + 0.5) * f, (0.5 * f - 0.5) * f * f], -1)


def _pad_quadratic(g: torch.Tensor) -> torch.Tensor:
    """Extend a grid ``[L, n, m, C]`` by one sample each side (dims 1, 2) by quadratic extrapolation."""
    g = torch.cat([3 * g[:, :1] - 3 * g[:, 1:2] + g[:, 2:3], g, 3 * g[:, -1:] - 3 * g[:, -2:-1] + g[:, -3:-2]], 1)
    return torch.cat([3 * g[:, :, :1] - 3 * g[:, :, 1:2] + g[:, :, 2:3], g,
                      3 * g[:, :, -1:] - 3 * g[:, :, -2:-1] + g[:, :, -3:-2]], 2)


def _keys_matrix(t: torch.Tensor, n: int) -> torch.Tensor:
    """``[len(t), n + 2]``: Keys cubic interpolation at ``t`` in [-1, 1] (and a little beyond) from
    ``n`` uniform samples ``linspace(-1, 1, n)`` padded by one each side (:func:`_pad_quadratic`)."""
    g = (t.double() + 1) / 2 * (n - 1)
    i = torch.floor(g).clamp(0, n - 2)
    M = torch.zeros(len(t), n + 2, dtype=torch.float64)
    M.scatter_add_(1, i.long()[:, None] + torch.arange(4), _keys(g - i))
    return M


def _keys_eval(grid: torch.Tensor, my: torch.Tensor, mx: torch.Tensor) -> torch.Tensor:
    """Separable Keys cubic of a padded grid ``[L, n + 2, m + 2, C]`` on the tensor grid of
    ``my [H, n + 2]`` x ``mx [W, m + 2]``: ``[L, H, W, C]``."""
    return torch.einsum("ia,labc,jb->lijc", my, grid, mx)


class ResampledBank:
    """Per-resolution tables (see module docstring). Build through :meth:`PSFBank.resample_to`.

    Attributes (``L`` wavelengths, ``N = H W``, ``G`` field samples, ``J`` footprint taps):
        splat_index, splat_weight: ``[L, J, N]`` canvas index (dump slot ``Hc Wc``) and weight of
            each display pixel's footprint: the overlap area ``a_p(q)`` (radiance) or ``a_p(q) / A_p``
            (energy).
        area: ``[L, N]`` area magnification ``A_p`` of the chief-ray map (output px per display px).
        field_index, field_weight: ``[4, N]`` bilinear field blend at each display pixel (energy).
        out_field_index, out_field_weight: ``[L, 4, N]`` bilinear field blend at the display point
            whose chief ray lands on each output pixel (radiance).
        transmission: ``[L, G]`` traced pupil transmission per field sample (1 where the bank has none).
        vignetting: ``[L, N]`` ``T`` blended at each output pixel (radiance; ones for energy).
    """

    def __init__(self, bank: "PSFBank", height: int, width: int, region: "ImageRegion", *, device: torch.device,
                 dtype: torch.dtype, radiometry: Radiometry = "radiance"):
        if radiometry not in RADIOMETRIES:
            raise InputValueError(f"radiometry must be one of {RADIOMETRIES}, got {radiometry!r}")
        self.bank, self.H, self.W, self.device, self.dtype = bank, height, width, device, dtype
        self.region, self.radiometry = region, radiometry
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
        self.transmission = bank.transmission.reshape(self.L, -1).to(device, torch.float64)
        self.field_index, self.field_weight = self._field_weights()   # [4, N] long, [4, N]
        self.splat_index, self.splat_weight, self.area = self._footprints()   # [L, J, N] x2, [L, N]
        if radiometry == "radiance":
            self.out_field_index, self.out_field_weight = self._output_field_weights()   # [L, 4, N]
            t = torch.stack([self.transmission[li][self.out_field_index[li]] for li in range(self.L)])
            self.vignetting = (t * self.out_field_weight.double()).sum(1).to(dtype)     # [L, N]
        else:
            self.vignetting = torch.ones(self.L, height * width, device=device, dtype=dtype)

    # ----------------------------------------------------------------- per-pixel field blending
    def _pixel_centres(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``[H, W]`` display-normalised x and y of the image pixel centres."""
        u = ((2 * torch.arange(self.W, dtype=torch.float64) + 1) / self.W - 1) * self.region.half_x
        v = ((2 * torch.arange(self.H, dtype=torch.float64) + 1) / self.H - 1) * self.region.half_y
        V, U = torch.meshgrid(v, u, indexing="ij")
        return U, V

    def _field_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        U, V = self._pixel_centres()
        idx, w = _bilinear_fields(self.bank.field_x, self.bank.field_y, U, V)
        return idx.reshape(4, -1).to(self.device), w.reshape(4, -1).to(self.device, self.dtype)

    def _output_field_weights(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Field blend of each output pixel: bilinear weights at the display point ``d(q)`` whose
        chief ray lands on the pixel's centre. The inverse chief-ray map is solved by Newton on the
        cubic interpolant at the nodes of a uniform ``INVERSE_GRID``-square grid of landing points
        and interpolated from there with the same cubic (error < 1e-6 of the half-width: tested)."""
        n = INVERSE_GRID
        t = torch.linspace(-1, 1, n, dtype=torch.float64)
        ty, tx = (g.expand(self.L, -1, -1) for g in torch.meshgrid(t, t, indexing="ij"))
        dx, dy = tx.clone(), ty.clone()
        for _ in range(8):
            c, (j11, j12, j21, j22) = self._chief_at(dx, dy, per_wavelength=True, jacobian=True)
            rx, ry = tx - c[..., 0], ty - c[..., 1]
            det = j11 * j22 - j12 * j21
            dx, dy = dx + (j22 * rx - j12 * ry) / det, dy + (j11 * ry - j21 * rx) / det
        c = self._chief_at(dx, dy, per_wavelength=True)
        err = torch.maximum((c[..., 0] - tx).abs(), (c[..., 1] - ty).abs()).max().item()
        if not err < 1e-10:
            raise InputValueError(f"PSF bank: the chief-ray map cannot be inverted (residual {err:.3g})")
        U, V = self._pixel_centres()
        my, mx = _keys_matrix(V[:, 0], n), _keys_matrix(U[0], n)
        d = _keys_eval(_pad_quadratic(torch.stack([dx, dy], -1)), my, mx)          # [L, H, W, 2]
        idx, w = _bilinear_fields(self.bank.field_x, self.bank.field_y, d[..., 0], d[..., 1])   # [4, L, H, W]
        return (idx.transpose(0, 1).reshape(self.L, 4, -1).to(self.device),
                w.transpose(0, 1).reshape(self.L, 4, -1).to(self.device, self.dtype))

    # ----------------------------------------------------------------- chief-ray footprints
    @overload
    def _chief_at(self, u: torch.Tensor, v: torch.Tensor, per_wavelength: bool = ..., jacobian: Literal[False] = ...
                  ) -> torch.Tensor: ...

    @overload
    def _chief_at(self, u: torch.Tensor, v: torch.Tensor, per_wavelength: bool = ..., *, jacobian: Literal[True]
                  ) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]: ...

    def _chief_at(self, u: torch.Tensor, v: torch.Tensor, per_wavelength: bool = False, jacobian: bool = False
                  ) -> torch.Tensor | tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        """Chief-ray landing ``[L, *u.shape, 2]`` (normalised) at normalised display points ``u, v``
        (the same for every wavelength, or ``[L, ...]`` with ``per_wavelength``; then ``[*u.shape, 2]``).
        With ``jacobian``, also its derivatives ``(dX/du, dX/dv, dY/du, dY/dv)``.

        Separable Keys cubic convolution (a = -1/2: reproduces quadratics, C1), so the derivative,
        the local magnification, is continuous and a flat field shows no steps at grid lines.
        The grid is extended by one sample each side by quadratic extrapolation."""
        ch = _pad_quadratic(self.bank.chief.double().to(u.device))             # [L, Cy + 2, Cx + 2, 2]
        Cy, Cx = self.bank.chief.shape[1:3]
        L, shape = self.L, u.shape
        ch = ch.reshape(L, -1, 2)

        def taps(t: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
            g = (t.double() + 1) / 2 * (n - 1)                                 # grid units, 0..n-1
            i = torch.floor(g).clamp(0, n - 2)
            f = g - i
            w = _keys(f)
            dw = torch.stack([(-1.5 * f + 2.0) * f - 0.5, (4.5 * f - 5.0) * f, (-4.5 * f + 4.0) * f + 0.5,
                              (1.5 * f - 1.0) * f], -1) * ((n - 1) / 2)
            return i.long()[..., None] + torch.arange(4, device=t.device), w, dw   # padded grid index

        u, v = u.reshape(L, -1) if per_wavelength else u.reshape(-1), v.reshape(L, -1) if per_wavelength else v.reshape(-1)
        outs: list[list[torch.Tensor]] = []
        step = 1 << 16
        for s in range(0, u.shape[-1], step):
            iy, wy, dwy = taps(v[..., s:s + step], Cy)
            ix, wx, dwx = taps(u[..., s:s + step], Cx)
            flat = (iy[..., :, None] * (Cx + 2) + ix[..., None, :]).flatten(-2)     # [(L,) P, 16]
            vals = torch.stack([ch[li, flat[li] if per_wavelength else flat] for li in range(L)])   # [L, P, 16, 2]
            parts = [(wy[..., :, None] * wx[..., None, :])]
            if jacobian:
                parts += [wy[..., :, None] * dwx[..., None, :], dwy[..., :, None] * wx[..., None, :]]
            outs.append([torch.einsum("...k,l...kc->l...c" if not per_wavelength else "l...k,l...kc->l...c",
                                      p.flatten(-2), vals) for p in parts])
        res = [torch.cat([o[i] for o in outs], -2) for i in range(len(outs[0]))]
        lead = shape[1:] if per_wavelength else shape
        val = res[0].reshape(L, *lead, 2)
        if not jacobian:
            return val
        du, dv = res[1].reshape(L, *lead, 2), res[2].reshape(L, *lead, 2)
        return val, (du[..., 0], dv[..., 0], du[..., 1], dv[..., 1])

    def corners(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``[L, H + 1, W + 1]`` canvas x and y (output px) of the chief-ray images of the pixel corners."""
        H, W, m = self.H, self.W, self.m
        sx, sy = self.region.half_x, self.region.half_y
        ue = 2 * torch.arange(W + 1, dtype=torch.float64) / W - 1
        ve = 2 * torch.arange(H + 1, dtype=torch.float64) / H - 1
        ch = _keys_eval(_pad_quadratic(self.bank.chief.double()), _keys_matrix(ve * sy, self.bank.chief.shape[1]),
                        _keys_matrix(ue * sx, self.bank.chief.shape[2]))
        return (ch[..., 0] / sx + 1) * W / 2 + m, (ch[..., 1] / sy + 1) * H / 2 + m

    def _footprints(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Exact footprints: each display pixel's quad (chief-ray images of its corners; the image
        pixel's display position is ``u`` times the region's half-extent, landing points divided by
        it) intersected with the output pixels of the canvas (:func:`quad_overlaps`), in chunks of
        pixels (the temporaries stay in cache), each over the offsets its own quads reach."""
        X, Y = self.corners()
        L, N, dump = self.L, self.H * self.W, self.Hc * self.Wc
        qx = torch.stack([X[:, :-1, :-1], X[:, :-1, 1:], X[:, 1:, 1:], X[:, 1:, :-1]]).reshape(4, L, -1)
        qy = torch.stack([Y[:, :-1, :-1], Y[:, :-1, 1:], Y[:, 1:, 1:], Y[:, 1:, :-1]]).reshape(4, L, -1)
        del X, Y
        cross = [qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4)]
        area = 0.5 * (cross[0] + cross[1] + cross[2] + cross[3])                # [L, N]
        del cross
        if not (area > 0).all():
            raise InputValueError("PSF bank: the chief-ray map folds over (not monotonic) at this resolution")
        x0, y0 = torch.floor(qx.min(0).values), torch.floor(qy.min(0).values)
        ex = (torch.ceil(qx.max(0).values) - x0).long()                          # [L, N] extent in output px
        ey = (torch.ceil(qy.max(0).values) - y0).long()
        jx, jy = int(ex.max()), int(ey.max())
        ox = torch.arange(jx).repeat(jy)[None, :, None]                          # offset j = oy * jx + ox
        oy = torch.arange(jy).repeat_interleave(jx)[None, :, None]
        ix0, iy0 = x0.long(), y0.long()

        def inside_of(sel: slice | torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            px, py = ix0[:, None, sel] + ox, iy0[:, None, sel] + oy                # [L, J, n]
            return (px >= 0) & (px < self.Wc) & (py >= 0) & (py < self.Hc), py * self.Wc + px

        # canvas index of every offset; offsets outside the canvas (only pixels near its edge
        # can reach there) go to the dump slot
        idx = (iy0 * self.Wc + ix0)[:, None, :] + (oy * self.Wc + ox)
        edge = ((ix0 < 0) | (ix0 + jx > self.Wc) | (iy0 < 0) | (iy0 + jy > self.Hc)).any(0)   # [N]
        at_edge = edge.nonzero().squeeze(1)
        if at_edge.numel():
            inside, flat = inside_of(at_edge)
            idx[:, :, at_edge] = torch.where(inside, flat, dump)
        wts = torch.zeros(L, jy, jx, N, dtype=self.dtype)
        step = max(1, _FOOTPRINT_CHUNK // L)
        for s in range(0, N, step):
            sl = slice(s, s + step)  # a slice past the end stops at N
            cjx, cjy = int(ex[:, sl].max()), int(ey[:, sl].max())
            w = quad_overlaps(qx[:, :, sl], qy[:, :, sl], x0[:, sl], y0[:, sl], cjx, cjy).clamp_min(0)   # [cjy, cjx, L, n]
            if self.radiometry == "energy":
                w = w / area[:, sl]
            if bool(edge[sl].any()):
                ins = inside_of(sl)[0].view(L, jy, jx, -1)[:, :cjy, :cjx].permute(1, 2, 0, 3)
                w = torch.where(ins, w, 0)
            wts[:, :cjy, :cjx, sl] = w.permute(2, 0, 1, 3)
        return idx.to(self.device), wts.reshape(L, jy * jx, N).to(self.device), area.to(self.device, self.dtype)

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

    def box_matrices(self, li: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``[G, k, K]`` x 2: the box-overlap matrices (rows, columns) of every field at wavelength ``li``."""
        K = self.bank.psf.shape[-1]
        p = self.bank.psf_pitch_mm[li].reshape(-1).double()
        return _box_matrix(p / self._px[1], K, self.m), _box_matrix(p / self._px[0], K, self.m)

    def field_kernels(self, li: int, fields: torch.Tensor, boxes: tuple[torch.Tensor, torch.Tensor] | None = None
                      ) -> tuple[torch.Tensor, int]:
        """``[nf, 2 r + 1, 2 r + 1]`` float64: the kernels of ``fields`` (flat field indices) at
        wavelength ``li``, the taps ``-r .. r`` of :attr:`kernels` with ``r <= m`` the reach of
        these fields (beyond it their kernels are 0), computed without the full ``[L, G, k, k]``
        table; and ``r``. ``boxes``: :meth:`box_matrices` of ``li`` when a caller asks for many groups."""
        b = self.bank
        K = b.psf.shape[-1]
        f = fields.cpu()
        p = b.psf_pitch_mm[li].reshape(-1)[f].double()
        reach = float(p.max()) * (K // 2 + 0.5) / min(self._px)
        r = min(self.m, int(math.ceil(reach - 0.5 - 1e-9)))
        if boxes is None:
            wy, wx = _box_matrix(p / self._px[1], K, r), _box_matrix(p / self._px[0], K, r)   # [nf, 2r+1, K]
        else:
            wy, wx = (bx[f, self.m - r:self.m + r + 1] for bx in boxes)
        out = torch.einsum("gtk,gkl,gsl->gts", wy, b.psf[li].reshape(-1, K, K)[f].double(), wx)
        return out.to(self.device), r

    def pixel_kernels(self, li: int, taps: torch.Tensor) -> torch.Tensor:
        """``[T, N]``: value of tap ``taps`` (flat index into ``k x k``) of every display pixel's
        blended PSF (energy) or of every output pixel's (radiance, transmission included)."""
        kf = self.kernels[li].reshape(self.kernels.shape[1], -1)[:, taps]   # [G, T]
        if self.radiometry == "radiance":
            idx = self.out_field_index[li]
            w = self.out_field_weight[li] * self.transmission[li][idx].to(self.dtype)
        else:
            idx, w = self.field_index, self.field_weight
        out = kf[idx[0]] * w[0, :, None]
        for i in range(1, 4):
            out = out + kf[idx[i]] * w[i, :, None]
        return out.T

    def zones(self, zone: int, tol: float, max_rank: int | None = None) -> list[list]:
        """Field-group decomposition of the operator (cached), per wavelength a list of buckets: the
        fields are split into groups of ``zone x zone``; within a group, the kernels are replaced
        by their truncated SVD with the smallest rank whose relative Frobenius residual is <= ``tol``
        (capped by ``max_rank``). Because each pixel's PSF is a bilinear blend of field PSFs,
        ``zone=1`` (any tol) and ``tol=0`` are exact. Radiance: :class:`GatherBucket` (the field
        blend applied where the light arrives); energy: :class:`Bucket` (where it leaves)."""
        key = (zone, float(tol), max_rank)
        if key not in self._zones:
            build = _build_gather if self.radiometry == "radiance" else _build_zones
            self._zones[key] = build(self, zone, float(tol), max_rank)
        return self._zones[key]
