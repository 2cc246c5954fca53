"""Sequential ray tracing through a :class:`Prescription` (numpy, float64), and a paraxial ABCD model.

Rays leave a display point at z = 0, refract at (or reflect off) each surface in turn (vector Snell;
even aspheres and conics intersected by Newton's method from the conic's closed-form hit; a
decentred or tilted surface in its own frame), and reach the eye pupil plane; their backward
extension crosses the virtual image plane (``image_z``), which is where an eye accommodated to the
virtual image distance sees them (a perfect eye focused on a plane maps every ray to the point where
it crosses that plane, seen from the pupil centre). Display points are in mm from the lens axis
(the display centre when ``display_offset_mm`` is zero); the pupil is centred on the axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from controlgs_adapter.errors import InputValueError

from .prescription import Prescription, Surface

__all__ = ["trace", "trace_exit", "chief_ray", "chief_ray_2d", "paraxial", "Paraxial", "real_magnification"]

ASPHERE_TOL_MM = 1e-13   # Newton steps along the ray stop below this
_ASPHERE_ITERS = 50


def _rotation(sf: Surface) -> np.ndarray:
    """``R = R_y(b) R_x(a)`` of the surface's tilt ``(a, b)`` degrees: local -> global directions."""
    a, b = math.radians(sf.tilt[0]), math.radians(sf.tilt[1])
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(a), -math.sin(a)], [0.0, math.sin(a), math.cos(a)]])
    rot_y = np.array([[math.cos(b), 0.0, math.sin(b)], [0.0, 1.0, 0.0], [-math.sin(b), 0.0, math.cos(b)]])
    return rot_y @ rot_x


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("...i,...i", a, b)


def _hit(sf: Surface, q: np.ndarray, d: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersection of rays ``q + t d`` (surface frame, vertex at 0) with the surface, on the sheet
    through its vertex; returns the points and the (unnormalised) surface normals there; clears ``ok``
    where a ray misses. Conic: ``c (x^2 + y^2 + (1 + k) z^2) - 2 z = 0`` solved in closed form (the root
    on the vertex's half, ``(1 + k) c z <= 1``, of a sphere or ellipsoid); asphere:
    Newton on ``z - sag(x, y)`` along the ray from the conic's hit."""
    c, k = sf.curvature, sf.conic
    a: float | np.ndarray = c
    b = c * _dot(q, d) - d[..., 2]
    cc = c * _dot(q, q) - 2 * q[..., 2]
    if k != 0.0:
        a = c * (1.0 + k * d[..., 2] ** 2)
        b = b + c * k * q[..., 2] * d[..., 2]
        cc = cc + c * k * q[..., 2] ** 2
    disc = b * b - a * cc
    ok &= disc >= 0
    # the root without cancellation; a ray starting beyond the centre of curvature (b d_z > 0) may meet
    # the far half first: then the other root
    qa = -b - np.copysign(np.sqrt(np.maximum(disc, 0.0)), b)
    t = cc / qa
    off = (disc >= 0) & (b * d[..., 2] > 0) & ((1.0 + k) * c * (q[..., 2] + t * d[..., 2]) > 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(off, qa / a, t)
    q = q + t[..., None] * d
    if not any(sf.aspheric):                              # all-zero coefficients: the conic itself
        return q, np.stack([c * q[..., 0], c * q[..., 1], c * (1.0 + k) * q[..., 2] - 1.0], -1)
    coef = np.array(sf.aspheric)
    powers = np.arange(2, len(coef) + 2)                  # A_2i r^2i = A_2i (r^2)^i, i = 2, 3, ...
    for _ in range(_ASPHERE_ITERS):
        r2 = q[..., 0] ** 2 + q[..., 1] ** 2
        arg = 1.0 - (1.0 + k) * c * c * r2
        sq = np.sqrt(np.maximum(arg, 0.0))
        rp = r2[..., None] ** (powers - 1)                    # r^(2i - 2)
        sag = c * r2 / (1.0 + sq) + r2 * (rp @ coef)
        with np.errstate(divide="ignore", invalid="ignore"):
            slope_r = c / sq + rp @ (2 * powers * coef)       # (d sag / d r) / r
            dt = -(q[..., 2] - sag) / (d[..., 2] - slope_r * (q[..., 0] * d[..., 0] + q[..., 1] * d[..., 1]))
        dt = np.where(np.isfinite(dt) & (arg > 0), dt, 0.0)
        q = q + dt[..., None] * d
        if np.abs(dt).max(initial=0.0) <= ASPHERE_TOL_MM:
            break
    ok &= (arg > 0) & np.isfinite(slope_r) & (np.abs(q[..., 2] - sag) <= 1e-9)
    return q, np.stack([slope_r * q[..., 0], slope_r * q[..., 1], -np.ones_like(r2)], -1)


def trace_exit(rx: Prescription, wavelength_nm: float, x: ArrayLike, y: ArrayLike, u: ArrayLike, v: ArrayLike
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trace rays from display points ``(x, y, 0)`` with direction ``(u, v, 1)`` (slopes, unnormalised)
    through every surface. Returns ``(p, d, ok)``: the last surface's hits ``[..., 3]`` (mm), the unit
    directions after it ``[..., 3]`` and the mask of rays that met every surface inside its
    semi-diameter without total internal reflection (before any check of the final direction)."""
    x, y, u, v = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x, y, u, v)))
    n = np.sqrt(u * u + v * v + 1.0)
    d = np.stack([u / n, v / n, 1.0 / n], -1)                      # [..., 3] unit direction
    p = np.stack([x, y, np.zeros_like(x)], -1)
    ok = np.ones(x.shape, dtype=bool)
    n1 = 1.0
    with np.errstate(over="ignore", invalid="ignore"):  # rays sent off to infinity fail ok, quietly
        for z0, sf in zip(rx.vertices, rx.surfaces):
            n2 = rx.index(sf.material, wavelength_nm)
            if sf.moved:
                origin, rot = np.array([sf.decenter[0], sf.decenter[1], z0]), _rotation(sf)
                q, d = (p - origin) @ rot, d @ rot                     # into the surface's frame: R^T (p - o)
            else:
                q = p - np.array([0.0, 0.0, z0])
            q, nrm = _hit(sf, q, d, ok)
            ok &= q[..., 0] ** 2 + q[..., 1] ** 2 <= sf.semi_diameter ** 2
            nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
            cosi = -np.einsum("...i,...i", nrm, d)
            nrm = np.where(cosi[..., None] < 0, -nrm, nrm)
            cosi = np.abs(cosi)
            if sf.mirror:
                d = d + (2.0 * cosi)[..., None] * nrm
            else:
                mu = n1 / n2
                k = 1.0 - mu * mu * (1.0 - cosi * cosi)
                ok &= k >= 0
                d = mu * d + (mu * cosi - np.sqrt(np.maximum(k, 0.0)))[..., None] * nrm
            if sf.moved:
                p, d = origin + q @ rot.T, d @ rot.T
            else:
                p = q + np.array([0.0, 0.0, z0])
            n1 = n2
    return p, d, ok


def trace(rx: Prescription, wavelength_nm: float, x: ArrayLike, y: ArrayLike, u: ArrayLike, v: ArrayLike
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Trace rays from display points ``(x, y, 0)`` with direction ``(u, v, 1)`` (slopes, unnormalised).

    All arrays broadcast together. Returns ``(xp, yp, X, Y, ok)``: the pupil-plane hit, the
    backward extension's crossing of the virtual image plane (mm), and a bool mask of rays that
    passed every surface inside its semi-diameter without total internal reflection and leave
    toward the eye.
    """
    p, d, ok = trace_exit(rx, wavelength_nm, x, y, u, v)
    ok &= d[..., 2] > 0
    su, sv = d[..., 0] / d[..., 2], d[..., 1] / d[..., 2]
    zp, zi = rx.pupil_z, rx.image_z
    xp, yp = p[..., 0] + su * (zp - p[..., 2]), p[..., 1] + sv * (zp - p[..., 2])
    X, Y = p[..., 0] + su * (zi - p[..., 2]), p[..., 1] + sv * (zi - p[..., 2])
    return xp, yp, X, Y, ok


def chief_ray(rx: Prescription, wavelength_nm: float, h: np.ndarray, iters: int = 40
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Meridional chief rays from display heights ``h`` (mm, on +y): the slope ``v`` whose ray crosses
    the pupil centre, found by damped Newton from the straight-line guess ``-h / path_length`` (``path_length``
    is ``pupil_z`` unless there are mirrors) on the primary branch.

    Returns ``(v, Y, ok)``: slope, virtual-image-plane height (mm) and convergence mask.
    """
    h = np.asarray(h, dtype=np.float64)
    v = -h / rx.path_length
    eps = 1e-7
    for _ in range(iters):
        _, y0, _, _, _ = trace(rx, wavelength_nm, 0.0, h, 0.0, v)
        _, y1, _, _, _ = trace(rx, wavelength_nm, 0.0, h, 0.0, v + eps)
        dv = -y0 / ((y1 - y0) / eps)
        v = v + np.clip(dv, -0.05, 0.05)
    _, yp, _, Y, ok = trace(rx, wavelength_nm, 0.0, h, 0.0, v)
    return v, Y, ok & (np.abs(yp) < 1e-9)


def chief_ray_2d(rx: Prescription, wavelength_nm: float, x: ArrayLike, y: ArrayLike, iters: int = 40
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chief rays from display points ``(x, y)`` (mm from the lens axis): the slopes ``(u, v)`` whose
    ray crosses the pupil centre, by Newton's method on both slopes (forward-difference Jacobian, steps
    clamped to 0.05 per slope) from the guess ``-(x, y) / path_length``; for any lens.

    Returns ``(u, v, X, Y, ok)``: slopes, virtual-image-plane landing (mm) and the mask of rays that
    pass and cross the pupil within 1e-9 mm of its centre.
    """
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    u, v = -x / rx.path_length, -y / rx.path_length
    eps = 1e-7
    for _ in range(iters):
        xp, yp, _, _, _ = trace(rx, wavelength_nm, x, y, u, v)
        xu, yu, _, _, _ = trace(rx, wavelength_nm, x, y, u + eps, v)
        xv, yv, _, _, _ = trace(rx, wavelength_nm, x, y, u, v + eps)
        a, b, c, d = (xu - xp) / eps, (xv - xp) / eps, (yu - yp) / eps, (yv - yp) / eps
        det = a * d - b * c
        with np.errstate(divide="ignore", invalid="ignore"):
            du, dv = (-d * xp + b * yp) / det, (c * xp - a * yp) / det
        u = u + np.clip(np.nan_to_num(du), -0.05, 0.05)
        v = v + np.clip(np.nan_to_num(dv), -0.05, 0.05)
    xp, yp, X, Y, ok = trace(rx, wavelength_nm, x, y, u, v)
    return u, v, X, Y, ok & (np.hypot(xp, yp) < 1e-9)


@dataclass(frozen=True)
class Paraxial:
    efl: float                # effective focal length of the lens (mm)
    image_distance: float     # paraxial virtual image distance from the pupil (mm, positive = in front of the eye)
    magnification: float      # lateral magnification at the paraxial image (virtual, erect -> positive)


def paraxial(rx: Prescription, wavelength_nm: float) -> Paraxial:
    """Independent paraxial (ABCD, reduced-angle) model of the same prescription: vertex curvatures
    (conic and aspheric terms do not change the paraxial optics); a mirror is a refraction into the
    index ``-n`` (so the negative thicknesses after it are positive reduced distances). A decentred
    or tilted surface is refused (the model is rotationally symmetric); a display offset is not seen
    (the figures are about the lens axis)."""
    m = np.eye(2)
    n1 = 1.0
    surfaces = rx.surfaces
    for i, sf in enumerate(surfaces):
        if sf.moved:
            raise InputValueError(f"paraxial: surfaces[{i}] is decentred or tilted; the paraxial model needs "
                                  "surfaces centred on the axis")
        n2 = -n1 if sf.mirror else rx.index(sf.material, wavelength_nm) * math.copysign(1.0, n1)
        power = 0.0 if math.isinf(sf.radius) else (n2 - n1) / sf.radius
        m = np.array([[1.0, 0.0], [-power, 1.0]]) @ m                  # refraction, state (y, n*u)
        if i + 1 < len(surfaces):
            m = np.array([[1.0, sf.thickness / n2], [0.0, 1.0]]) @ m   # transfer inside the lens stack
        n1 = n2
    efl = -1.0 / m[1, 0]
    # object at -object_distance from the first vertex: y_out = (A + ... ) ; image of an on-axis point
    obj = np.array([[1.0, rx.object_distance], [0.0, 1.0]])
    s = m @ obj                               # display -> just after the last surface
    # an on-axis ray (0, u): y = B u, nu = D u; the image lies where y + t*nu = 0 -> t = -B/D behind the last vertex
    t_img = -s[0, 1] / s[1, 1]                # negative: virtual, in front of the last vertex (toward the display)
    mag = s[0, 0] + t_img * s[1, 0]           # a ray from display height 1 with slope 0, at the image plane
    return Paraxial(efl=efl, image_distance=surfaces[-1].thickness - t_img, magnification=mag)


def real_magnification(rx: Prescription, wavelength_nm: float) -> float:
    """Chief-ray magnification on the virtual image plane (``Y / h`` for a tiny field); for a lens
    that is not rotationally symmetric, the mean of ``dX / dx`` and ``dY / dy`` at the axis (central
    differences of :func:`chief_ray_2d`'s landings, 1e-4 mm)."""
    if not rx.rotationally_symmetric:
        e = 1e-4
        _, _, X, Y, _ = chief_ray_2d(rx, wavelength_nm, np.array([e, -e, 0.0, 0.0]), np.array([0.0, 0.0, e, -e]))
        return float(((X[0] - X[1]) + (Y[2] - Y[3])) / (4 * e))
    h = np.array([1e-4])
    _, Y, _ = chief_ray(rx, wavelength_nm, h)
    return float(Y[0] / h[0])
