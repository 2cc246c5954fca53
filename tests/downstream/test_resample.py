"""Tests of ``controlgs_adapter.downstream.resample``: the area filter from S to S/d against the exact
area average (brute force), integer factors as exact block means, the display size (the no-supersampling
camera's), the stage's no-supersampling pass-through and its refusals. The stage contract (identity at
d = 1, gradients, twin) is checked in ``test_stage_contract.py``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.oled import OLEDEmission, oled_emission
from controlgs_adapter.downstream.resample import AreaResample, area_resample, resampled_size
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import ShapeError, StateRangeError
from controlgs_adapter.state import Camera

D = torch.float64


def _area_average(img: np.ndarray, out_h: int, out_w: int) -> np.ndarray:
    """Brute force: every output pixel integrates the piecewise-constant input over its footprint."""
    c, h, w = img.shape
    sy, sx = h / out_h, w / out_w
    out = np.zeros((c, out_h, out_w))
    for j in range(out_h):
        for k in range(out_w):
            acc = np.zeros(c)
            for i in range(h):
                oy = max(0.0, min(i + 1, (j + 1) * sy) - max(i, j * sy))
                if oy == 0:
                    continue
                for m in range(w):
                    ox = max(0.0, min(m + 1, (k + 1) * sx) - max(m, k * sx))
                    acc += oy * ox * img[:, i, m]
            out[:, j, k] = acc / (sy * sx)
    return out


@settings(max_examples=20, deadline=None)
@given(st.integers(1, 13), st.integers(1, 13), st.floats(1.0, 8.0))
def test_area_resample_matches_brute_force(h, w, d):
    img = torch.rand(3, h, w, dtype=D)
    out = area_resample(img, d)
    oh, ow = resampled_size((h, w), d)
    assert out.shape == (3, oh, ow) == (3, max(1, round(h / d)), max(1, round(w / d)))
    assert np.allclose(out.numpy(), _area_average(img.numpy(), oh, ow), atol=1e-12)
    assert float(out.mean()) == pytest.approx(float(img.mean()), abs=1e-12)  # light is conserved


@pytest.mark.parametrize("n_in, d, n_out", [(5, 2.5, 2), (5, 5 / 3, 3), (7, 7 / 3, 3), (9, 2.0, 4)])
def test_area_resample_along_either_axis_is_the_exact_area_average(n_in, d, n_out):
    row = [float(v * v % 7) + 0.25 * v for v in range(n_in)]
    img = torch.tensor(row, dtype=D)[None, None, :].expand(3, 2, n_in).clone()
    for x in (img, img.transpose(-1, -2).contiguous()):                      # along the rows and the columns
        out = area_resample(x, d)
        assert n_out in out.shape[-2:]
        assert np.allclose(out.numpy(), _area_average(x.numpy(), *out.shape[-2:]), atol=1e-12)


def test_area_resample_values_and_unequal_axis_ratios():
    """5 -> 2: output 0 covers [0, 2.5): (1 + 2 + 0.5 * 3) / 2.5 = 1.8; output 1: (0.5 * 3 + 4 + 5) / 2.5 =
    4.2. 4 x 9 at d = 2.6 -> 2 x 3 (round(1.54), round(3.46)): both divide, but the ratios 2 and 3 differ;
    8 x 9 at d = 2 -> 4 x 4 (round(4.5) = 4): rows divide, columns do not."""
    img = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=D)[None, None].expand(3, 1, 5).clone()
    assert area_resample(img, 2.5)[0, 0].tolist() == pytest.approx([1.8, 4.2])
    g = torch.Generator().manual_seed(3)
    x = torch.rand(3, 4, 9, generator=g, dtype=D)
    out = area_resample(x, 2.6)
    assert out.shape == (3, 2, 3)
    assert torch.allclose(out, x.reshape(3, 2, 2, 3, 3).mean(dim=(2, 4)), atol=1e-12)
    y = torch.rand(3, 8, 9, generator=g, dtype=D)
    assert np.allclose(area_resample(y, 2.0).numpy(), _area_average(y.numpy(), 4, 4), atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("k", [2, 3, 4, 5])
def test_integer_factor_is_the_exact_block_mean(k, dtype):
    """``area_resample`` docstring: at an integer factor k dividing both H and W (non-square frames included)
    each output is its k x k block's sum / (k * k), the correctly rounded mean when the sum is exact: 8-bit
    pixel values on a 3k x 4k frame against the float64 block mean rounded once to ``dtype``; it is average
    pooling, and the general path at k + 1e-9 agrees with it."""
    g = torch.Generator().manual_seed(k)
    x = torch.randint(0, 256, (2, 3, 3 * k, 4 * k), generator=g).to(dtype)
    ref = x.double().reshape(2, 3, 3, k, 4, k).sum(dim=(3, 5)) / (k * k)
    out = area_resample(x, float(k))
    assert out.shape == (2, 3, 3, 4) and out.dtype == dtype
    assert torch.equal(out, ref.to(dtype))
    img = torch.rand(2, 3, 12 * k, 24, dtype=dtype, generator=g)
    if 24 % k == 0:
        assert torch.allclose(area_resample(img, k), F.avg_pool2d(img, k), atol=1e-7)
        assert torch.allclose(area_resample(img, float(k) + 1e-9), F.avg_pool2d(img, k), atol=1e-6)


def test_constant_image_and_identity():
    img = torch.full((3, 9, 7), 0.3, dtype=D)
    out = area_resample(img, 2.7)
    assert torch.allclose(out, torch.full_like(out, 0.3), atol=1e-14)
    assert area_resample(img, 1.0) is img


@settings(max_examples=15, deadline=None)
@given(st.integers(1, 6), st.integers(1, 6), st.integers(1, 4))
def test_area_filter_undoes_box_emission(h, w, k):
    img = torch.rand(3, h, w, dtype=D)
    assert torch.allclose(area_resample(oled_emission(img, (h * k, w * k)), k), img, atol=1e-14)


def test_resampled_size_is_the_no_ss_cameras():
    """``max(1, round(S / d))`` per axis with Python's rounding, as ``Camera.scaled``."""
    assert resampled_size((10, 7), 3.0) == (3, 2)
    assert resampled_size((5, 6), 2.0) == (2, 3)  # round(2.5) = 2
    assert resampled_size((2, 2), 8.0) == (1, 1)
    assert resampled_size((16, 9), 1.0) == (16, 9)
    cam = Camera(torch.eye(4), torch.tensor([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]]), 80, 60)
    for d in (1.0, 1.5, 2.0, 3.3, 8.0):
        low = cam.scaled(d)
        assert resampled_size((60, 80), d) == (low.height, low.width)


@pytest.mark.parametrize("bad", ["two", None, float("nan"), float("inf"), 0.99, 0.5, 0.0, -2.0])
def test_bad_factors_are_state_range_errors_naming_the_argument(bad):
    with pytest.raises(StateRangeError, match=rf"d must be .*got {bad!r}"):
        area_resample(torch.rand(3, 4, 4), bad)
    with pytest.raises(StateRangeError, match="max_factor must be"):
        AreaResample(max_factor=bad)


def test_resample_stage_passes_the_no_ss_baseline_through_and_checks_its_input():
    """An image already at the display size round(S / d) (the no-supersampling baseline) comes back as it
    is; any other size than native or display is refused; a factor above the stage's max_factor is refused
    naming it."""
    stage = AreaResample(max_factor=4)
    img = torch.rand(3, 20, 30)
    ctx = StageContext((20, 30))
    low = torch.rand(3, 8, 12)  # round(20 / 2.5), round(30 / 2.5)
    assert stage(low, RuntimeState(2.5), ctx) is low
    with pytest.raises(ShapeError, match=r"native size \(20, 30\) or the display size \(8, 12\)"):
        stage(torch.rand(3, 10, 10), RuntimeState(2.5), ctx)
    with pytest.raises(StateRangeError, match="downsample 5.0.*max_factor 4.0"):
        stage(img, RuntimeState(5.0), ctx)


def test_stages_used_as_plain_modules_take_the_image_size_as_native():
    """A stage called without a context on a 12 x 20 image: resampling by 4 gives 3 x 5, each output pixel
    the mean of its 4 x 4 block; the OLED stage keeps the size."""
    image = torch.rand(3, 12, 20, generator=torch.Generator().manual_seed(5), dtype=D)
    out = AreaResample()(image, RuntimeState(downsample=4.0))
    want = torch.stack([torch.stack([torch.stack([image[c, 4 * i:4 * i + 4, 4 * j:4 * j + 4].mean() for j in range(5)])
                                     for i in range(3)]) for c in range(3)])
    torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    assert OLEDEmission()(image, RuntimeState()).shape == (3, 12, 20)
