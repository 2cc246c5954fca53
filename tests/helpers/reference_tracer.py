"""A slow, independent reference ray tracer for the optics tests: one ray at a time in plain Python.

Written unlike the library's tracer: a surface's frame is reached with Rodrigues rotations of vectors;
the intersection is found by scanning and bisecting the implicit function ``z - sag(x, y)`` along the
ray; the normal is the sag's gradient by complex-step differentiation; refraction and reflection turn
the ray by angles in its plane of incidence (``n1 sin i = n2 sin r``).
"""

from __future__ import annotations

import cmath
import math
from typing import Any

Vec = tuple[float, float, float]


def _add(a: Vec, b: Vec, s: float = 1.0) -> Vec:
    return (a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2])


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _unit(a: Vec) -> Vec:
    n = math.sqrt(_dot(a, a))
    return (a[0] / n, a[1] / n, a[2] / n)


def _rotate(v: Vec, axis: Vec, deg: float) -> Vec:
    """Rodrigues: ``v`` turned by ``deg`` degrees about the unit ``axis`` (right-handed)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    kv = _cross(axis, v)
    kk = _dot(axis, v) * (1 - c)
    return (v[0] * c + kv[0] * s + axis[0] * kk, v[1] * c + kv[1] * s + axis[1] * kk, v[2] * c + kv[2] * s + axis[2] * kk)


X_AXIS, Y_AXIS = (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)


def _to_local(v: Vec, tilt: tuple[float, float]) -> Vec:
    return _rotate(_rotate(v, Y_AXIS, -tilt[1]), X_AXIS, -tilt[0])


def _to_global(v: Vec, tilt: tuple[float, float]) -> Vec:
    return _rotate(_rotate(v, X_AXIS, tilt[0]), Y_AXIS, tilt[1])


def sag(sf: Any, x: complex, y: complex) -> complex:
    """The even asphere's sag at ``(x, y)`` (complex arguments allowed, for complex-step derivatives)."""
    c = 0.0 if math.isinf(sf.radius) else 1.0 / sf.radius
    r2 = x * x + y * y
    z = c * r2 / (1 + cmath.sqrt(1 - (1 + sf.conic) * c * c * r2))
    for i, a in enumerate(sf.aspheric):
        z += a * r2 ** (i + 2)
    return z


def _defined(sf: Any, x: float, y: float) -> bool:
    c = 0.0 if math.isinf(sf.radius) else 1.0 / sf.radius
    return 1 - (1 + sf.conic) * c * c * (x * x + y * y) >= 0


def _intersect(sf: Any, q: Vec, d: Vec, reach: float) -> float | None:
    """Smallest ``t`` in (0, reach] where ``q + t d`` crosses ``z = sag(x, y)``: a scan of 4000 steps for
    the first sign change, then bisection to the last bit."""
    def f(t: float) -> float | None:
        x, y, z = _add(q, d, t)
        return z - sag(sf, x, y).real if _defined(sf, x, y) else None

    steps = 4000
    prev_t, prev_f = 1e-9, f(1e-9)
    for i in range(1, steps + 1):
        t = 1e-9 + reach * i / steps
        ft = f(t)
        if prev_f is not None and ft is not None and (prev_f <= 0) != (ft <= 0):
            lo, hi, flo = prev_t, t, prev_f
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                if mid in (lo, hi):
                    break
                fm = f(mid)
                assert fm is not None
                if (fm <= 0) == (flo <= 0):
                    lo, flo = mid, fm
                else:
                    hi = mid
            return 0.5 * (lo + hi)
        prev_t, prev_f = t, ft
    return None


def _normal(sf: Any, x: float, y: float) -> Vec:
    """Unit normal ``(-dz/dx, -dz/dy, 1)`` by complex-step derivatives of the sag (exact to rounding)."""
    h = 1e-30
    sx = sag(sf, complex(x, h), y).imag / h
    sy = sag(sf, x, complex(y, h)).imag / h
    return _unit((-sx, -sy, 1.0))


def _turn(d: Vec, nrm: Vec, n1: float, n2: float, mirror: bool) -> Vec | None:
    """The direction after the surface: the angle of incidence ``i`` to the normal facing along ``d``,
    the exit angle (``pi - i`` reflected, ``asin(n1 sin i / n2)`` refracted) in the plane of incidence;
    ``None`` for total internal reflection."""
    if _dot(d, nrm) < 0:
        nrm = (-nrm[0], -nrm[1], -nrm[2])
    along = _cross(nrm, d)
    i = math.atan2(math.sqrt(_dot(along, along)), _dot(d, nrm))
    tangent = _add(d, nrm, -_dot(d, nrm))
    tn = math.sqrt(_dot(tangent, tangent))
    tangent = (0.0, 0.0, 0.0) if tn == 0 else (tangent[0] / tn, tangent[1] / tn, tangent[2] / tn)
    if mirror:
        return _add((-nrm[0] * math.cos(i), -nrm[1] * math.cos(i), -nrm[2] * math.cos(i)), tangent, math.sin(i))
    s = n1 * math.sin(i) / n2
    if s > 1:
        return None
    r = math.asin(s)
    return _add((nrm[0] * math.cos(r), nrm[1] * math.cos(r), nrm[2] * math.cos(r)), tangent, math.sin(r))


def trace_one(rx: Any, lam: float, x: float, y: float, u: float, v: float, reach: float = 200.0
              ) -> tuple[Vec, Vec] | None:
    """One ray from display point ``(x, y, 0)`` with slopes ``(u, v)`` through ``rx``'s surfaces; returns
    the last surface's hit and the unit direction after it, or ``None`` if the ray misses a surface or
    its semi-diameter, or is totally internally reflected."""
    p: Vec = (x, y, 0.0)
    d = _unit((u, v, 1.0))
    n1 = 1.0
    for z0, sf in zip(rx.vertices, rx.surfaces):
        n2 = rx.index(sf.material, lam)
        origin: Vec = (sf.decenter[0], sf.decenter[1], z0)
        q, dl = _to_local(_add(p, origin, -1.0), sf.tilt), _to_local(d, sf.tilt)
        t = _intersect(sf, q, dl, reach)
        if t is None:
            return None
        q = _add(q, dl, t)
        if q[0] ** 2 + q[1] ** 2 > sf.semi_diameter ** 2:
            return None
        dl2 = _turn(dl, _normal(sf, q[0], q[1]), n1, n2, sf.mirror)
        if dl2 is None:
            return None
        p, d = _add(origin, _to_global(q, sf.tilt)), _to_global(dl2, sf.tilt)
        n1 = n2
    return p, d
