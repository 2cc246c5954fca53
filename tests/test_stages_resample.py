"""Anti-aliasing resampling P_res (area filter) and the OLED box emission D_phys."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.foveation import Foveation, foveation
from controlgs_adapter.downstream.oled import OLEDEmission, oled_emission
from controlgs_adapter.downstream.resample import AreaResample, area_resample, resampled_size
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError, ShapeError, StateError
from controlgs_adapter.state import Camera, RuntimeState



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


def test_box_emission_is_nearest_with_pixel_centres():
    img = torch.rand(2, 3, 4, 5, dtype=torch.float64)
    up = oled_emission(img, (8, 15))
    assert torch.equal(up, img.repeat_interleave(2, -2).repeat_interleave(3, -1))
    odd = oled_emission(img, (7, 9))
    rows = [math.floor((i + 0.5) * 4 / 7) for i in range(7)]
    cols = [math.floor((j + 0.5) * 5 / 9) for j in range(9)]
    assert torch.equal(odd, img[..., rows, :][..., cols])
    assert oled_emission(img, (4, 5)) is img


@settings(max_examples=15, deadline=None)
@given(st.integers(1, 6), st.integers(1, 6), st.integers(1, 4))
def test_area_filter_undoes_box_emission(h, w, k):
    img = torch.rand(3, h, w, dtype=torch.float64)
    assert torch.allclose(area_resample(oled_emission(img, (h * k, w * k)), k), img, atol=1e-14)


def test_gradcheck_box_emission_and_stage():
    img = torch.rand(3, 3, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: oled_emission(x, (7, 9)), (img,))
    stage = OLEDEmission()
    assert stage.is_identity(RuntimeState(1.0)) and not stage.is_identity(RuntimeState(2.0))
    assert stage(img, RuntimeState(2.0), StageContext((6, 8))).shape == (3, 6, 8)
    with pytest.raises(ShapeError, match="at least"):
        oled_emission(img, (2, 4))
    with pytest.raises(InputValueError, match="image"):
        oled_emission(img.float().half(), (6, 8))


def test_foveation_stub_is_identity():
    img = torch.rand(3, 4, 4)
    stage = Foveation()
    assert stage.is_identity(RuntimeState(gaze=(0.2, -0.1)))
    assert stage(img, RuntimeState(gaze=(0.2, -0.1)), StageContext((4, 4))) is img
    assert foveation(img, None) is img
