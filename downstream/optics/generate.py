"""Build a :class:`PSFBank` from a lens prescription with the built-in ray tracer (numpy only).

PSF model per field point and wavelength (documented in ``docs/explanation/optics.md``):

1. the chief ray (through the pupil centre) gives the landing point on the virtual image plane;
2. a ``N x N`` grid of launch slopes (aimed through the chief ray's slope -> pupil Jacobian) is
   traced; each ray stands for the pupil area of its grid cell (the determinant of the traced
   slope -> pupil map times the cell, so the pupil is sampled uniformly in area, not in slope);
   rays that miss the 4 mm pupil, a lens aperture or refract totally are dropped; the rest cross
   the virtual image plane at the geometric spot (eye accommodated to that plane); the pupil
   transmission is the pupil area of the passing rays (primary branch) over the pupil's area;
3. the spot, binned into the ``K x K`` box cells, is convolved with the diffraction-limited Airy
   pattern of the pupil (exact in both limits: Airy at the diffraction-limited centre, geometric
   spot where aberrations dominate; approximate in between).

A rotationally symmetric lens (no decentre, tilt or display offset) has its spots traced once per
distinct field radius in the meridional plane and rotated to each field, and its chief rays found
by the meridional search; any other lens has every field point's spot traced directly (launch grid
aimed through the full 2 x 2 slope -> pupil Jacobian) and its chief rays found by the 2-D search.
Chief rays are stored in display-centred normalised output coordinates: ``axis + landing about the
axis / reference magnification`` (a distortion-free lens maps every display point to itself).
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
import torch

from controlgs_adapter.checks import brief
from controlgs_adapter.errors import InputValueError

from .bank import PSFBank
from .prescription import CARDBOARD, Prescription
from .raytrace import chief_ray, chief_ray_2d, paraxial, real_magnification, trace

__all__ = ["build_bank", "lens_figures"]

ASSUMPTIONS = [
    "eye pupil fixed on the optical axis at the eye-relief distance (no eye rotation, no pupil swim)",
    "eye accommodated to the virtual image plane at virtual_image_distance_mm (667 mm); PSFs are ray "
    "crossings of that plane, seen from the pupil centre",
    "PSF = geometric spot (pupil grid) convolved with the Airy pattern of the pupil (scalar, monochromatic)",
    "only the primary image branch is modelled: near the lens rim the display corner is also seen a second "
    "time through a fold of the rim zone; those rays are outside the local pupil grid and are not in the bank",
    "PSFs are normalised to unit sum; the pupil transmission per field (rays blocked by a lens aperture, "
    "uniform pupil-area weighting) times the prescription's efficiency (the modelled path's throughput; light "
    "on other paths, e.g. a pancake's ghosts, is not modelled) is recorded in meta.transmission and applied by "
    "the radiance radiometry",
    "each display primary is one wavelength (656 / 550 / 486 nm)",
]


def _airy(r_norm: np.ndarray) -> np.ndarray:
    """Airy intensity ``(2 J1(x) / x)^2`` at ``x = 1.2197 * pi * r_norm`` (``r_norm = 1``: first zero)."""
    x = torch.as_tensor(1.21967 * math.pi * r_norm, dtype=torch.float64)
    j = torch.special.bessel_j1(x)
    out = torch.where(x > 1e-8, (2 * j / x.clamp_min(1e-8)) ** 2, torch.ones_like(x))
    return out.numpy()


def _bin(dx: np.ndarray, dy: np.ndarray, pitch: float, K: int, weight: np.ndarray) -> np.ndarray:
    """Box-cell histogram (bilinear) of weighted points, centred on sample K // 2."""
    c = K // 2
    fx, fy = dx / pitch + c, dy / pitch + c
    x0, y0 = np.floor(fx).astype(np.int64), np.floor(fy).astype(np.int64)
    ax, ay = fx - x0, fy - y0
    out = np.zeros(K * K)
    for ox, wx in ((0, 1 - ax), (1, ax)):
        for oy, wy in ((0, 1 - ay), (1, ay)):
            xi, yi = np.clip(x0 + ox, 0, K - 1), np.clip(y0 + oy, 0, K - 1)
            out += np.bincount(yi * K + xi, weights=wx * wy * weight, minlength=K * K)
    return out.reshape(K, K)


def _pupil_area(xp: np.ndarray, yp: np.ndarray, hu: float, hv: float) -> np.ndarray:
    """Signed pupil area (mm^2) each ray of an ``n x n`` launch-slope grid (steps ``hu`` along axis
    1, ``hv`` along axis 0) stands for: ``det d(xp, yp) / d(u, v) hu hv`` by central differences
    (one-sided at the grid's edge); its sign flips past a fold of the map; NaN where a neighbour
    is not finite."""
    with np.errstate(invalid="ignore"):
        xu, xv = np.gradient(xp, axis=1) / hu, np.gradient(xp, axis=0) / hv
        yu, yv = np.gradient(yp, axis=1) / hu, np.gradient(yp, axis=0) / hv
        return (xu * yv - xv * yu) * hu * hv


def _spot(rx: Prescription, lam: float, r: float, v0: float, Y0: float, n: int
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """Geometric spot of display height ``r`` (mm, meridional: field on +y) on the virtual image plane.

    A square grid of launch slopes, aimed through the chief ray's slope -> pupil Jacobian, is
    widened (and refined to keep ~``n`` rays across the pupil) until its outline lands outside the
    pupil, i.e. it covers the whole disc (the aim is linear, the map is not: a missed sliver of
    the rim, 0.1 % of the area, moved the mid-edge coma centroid by 0.02 px). Returns the
    kept rays' offsets from the chief ray ``(x, y)`` (mm on the image plane), their pupil areas
    (the weights: uniform in pupil area; rim cells by the fraction inside the disc), the
    transmission (pupil area whose rays pass every aperture on the primary branch, over the
    pupil's area) and the fraction of the pupil the primary branch covers."""
    eps = 1e-6
    xp_a, yp_a, _, _, _ = trace(rx, lam, 0.0, r, np.array([0.0, eps, 0.0]), v0 + np.array([0.0, 0.0, eps]))
    jx, jy = (xp_a[1] - xp_a[0]) / eps, (yp_a[2] - yp_a[0]) / eps
    return _spot_traced(rx, lam, (0.0, r), (0.0, v0), (0.0, Y0), n, np.array([[jx, 0.0], [0.0, jy]]))


def _spot_2d(rx: Prescription, lam: float, xy: tuple[float, float], uv0: tuple[float, float],
             XY0: tuple[float, float], n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """:func:`_spot` of display point ``xy`` (mm from the lens axis) of any lens, its chief ray's slopes
    ``uv0`` and landing ``XY0``: the launch grid is aimed through the full 2 x 2 slope -> pupil Jacobian."""
    eps = 1e-6
    xa, ya, _, _, _ = trace(rx, lam, xy[0], xy[1], uv0[0] + np.array([0.0, eps, 0.0]), uv0[1] + np.array([0.0, 0.0, eps]))
    jac = np.array([[xa[1] - xa[0], xa[2] - xa[0]], [ya[1] - ya[0], ya[2] - ya[0]]]) / eps
    return _spot_traced(rx, lam, xy, uv0, XY0, n, jac)


def _spot_traced(rx: Prescription, lam: float, xy: tuple[float, float], uv0: tuple[float, float],
                 XY0: tuple[float, float], n: int, jac: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
    """The spot of :func:`_spot` from display point ``xy`` around the chief ray (slopes ``uv0``, landing
    ``XY0``), the launch grid aimed through ``jac`` = d(xp, yp) / d(u, v) (diagonal: the meridional case)."""
    pr = rx.pupil_radius
    (ja, jb), (jc, jd) = jac
    diagonal = jb == 0.0 and jc == 0.0
    for span in (1.02, 1.2, 1.45, 1.75, 2.1):
        m = int(round(n * span / 1.02))
        g = ((np.arange(m) + 0.5) / m * 2 - 1) * span * pr
        GX, GY = np.meshgrid(g, g)
        if diagonal:
            PX, PY = uv0[0] + GX / ja, uv0[1] + GY / jd
        else:
            det = ja * jd - jb * jc
            PX, PY = uv0[0] + (jd * GX - jb * GY) / det, uv0[1] + (ja * GY - jc * GX) / det
        xp, yp, Xs, Ys, ok = trace(rx, lam, xy[0], xy[1], PX, PY)
        rim = np.concatenate([xp[[0, -1]].ravel() ** 2 + yp[[0, -1]].ravel() ** 2,
                              xp[:, [0, -1]].ravel() ** 2 + yp[:, [0, -1]].ravel() ** 2])
        if (rim > pr * pr).all():                       # the grid's outline lands outside the pupil
            break
    if diagonal:
        area = _pupil_area(xp, yp, 2 * span * pr / m / ja, 2 * span * pr / m / jd) * np.sign(ja * jd)
    else:                                               # per grid cell of the aimed (pupil-mm) targets
        area = _pupil_area(xp, yp, 2 * span * pr / m, 2 * span * pr / m)
    primary = np.isfinite(area) & (area > 0)            # past a fold (second image) the sign flips
    cell = np.sqrt(np.abs(np.where(primary, area, 0.0)))
    with np.errstate(invalid="ignore", divide="ignore"):
        inside = np.clip(0.5 + (pr - np.hypot(xp, yp)) / cell, 0.0, 1.0)     # rim cells: fraction in the disc
    w = np.where(primary, area * inside, 0.0)
    keep = ok & (w > 0)
    full = math.pi * pr * pr
    return (Xs[keep] - XY0[0], Ys[keep] - XY0[1], w[keep], min(float(w[keep].sum() / full), 1.0),
            float(w.sum() / full))


def _airy_kernel(pitch: float, r_airy: float, K: int, supersample: int = 5) -> np.ndarray:
    """Airy pattern integrated over ``K x K`` box cells of ``pitch`` (unit sum)."""
    c = K // 2
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    g = ((np.arange(K) - c)[:, None] + sub[None, :]).ravel() * pitch  # [K * s]
    r = np.hypot(g[:, None], g[None, :]) / r_airy
    a = _airy(r).reshape(K, supersample, K, supersample).sum((1, 3))
    return a / a.sum()


def _conv_same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Linear convolution of two square ``K x K`` arrays cropped to the centred ``K x K`` (negative
    FFT round-off clipped to 0)."""
    K = len(a)
    n = 2 * K - 1
    f = np.fft.irfft2(np.fft.rfft2(a, (n, n)) * np.fft.rfft2(b, (n, n)), (n, n))
    c = K // 2
    return np.clip(f[c:c + K, c:c + K], 0, None)


def lens_figures(rx: Prescription) -> dict[str, Any]:
    """Paraxial and real-ray figures of merit (per wavelength) for reports and the bank's meta.

    Rotationally symmetric lens: the display corner's chief-ray landing (px from the centre at 1024 px
    across, per axis) and its radial distortion. Any other lens: the same at the 4 display corners
    (-x -y, +x -y, -x +y, +x +y): landings ``[x, y]`` in px from the display centre (a distortion-free
    lens: +-512) and distortion radial about the lens axis; paraxial figures only where every surface is
    centred (else ``None``)."""
    out: dict[str, Any] = {}
    m_ref = real_magnification(rx, rx.reference_wavelength)
    half = rx.display_mm[0] / 2
    corner = math.hypot(*rx.display_mm) / 2
    centred = not any(sf.moved for sf in rx.surfaces)
    for lam in rx.wavelengths:
        p = paraxial(rx, lam) if centred else None
        fig: dict[str, Any] = {"efl_mm": None if p is None else p.efl,
                               "paraxial_image_distance_mm": None if p is None else p.image_distance,
                               "paraxial_magnification": None if p is None else p.magnification,
                               "chief_magnification_on_image_plane": real_magnification(rx, lam)}
        if rx.rotationally_symmetric:
            _, Y, ok = chief_ray(rx, lam, np.array([corner]))
            fig["corner_landing_px_at_1024"] = float(Y[0] / m_ref / corner * 512)  # per axis, from the centre (corner: 512)
            fig["corner_distortion_pct"] = float((Y[0] / m_ref / corner - 1) * 100)
        else:
            (ox, oy), (hw, hh) = rx.display_offset, (rx.display_mm[0] / 2, rx.display_mm[1] / 2)
            cx, cy = np.array([-hw, hw, -hw, hw]) - ox, np.array([-hh, -hh, hh, hh]) - oy   # about the lens axis
            _, _, X, Y, ok = chief_ray_2d(rx, lam, cx, cy)
            fig["corner_landing_px_at_1024"] = [[float((ox + a / m_ref) / hw * 512), float((oy + b / m_ref) / hh * 512)]
                                                for a, b in zip(X, Y)]
            fig["corner_distortion_pct"] = [float((np.hypot(a, b) / m_ref / np.hypot(c, d) - 1) * 100)
                                            for a, b, c, d in zip(X, Y, cx, cy)]
        out[f"{lam:g}nm"] = fig
    out["reference_magnification"] = m_ref
    out["px_per_mm_display_at_1024"] = 1024 / rx.display_mm[0]
    out["mm_on_image_plane_per_px_at_1024"] = m_ref * rx.display_mm[0] / 1024
    out["half_width_mm"] = half
    return out


def _check_int(name: str, value: Any, low: int, *, odd: bool = False) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low or (odd and value % 2 == 0):
        raise InputValueError(f"{name} must be {'an odd' if odd else 'an'} integer >= {low}, got {brief(value)}")
    if value > 2**31 - 1:  # a sample count or grid side; beyond int32 it overflows the float and int maths
        raise InputValueError(f"{name} must be {'an odd' if odd else 'an'} integer >= {low} and <= 2147483647, "
                              f"got {brief(value)}")


def _psf(dx: np.ndarray, dy: np.ndarray, wt: np.ndarray, r_airy: float, min_pitch: float, K: int
         ) -> tuple[np.ndarray, float]:
    """A ``K x K`` PSF (unit sum) and its pitch (mm) from a spot's offsets ``dx, dy`` (display-equivalent
    mm) and weights: the pitch fits the spot plus 3 Airy radii, at least ``min_pitch``."""
    extent = max(np.abs(dx).max(initial=0.0), np.abs(dy).max(initial=0.0)) + 3 * r_airy
    p = max(min_pitch, extent / (K // 2 - 0.5))
    img = _conv_same(_bin(dx, dy, p, K, wt), _airy_kernel(p, r_airy, K))
    return img / img.sum(), p


def build_bank(prescription: Mapping[str, Any] | Prescription | None = None, *, grid: tuple[int, int] = (30, 30),
               psf_size: int = 33, pupil_samples: int = 192, chief_grid: tuple[int, int] = (65, 65),
               min_pitch_px: float = 0.125, reference_width_px: int = 1024, progress: bool = False,
               use_symmetry: bool = True) -> PSFBank:
    """Trace a PSF bank. ``min_pitch_px`` is the finest PSF sample pitch, in display pixels at
    ``reference_width_px`` across the display (1/8 px at 1024 px by default). ``progress=True`` prints
    one line per traced wavelength to stdout (``controlgs optics build-bank`` turns it on); by default a
    library call prints nothing. ``meta["generator"]["min_pupil_coverage"]`` is the smallest fraction
    of the eye pupil's area the traced rays cover, over field radii and wavelengths, rounded to 5
    decimals and at most 1 (a quadrature that sums slightly over the disc's area reads as full coverage).
    ``use_symmetry=False`` traces every field point and chief ray in 2-D even on a rotationally
    symmetric lens (what any other lens gets). ``meta["transmission"]`` is the pupil transmission times
    the prescription's ``efficiency``; ``meta["lens"]`` records the lens axis on the display (normalised
    coordinates) and whether the lens is rotationally symmetric."""
    rx = prescription if isinstance(prescription, Prescription) else Prescription(prescription or CARDBOARD)
    _check_int("psf_size", psf_size, 5, odd=True)
    if not isinstance(grid, (tuple, list)) or len(grid) != 2:
        raise InputValueError(f"grid must be (Gy, Gx), got {grid!r}")
    for name, v in (("grid[0] (Gy)", grid[0]), ("grid[1] (Gx)", grid[1])):
        _check_int(name, v, 1)
    if not isinstance(chief_grid, (tuple, list)) or len(chief_grid) != 2:
        raise InputValueError(f"chief_grid must be (Cy, Cx), got {chief_grid!r}")
    for name, v in (("chief_grid[0]", chief_grid[0]), ("chief_grid[1]", chief_grid[1])):
        _check_int(name, v, 2)
    _check_int("pupil_samples", pupil_samples, 4)
    _check_int("reference_width_px", reference_width_px, 1)
    if isinstance(min_pitch_px, bool) or not isinstance(min_pitch_px, (int, float)) or not (
            math.isfinite(min_pitch_px) and min_pitch_px > 0):
        raise InputValueError(f"min_pitch_px must be a finite number > 0, got {min_pitch_px!r}")
    if not isinstance(use_symmetry, bool):
        raise InputValueError(f"use_symmetry must be True or False, got {brief(use_symmetry)}")
    Gy, Gx = grid
    W_mm, H_mm = rx.display_mm
    symmetric = use_symmetry and rx.rotationally_symmetric
    ox, oy = rx.display_offset
    m_ref = real_magnification(rx, rx.reference_wavelength)
    fx = -1 + (2 * np.arange(Gx) + 1) / Gx          # normalised field centres
    fy = -1 + (2 * np.arange(Gy) + 1) / Gy
    X_mm, Y_mm = np.meshgrid(fx * W_mm / 2, fy * H_mm / 2)   # [Gy, Gx]
    radii, inv = np.unique(np.round(np.hypot(X_mm, Y_mm), 9), return_inverse=True)
    inv = inv.reshape(Gy, Gx)
    K = psf_size
    min_pitch = min_pitch_px * W_mm / reference_width_px
    L = len(rx.wavelengths)
    psf = np.zeros((L, Gy, Gx, K, K))
    pitch = np.zeros((L, Gy, Gx))
    transmission = np.zeros((L, Gy, Gx))
    chief = np.zeros((L, chief_grid[0], chief_grid[1], 2))
    cx, cy = np.linspace(-1, 1, chief_grid[1]), np.linspace(-1, 1, chief_grid[0])
    CX, CY = np.meshgrid(cx * W_mm / 2, cy * H_mm / 2)
    CR = np.hypot(CX, CY)
    n = pupil_samples
    coverage = 1.0
    pr = rx.pupil_radius
    for li, lam in enumerate(rx.wavelengths):
        # chief rays on the warp grid
        if symmetric:
            _, Yc, okc = chief_ray(rx, lam, CR.ravel())
        else:
            _, _, Xc, Yc, okc = chief_ray_2d(rx, lam, (CX - ox).ravel(), (CY - oy).ravel())
        if not okc.all():
            raise InputValueError(f"prescription: the chief rays of {int((~okc).sum())} warp-grid points (up to "
                                  f"{CR.ravel()[~okc].max():.4g} mm from the display centre) at {lam:g} nm are blocked "
                                  "by a lens aperture (semi_diameter_mm) or did not converge")
        if symmetric:
            scale = np.where(CR > 0, Yc.reshape(CR.shape) / np.maximum(CR, 1e-12), real_magnification(rx, lam)) / m_ref
            chief[li, ..., 0] = CX * scale / (W_mm / 2)
            chief[li, ..., 1] = CY * scale / (H_mm / 2)
        else:
            chief[li, ..., 0] = (ox + Xc.reshape(CR.shape) / m_ref) / (W_mm / 2)
            chief[li, ..., 1] = (oy + Yc.reshape(CR.shape) / m_ref) / (H_mm / 2)
        r_airy = 1.21967 * lam * 1e-6 * rx.image_distance / (2 * pr) / m_ref   # display-equivalent mm
        if symmetric:   # spots per distinct radius, in the meridional frame (field on +y), rotated to each field
            v0, Y0, _ = chief_ray(rx, lam, radii)
            spots = []
            for ri, r in enumerate(radii):
                sx, sy, wt, tr, cov = _spot(rx, lam, r, v0[ri], Y0[ri], n)
                coverage = min(coverage, cov)
                spots.append((sx / m_ref, sy / m_ref, wt, tr))
            for iy in range(Gy):
                for ix in range(Gx):
                    sx, sy, wt, tr = spots[inv[iy, ix]]
                    r = math.hypot(X_mm[iy, ix], Y_mm[iy, ix])
                    ex, ey = (X_mm[iy, ix] / r, Y_mm[iy, ix] / r) if r > 0 else (0.0, 1.0)
                    dx, dy = sx * ey + sy * ex, -sx * ex + sy * ey              # rotate (0, 1) -> (ex, ey)
                    psf[li, iy, ix], pitch[li, iy, ix] = _psf(dx, dy, wt, r_airy, min_pitch, K)
                    transmission[li, iy, ix] = tr
        else:           # every field point traced in 2-D about its own chief ray
            lx, ly = X_mm - ox, Y_mm - oy
            u0, v0, X0, Y0, _ = chief_ray_2d(rx, lam, lx, ly)
            for iy in range(Gy):
                for ix in range(Gx):
                    sx, sy, wt, tr, cov = _spot_2d(rx, lam, (lx[iy, ix], ly[iy, ix]), (u0[iy, ix], v0[iy, ix]),
                                                   (X0[iy, ix], Y0[iy, ix]), n)
                    coverage = min(coverage, cov)
                    psf[li, iy, ix], pitch[li, iy, ix] = _psf(sx / m_ref, sy / m_ref, wt, r_airy, min_pitch, K)
                    transmission[li, iy, ix] = tr
        if progress:
            fields = f"{len(radii)} field radii" if symmetric else f"{Gy * Gx} field points"
            print(f"  traced {lam:g} nm: {fields} x >= {n * n} launch slopes")
    meta = {"prescription": rx.spec, "assumptions": ASSUMPTIONS,
            "generator": {"tool": "controlgs_adapter.downstream.optics.generate.build_bank", "grid": list(grid),
                          "psf_size": K, "pupil_samples": n, "chief_grid": list(chief_grid),
                          "min_pitch_px": min_pitch_px, "reference_width_px": reference_width_px,
                          "pupil_weighting": "uniform in pupil area", "min_pupil_coverage": round(coverage, 5)},
            "figures": lens_figures(rx), "transmission": (transmission * rx.efficiency).round(4).tolist(),
            "lens": {"axis": [ox / (W_mm / 2), oy / (H_mm / 2)], "rotationally_symmetric": rx.rotationally_symmetric,
                     "psf": True, "kind": "prescription"}}
    return PSFBank(psf=torch.from_numpy(psf), psf_pitch_mm=torch.from_numpy(pitch), field_x=torch.from_numpy(fx),
                   field_y=torch.from_numpy(fy), chief=torch.from_numpy(chief), chief_x=torch.from_numpy(cx),
                   chief_y=torch.from_numpy(cy), wavelengths_nm=tuple(rx.wavelengths), display_mm=(W_mm, H_mm),
                   meta=meta)
