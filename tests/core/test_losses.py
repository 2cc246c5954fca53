"""Tests of ``controlgs_adapter.losses``."""

from __future__ import annotations

import math
from typing import Any, Callable

import pytest
import torch

from controlgs_adapter.errors import ControlGSError, InputValueError, ShapeError
from controlgs_adapter.losses import LPIPS_UNAVAILABLE, ImageLoss, LossWeights, image_loss
from controlgs_adapter.metrics import ssim
from controlgs_adapter.state import RuntimeState
from controlgs_adapter.training import TrainConfig


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


LOSS_CASES = [("l1", math.inf), ("l1", math.nan), ("l1", -1.0), ("l1", "a"), ("l1", None), ("ssim", math.inf),
              ("mse", math.inf), ("mse", True), ("lpips", 1.0)]


@pytest.mark.parametrize("name, value", LOSS_CASES, ids=[f"{n}={v!r}" for n, v in LOSS_CASES])
def test_loss_weights(name, value):
    _raises(lambda: LossWeights(**{name: value}), InputValueError, "lpips" if name == "lpips" else name)


def _pair(seed, shape=(3, 17, 21), dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=dtype)
    y = (x + 0.1 * torch.randn(shape, generator=g, dtype=dtype)).clamp(0, 1)
    return x, y


def test_loss_weights_and_value():
    x, y = _pair(3, (3, 16, 16))
    assert float(image_loss(x, x)) == pytest.approx(0.0, abs=1e-12)
    d = x - y
    want = 0.8 * d.abs().mean() + 10.0 * d.square().mean() + 0.2 * (1 - ssim(x, y))
    assert float(image_loss(x, y)) == pytest.approx(float(want), abs=1e-12)
    only_mse = LossWeights(l1=0.0, ssim=0.0, mse=1.0)
    assert float(image_loss(x, y, only_mse)) == pytest.approx(float(d.square().mean()), abs=1e-12)


D = torch.float64


def _images(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(3, h, w, generator=g, dtype=D)
    y = (x + 0.2 * torch.randn(3, h, w, generator=g, dtype=D)).clamp(0, 1)
    return x, y


def _ssim_by_hand(x: torch.Tensor, y: torch.Tensor, data_range: float, size: int, sigma: float) -> float:
    """Brute-force SSIM: every valid window position, Gaussian weights g(u) g(v), exp(-r^2 / 2 sigma^2)
    normalised, c1 = (0.01 L)^2, c2 = (0.03 L)^2, mean over channels and positions."""
    r = [i - (size - 1) / 2 for i in range(size)]
    g = [math.exp(-t * t / (2 * sigma * sigma)) for t in r]
    g = [v / sum(g) for v in g]
    w = torch.tensor([[a * b for b in g] for a in g], dtype=D)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    vals = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - size + 1):
            for j in range(x.shape[2] - size + 1):
                px, py = x[c, i:i + size, j:j + size], y[c, i:i + size, j:j + size]
                mx, my = (w * px).sum(), (w * py).sum()
                vx, vy = (w * px * px).sum() - mx * mx, (w * py * py).sum() - my * my
                cxy = (w * px * py).sum() - mx * my
                vals.append(float((2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2))))
    return sum(vals) / len(vals)


@pytest.mark.parametrize("weights", [LossWeights(l1=0.3, ssim=0.5, mse=2.0), LossWeights(l1=0.0, ssim=0.0, mse=1.0),
                                     LossWeights(l1=1.0, ssim=1.0, mse=0.0)])
def test_image_loss_weights_by_hand(weights):
    x, y = _images(12, 13, 3)
    got = float(image_loss(x[None], y[None], weights))
    d = (x - y).flatten().tolist()
    want = (weights.l1 * sum(abs(v) for v in d) / len(d) + weights.mse * sum(v * v for v in d) / len(d)
            + weights.ssim * (1.0 - _ssim_by_hand(x, y, 1.0, 11, 1.5)))
    assert got == pytest.approx(want, rel=1e-10)
    assert float(ImageLoss(weights)(x[None], y[None])) == pytest.approx(want, rel=1e-10)  # the module form


def test_image_loss_module_names_pred_and_target_in_its_call_order():
    """``ImageLoss()(pred, target)``: a shape mismatch names ``pred``'s shape first, as the call gave them."""
    from controlgs_adapter.errors import ShapeError
    from controlgs_adapter.losses import ImageLoss

    with pytest.raises(ShapeError, match=r"pred and target must have the same shape, got \[3, 16, 16\] and \[3, 12, 12\]"):
        ImageLoss()(torch.rand(3, 16, 16), torch.rand(3, 12, 12))


def test_loss_weights_defaults_and_refusals():
    w = LossWeights()
    assert (w.l1, w.ssim, w.mse, w.lpips) == (0.8, 0.2, 10.0, 0.0)  # the paper's real-scene weights (Eq. 14)
    assert LossWeights(l1=0, ssim=0, mse=0).l1 == 0.0
    with pytest.raises(InputValueError, match=r"loss weight mse must be a finite number in \[0, inf\), got -1"):
        LossWeights(mse=-1)
    with pytest.raises(InputValueError) as e:
        LossWeights(lpips=0.1)
    assert str(e.value) == LPIPS_UNAVAILABLE + " (got lpips=0.1)"


def test_image_loss_by_hand():
    pred = torch.full((2, 3, 12, 12), 0.5, dtype=torch.float64)
    target = torch.full((2, 3, 12, 12), 0.25, dtype=torch.float64)
    # L1 and MSE only: 0.8 * 0.25 + 10 * 0.25^2 = 0.2 + 0.625
    got = image_loss(pred, target, LossWeights(ssim=0.0))
    assert math.isclose(float(got), 0.825, rel_tol=1e-14)
    # SSIM of two constant images (zero variances): (2ab + C1) / (a^2 + b^2 + C1), C1 = 0.01^2
    s = (2 * 0.5 * 0.25 + 1e-4) / (0.5**2 + 0.25**2 + 1e-4)
    got = image_loss(pred, target, LossWeights(l1=0.0, ssim=1.0, mse=0.0))
    assert math.isclose(float(got), 1.0 - s, rel_tol=1e-9)
    # defaults: 0.8 L1 + 0.2 (1 - SSIM) + 10 MSE
    assert math.isclose(float(image_loss(pred, target)), 0.825 + 0.2 * (1.0 - s), rel_tol=1e-9)
    assert math.isclose(float(ImageLoss(LossWeights(ssim=0.0))(pred, target)), 0.825, rel_tol=1e-14)
    assert float(image_loss(pred, pred)) == 0.0
    # sign matters for L1 (|d|), not a plain mean of differences: 0.8 * 0.25 + 10 * 0.0625
    assert math.isclose(float(image_loss(target, pred, LossWeights(ssim=0.0))), 0.825, rel_tol=1e-14)
    with pytest.raises(ShapeError):
        image_loss(pred, target[..., :11])


def test_value_objects_are_frozen():
    import dataclasses

    from controlgs_adapter.controlgs import Target
    from controlgs_adapter.plugins import PluginInfo

    objs = [(LossWeights(), "l1"), (RuntimeState(), "downsample"), (TrainConfig(), "lr"),
            (Target("d", "d.0", 3, 4, False), "fc1"), (PluginInfo("stage", "n", "p", "s", None), "name")]
    for obj, field in objs:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, field, 1)
    assert hash(LossWeights()) == hash(LossWeights(0.8, 0.2, 10.0, 0.0))  # frozen dataclasses hash by value


def test_image_loss_checks_name_pred_and_target_in_order():
    from controlgs_adapter.errors import ShapeError as _ShapeError
    from controlgs_adapter.losses import image_loss

    with pytest.raises(_ShapeError, match=r"pred and target must have the same shape, got \[3, 4, 4\] and \[3, 4, 5\]"):
        image_loss(torch.rand(3, 4, 4), torch.rand(3, 4, 5))
    with pytest.raises(_ShapeError, match="target"):
        image_loss(torch.rand(3, 4, 4), torch.rand(2, 4, 4))
