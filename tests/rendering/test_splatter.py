"""Tests of ``controlgs_adapter.rendering.splatter``: the tiled splatter against the float64 brute-force reference
(images and gradients, float32 and float64), closed forms, early termination and its error bound, chunked and
recomputed passes, degenerate Gaussians (needles, scales far beyond the image), invariances, and its refusals."""

from __future__ import annotations

import copy
import math
from typing import Any

import pytest
import torch
import torch.nn.functional as F
from helpers.splat_scenes import F64, camera_to_world_points, make_camera, random_scene
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.checks import value_checks
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.protocol import render_view
from controlgs_adapter.rendering.splatter import RasterOutput, rasterize
from controlgs_adapter.rendering.splatter_reference import rasterize_reference
from controlgs_adapter.state import Camera

#: a 16 x 12 float64 camera for the degenerate-Gaussian tests
W, H = 16, 12
CAM = Camera(torch.eye(4, dtype=F64), torch.tensor([[14.0, 0.0, 8.0], [0.0, 14.0, 6.0], [0.0, 0.0, 1.0]], dtype=F64), W, H)


def _stack(out) -> torch.Tensor:
    return torch.cat([out.color, out.alpha, out.depth])


def _camera(f: float = 20.0, width: int = 24, height: int = 16) -> Camera:
    """Identity pose, principal point at the image centre."""
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=F64)
    return Camera(torch.eye(4, dtype=F64), k, width, height)


def _one(mean: list[float], scale: list[float], q: list[float], o: float, color: list[float] | None = None
         ) -> tuple[torch.Tensor, ...]:
    """One float64 Gaussian (white unless ``color``)."""
    return (torch.tensor([mean], dtype=F64), torch.tensor([scale], dtype=F64), torch.tensor([q], dtype=F64),
            torch.tensor([o], dtype=F64), torch.tensor([color or [1.0, 1.0, 1.0]], dtype=F64))


def _wide_scene():
    """A 37 x 11 camera (unrotated, principal point off-centre) and Gaussians placed by pixel: inside,
    straddling each border, entirely off-screen below and right, and one behind the near plane."""
    w, h = 37, 11
    k = torch.tensor([[30.0, 0, 17.3], [0, 28.0, 5.9], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, w, h)
    # (u, v) pixel positions and depths
    uv = torch.tensor([[5.0, 5.0], [18.0, 10.6], [36.4, 3.0], [-0.5, 7.0], [20.0, -0.4], [18.0, 12.5],
                       [45.0, 5.0], [9.0, 2.0], [30.0, 8.0], [18.0, 5.0]], dtype=F64)
    z = torch.tensor([2.0, 1.5, 3.0, 2.5, 1.2, 2.0, 2.0, 4.0, 0.15, 3.5], dtype=F64)
    x = (uv[:, 0] - 17.3) / 30.0 * z
    y = (uv[:, 1] - 5.9) / 28.0 * z
    means = torch.stack([x, y, z], -1)
    g = torch.Generator().manual_seed(3)
    scales = 0.02 + 0.05 * torch.rand(10, 3, generator=g, dtype=F64)
    rot = torch.randn(10, 4, generator=g, dtype=F64)
    opac = 0.3 + 0.69 * torch.rand(10, generator=g, dtype=F64)
    colors = torch.rand(10, 3, generator=g, dtype=F64)
    return cam, (means, scales, rot, opac, colors)


def _smooth_scene():
    """A few wide Gaussians covering an 8x8 image: every pixel is well inside every footprint, alpha
    stays in (1/255, 0.99) and T > 1e-4, so no cut-off lies within a finite-difference step."""
    cam = Camera(torch.eye(4, dtype=F64), torch.tensor([[8.0, 0, 4.2], [0, 9.0, 3.9], [0, 0, 1]], dtype=F64), 8, 8)
    means = torch.tensor([[0.05, -0.02, 2.0], [-0.1, 0.08, 2.5], [0.12, 0.1, 3.0]], dtype=F64)
    scales = torch.tensor([[0.9, 0.6, 0.3], [0.7, 1.1, 0.5], [1.2, 0.8, 0.9]], dtype=F64)
    rotations = torch.tensor([[0.9, 0.1, -0.2, 0.3], [0.5, 0.5, 0.1, -0.4], [1.2, -0.3, 0.2, 0.1]], dtype=F64)
    opacities = torch.tensor([0.55, 0.7, 0.8], dtype=F64)
    colors = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.8, 0.3], [0.1, 0.3, 0.9]], dtype=F64)
    bg = torch.tensor([0.4, 0.4, 0.2], dtype=F64)
    return (means, scales, rotations, opacities, colors, bg), cam


def _opaque_stack(n: int = 40, seed: int = 2):
    """Layers of large, fairly opaque Gaussians over a 23 x 17 image: most pixels terminate (T < 1e-4)."""
    cam = make_camera()
    g = torch.Generator().manual_seed(seed)
    z = 1.0 + 3.0 * torch.rand(n, generator=g, dtype=F64)
    xy = (torch.rand(n, 2, generator=g, dtype=F64) * 2 - 1) * 0.3 * z[:, None]
    means = camera_to_world_points(cam, torch.cat([xy, z[:, None]], -1))
    scales = 0.25 * z[:, None] * (0.5 + torch.rand(n, 3, generator=g, dtype=F64))
    rotations = torch.randn(n, 4, generator=g, dtype=F64)
    opacities = 0.5 + 0.5 * torch.rand(n, generator=g, dtype=F64)
    colors = torch.rand(n, 3, generator=g, dtype=F64)
    return (means, scales, rotations, opacities, colors), cam


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


# ----------------------------------------------------------------------------- against the float64 reference

@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("tile_size", [4, 16])
@pytest.mark.parametrize("t_min", [0.0, 1e-4])
def test_matches_reference_float64(seed: int, tile_size: int, t_min: float, monkeypatch: pytest.MonkeyPatch) -> None:
    """Same threshold, same image; the depth-rank passes of early termination (here of 1, 2, 4, ...
    records per tile) change nothing."""
    monkeypatch.setattr(splatter, "_PASS_FIRST", 1)
    cam = make_camera()
    scene = random_scene(seed, 60, cam)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    fast = rasterize(*scene, cam, bg, tile_size=tile_size, transmittance_min=t_min)
    ref = rasterize_reference(*scene, cam, bg, transmittance_min=t_min)
    assert fast.color.shape == (3, 17, 23) and fast.alpha.shape == fast.depth.shape == (1, 17, 23)
    torch.testing.assert_close(_stack(fast), _stack(ref), rtol=1e-10, atol=1e-10)
    assert torch.equal(fast.visible, ref.visible)
    assert 0 < int(fast.visible.sum()) < 60  # some culled, some drawn: the scene exercises both


def test_matches_reference_float32() -> None:
    cam = make_camera(dtype=torch.float32)
    scene = random_scene(11, 60, cam, dtype=torch.float32)
    fast = rasterize(*scene, cam)
    ref = rasterize_reference(*scene, cam)
    assert fast.color.dtype == torch.float32
    err = (_stack(fast).double() - _stack(ref)).abs()
    assert float(err[:4].max()) < 1e-4  # colour and alpha
    assert float(err[4].max()) < 1e-3  # depth (scene units ~5)


def test_gradients_match_reference() -> None:
    cam = make_camera()
    scene = random_scene(3, 40, cam)
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=F64)
    weights = torch.randn(5, 17, 23, generator=torch.Generator().manual_seed(0), dtype=F64)
    grads = []
    for fn in (rasterize, rasterize_reference):
        inputs = [t.clone().requires_grad_() for t in (*scene, bg)]
        loss = (_stack(fn(*inputs[:5], cam, inputs[5])) * weights).sum()
        grads.append(torch.autograd.grad(loss, inputs))
    for name, g_fast, g_ref in zip(("means", "scales", "rotations", "opacities", "colors", "background"), *grads):
        assert float(g_ref.abs().max()) > 0, name
        torch.testing.assert_close(g_fast, g_ref, rtol=1e-8, atol=1e-9, msg=name)


def test_gradcheck() -> None:
    inputs, cam = _smooth_scene()
    ref = rasterize_reference(*inputs[:5], cam, inputs[5])
    assert bool(ref.visible.all()) and float(ref.alpha.min()) > 0.1  # the scene is as intended
    inputs = tuple(t.clone().requires_grad_() for t in inputs)

    def fn(*args):
        return _stack(rasterize(*args[:5], cam, args[5], tile_size=4))

    # fast mode compares u^T J v (analytic) with finite differences for random u, v: any wrong entry of
    # the Jacobian fails it; the full Jacobian (45 inputs x 320 outputs) would take ~20 s
    torch.manual_seed(0)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-6, fast_mode=True)


@pytest.mark.parametrize("limits", [None, (40, 64)])
def test_wide_image_borders_background_and_small_chunks_match_the_reference(limits, monkeypatch):
    cam, scene = _wide_scene()
    if limits is not None:  # chunks of a few tiles, passes of a few pairs
        monkeypatch.setattr(splatter, "_KEY_LIMIT", limits[0])
        monkeypatch.setattr(splatter, "_PAIR_BUDGET", limits[1])
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    for t_min in (0.0, 0.3):
        got = rasterize(*scene, cam, bg, tile_size=4, transmittance_min=t_min)
        ref = rasterize_reference(*scene, cam, bg, transmittance_min=t_min)
        for name in ("color", "alpha", "depth"):
            assert torch.allclose(getattr(got, name), getattr(ref, name), atol=1e-10), (name, t_min)
        assert torch.equal(got.visible, ref.visible)
    # visibility: off-screen right (45, 5) and behind the near plane (z = 0.15) are not visible
    assert not got.visible[6] and not got.visible[8] and got.visible[[0, 1, 7, 9]].all()
    # where nothing is drawn the pixel is the background colour exactly, with T = 1 - alpha elsewhere
    empty = got.alpha[0] == 0
    assert empty.any() and torch.equal(got.color[:, empty], bg[:, None].expand(3, int(empty.sum())))


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 30), tile_size=st.sampled_from([3, 4, 16]))
def test_every_pair_above_alpha_min_is_enumerated(seed: int, n: int, tile_size: int) -> None:
    """The candidate culling (alpha box, tiles, chunks) drops no (pixel, Gaussian) pair with alpha >= 1/255
    inside the footprint (counted by brute force), and the image matches the float64 oracle."""
    cam = make_camera(19, 13)
    scene = random_scene(seed, n, cam)
    enumerated = []
    expand = splatter._chunk_passes

    def counting(*args):
        passes, first = expand(*args)
        enumerated.extend(int((p.alpha > 0).sum()) for p in passes)
        return passes, first

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(splatter, "_chunk_passes", counting)
        fast = rasterize(*scene, cam, tile_size=tile_size, transmittance_min=0.0)
    means, scales, rotations, opacities = scene[:4]
    w2c, k = cam.world_to_camera, cam.intrinsics
    means_cam = means @ w2c[:3, :3].t() + w2c[:3, 3]
    front = means_cam[:, 2] > splatter.NEAR_PLANE
    uv, cov2d, conic = splatter.project_gaussians(means_cam[front], scales[front], rotations[front], w2c, k, 19, 13)
    rect, _ = splatter._footprints(uv, cov2d, opacities[front], 19, 13)
    ys, xs = torch.meshgrid(torch.arange(13, dtype=F64), torch.arange(19, dtype=F64), indexing="ij")
    dx = xs.reshape(-1, 1) + 0.5 - uv[:, 0]  # [HW, M]
    dy = ys.reshape(-1, 1) + 0.5 - uv[:, 1]
    alpha = opacities[front] * torch.exp(-0.5 * (conic[:, 0] * dx * dx + conic[:, 2] * dy * dy) - conic[:, 1] * dx * dy)
    ix, iy = xs.reshape(-1, 1), ys.reshape(-1, 1)
    inside = (ix >= rect[:, 0]) & (ix <= rect[:, 1]) & (iy >= rect[:, 2]) & (iy <= rect[:, 3])
    assert sum(enumerated) == int((inside & (alpha >= splatter.ALPHA_MIN)).sum())
    torch.testing.assert_close(_stack(fast), _stack(rasterize_reference(*scene, cam, transmittance_min=0.0)),
                               rtol=1e-10, atol=1e-10)


def test_float32_needles_near_the_camera() -> None:
    """Long thin Gaussians close to the camera have a nearly singular 2D covariance with huge entries:
    the float32 determinant must not cancel (it would turn them into opaque slabs)."""
    cam = Camera(torch.eye(4), torch.tensor([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]), 100, 100)
    g = torch.Generator().manual_seed(0)
    n = 12
    means = torch.tensor([0.0, 0.0, 0.3]) + 0.05 * torch.randn(n, 3, generator=g)
    scales = torch.tensor([[1e2, 1e-4, 1e-4]]).expand(n, 3)
    args = (means, scales, torch.randn(n, 4, generator=g), torch.full((n,), 0.5), torch.rand(n, 3, generator=g))
    fast, ref = rasterize(*args, cam), rasterize_reference(*args, cam)
    assert float((fast.alpha.double() - ref.alpha).abs().max()) < 2e-3
    assert float((fast.color.double() - ref.color).abs().max()) < 2e-3


# ----------------------------------------------------------------------------- closed forms

@pytest.mark.parametrize("x_over_z", [0.0, 0.25])
def test_single_gaussian_closed_form(x_over_z: float) -> None:
    """One isotropic Gaussian (sigma s) at (X, 0, Z): its 2D covariance is
    s^2 [[f^2/Z^2 (1 + X^2/Z^2), 0], [0, f^2/Z^2]] + 0.3 I, so every pixel is known in closed form
    (checks the conventions that the reference shares: Jacobian, low-pass, pixel centres, cut-offs)."""
    f, z, s, o = 20.0, 2.0, 0.05, 0.8
    x = x_over_z * z
    cam = Camera(torch.eye(4, dtype=F64), torch.tensor([[f, 0, 8.0], [0, f, 8.0], [0, 0, 1]], dtype=F64), 24, 16)
    args = (torch.tensor([[x, 0.0, z]], dtype=F64), torch.full((1, 3), s, dtype=F64),
            torch.tensor([[1.0, 0, 0, 0]], dtype=F64), torch.tensor([o], dtype=F64),
            torch.tensor([[0.2, 0.5, 1.0]], dtype=F64))
    out = rasterize(*args, cam)
    var_x = (s * f / z) ** 2 * (1 + x_over_z**2) + 0.3
    var_y = (s * f / z) ** 2 + 0.3
    u0, v0 = f * x_over_z + 8.0, 8.0
    xs = torch.arange(24, dtype=F64) + 0.5 - u0
    ys = torch.arange(16, dtype=F64) + 0.5 - v0
    alpha = o * torch.exp(-0.5 * (ys[:, None] ** 2 / var_y + xs[None, :] ** 2 / var_x))
    r = 3 * math.sqrt(max(var_x, var_y))
    alpha = alpha * (xs.abs()[None, :] <= r) * (ys.abs()[:, None] <= r) * (alpha >= 1 / 255)
    assert int((alpha > 0).sum()) >= 9
    torch.testing.assert_close(out.alpha[0], alpha, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.color, alpha * args[4][0].view(3, 1, 1), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.depth[0], alpha * z, rtol=1e-12, atol=1e-12)


def test_background_is_weighted_by_the_remaining_transmittance():
    """One Gaussian at the principal point, opacity 0.5: the centre pixel has alpha 0.5 exp(-m/2)
    (m its Mahalanobis distance, the low-pass included), colour c alpha + bg (1 - alpha)."""
    w = h = 5
    k = torch.tensor([[10.0, 0, 2.5], [0, 10.0, 2.5], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, w, h)
    s = 0.05
    out = rasterize(torch.tensor([[0.0, 0.0, 1.0]], dtype=F64), torch.full((1, 3), s, dtype=F64),
                    torch.tensor([[1.0, 0, 0, 0]], dtype=F64), torch.tensor([0.5], dtype=F64),
                    torch.tensor([[1.0, 0.0, 0.0]], dtype=F64), cam, torch.tensor([0.0, 1.0, 0.0], dtype=F64))
    var = (10.0 * s) ** 2 + 0.3  # px^2: (f s / z)^2 + low-pass, isotropic
    a = 0.5  # the centre pixel (2.5, 2.5) sits on the mean
    assert math.isclose(float(out.alpha[0, 2, 2]), a, rel_tol=1e-12)
    assert torch.allclose(out.color[:, 2, 2], torch.tensor([a, 1 - a, 0.0], dtype=F64), atol=1e-12)
    a1 = 0.5 * math.exp(-0.5 * 1.0 / var)  # one pixel to the right
    assert torch.allclose(out.color[:, 2, 3], torch.tensor([a1, 1 - a1, 0.0], dtype=F64), atol=1e-12)


def test_fast_path_output_types_and_shapes() -> None:
    cam = _camera(width=10, height=7)
    out = rasterize(*_one([0.0, 0.0, 2.0], [0.05, 0.05, 0.05], [1.0, 0, 0, 0], 0.5), cam)
    assert isinstance(out, RasterOutput)
    assert out.color.shape == (3, 7, 10) and out.alpha.shape == (1, 7, 10) and out.depth.shape == (1, 7, 10)
    assert out.visible.dtype == torch.bool and out.visible.shape == (1,)


def test_empty_scene_and_all_culled() -> None:
    cam = make_camera()
    bg = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    empty = [torch.zeros(0, 3, dtype=F64), torch.zeros(0, 3, dtype=F64), torch.zeros(0, 4, dtype=F64),
             torch.zeros(0, dtype=F64), torch.zeros(0, 3, dtype=F64)]
    out = rasterize(*empty, cam, bg)
    torch.testing.assert_close(out.color, bg.view(3, 1, 1).expand(3, 17, 23))
    assert float(out.alpha.abs().max()) == 0 and out.visible.shape == (0,)
    # everything behind the camera: background, nothing visible, and backward still runs (zero grads)
    scene = [t.clone().requires_grad_() for t in random_scene(0, 10, cam, hard=False)]
    with torch.no_grad():
        scene[0].copy_(camera_to_world_points(cam, torch.tensor([[0.0, 0.0, -2.0]], dtype=F64).expand(10, 3)))
    out = rasterize(*scene, cam, bg)
    assert not bool(out.visible.any())
    torch.testing.assert_close(out.color, bg.view(3, 1, 1).expand(3, 17, 23))
    out.color.sum().backward()
    assert all(float(t.grad.abs().max()) == 0 for t in scene if t.grad is not None)


def test_supersampling_matches_direct_rendering_on_smooth_content() -> None:
    """Area-pooling a render at S approximates rendering at camera.scaled(d) when the content is
    band-limited: this pins the pixel-centre and intrinsics-scaling conventions (a half-pixel shift fails)."""
    cam = make_camera(48, 32, yaw=0.0)
    scene = list(random_scene(2, 30, cam, hard=False))
    scene[1] = scene[1] * 0 + 0.3  # wide blobs, several pixels at S/2
    pooled = F.avg_pool2d(rasterize(*scene, cam).color.unsqueeze(0), 2).squeeze(0)
    small_cam = cam.scaled(2)
    small = rasterize(*scene, small_cam).color
    assert small.shape == pooled.shape == (3, 16, 24)
    err = float((pooled - small).abs().mean())
    assert err < 0.006
    k = small_cam.intrinsics.clone()
    k[0, 2] += 0.5  # the same camera with the principal point half a pixel off
    shifted = rasterize(*scene, Camera(small_cam.world_to_camera, k, 24, 16)).color
    assert float((pooled - shifted).abs().mean()) > 2 * err


# ----------------------------------------------------------------------------- early termination, depth passes, chunks and the pair cache

def test_early_termination_error_bound() -> None:
    """Against the exact oracle (no termination), a terminated pixel's colour, alpha and depth are off by
    at most ``T_stop max|f - f_bg|`` (``T_stop = 1 - alpha``, the transmittance it stopped at, which is
    below ``transmittance_min / (1 - ALPHA_MAX)``); the other pixels are exact."""
    scene, cam = _opaque_stack()
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    for t_min in (1e-4, 1e-2):
        fast = rasterize(*scene, cam, bg, transmittance_min=t_min)
        torch.testing.assert_close(_stack(fast), _stack(rasterize_reference(*scene, cam, bg, transmittance_min=t_min)),
                                   rtol=1e-10, atol=1e-10)
        exact = rasterize_reference(*scene, cam, bg, transmittance_min=0.0)
        err = (_stack(fast) - _stack(exact)).abs()  # [5, H, W]
        t_stop = 1 - fast.alpha[0]
        stopped = err.amax(0) > 1e-9  # beyond float64 rounding
        assert int(stopped.sum()) > 0.5 * stopped.numel()  # the scene exercises termination
        assert float(t_stop[stopped].max()) < t_min / (1 - splatter.ALPHA_MAX)
        z = (scene[0] @ cam.world_to_camera[:3, :3].t() + cam.world_to_camera[:3, 3])[:, 2]
        spread = torch.cat([(scene[4] - bg).abs().amax(0), torch.ones(1, dtype=F64), z.abs().amax().view(1)])
        assert bool((err <= t_stop * spread.view(5, 1, 1) + 1e-10).all())


def test_gradcheck_with_early_termination() -> None:
    """Gradients of the drawn splats where pixels terminate (generic scene: no threshold crossing within
    the finite-difference step)."""
    scene, cam = _opaque_stack(n=8, seed=4)
    scene = (*scene[:3], torch.full((8,), 0.93, dtype=F64), scene[4])
    bg = torch.tensor([0.4, 0.4, 0.2], dtype=F64)
    exact = rasterize_reference(*scene, cam, bg, transmittance_min=0.0)
    assert not torch.allclose(_stack(rasterize(*scene, cam, bg)), _stack(exact), atol=1e-9)  # some pixels stop
    inputs = tuple(t.clone().requires_grad_() for t in (*scene, bg))

    def fn(*args):
        return _stack(rasterize(*args[:5], cam, args[5], tile_size=4))

    torch.manual_seed(0)
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-6, fast_mode=True)


@pytest.mark.parametrize("budget", [64, 1 << 21])
def test_exact_compositing_carries_the_transmittance_across_depth_passes(budget: int, monkeypatch) -> None:
    """``transmittance_min=0`` composites every splat (rasterize's docstring). A chunk whose candidate
    pairs exceed ``_PAIR_BUDGET`` is expanded in several depth passes; each pixel's later passes must start
    from its transmittance after the earlier ones (a pass restarting at T = 1 gives alpha > 1 on a
    crowded pixel). A tiny budget forces many passes on a small image; the float64 brute-force reference
    decides, for the image and for the gradients."""
    monkeypatch.setattr(splatter, "_PAIR_BUDGET", budget)
    cam = make_camera()
    scene = random_scene(5, 60, cam, hard=False)
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    weights = torch.randn(5, 17, 23, generator=torch.Generator().manual_seed(2), dtype=F64)

    def run(fn: Any) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        inputs = [t.clone().requires_grad_() for t in scene]
        out = fn(*inputs, cam, bg, transmittance_min=0.0)
        stack = torch.cat([out.color, out.alpha, out.depth])
        return stack.detach(), torch.autograd.grad((stack * weights).sum(), inputs)

    got, got_grads = run(lambda *a, **k: rasterize(*a, tile_size=4, **k))
    ref, ref_grads = run(rasterize_reference)
    assert float(ref[3].max()) > 0.8  # crowded pixels: a pass restarting at T = 1 overshoots them
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-10)
    for g, r in zip(got_grads, ref_grads):
        torch.testing.assert_close(g, r, rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("opaque", [False, True])
def test_chunked_and_recomputed_backward_agree(opaque: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """Chunks of two tiles, a tiny pair budget (many passes), no pair cache (backward recomputes) and
    depth-rank passes of 1, 2, 4, ... records per tile give the same result."""
    scene, cam = _opaque_stack() if opaque else (random_scene(5, 50, make_camera()), make_camera())
    weights = torch.randn(5, 17, 23, generator=torch.Generator().manual_seed(1), dtype=F64)

    def run():
        inputs = [t.clone().requires_grad_() for t in scene]
        out = _stack(rasterize(*inputs, cam, tile_size=4))
        return out, torch.autograd.grad((out * weights).sum(), inputs)

    out_a, grads_a = run()
    monkeypatch.setattr(splatter, "_KEY_LIMIT", 2 * 16 + 1)
    monkeypatch.setattr(splatter, "_PAIR_BUDGET", 64)
    monkeypatch.setattr(splatter, "_CACHE_BYTES", 0)
    monkeypatch.setattr(splatter, "_PASS_FIRST", 1)
    out_b, grads_b = run()
    torch.testing.assert_close(out_b, out_a, rtol=1e-12, atol=1e-12)
    for g_a, g_b in zip(grads_a, grads_b):
        torch.testing.assert_close(g_b, g_a, rtol=1e-10, atol=1e-12)


def test_a_tile_whose_pixels_all_terminated_takes_no_further_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 3 x 3 image in one 4 x 4 tile (7 padding pixels, which no record covers and which count as
    terminated from the start) under 12 wide splats of opacity 0.95 (alpha in (0.945, 0.95] at every pixel:
    G > 0.995 within 1.5 px of the centre for the first four, sigma = 3 px x 20 / z >= 15 px): with one depth rank per pass (tiny pair budget), every
    pixel draws three (T <= 0.055^3 = 1.7e-4 stays >= 1e-4) and stops at the fourth (T <= 0.055^4 < 1e-5),
    so the tile is done after 4 passes; the 8 other ranks are never expanded."""
    monkeypatch.setattr(splatter, "_PAIR_BUDGET", 4)
    monkeypatch.setattr(splatter, "_PASS_FIRST", 1)
    calls: list[int] = []
    expand = splatter._candidates

    def counting(*args):  # type: ignore[no-untyped-def]
        calls.append(int(args[3].numel()))
        return expand(*args)

    monkeypatch.setattr(splatter, "_candidates", counting)
    k = torch.tensor([[3.0, 0.0, 1.5], [0.0, 3.0, 1.5], [0.0, 0.0, 1.0]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, 3, 3)
    n = 12
    means = torch.tensor([[0.0, 0.0, 1.0 + i] for i in range(n)], dtype=F64)
    out = rasterize(means, torch.full((n, 3), 20.0, dtype=F64), torch.tensor([[1.0, 0, 0, 0]] * n, dtype=F64),
                    torch.full((n,), 0.95, dtype=F64), torch.rand(n, 3, generator=torch.Generator().manual_seed(0),
                                                                  dtype=F64), cam, tile_size=4)
    # three splats drawn: T = prod (1 - alpha_i) in [0.05^3, 0.055^3]
    assert float(out.alpha.min()) >= 1 - 0.055**3 and float(out.alpha.max()) <= 1 - 0.05**3 + 1e-12
    assert len(calls) == 4, calls


def test_pairs_that_fit_the_cache_exactly_are_kept_for_backward(monkeypatch: pytest.MonkeyPatch) -> None:
    """A chunk's pairs are kept while they fit in ``_CACHE_BYTES`` (size <= what is left): with a cache of
    exactly their size, backward reuses them (no second expansion); one byte less, it recomputes them;
    the gradients agree."""
    sizes: list[int] = []
    expand = splatter._chunk_passes

    def counting(*args):  # type: ignore[no-untyped-def]
        passes, first = expand(*args)
        sizes.append(sum(p.nbytes() for p in passes))
        return passes, first

    monkeypatch.setattr(splatter, "_chunk_passes", counting)
    g = _one([0.0, 0.0, 2.0], [0.1, 0.05, 0.02], [0.9, 0.1, 0.2, 0.3], 0.8)
    cam = _camera(width=12, height=10)  # one 16 px tile: one chunk

    def grads(cache: int) -> tuple[int, torch.Tensor]:
        monkeypatch.setattr(splatter, "_CACHE_BYTES", cache)
        sizes.clear()
        means = g[0].clone().requires_grad_(True)
        out = rasterize(means, *g[1:], cam)
        n_forward = len(sizes)
        (grad,) = torch.autograd.grad(out.color.sum(), means)
        return len(sizes) - n_forward, grad

    grads(1 << 30)
    size = sizes[0]
    assert size > 0 and len(sizes) == 1
    recomputed, exact_fit = grads(size)
    assert recomputed == 0
    recomputed, too_small = grads(size - 1)
    assert recomputed == 1
    torch.testing.assert_close(exact_fit, too_small, rtol=0, atol=0)


# ----------------------------------------------------------------------------- Gaussians far beyond the image

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


# ----------------------------------------------------------------------------- invariances

@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 25))
def test_permutation_invariance(seed: int, n: int) -> None:
    cam = make_camera(12, 9)
    scene = random_scene(seed, n, cam, hard=False)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed + 1))
    a = rasterize(*scene, cam)
    b = rasterize(*(t[perm] for t in scene), cam)
    torch.testing.assert_close(_stack(b), _stack(a), rtol=1e-12, atol=1e-12)
    assert torch.equal(b.visible, a.visible[perm])


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 25), extra=st.integers(1, 10))
def test_zero_opacity_adds_nothing(seed: int, n: int, extra: int) -> None:
    cam = make_camera(12, 9)
    scene = random_scene(seed, n, cam)
    ghosts = list(random_scene(seed + 7, extra, cam, hard=False))
    ghosts[3] = torch.zeros_like(ghosts[3])
    both = [torch.cat([a, b]) for a, b in zip(scene, ghosts)]
    bg = torch.tensor([0.3, 0.6, 0.1], dtype=F64)
    # equal up to float64 summation order: other torch builds (2.11 with CUDA, measured on the GPU machine)
    # vectorise the longer sums differently, 1.3e-15 apart
    torch.testing.assert_close(_stack(rasterize(*both, cam, bg)), _stack(rasterize(*scene, cam, bg)), rtol=0, atol=1e-13)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(0, 40))
def test_outputs_are_bounded(seed: int, n: int) -> None:
    """alpha in [0, 1]; colours in [0, 1] stay in [0, 1]; depth within alpha * [near, max z]."""
    cam = make_camera(12, 9, dtype=torch.float32)
    scene = random_scene(seed, n, cam, dtype=torch.float32)
    bg = torch.rand(3, generator=torch.Generator().manual_seed(seed))
    out = rasterize(*scene, cam, bg)
    eps = 1e-5
    assert float(out.alpha.min()) >= 0 and float(out.alpha.max()) <= 1 + eps
    assert float(out.color.min()) >= -eps and float(out.color.max()) <= 1 + eps
    z_max = float(cam.to_camera(scene[0])[:, 2].max()) if n else 0.0
    assert bool((out.depth <= out.alpha * z_max + 1e-4).all())
    assert bool((out.depth >= out.alpha * splatter.NEAR_PLANE - 1e-4).all())


# ----------------------------------------------------------------------------- refusals

def test_input_refusals_name_the_argument() -> None:
    cam = make_camera()
    scene = list(random_scene(0, 5, cam, hard=False))

    def call(i, value, error, match):
        args = list(scene)
        args[i] = value
        with pytest.raises(error, match=match):
            rasterize(*args, cam)

    call(0, scene[0][:, :2], ShapeError, "means")
    call(1, scene[1][:4], ShapeError, "scales")
    call(2, scene[2][:, :3], ShapeError, "rotations")
    call(3, scene[3].unsqueeze(-1), ShapeError, "opacities")
    call(4, scene[4].float(), InputValueError, "colors.*dtype")
    bad = scene[0].clone()
    bad[2, 1] = float("nan")
    call(0, bad, InputValueError, "means.*non-finite")
    call(1, -scene[1], InputValueError, "scales must be >= 0")
    call(3, scene[3] + 1.5, InputValueError, "opacities must lie in")
    zero_q = scene[2].clone()
    zero_q[1] = 0
    call(2, zero_q, InputValueError, "non-zero quaternions")
    call(0, scene[0].tolist(), InputValueError, "means must be a torch.Tensor")
    with pytest.raises(InputValueError, match="camera"):
        rasterize(*scene, "not a camera")  # type: ignore[arg-type]
    with pytest.raises(ShapeError, match="background"):
        rasterize(*scene, cam, torch.zeros(4, dtype=F64))
    with pytest.raises(InputValueError, match="tile_size"):
        rasterize(*scene, cam, tile_size=0)
    g, cam = _one([0.0, 0.0, 2.0], [0.05] * 3, [1.0, 0, 0, 0], 0.5), _camera()
    with pytest.raises(InputValueError, match="tile_size must be a positive int, got 4.0"):
        rasterize(*g, cam, tile_size=4.0)  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="tile_size must be a positive int, got -2"):
        rasterize(*g, cam, tile_size=-2)
    rasterize(*g, cam, tile_size=1)  # the smallest tile
    with pytest.raises(InputValueError, match="background"):
        rasterize(*g, cam, torch.zeros(3, dtype=torch.float32))  # another dtype than means
    with pytest.raises(InputValueError, match="background"):
        rasterize(*g, cam, torch.tensor([0.0, float("inf"), 0.0], dtype=F64))
    bad = g[2].clone()
    bad[0, 1] = float("nan")
    with pytest.raises(InputValueError, match="rotations"):
        rasterize(g[0], g[1], bad, g[3], g[4], cam)
    with pytest.raises(InputValueError, match="opacities must lie in"):
        rasterize(g[0], g[1], g[2], torch.tensor([-0.01], dtype=F64), g[4], cam)
    with pytest.raises(InputValueError, match=r"scales must be >= 0 \(linear, not log\), got min -0.05"):
        rasterize(g[0], -g[1], g[2], g[3], g[4], cam)
    # bounds accepted: opacity 0 and 1, scale 0
    for o in (0.0, 1.0):
        rasterize(g[0], g[1] * 0, g[2], torch.tensor([o], dtype=F64), g[4], cam)


@pytest.mark.parametrize("value", [-0.1, 1.0, 1.5, "0.1", None])
def test_transmittance_min_must_be_in_0_1(value: object) -> None:
    with pytest.raises(InputValueError, match=rf"transmittance_min.*got {value!r}$"):
        rasterize(*_one([0.0, 0.0, 2.0], [0.05] * 3, [1.0, 0, 0, 0], 0.5), _camera(),
                  transmittance_min=value)  # type: ignore[arg-type]


@pytest.mark.parametrize("i", range(6))
def test_tensors_on_another_device_are_refused_by_name(i: int) -> None:
    """Each input on the meta device (value checks off, so that only the device check can refuse it)."""
    names = ["means", "scales", "rotations", "opacities", "colors", "background"]
    args = [*_one([0.0, 0.0, 2.0], [0.05] * 3, [1.0, 0, 0, 0], 0.5), torch.zeros(3, dtype=F64)]
    args[i] = args[i].to("meta")
    with value_checks(False), pytest.raises(InputValueError, match=f"tensors must be on one device, got .*{names[i]}=meta"):
        rasterize(*args[:5], _camera(), args[5])


# ----------------------------------------------------------------------------- the reference model's render

# ------------------------------------------------------------------------------ the splatter
BOTH = [rasterize, rasterize_reference]


def _splat_camera(f: float = 20.0, width: int = 24, height: int = 16) -> Camera:
    """Identity pose, principal point at the image centre."""
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=F64)
    return Camera(torch.eye(4, dtype=F64), k, width, height)


def _closed_form_alpha(cov: torch.Tensor, u0: float, v0: float, o: float, width: int, height: int) -> torch.Tensor:
    """``[H, W]`` alpha of one Gaussian with 2D covariance ``cov`` (low-pass included) at ``(u0, v0)``:
    ``o exp(-d^T cov^-1 d / 2)``, zero outside the 3 sqrt(lambda_max) square and below 1/255, clamped at 0.99."""
    xs = torch.arange(width, dtype=F64) + 0.5 - u0
    ys = torch.arange(height, dtype=F64) + 0.5 - v0
    d = torch.stack(torch.broadcast_tensors(xs[None, :], ys[:, None]), dim=-1)  # [H, W, 2]
    maha = torch.einsum("hwi,ij,hwj->hw", d, torch.linalg.inv(cov), d)
    alpha = (o * torch.exp(-0.5 * maha)).clamp(max=0.99)
    r = 3 * math.sqrt(float(torch.linalg.eigvalsh(cov)[-1]))
    return alpha * (d.abs() <= r).all(-1) * (alpha >= 1 / 255)


@pytest.mark.parametrize("fn", BOTH)
def test_near_plane_is_a_strict_cut_at_0_2(fn) -> None:  # type: ignore[no-untyped-def]
    cam = _splat_camera()
    for z, seen in ((0.2, False), (0.2 + 1e-9, True), (0.21, True), (0.19, False)):
        out = fn(*_one([0.0, 0.0, z], [0.001, 0.001, 0.001], [1.0, 0, 0, 0], 0.9), cam)
        assert bool(out.visible[0]) is seen, z
        assert (float(out.alpha.max()) > 0) is seen, z


@pytest.mark.parametrize("fn", BOTH)
def test_jacobian_is_clamped_to_the_widened_frustum(fn) -> None:  # type: ignore[no-untyped-def]
    """A wide Gaussian whose mean lies outside the image: x/z = 1 and y/z = 0.7 enter the Jacobian clamped
    to the image widened by 15 % per side, (12 + 0.15 * 24) / 20 = 0.78 and (8 + 0.15 * 16) / 20 = 0.52;
    ``cov = s^2 (f/z)^2 [[1 + tx^2, tx ty], [tx ty, 1 + ty^2]] + 0.3 I`` (isotropic Sigma = s^2 I)."""
    cam, f, z, s, o = _splat_camera(), 20.0, 2.0, 0.3, 0.9
    out = fn(*_one([1.0 * z, 0.7 * z, z], [s, s, s], [1.0, 0, 0, 0], o), cam)
    tx, ty = 0.78, 0.52
    g = (s * f / z) ** 2
    cov = torch.tensor([[g * (1 + tx * tx) + 0.3, g * tx * ty], [g * tx * ty, g * (1 + ty * ty) + 0.3]], dtype=F64)
    want = _closed_form_alpha(cov, f * 1.0 + 12, f * 0.7 + 8, o, 24, 16)
    assert int((want > 0).sum()) >= 10 and bool(out.visible[0])  # the footprint reaches into the image
    torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)
    # the same on the other sides (x/z = -1, y/z = -0.7): the lower limits
    out = fn(*_one([-1.0 * z, -0.7 * z, z], [s, s, s], [1.0, 0, 0, 0], o), cam)
    want = _closed_form_alpha(cov, 12 - f * 1.0, 8 - f * 0.7, o, 24, 16)
    torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("fn", BOTH)
def test_quaternion_is_w_x_y_z_and_normalised(fn) -> None:  # type: ignore[no-untyped-def]
    """(cos 45, 0, 0, sin 45) turns the local x axis onto y: the long axis (sx) lies along the image's
    rows' direction v; times 3 (unnormalised) is the same rotation."""
    cam, f, z, o = _splat_camera(), 20.0, 2.0, 0.8
    sx, sy = 0.15, 0.04
    h = math.sqrt(0.5)
    want = _closed_form_alpha(torch.tensor([[(sy * f / z) ** 2 + 0.3, 0.0], [0.0, (sx * f / z) ** 2 + 0.3]], dtype=F64),
                              12.0, 8.0, o, 24, 16)
    for q in ([h, 0.0, 0.0, h], [3 * h, 0.0, 0.0, 3 * h]):
        out = fn(*_one([0.0, 0.0, z], [sx, sy, 0.01], q, o), cam)
        torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)
    # about x by 90 degrees: (cos 45, sin 45, 0, 0) turns local y onto z (depth): only sx shows, along u
    out = fn(*_one([0.0, 0.0, z], [sx, sy, 0.01], [h, h, 0.0, 0.0], o), cam)
    want = _closed_form_alpha(torch.tensor([[(sx * f / z) ** 2 + 0.3, 0.0], [0.0, (0.01 * f / z) ** 2 + 0.3]], dtype=F64),
                              12.0, 8.0, o, 24, 16)
    torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("fn", BOTH)
def test_alpha_clamp_and_default_early_termination_by_hand(fn) -> None:  # type: ignore[no-untyped-def]
    """Three splats centred on pixel (12, 8)'s centre (G = 1 there), opacity 0.9878, at z = 2, 3, 4:
    alpha 0.9878 each, T after two = 0.0122^2 = 1.4884e-4 >= 1e-4 (drawn), after three 1.8e-6 < 1e-4:
    the third is not drawn by default; with transmittance_min = 0 it is. Opacity 1 is clamped to 0.99."""
    cam = _splat_camera()
    u, v = 12.5, 8.5  # pixel (12, 8)'s centre: x / z = (12.5 - 12) / 20
    zs = [2.0, 3.0, 4.0]
    means = torch.tensor([[(u - 12) / 20 * z, (v - 8) / 20 * z, z] for z in zs], dtype=F64)
    scales = torch.full((3, 3), 0.01, dtype=F64)
    rot = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    a = 0.9878
    out = fn(means, scales, rot, torch.full((3,), a, dtype=F64), colors, cam)
    w = [a, a * (1 - a), a * (1 - a) ** 2]
    assert float(out.color[0, 8, 12]) == pytest.approx(w[0], abs=1e-12)
    assert float(out.color[1, 8, 12]) == pytest.approx(w[1], abs=1e-12)
    assert float(out.color[2, 8, 12]) == 0.0  # terminated before the third
    assert float(out.alpha[0, 8, 12]) == pytest.approx(1 - (1 - a) ** 2, abs=1e-12)
    assert float(out.depth[0, 8, 12]) == pytest.approx(2 * w[0] + 3 * w[1], abs=1e-11)
    exact = fn(means, scales, rot, torch.full((3,), a, dtype=F64), colors, cam, transmittance_min=0.0)
    assert float(exact.color[2, 8, 12]) == pytest.approx(w[2], abs=1e-12)
    assert float(exact.alpha[0, 8, 12]) == pytest.approx(1 - (1 - a) ** 3, abs=1e-12)
    # opacity 1: alpha clamped to 0.99, T = 0.01 of the background shows
    out = fn(means[:1], scales[:1], rot[:1], torch.ones(1, dtype=F64), colors[:1], cam,
             torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    assert float(out.alpha[0, 8, 12]) == pytest.approx(0.99, abs=1e-12)
    assert float(out.color[2, 8, 12]) == pytest.approx(0.01, abs=1e-12)  # 1 % of the blue background shows


def test_opacity_exactly_at_the_clamp_keeps_its_gradient() -> None:
    """Opacity 0.99 centred on a pixel centre: alpha = 0.99 there exactly (G = 1), on the clamp's kink. As
    ``torch.clamp`` (the reference), the clamp passes the gradient at equality: d alpha / d o = G = 1; only
    an alpha above 0.99 is frozen (zero gradient)."""
    cam = _splat_camera(f=20.0, width=16, height=16)  # principal point (8, 8): pixel (8, 8)'s centre is x / z = 0.5 / 20
    z = 2.0
    for o, want in ((0.99, 1.0), (0.995, 0.0)):
        for fn in BOTH:
            op = torch.tensor([o], dtype=F64, requires_grad=True)
            g = _one([0.5 / 20 * z, 0.5 / 20 * z, z], [0.05] * 3, [1.0, 0, 0, 0], o)
            out = fn(g[0], g[1], g[2], op, g[4], cam)
            assert float(out.alpha[0, 8, 8].detach()) == pytest.approx(0.99, abs=1e-14)
            (grad,) = torch.autograd.grad(out.alpha[0, 8, 8], op)
            assert float(grad) == pytest.approx(want, abs=1e-12), (fn.__name__, o)


STATE = RuntimeState(downsample=2.0, power_saving=0.4)


# --------------------------------------------------------------------------------- degenerate anchors
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
    """Scales of 1e20 (or a log-scale whose exp overflows float32): the image and every adapter gradient stay
    finite and equal the float64 render without the splatter's spread cap."""
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


def test_without_the_spread_cap_the_float32_adapter_gradients_are_nan(tiny: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """What the cap prevents: NaN in every adapter tensor from one anchor of scale 1e20."""
    scene, model = tiny
    anchor = _drawn_anchor(model, scene)
    monkeypatch.setattr(splatter, "MAX_SPREAD", math.inf)
    monkeypatch.setattr(splatter, "_MAX_SPREAD_PX", math.inf)
    _, grads = _adapter_grads(model, scene, anchor, math.log(1e20), torch.float32)
    assert all(not bool(torch.isfinite(g).all()) for g in grads.values())
