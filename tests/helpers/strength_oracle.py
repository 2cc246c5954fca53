"""The strength schedules (Eqs. 10-11) in plain Python floats, and run-time states to draw them at."""

from __future__ import annotations

import math

from hypothesis import strategies as st

from controlgs_adapter import RuntimeState

#: run-time states, including ones beyond the schedules' endpoints (there the strength clamps)
STATES = st.builds(
    RuntimeState,
    downsample=st.floats(1.0, 64.0),  # beyond the supported 8
    power_saving=st.floats(0.0, 0.999),  # beyond the supported 0.8
    gaze=st.none() | st.tuples(st.floats(-1, 1), st.floats(-1, 1)),
)


def _clamp01(v: float) -> float:
    return min(max(v, 0.0), 1.0)


def reference_strengths(state: RuntimeState, xy: tuple[float, float], lens: tuple[float, float] = (0.0, math.sqrt(2)),
                        foveation: tuple[float, float] = (0.0, math.sqrt(2))) -> dict[str, float]:
    """Each built-in module's strength for an anchor at display position ``xy``; ``lens`` and
    ``foveation``: their (lo, hi) endpoints."""
    r = math.hypot(*xy)
    ecc = 0.0 if state.gaze is None else math.hypot(xy[0] - state.gaze[0], xy[1] - state.gaze[1])
    return {
        "lens": _clamp01((r - lens[0]) / (lens[1] - lens[0])),
        "resample": _clamp01(math.log2(state.downsample) / 3.0),
        "display": _clamp01(state.power_saving / 0.8),
        "foveation": _clamp01((ecc - foveation[0]) / (foveation[1] - foveation[0])),
    }
