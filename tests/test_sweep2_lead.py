"""Misses of the lead's last fresh sample (seed 5150001), each pinned."""

import numpy as np

from controlgs_adapter.downstream.optics.prescription import Prescription
from controlgs_adapter.downstream.optics.raytrace import trace


def test_trace_computes_in_float64_whatever_the_input_dtype():
    """float32 display points and slopes are traced in float64: the same rays as float64 input, to the
    bit (a float32 trace through the lens differs by ~1e-5 mm), and float64 outputs."""
    rx = Prescription.cardboard()
    h = np.linspace(0.0, 16.0, 9)
    v = np.linspace(-0.3, 0.0, 9)
    ref = trace(rx, 550.0, np.zeros(9), h, np.zeros(9), v)
    low = trace(rx, 550.0, np.zeros(9, np.float32), h.astype(np.float32), np.zeros(9, np.float32), v.astype(np.float32))
    h32, v32 = h.astype(np.float32).astype(np.float64), v.astype(np.float32).astype(np.float64)
    ref32 = trace(rx, 550.0, np.zeros(9), h32, np.zeros(9), v32)  # the float32 inputs' exact values, traced in float64
    for a, b in zip(low, ref32):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert all(a.dtype == np.float64 for a in low[:4])
    assert np.array_equal(low[4], ref[4])
