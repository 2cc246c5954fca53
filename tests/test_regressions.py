"""Behaviours a sampled mutation run showed no test was pinning (issue 15, section 5): the display
power per channel, the injection's grad mode, P_ref detached without a reference, the order of
stages placed after the same stage, big-endian PLY, the clamp before the metrics, and the
strengths users see, each against an absolute value or an independent computation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.formats.backbone import read_ply
from controlgs_adapter.downstream.display import DisplayMapping, display_mapping, display_power, display_power_watts
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.evaluation import scores

from scaffold_standin import ScaffoldStandIn, make_camera


@pytest.mark.parametrize("channel, alpha", [(0, 228.52), (1, 205.66), (2, 567.64)])
def test_display_power_per_channel(channel, alpha):
    """P = mean(alpha R + beta G + gamma B) on linear RGB (DESIGN.md), each primary on its own."""
    img = torch.zeros(3, 4, 6, dtype=torch.float64)
    img[channel, :2] = 0.5  # half the pixels at 0.5: mean 0.25
    assert float(display_power(img)) == pytest.approx(alpha * 0.25, rel=1e-12)
    assert float(display_power_watts(img)) == pytest.approx(alpha * 0.25 * 3e-3, rel=1e-12)
    srgb = torch.zeros(3, 2, 2, dtype=torch.float64)
    srgb[channel] = 0.5  # sRGB 0.5 = linear ((0.5 + 0.055) / 1.055) ** 2.4
    assert float(display_power(srgb, encoding="srgb")) == pytest.approx(alpha * ((0.555 / 1.055) ** 2.4), rel=1e-9)


def test_no_grad_decode_then_grad_decode_in_one_block_has_a_graph():
    """The injection cached under no_grad must not be reused by a decode with grad enabled."""
    torch.manual_seed(0)
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model, modules=("resample",), cond_dim=4)
    with torch.no_grad():
        cgs.injector.conditions.normal_()
    x = model.decoder_input(cam.center)
    with cgs.conditioned(RuntimeState(downsample=4.0), camera=cam):
        with torch.no_grad():
            model.decode(x)
        loss = sum(y.sum() for y in model.decode(x).values())
    assert loss.requires_grad
    loss.backward()
    assert cgs.injector.conditions.grad is not None and cgs.injector.conditions.grad.abs().sum() > 0
    cgs.unwrap()


def test_display_without_reference_detaches_p_ref():
    """No reference: P_ref = P(image) is a constant, so the gradient is that of
    image * (1 - rho) * P(image).detach() / P(image)."""
    g = torch.Generator().manual_seed(1)
    base = torch.rand(2, 3, 5, 7, generator=g, dtype=torch.float64) * 0.8
    weights = torch.rand(2, 3, 5, 7, generator=g, dtype=torch.float64)
    rho = 0.3

    def grad(fn):
        x = base.clone().requires_grad_(True)
        (fn(x) * weights).sum().backward()
        return x.grad

    def by_hand(x):
        p = display_power(x)
        return x * ((1 - rho) * p.detach() / p)[:, None, None, None]

    want = grad(by_hand)
    assert not torch.allclose(want, torch.full_like(want, 1 - rho) * weights)  # the power's gradient is not zero
    stage = DisplayMapping(p_ref="ground_truth")
    ctx = StageContext(native_size=(5, 7))
    assert torch.allclose(grad(lambda x: stage(x, RuntimeState(power_saving=rho), ctx)), want, atol=1e-12, rtol=0)
    assert torch.allclose(grad(lambda x: display_mapping(x, rho)), want, atol=1e-12, rtol=0)


def _stage(name: str, after: str, order: float) -> Stage:
    return type(name.title(), (Stage,), {"name": name, "after": after, "order": order,
                                          "forward": lambda self, image, state, ctx: image})()


def test_stages_placed_after_the_same_stage_keep_their_order():
    base = list(Pipeline.from_config(["resample", "display"]).stages)
    for stages in ([_stage("b", "resample", 50.0), _stage("a", "resample", 60.0)],
                   [_stage("a", "resample", 60.0), _stage("b", "resample", 50.0)]):
        assert Pipeline([*stages, *base]).names == ["resample", "b", "a", "display", "oled"]
    same = [_stage("q", "resample", 50.0), _stage("p", "resample", 50.0)]
    assert Pipeline([*same, *base]).names == ["resample", "p", "q", "display", "oled"]


def test_big_endian_ply_read_as_big_endian(tmp_path):
    values = {"x": np.array([1.5, -2.25, 3e-3], ">f4"), "level": np.array([1, 2, 300], ">i4"),
              "w": np.array([0.1, 2.0, -7.0], ">f8")}
    header = ("ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty int level\n"
              "property double w\nend_header\n")
    table = np.empty(3, dtype=[("x", ">f4"), ("level", ">i4"), ("w", ">f8")])
    for k, v in values.items():
        table[k] = v
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + table.tobytes())
    fields, _ = read_ply(path)
    for k, v in values.items():
        assert fields[k].tolist() == v.tolist(), k
        assert fields[k].dtype.isnative


def test_metrics_clamp_the_eye_image():
    """A saturated eye image is clamped to [0, 1] before PSNR/SSIM (what the display can hold)."""
    gt = torch.full((3, 16, 16), 0.9, dtype=torch.float64)
    eye = gt.clone()
    eye[:, :8] = 1.4  # half the pixels overshoot: clamped to 1.0, error 0.1
    eye[0, 8:, :2] = -0.3  # a negative corner: clamped to 0, error 0.9
    err = torch.full((3, 16, 16), 0.0, dtype=torch.float64)
    err[:, :8] = 0.1
    err[0, 8:, :2] = 0.9
    want = 10 * math.log10(1.0 / float((err ** 2).mean()))
    got = scores(eye, gt, {})
    assert got["psnr"] == pytest.approx(want, abs=1e-9)
    assert got["psnr"] == pytest.approx(16.60051938305649, abs=1e-9)  # = 10 log10(768 / 16.8)


def test_strengths_reported_are_the_schedules_absolute_values():
    """lambda = log2(d) / 3 (resample), rho / 0.8 (display), |p| / sqrt(2) clamped (lens)."""
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model, cond_dim=4)
    lam = cgs.strengths(RuntimeState(downsample=2.0, power_saving=0.3), cam)
    assert torch.allclose(lam["resample"].double(), torch.full_like(lam["resample"].double(), 1 / 3), atol=1e-7)
    assert torch.allclose(lam["display"].double(), torch.full_like(lam["display"].double(), 0.375), atol=1e-7)
    from controlgs_adapter.downstream.placement import to_display

    p = to_display(cam.normalized_screen(model.get_anchor.detach()).double(), cam.height, cam.width, cgs.placement)
    want = (p.norm(dim=1) / math.sqrt(2)).clamp(0, 1)
    assert torch.allclose(lam["lens"].double(), want, atol=1e-6)
    assert 0 < float(want.min()) < float(want.max()) < 1
    cgs.unwrap()
