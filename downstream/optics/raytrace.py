"""Sequential ray tracing through a :class:`Prescription` (numpy, float64), and a paraxial ABCD model.

Rays leave a display point at z = 0, refract at spherical surfaces (vector Snell), reach the eye
pupil plane; their backward extension crosses the virtual image plane (``image_z``), which is
where an eye accommodated to the virtual image distance sees them (a perfect eye focused on a
plane maps every ray to the point where it crosses that plane, seen from the pupil centre).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .prescription import Prescription

__all__ = ["trace", "chief_ray", "paraxial", "Paraxial", "real_magnification"]


def trace(rx: Prescription, wavelength_nm: float, x: ArrayLike, y: ArrayLike, u: ArrayLike, v: ArrayLike
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Trace rays from display points ``(x, y, 0)`` with direction ``(u, v, 1)`` (slopes, unnormalised).

    All arrays broadcast together. Returns ``(xp, yp, X, Y, ok)``: the pupil-plane hit, the
    backward extension's crossing of the virtual image plane (mm), and a bool mask of rays that
    passed every surface inside its semi-diameter without total internal reflection.
    """
    x, y, u, v = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x, y, u, v)))
    n = np.sqrt(u * u + v * v + 1.0)
    d = np.stack([u / n, v / n, 1.0 / n], -1)                      # [..., 3] unit direction
    p = np.stack([x, y, np.zeros_like(x)], -1)
    ok = np.ones(x.shape, dtype=bool)
    n1 = 1.0
    for z0, sf in zip(rx.vertices, rx.surfaces):
        n2 = rx.index(sf.material, wavelength_nm)
        q = p - np.array([0.0, 0.0, z0])
        c = 0.0 if math.isinf(sf.radius) else 1.0 / sf.radius
        b = c * np.einsum("...i,...i", q, d) - d[..., 2]
        cc = c * np.einsum("...i,...i", q, q) - 2 * q[..., 2]
        disc = b * b - c * cc
        ok &= disc >= 0
        t = cc / (-b + np.sqrt(np.maximum(disc, 0.0)))
        q = q + t[..., None] * d
        ok &= q[..., 0] ** 2 + q[..., 1] ** 2 <= sf.semi_diameter ** 2
        nrm = np.stack([c * q[..., 0], c * q[..., 1], c * q[..., 2] - 1.0], -1)
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        cosi = -np.einsum("...i,...i", nrm, d)
        nrm = np.where(cosi[..., None] < 0, -nrm, nrm)
        cosi = np.abs(cosi)
        mu = n1 / n2
        k = 1.0 - mu * mu * (1.0 - cosi * cosi)
        ok &= k >= 0
        d = mu * d + (mu * cosi - np.sqrt(np.maximum(k, 0.0)))[..., None] * nrm
        p = q + np.array([0.0, 0.0, z0])
        n1 = n2
    ok &= d[..., 2] > 0
    su, sv = d[..., 0] / d[..., 2], d[..., 1] / d[..., 2]
    zp, zi = rx.pupil_z, rx.image_z
    xp, yp = p[..., 0] + su * (zp - p[..., 2]), p[..., 1] + sv * (zp - p[..., 2])
    X, Y = p[..., 0] + su * (zi - p[..., 2]), p[..., 1] + sv * (zi - p[..., 2])
    return xp, yp, X, Y, ok


def chief_ray(rx: Prescription, wavelength_nm: float, h: np.ndarray, iters: int = 40
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Meridional chief rays from display heights ``h`` (mm, on +y): the slope ``v`` whose ray crosses
    the pupil centre, found by damped Newton from the paraxial guess on the primary branch.

    Returns ``(v, Y, ok)``: slope, virtual-image-plane height (mm) and convergence mask.
    """
    h = np.asarray(h, dtype=np.float64)
    v = -h / rx.pupil_z
    eps = 1e-7
    for _ in range(iters):
        _, y0, _, _, _ = trace(rx, wavelength_nm, 0.0, h, 0.0, v)
        _, y1, _, _, _ = trace(rx, wavelength_nm, 0.0, h, 0.0, v + eps)
        dv = -y0 / ((y1 - y0) / eps)
        v = v + np.clip(dv, -0.05, 0.05)
    _, yp, _, Y, ok = trace(rx, wavelength_nm, 0.0, h, 0.0, v)
    return v, Y, ok & (np.abs(yp) < 1e-9)


@dataclass(frozen=True)
class Paraxial:
    efl: float                # effective focal length of the lens (mm)
    image_distance: float     # paraxial virtual image distance from the pupil (mm, positive = in front of the eye)
    magnification: float      # lateral magnification at the paraxial image (virtual, erect -> positive)


def paraxial(rx: Prescription, wavelength_nm: float) -> Paraxial:
    """Independent paraxial (ABCD, reduced-angle) model of the same prescription."""
    m = np.eye(2)
    n1 = 1.0
    surfaces = rx.surfaces
    for i, sf in enumerate(surfaces):
        n2 = rx.index(sf.material, wavelength_nm)
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
    """Chief-ray magnification on the virtual image plane (``Y / h`` for a tiny field)."""
    h = np.array([1e-4])
    _, Y, _ = chief_ray(rx, wavelength_nm, h)
    return float(Y[0] / h[0])
