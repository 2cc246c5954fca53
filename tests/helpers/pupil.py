"""Rays aimed by Newton's method at given points of the exit pupil: an independent reference for the
PSF generator's slope grid (test helpers)."""

from __future__ import annotations

from typing import Any

import numpy as np

from controlgs_adapter.downstream.optics.raytrace import trace


def aim_rays(rx: Any, lam: float, r: float, v0: float, tx: np.ndarray, ty: np.ndarray,
             iterations: int) -> tuple[np.ndarray, ...]:
    """Slopes of the rays from display height ``r`` mm (on +y) at ``lam`` nm that cross the pupil at
    ``(tx, ty)`` mm, found by ``iterations`` Newton steps from the chief ray's slope ``v0`` (forward
    differences, step 1e-7); returns :func:`trace`'s ``(xp, yp, X, Y, ok)`` of the aimed rays."""
    u, v = np.zeros_like(tx), np.full_like(tx, v0)
    eps = 1e-7
    for _ in range(iterations):
        xp, yp, _, _, _ = trace(rx, lam, 0.0, r, u, v)
        xu, yu, _, _, _ = trace(rx, lam, 0.0, r, u + eps, v)
        xv, yv, _, _, _ = trace(rx, lam, 0.0, r, u, v + eps)
        a, b, c, d = (xu - xp) / eps, (xv - xp) / eps, (yu - yp) / eps, (yv - yp) / eps
        ex, ey = tx - xp, ty - yp
        det = a * d - b * c
        u, v = u + (d * ex - b * ey) / det, v + (a * ey - c * ex) / det
    return trace(rx, lam, 0.0, r, u, v)
