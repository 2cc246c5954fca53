"""Degenerate anchors (scales of 1e20, or a log-scale whose exp overflows float32) keep every adapter
gradient finite, equal to the float64 render without the splatter's spread cap."""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.models.anchor_model import assemble_gaussians
from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.protocol import render_view

STATE = RuntimeState(downsample=2.0, power_saving=0.4)


def _adapter_grads(model: Any, scene: Any, anchor: int, log_scale: float | None, dtype: torch.dtype,
                   ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Render test view 0 through a wrapped copy of ``model`` (anchor ``anchor``'s Gaussian log-scales set to
    ``log_scale``; its Gaussians get scales of about exp(log_scale)) and return the image and the gradients of a
    fixed weighted sum of it in every adapter tensor."""
    m = copy.deepcopy(model).to(dtype)
    if log_scale is not None:
        with torch.no_grad():
            m._scaling[anchor, 3:] = log_scale
    cgs = ControlGS.wrap(m)
    try:
        with torch.no_grad():
            for i, p in enumerate(cgs.injector.parameters()):
                p.copy_(0.05 * torch.randn(p.shape, generator=torch.Generator().manual_seed(i), dtype=torch.float64))
        cam = scene.test_cameras[0]
        image = render_view(cgs, m, cam, STATE, scene.background.to(dtype))
        (image * torch.linspace(-1.0, 1.0, image.numel(), dtype=dtype).view_as(image)).sum().backward()
        return image.detach(), {n: p.grad.detach().clone() for n, p in cgs.injector.named_parameters()}
    finally:
        cgs.unwrap()


def _drawn_anchor(model: Any, scene: Any) -> int:
    """The anchor of the most opaque Gaussian the test view draws."""
    cam = scene.test_cameras[0]
    with torch.no_grad():
        g = model.decode(cam, model.visible_anchors(cam))
    return int(g.anchor_of[g.opacities.argmax()])


@pytest.mark.parametrize("log_scale", [math.log(1e20), 100.0])  # 100: exp overflows to inf in float32
def test_a_degenerate_anchor_keeps_every_adapter_gradient_finite(tiny: Any, log_scale: float,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    scene, model = tiny
    anchor = _drawn_anchor(model, scene)
    image, grads = _adapter_grads(model, scene, anchor, log_scale, torch.float32)
    assert bool(torch.isfinite(image).all())
    plain, _ = _adapter_grads(model, scene, anchor, None, torch.float32)
    assert float((image - plain).abs().max()) > 1e-3  # the degenerate Gaussians are drawn (a veil over the view)
    assert set(grads) >= {"conditions", "projections.lens.d8.weight", "projections.display.d8.weight"}
    for name, grad in grads.items():
        assert bool(torch.isfinite(grad).all()), name
        assert float(grad.abs().max()) > 0.0, name
    # the reference: float64 (scales up to ~1e75 representable there) without the spread cap
    monkeypatch.setattr(splatter, "MAX_SPREAD", math.inf)
    monkeypatch.setattr(splatter, "_MAX_SPREAD_PX", math.inf)
    ref_image, ref_grads = _adapter_grads(model, scene, anchor, log_scale, torch.float64)
    torch.testing.assert_close(image.double(), ref_image, rtol=0, atol=1e-5)
    for name, grad in grads.items():
        err = float((grad.double() - ref_grads[name]).norm() / ref_grads[name].norm())
        assert err < 1e-4, (name, err)


def test_without_the_cap_the_float32_adapter_gradients_are_nan(tiny: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """What the cap prevents (the adversarial finding): NaN in every adapter tensor from one anchor."""
    scene, model = tiny
    anchor = _drawn_anchor(model, scene)
    monkeypatch.setattr(splatter, "MAX_SPREAD", math.inf)
    monkeypatch.setattr(splatter, "_MAX_SPREAD_PX", math.inf)
    _, grads = _adapter_grads(model, scene, anchor, math.log(1e20), torch.float32)
    assert all(not bool(torch.isfinite(g).all()) for g in grads.values())


def test_assemble_gaussians_takes_an_overflowed_scaling_as_the_largest_float() -> None:
    k, r = 2, 3
    scaling = torch.ones(r, 6)
    scaling[1, 3:] = math.inf
    scale_rot = torch.randn(r * k, 7, requires_grad=True)
    g = assemble_gaussians(torch.arange(r), k, torch.zeros(r, 3), torch.zeros(r * k, 3), scaling, torch.ones(r * k),
                           torch.rand(r * k, 3), scale_rot, torch.ones(r * k, dtype=torch.bool))
    assert bool(torch.isfinite(g.scales).all())
    assert torch.equal(g.scales[2:4], torch.finfo(torch.float32).max * torch.sigmoid(scale_rot[2:4, :3]))
    assert torch.equal(g.scales[:2], torch.sigmoid(scale_rot[:2, :3]))  # finite scalings unchanged
    g.scales.sum().backward()
    assert scale_rot.grad is not None and bool(torch.isfinite(scale_rot.grad).all())
