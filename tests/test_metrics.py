"""PSNR/SSIM against an independent float64 numpy brute force and scikit-image; the loss."""

import math
import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.losses import LossWeights, image_loss
from controlgs_adapter.metrics import psnr, ssim


def _pair(seed, shape=(3, 17, 21), dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=dtype)
    y = (x + 0.1 * torch.randn(shape, generator=g, dtype=dtype)).clamp(0, 1)
    return x, y


def _ssim_bruteforce(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. with an explicit 11x11 Gaussian (sigma 1.5) at every valid window position."""
    r = np.arange(11) - 5.0
    g1 = np.exp(-r**2 / (2 * 1.5**2))
    w = np.outer(g1, g1) / np.outer(g1, g1).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - 10):
            for j in range(x.shape[2] - 10):
                a, b = x[c, i:i + 11, j:j + 11], y[c, i:i + 11, j:j + 11]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
                cov = (w * (a - ma) * (b - mb)).sum()
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_matches_bruteforce():
    x, y = _pair(0)
    assert float(ssim(x, y)) == pytest.approx(_ssim_bruteforce(x.numpy(), y.numpy()), abs=1e-12)
    # float32 path agrees to float32 precision, batch dims are kept
    xb, yb = torch.stack([x, y]).float(), torch.stack([y, x]).float()
    out = ssim(xb, yb)
    assert out.shape == (2,) and float((out - float(ssim(x, y))).abs().max()) < 1e-5


def test_against_scikit_image():
    metrics = pytest.importorskip("skimage.metrics")
    x, y = _pair(1, (3, 32, 40))
    a, b = x.permute(1, 2, 0).numpy(), y.permute(1, 2, 0).numpy()
    ref = metrics.structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False)
    assert float(ssim(x, y)) == pytest.approx(ref, abs=1e-6)
    assert float(psnr(x, y)) == pytest.approx(metrics.peak_signal_noise_ratio(a, b, data_range=1.0), abs=1e-9)


def test_psnr_known_value_and_identity():
    x = torch.zeros(3, 4, 4)
    assert float(psnr(x, x + 0.1)) == pytest.approx(20.0, abs=1e-4)
    assert float(psnr(x, x)) == float("inf")
    assert float(ssim(torch.rand(3, 12, 12), torch.rand(3, 12, 12) * 0)) < 0.5


def test_psnr_data_range_by_hand():
    # 8-bit values: an error of 5 levels everywhere is 10 log10(255^2 / 25) = 34.1514 dB
    x = torch.full((3, 4, 5), 100.0, dtype=torch.float64)
    assert float(psnr(x, x + 5.0, data_range=255.0)) == pytest.approx(10 * math.log10(255.0**2 / 25.0), abs=1e-9)
    assert float(psnr(x / 255.0, (x + 5.0) / 255.0)) == pytest.approx(34.15140352195873, abs=1e-9)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.0, 0.5))
def test_ssim_properties(seed, scale):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(3, 13, 15, generator=g, dtype=torch.float64)
    y = (x + scale * torch.randn(3, 13, 15, generator=g, dtype=torch.float64)).clamp(0, 1)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-12)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(y, x)), abs=1e-12)
    assert float(ssim(x, y)) <= 1.0 + 1e-12
    assert float(psnr(x, y)) == pytest.approx(float(psnr(y, x)), abs=1e-9)


def test_gradients():
    x, y = _pair(2, (3, 12, 13))
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ssim(t, y), (x,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda t: image_loss(t, y), (x,), fast_mode=True)


def test_loss_weights_and_value():
    x, y = _pair(3, (3, 16, 16))
    assert float(image_loss(x, x)) == pytest.approx(0.0, abs=1e-12)
    d = x - y
    want = 0.8 * d.abs().mean() + 10.0 * d.square().mean() + 0.2 * (1 - ssim(x, y))
    assert float(image_loss(x, y)) == pytest.approx(float(want), abs=1e-12)
    only_mse = LossWeights(l1=0.0, ssim=0.0, mse=1.0)
    assert float(image_loss(x, y, only_mse)) == pytest.approx(float(d.square().mean()), abs=1e-12)


def test_errors_are_clear():
    with pytest.raises(InputValueError, match="LPIPS"):
        LossWeights(lpips=0.1)
    with pytest.raises(InputValueError, match="l1"):
        LossWeights(l1=-1.0)
    with pytest.raises(ShapeError, match="at least 11x11"):
        ssim(torch.rand(3, 8, 8), torch.rand(3, 8, 8))
    with pytest.raises(ShapeError, match="same shape"):
        psnr(torch.rand(3, 8, 8), torch.rand(3, 8, 9))
