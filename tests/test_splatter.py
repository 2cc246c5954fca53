"""The tiled splatter against the brute-force float64 reference, gradients, invariants, bad input."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.rendering.splatter_reference import rasterize_reference
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import Camera

F64 = torch.float64


def _rotation_z(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=F64)


def make_camera(width: int = 23, height: int = 17, dtype: torch.dtype = F64, yaw: float = 0.3) -> Camera:
    """Posed camera (rotation + translation), fx != fy, off-centre principal point."""
    w2c = torch.eye(4, dtype=F64)
    w2c[:3, :3] = _rotation_z(yaw) @ torch.tensor([[1.0, 0, 0], [0, 0.96, -0.28], [0, 0.28, 0.96]], dtype=F64)
    w2c[:3, 3] = torch.tensor([0.2, -0.1, 0.5], dtype=F64)
    k = torch.tensor([[1.1 * width, 0, 0.47 * width], [0, 1.05 * width, 0.53 * height], [0, 0, 1]], dtype=F64)
    return Camera(w2c.to(dtype), k.to(dtype), width, height)


def camera_to_world_points(camera: Camera, pts_cam: torch.Tensor) -> torch.Tensor:
    w2c = camera.world_to_camera.to(pts_cam.dtype)
    return (pts_cam - w2c[:3, 3]) @ w2c[:3, :3]


def random_scene(seed: int, n: int, camera: Camera, dtype: torch.dtype = F64, hard: bool = True):
    """Gaussians placed in camera space (so that most land on screen), then moved to world space.

    ``hard`` mixes in the corner cases: behind the camera, on/near the near plane, huge and tiny scales,
    degenerate (flat, needle, point) covariances, fully transparent and fully opaque ones, off-screen."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=F64)

    z = 1.0 + 4.0 * rand(n)
    xy = (rand(n, 2) * 2 - 1) * 0.6 * z[:, None]
    scales = 0.02 * torch.exp(1.2 * torch.randn(n, 3, generator=g, dtype=F64))
    opac = rand(n)
    if hard:
        kinds = torch.arange(n) % 10
        z = torch.where(kinds == 1, -z, z)  # behind the camera
        z = torch.where(kinds == 2, 0.15 + 0.1 * rand(n), z)  # straddling the near plane (0.2)
        scales = torch.where((kinds == 3)[:, None], 3.0 * scales / scales.amax(-1, keepdim=True), scales)  # huge
        scales = torch.where((kinds == 4)[:, None], 1e-7 * rand(n, 3), scales)  # tiny
        flat = torch.tensor([1.0, 1.0, 0.0], dtype=F64)
        scales = torch.where((kinds == 5)[:, None], scales * flat, scales)  # flat disc
        scales = torch.where((kinds == 6)[:, None], scales * torch.tensor([0.0, 1.0, 0.0], dtype=F64), scales)
        opac = torch.where(kinds == 7, torch.zeros_like(opac), opac)  # fully transparent
        opac = torch.where(kinds == 8, torch.ones_like(opac), opac)  # opaque: alpha clamp at 0.99
        xy = torch.where((kinds == 9)[:, None], xy * 3.0, xy)  # mostly off-screen
    means = camera_to_world_points(camera, torch.cat([xy, z[:, None]], -1))
    rot = torch.randn(n, 4, generator=g, dtype=F64) * (0.5 + rand(n, 1))  # unnormalised
    colors = rand(n, 3)
    return tuple(t.to(dtype) for t in (means, scales, rot, opac, colors))


def _stack(out) -> torch.Tensor:
    return torch.cat([out.color, out.alpha, out.depth])


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


def test_input_errors() -> None:
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
