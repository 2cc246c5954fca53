"""The splatter on degenerate Gaussians: scales far beyond the image (1e20, float32's largest) render a
saturated footprint with finite gradients, equal to the float64 splat without the spread cap."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.state import Camera

W, H = 16, 12
CAM = Camera(torch.eye(4, dtype=torch.float64),
             torch.tensor([[14.0, 0.0, 8.0], [0.0, 14.0, 6.0], [0.0, 0.0, 1.0]], dtype=torch.float64), W, H)


def _gaussians(big: float | None) -> list[torch.Tensor]:
    """Eight Gaussians in front of the camera (float64); with ``big``, number 3 gets scale ``big`` on two axes."""
    g = torch.Generator().manual_seed(0)
    n = 8
    means = torch.cat([torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5,
                       2.0 + 2.0 * torch.rand(n, 1, generator=g, dtype=torch.float64)], 1)
    scales = 0.05 + 0.2 * torch.rand(n, 3, generator=g, dtype=torch.float64)
    if big is not None:
        scales[3, :2] = big
    rotations = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opacities = 0.2 + 0.6 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [means, scales, rotations, opacities, colors]


def _render(tensors: list[torch.Tensor], dtype: torch.dtype) -> tuple[torch.Tensor, list[torch.Tensor]]:
    leaves = [t.to(dtype).requires_grad_(True) for t in tensors]
    out = rasterize(*leaves, CAM, torch.tensor([0.1, 0.2, 0.3], dtype=dtype), transmittance_min=0.0)
    weight = torch.linspace(-1.0, 1.0, 3 * H * W, dtype=dtype).view(3, H, W)
    ((out.color * weight).sum() + out.alpha.sum() + out.depth.mean()).backward()
    return out.color.detach(), [t.grad for t in leaves]


def _uncapped(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(splatter, "MAX_SPREAD", math.inf)
    monkeypatch.setattr(splatter, "_MAX_SPREAD_PX", math.inf)


@pytest.mark.parametrize("big", [1e20, 1e30, float(torch.finfo(torch.float32).max)])
def test_a_huge_gaussian_has_finite_gradients_equal_to_the_float64_splat(big: float, monkeypatch: pytest.MonkeyPatch) -> None:
    image, grads = _render(_gaussians(big), torch.float32)
    assert bool(torch.isfinite(image).all())
    for name, grad in zip(("means", "scales", "rotations", "opacities", "colors"), grads):
        assert bool(torch.isfinite(grad).all()), name
    _uncapped(monkeypatch)  # the reference: exact float64 math, no cap (representable there up to ~1e75)
    ref_image, ref_grads = _render(_gaussians(min(big, 1e60)), torch.float64)
    torch.testing.assert_close(image.double(), ref_image, rtol=0, atol=1e-5)
    for name, grad, ref in zip(("means", "scales", "rotations", "opacities", "colors"), grads, ref_grads):
        finite = torch.ones_like(ref, dtype=torch.bool)
        if name == "scales":  # d/d(scale) of the saturated axes: 0 (capped) here, ~1/scale in float64
            finite[3, :2] = False
            assert float(grad[3, :2].abs().max()) == 0.0 and float(ref[3, :2].abs().max()) < 1e-12
        err = (grad.double() - ref)[finite].norm() / ref[finite].norm()
        assert float(err) < 1e-4, (name, float(err))


def test_the_cap_changes_nothing_for_ordinary_gaussians(monkeypatch: pytest.MonkeyPatch) -> None:
    for dtype in (torch.float32, torch.float64):
        image, grads = _render(_gaussians(None), dtype)
        with monkeypatch.context() as m:
            _uncapped(m)
            ref_image, ref_grads = _render(_gaussians(None), dtype)
        assert torch.equal(image, ref_image)
        assert all(torch.equal(a, b) for a, b in zip(grads, ref_grads))


def test_without_the_cap_float32_gradients_are_nan(monkeypatch: pytest.MonkeyPatch) -> None:
    """What the cap prevents: the 2D covariance overflows and NaN reaches every input's gradient."""
    _uncapped(monkeypatch)
    _, grads = _render(_gaussians(1e20), torch.float32)
    assert not bool(torch.isfinite(grads[1]).all())
