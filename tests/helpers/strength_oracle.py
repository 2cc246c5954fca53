"""The strength schedules (Eqs. 10-11) in plain Python floats, and run-time states to draw them at."""

from __future__ import annotations

import functools
import math

import numpy as np
from hypothesis import strategies as st
from scipy.interpolate import RegularGridInterpolator

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.optics.bank import PSFBank

#: run-time states, including ones beyond the schedules' endpoints (there the strength clamps)
STATES = st.builds(
    RuntimeState,
    downsample=st.floats(1.0, 64.0),  # beyond the supported 8
    power_saving=st.floats(0.0, 0.999),  # beyond the supported 0.8
    gaze=st.none() | st.tuples(st.floats(-10, 10), st.floats(-10, 10)),  # degrees, inside Cardboard's field
)


@functools.lru_cache(maxsize=1)
def _cardboard_tangents() -> RegularGridInterpolator:
    """(X / D, Y / D) of the shipped Cardboard bank's green chief rays, interpolated by SciPy."""
    bank = PSFBank.default()
    scale = 12.0 * bank.meta["figures"]["reference_magnification"] / bank.meta["prescription"]["virtual_image_distance_mm"]
    chief = bank.chief[1].double().numpy() * scale
    return RegularGridInterpolator((bank.chief_y.double().numpy(), bank.chief_x.double().numpy()), chief)


def cardboard_eccentricity(xy: tuple[float, float], gaze: tuple[float, float]) -> float:
    """Degrees between the direction a display position ``xy`` (clamped to the display) is seen in through
    the Cardboard lens and the gaze ``(azimuth, elevation)`` in degrees (the angle of two 3-D vectors)."""
    t = _cardboard_tangents()([[min(max(xy[1], -1.0), 1.0), min(max(xy[0], -1.0), 1.0)]])[0]
    u = np.array([t[0], t[1], 1.0])
    v = np.array([math.tan(math.radians(gaze[0])), math.tan(math.radians(gaze[1])), 1.0])
    c = float(u @ v / np.linalg.norm(u) / np.linalg.norm(v))
    return math.degrees(math.acos(min(1.0, c)))


def _clamp01(v: float) -> float:
    return min(max(v, 0.0), 1.0)


def reference_strengths(state: RuntimeState, xy: tuple[float, float], lens: tuple[float, float] = (0.0, math.sqrt(2)),
                        foveation: tuple[float, float] = (0.0, 30.0)) -> dict[str, float]:
    """Each built-in module's strength for an anchor at display position ``xy``; ``lens`` and
    ``foveation``: their (lo, hi) endpoints (foveation in degrees through the Cardboard lens)."""
    r = math.hypot(*xy)
    ecc = 0.0 if state.gaze is None else cardboard_eccentricity(xy, state.gaze)
    return {
        "lens": _clamp01((r - lens[0]) / (lens[1] - lens[0])),
        "resample": _clamp01(math.log2(state.downsample) / 3.0),
        "display": _clamp01(state.power_saving / 0.8),
        "foveation": _clamp01((ecc - foveation[0]) / (foveation[1] - foveation[0])),
    }
