"""Tests of ``controlgs_adapter.downstream.resample``."""

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
from controlgs_adapter.errors import ShapeError, StateError, StateRangeError
from controlgs_adapter.state import Camera

D = torch.float64


def test_stages_used_as_plain_modules_take_the_image_size_as_native():
    """A stage called without a context on a 12 x 20 image: resampling by 4 gives 3 x 5, each output pixel
    the mean of its 4 x 4 block (by hand); the OLED stage keeps the size."""
    from controlgs_adapter.downstream.resample import AreaResample

    g = torch.Generator().manual_seed(5)
    image = torch.rand(3, 12, 20, generator=g, dtype=D)
    out = AreaResample()(image, RuntimeState(downsample=4.0))
    want = torch.stack([torch.stack([torch.stack([image[c, 4 * i:4 * i + 4, 4 * j:4 * j + 4].mean() for j in range(5)])
                                     for i in range(3)]) for c in range(3)])
    torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    assert OLEDEmission()(image, RuntimeState()).shape == (3, 12, 20)


def _area_reference(img: np.ndarray, out_h: int, out_w: int) -> np.ndarray:
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
    img = torch.rand(3, h, w, dtype=torch.float64)
    out = area_resample(img, d)
    oh, ow = resampled_size((h, w), d)
    assert out.shape == (3, oh, ow) == (3, max(1, round(h / d)), max(1, round(w / d)))
    assert np.allclose(out.numpy(), _area_reference(img.numpy(), oh, ow), atol=1e-12)
    assert float(out.mean()) == pytest.approx(float(img.mean()), abs=1e-12)  # light is conserved


@pytest.mark.parametrize("d", [2, 3, 4])
def test_integer_factor_is_average_pooling(d):
    img = torch.rand(2, 3, 12, 24, dtype=torch.float32)
    assert torch.allclose(area_resample(img, d), F.avg_pool2d(img, d), atol=1e-7)
    assert torch.allclose(area_resample(img, float(d) + 1e-9), F.avg_pool2d(img, d), atol=1e-6)  # general path agrees


def test_output_size_matches_the_no_ss_camera():
    cam = Camera(torch.eye(4), torch.tensor([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]]), 80, 60)
    for d in (1.0, 1.5, 2.0, 3.3, 8.0):
        low = cam.scaled(d)
        assert resampled_size((60, 80), d) == (low.height, low.width)


def test_constant_image_and_identity():
    img = torch.full((3, 9, 7), 0.3, dtype=torch.float64)
    assert torch.allclose(area_resample(img, 2.7), torch.full_like(area_resample(img, 2.7), 0.3), atol=1e-14)
    assert area_resample(img, 1.0) is img


@pytest.mark.parametrize("bad", [0.5, 0.0, -2.0, float("nan"), float("inf"), "two", None])
def test_bad_factor_raises(bad):
    with pytest.raises(StateError, match="d must be"):
        area_resample(torch.rand(3, 4, 4), bad)


def test_gradcheck_resample():
    img = torch.rand(2, 3, 7, 6, dtype=torch.float64, requires_grad=True)
    for d in (2.0, 2.6):
        assert torch.autograd.gradcheck(lambda x: area_resample(x, d), (img,))


def test_resample_stage():
    stage = AreaResample(max_factor=4)
    img = torch.rand(3, 20, 30)
    ctx = StageContext((20, 30))
    assert stage.is_identity(RuntimeState(1.0)) and not stage.is_identity(RuntimeState(1.5))
    assert torch.equal(stage(img, RuntimeState(2.5), ctx), area_resample(img, 2.5))
    low = torch.rand(3, 8, 12)  # no-SS baseline: already at round(S / 2.5)
    assert stage(low, RuntimeState(2.5), ctx) is low
    with pytest.raises(ShapeError, match="native size"):
        stage(torch.rand(3, 10, 10), RuntimeState(2.5), ctx)
    with pytest.raises(StateError, match="max_factor"):
        stage(img, RuntimeState(5.0), ctx)
    with pytest.raises(StateError, match="max_factor"):
        AreaResample(max_factor=0.5)


@settings(max_examples=15, deadline=None)
@given(st.integers(1, 6), st.integers(1, 6), st.integers(1, 4))
def test_area_filter_undoes_box_emission(h, w, k):
    img = torch.rand(3, h, w, dtype=torch.float64)
    assert torch.allclose(area_resample(oled_emission(img, (h * k, w * k)), k), img, atol=1e-14)


# ----------------------------------------------------------------------------- area_resample: integer factors
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("k", [3, 5])
def test_integer_factor_on_a_non_square_frame_is_the_exact_block_mean(k, dtype):
    """``area_resample`` docstring: at an integer factor k dividing both H and W (non-square frames
    included) each output is its k x k block's sum / (k * k), the correctly rounded mean when the sum is
    exact. 8-bit pixel values on a 3k x 4k frame: the reference is the float64 block mean (exact sums of
    at most 64 values < 256) rounded once to ``dtype``."""
    g = torch.Generator().manual_seed(k)
    x = torch.randint(0, 256, (2, 3, 3 * k, 4 * k), generator=g).to(dtype)
    ref = x.double().reshape(2, 3, 3, k, 4, k).sum(dim=(3, 5)) / (k * k)
    out = area_resample(x, float(k))
    assert out.shape == (2, 3, 3, 4) and out.dtype == dtype
    assert torch.equal(out, ref.to(dtype))


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


def _area_brute(row: list[float], n_out: int) -> list[float]:
    """Exact area average: repeat each input n_out times, average blocks of n_in (float64)."""
    n_in = len(row)
    fine = [v for v in row for _ in range(n_out)]
    return [sum(fine[j * n_in:(j + 1) * n_in]) / n_in for j in range(n_out)]


@pytest.mark.parametrize("n_in, d, n_out", [(5, 2.5, 2), (5, 5 / 3, 3), (7, 7 / 3, 3), (9, 2.0, 4)])
def test_area_resample_rows_match_the_exact_area_average(n_in, d, n_out):
    row = [float(v * v % 7) + 0.25 * v for v in range(n_in)]
    img = torch.tensor(row, dtype=D)[None, None, :].expand(3, 2, n_in).clone()
    out = area_resample(img, d)
    assert out.shape[-1] == n_out
    assert out[1, 0].tolist() == pytest.approx(_area_brute(row, n_out), abs=1e-12)
    # the same along the rows (the transpose path)
    out_t = area_resample(img.transpose(-1, -2).contiguous(), d)
    assert out_t[2, :, 0].tolist() == pytest.approx(_area_brute(row, n_out), abs=1e-12)


def test_area_resample_hand_value_and_unequal_axis_ratios():
    # 5 -> 2: output 0 covers [0, 2.5): (1 + 2 + 0.5 * 3) / 2.5 = 1.8; output 1: (0.5*3 + 4 + 5) / 2.5 = 4.2
    img = torch.tensor([1.0, 2.0, 3.0, 4.0, 5.0], dtype=D)[None, None].expand(3, 1, 5).clone()
    assert area_resample(img, 2.5)[0, 0].tolist() == pytest.approx([1.8, 4.2])
    # 4 x 9 at d = 2.6 -> 2 x 3 (round(1.54), round(3.46)): both divide, but the ratios 2 and 3 differ
    g = torch.Generator().manual_seed(3)
    x = torch.rand(3, 4, 9, generator=g, dtype=D)
    out = area_resample(x, 2.6)
    assert out.shape == (3, 2, 3)
    assert torch.allclose(out, x.reshape(3, 2, 2, 3, 3).mean(dim=(2, 4)), atol=1e-12)
    # 8 x 9 at d = 2 -> 4 x 4 (round(4.5) = 4): rows divide, columns do not
    y = torch.rand(3, 8, 9, generator=g, dtype=D)
    out2 = area_resample(y, 2.0)
    ref = torch.tensor([[_area_brute(r, 4) for r in y[c].reshape(4, 2, 9).mean(1).tolist()] for c in range(3)], dtype=D)
    assert torch.allclose(out2, ref, atol=1e-12)


def test_resampled_size_rounding_and_floor_of_one():
    assert resampled_size((10, 7), 3.0) == (3, 2)
    assert resampled_size((5, 6), 2.0) == (2, 3)  # round(2.5) = 2 (Python's rounding, as Camera.scaled)
    assert resampled_size((2, 2), 8.0) == (1, 1)
    assert resampled_size((16, 9), 1.0) == (16, 9)


@pytest.mark.parametrize("bad", ["two", None, float("nan"), float("inf"), 0.99, 0.0, -2.0])
def test_bad_factors_are_state_range_errors_naming_the_argument(bad):
    with pytest.raises(StateRangeError, match="d must be"):
        area_resample(_img([1.0, 1.0, 1.0], 2, 2), bad)
    with pytest.raises(StateRangeError, match="max_factor must be"):
        AreaResample(max_factor=bad)
