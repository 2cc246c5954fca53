"""Tests of ``controlgs_adapter.losses``: the loss weights of Eq. 14 and their refusals, and the image loss
(L1 + MSE + 1 - SSIM) against its terms written out and the brute-force SSIM."""

from __future__ import annotations

import math
import re

import pytest
import torch
from helpers.oracles import ssim_brute_force

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.losses import LPIPS_UNAVAILABLE, ImageLoss, LossWeights, image_loss

D64 = torch.float64


def _pair(seed: int, shape=(3, 12, 13)) -> tuple[torch.Tensor, torch.Tensor]:
    """A float64 image in [0, 1] and a noisy copy of it, clamped to [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=D64)
    return x, (x + 0.2 * torch.randn(shape, generator=g, dtype=D64)).clamp(0, 1)


# ------------------------------------------------------------------------------ the weights
def test_loss_weights_defaults_are_the_papers():
    w = LossWeights()
    assert (w.l1, w.ssim, w.mse, w.lpips) == (0.8, 0.2, 10.0, 0.0)  # the paper's real-scene weights (Eq. 14)
    assert LossWeights(l1=0, ssim=0, mse=0).l1 == 0.0


LOSS_CASES = [("l1", math.inf), ("l1", math.nan), ("l1", -1.0), ("l1", "a"), ("l1", None), ("ssim", math.inf),
              ("mse", math.inf), ("mse", True), ("mse", -1), ("lpips", 1.0), ("lpips", 0.1)]


@pytest.mark.parametrize("name, value", LOSS_CASES, ids=[f"{n}={v!r}" for n, v in LOSS_CASES])
def test_loss_weights_refusals_name_the_weight_and_value(name, value):
    """A weight that is not a finite number >= 0 is refused naming it and the value; any LPIPS weight > 0
    is refused with the reason LPIPS is not available."""
    with pytest.raises(InputValueError, match=rf"{name}.*{re.escape(repr(value))}") as e:
        LossWeights(**{name: value})
    if name == "lpips":
        assert str(e.value).startswith(LPIPS_UNAVAILABLE)


# ------------------------------------------------------------------------------ the loss
@pytest.mark.parametrize("weights", [LossWeights(), LossWeights(l1=0.3, ssim=0.5, mse=2.0),
                                     LossWeights(l1=0.0, ssim=0.0, mse=1.0), LossWeights(l1=1.0, ssim=1.0, mse=0.0)])
def test_image_loss_is_the_weighted_sum_of_its_terms(weights):
    """l1 |d| + mse d^2 (means over every value) + ssim (1 - SSIM), the SSIM by its brute-force definition;
    the function and the module form agree."""
    x, y = _pair(3)
    d = (x - y).flatten().tolist()
    want = (weights.l1 * sum(abs(v) for v in d) / len(d) + weights.mse * sum(v * v for v in d) / len(d)
            + weights.ssim * (1.0 - ssim_brute_force(x, y)))
    assert float(image_loss(x[None], y[None], weights)) == pytest.approx(want, rel=1e-10)
    assert float(ImageLoss(weights)(x[None], y[None])) == pytest.approx(want, rel=1e-10)
    assert float(image_loss(x, x, weights)) == pytest.approx(0.0, abs=1e-12)


def test_image_loss_of_constant_images():
    pred = torch.full((2, 3, 12, 12), 0.5, dtype=D64)
    target = torch.full((2, 3, 12, 12), 0.25, dtype=D64)
    # L1 and MSE only: 0.8 * 0.25 + 10 * 0.25^2 = 0.2 + 0.625
    assert math.isclose(float(image_loss(pred, target, LossWeights(ssim=0.0))), 0.825, rel_tol=1e-14)
    # SSIM of two constant images (zero variances): (2ab + C1) / (a^2 + b^2 + C1), C1 = 0.01^2
    s = (2 * 0.5 * 0.25 + 1e-4) / (0.5**2 + 0.25**2 + 1e-4)
    assert math.isclose(float(image_loss(pred, target, LossWeights(l1=0.0, ssim=1.0, mse=0.0))), 1.0 - s, rel_tol=1e-9)
    # defaults: 0.8 L1 + 0.2 (1 - SSIM) + 10 MSE
    assert math.isclose(float(image_loss(pred, target)), 0.825 + 0.2 * (1.0 - s), rel_tol=1e-9)
    assert math.isclose(float(ImageLoss(LossWeights(ssim=0.0))(pred, target)), 0.825, rel_tol=1e-14)
    assert float(image_loss(pred, pred)) == 0.0
    # sign matters for L1 (|d|), not a plain mean of differences: 0.8 * 0.25 + 10 * 0.0625
    assert math.isclose(float(image_loss(target, pred, LossWeights(ssim=0.0))), 0.825, rel_tol=1e-14)


def test_image_loss_gradients():
    x, y = _pair(2, (3, 12, 13))
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: image_loss(t, y), (x,), fast_mode=True)


def test_image_loss_checks_name_pred_and_target_in_call_order():
    """A shape mismatch names ``pred``'s shape first, as the call gave them, in the function and the module."""
    with pytest.raises(ShapeError, match=r"^pred and target .*\[3, 4, 4\] and \[3, 4, 5\]"):
        image_loss(torch.rand(3, 4, 4), torch.rand(3, 4, 5))
    with pytest.raises(ShapeError, match=r"^pred and target .*\[3, 16, 16\] and \[3, 12, 12\]"):
        ImageLoss()(torch.rand(3, 16, 16), torch.rand(3, 12, 12))
    with pytest.raises(ShapeError, match="target"):
        image_loss(torch.rand(3, 4, 4), torch.rand(2, 4, 4))
    with pytest.raises(ShapeError, match=r"\[2, 3, 12, 11\]"):
        image_loss(torch.zeros(2, 3, 12, 12), torch.zeros(2, 3, 12, 11))
