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


def aim_at_pupil_grid(rx: Any, lam: float, r: float, n: int = 64, iterations: int = 10) -> tuple[np.ndarray, ...]:
    """Rays from display height ``r`` mm (on +y) at ``lam`` nm aimed at the points of a uniform ``n x n`` grid
    over the exit pupil disc (equal pupil area each, from the chief ray's slope); returns :func:`trace`'s
    ``(xp, yp, X, Y, ok)`` of the aimed rays after checking they cross the pupil at their points (1e-9 mm)."""
    from controlgs_adapter.downstream.optics.raytrace import chief_ray

    v0, _, _ = chief_ray(rx, lam, np.array([r]))
    g = (np.arange(n) + 0.5) / n * 2 - 1
    px, py = np.meshgrid(g, g)
    inside = px ** 2 + py ** 2 <= 1
    tx, ty = px[inside] * rx.pupil_radius, py[inside] * rx.pupil_radius
    rays = aim_rays(rx, lam, r, v0[0], tx, ty, iterations)
    assert np.abs(rays[0] - tx).max() < 1e-9 and np.abs(rays[1] - ty).max() < 1e-9
    return rays
