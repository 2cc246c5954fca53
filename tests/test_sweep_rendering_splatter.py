"""The splatter's conventions pinned by closed forms (issue 15 section 5), each checked on the fast path
AND the float64 reference (they share the constants, so comparing them with each other cannot catch a
wrong one): the near plane's strict cut, the Jacobian's frustum clamp, the quaternion order, the 0.99
alpha clamp and the default early termination, and the refusals the other tests leave out."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.splatter import RasterOutput, rasterize
from controlgs_adapter.rendering.splatter_reference import rasterize_reference
from controlgs_adapter.state import Camera

F64 = torch.float64
BOTH = [rasterize, rasterize_reference]


def _camera(f: float = 20.0, width: int = 24, height: int = 16) -> Camera:
    """Identity pose, principal point at the image centre."""
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=F64)
    return Camera(torch.eye(4, dtype=F64), k, width, height)


def _one(mean: list[float], scale: list[float], q: list[float], o: float, color: list[float] | None = None
         ) -> tuple[torch.Tensor, ...]:
    return (torch.tensor([mean], dtype=F64), torch.tensor([scale], dtype=F64), torch.tensor([q], dtype=F64),
            torch.tensor([o], dtype=F64), torch.tensor([color or [1.0, 1.0, 1.0]], dtype=F64))


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
    cam = _camera()
    for z, seen in ((0.2, False), (0.2 + 1e-9, True), (0.21, True), (0.19, False)):
        out = fn(*_one([0.0, 0.0, z], [0.001, 0.001, 0.001], [1.0, 0, 0, 0], 0.9), cam)
        assert bool(out.visible[0]) is seen, z
        assert (float(out.alpha.max()) > 0) is seen, z


@pytest.mark.parametrize("fn", BOTH)
def test_jacobian_is_clamped_to_the_widened_frustum(fn) -> None:  # type: ignore[no-untyped-def]
    """A wide Gaussian whose mean lies outside the image: x/z = 1 and y/z = 0.7 enter the Jacobian clamped
    to the image widened by 15 % per side, (12 + 0.15 * 24) / 20 = 0.78 and (8 + 0.15 * 16) / 20 = 0.52;
    ``cov = s^2 (f/z)^2 [[1 + tx^2, tx ty], [tx ty, 1 + ty^2]] + 0.3 I`` (isotropic Sigma = s^2 I)."""
    cam, f, z, s, o = _camera(), 20.0, 2.0, 0.3, 0.9
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
    cam, f, z, o = _camera(), 20.0, 2.0, 0.8
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
    cam = _camera()
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


def test_fast_path_output_types_and_shapes() -> None:
    cam = _camera(width=10, height=7)
    out = rasterize(*_one([0.0, 0.0, 2.0], [0.05, 0.05, 0.05], [1.0, 0, 0, 0], 0.5), cam)
    assert isinstance(out, RasterOutput)
    assert out.color.shape == (3, 7, 10) and out.alpha.shape == (1, 7, 10) and out.depth.shape == (1, 7, 10)
    assert out.visible.dtype == torch.bool and out.visible.shape == (1,)


@pytest.mark.parametrize("value", [-0.1, 1.0, 1.5, "0.1", None])
def test_transmittance_min_refusals(value: object) -> None:
    with pytest.raises(InputValueError, match=r"transmittance_min must be a number in \[0, 1\), got"):
        rasterize(*_one([0.0, 0.0, 2.0], [0.05] * 3, [1.0, 0, 0, 0], 0.5), _camera(),
                  transmittance_min=value)  # type: ignore[arg-type]


def test_other_refusals() -> None:
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


@pytest.mark.parametrize("i", range(6))
def test_tensors_on_another_device_are_refused_by_name(i: int) -> None:
    """Each input on the meta device (value checks off, so that only the device check can refuse it)."""
    from controlgs_adapter.checks import value_checks

    names = ["means", "scales", "rotations", "opacities", "colors", "background"]
    args = [*_one([0.0, 0.0, 2.0], [0.05] * 3, [1.0, 0, 0, 0], 0.5), torch.zeros(3, dtype=F64)]
    args[i] = args[i].to("meta")
    with value_checks(False), pytest.raises(InputValueError, match=f"tensors must be on one device, got .*{names[i]}=meta"):
        rasterize(*args[:5], _camera(), args[5])


def test_a_tile_whose_pixels_all_terminated_takes_no_further_pass(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 3 x 3 image in one 4 x 4 tile (7 padding pixels, which no record covers and which count as
    terminated from the start) under 12 wide splats of opacity 0.95 (alpha in (0.945, 0.95] at every pixel:
    G > 0.995 within 1.5 px of the centre for the first four, sigma = 3 px x 20 / z >= 15 px): with one depth rank per pass (tiny pair budget), every
    pixel draws three (T <= 0.055^3 = 1.7e-4 stays >= 1e-4) and stops at the fourth (T <= 0.055^4 < 1e-5),
    so the tile is done after 4 passes; the 8 other ranks are never expanded."""
    from controlgs_adapter.rendering import splatter

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


def test_opacity_exactly_at_the_clamp_keeps_its_gradient() -> None:
    """Opacity 0.99 centred on a pixel centre: alpha = 0.99 there exactly (G = 1), on the clamp's kink. As
    ``torch.clamp`` (the reference), the clamp passes the gradient at equality: d alpha / d o = G = 1; only
    an alpha above 0.99 is frozen (zero gradient)."""
    cam = _camera(f=20.0, width=16, height=16)  # principal point (8, 8): pixel (8, 8)'s centre is x / z = 0.5 / 20
    z = 2.0
    for o, want in ((0.99, 1.0), (0.995, 0.0)):
        for fn in BOTH:
            op = torch.tensor([o], dtype=F64, requires_grad=True)
            g = _one([0.5 / 20 * z, 0.5 / 20 * z, z], [0.05] * 3, [1.0, 0, 0, 0], o)
            out = fn(g[0], g[1], g[2], op, g[4], cam)
            assert float(out.alpha[0, 8, 8].detach()) == pytest.approx(0.99, abs=1e-14)
            (grad,) = torch.autograd.grad(out.alpha[0, 8, 8], op)
            assert float(grad) == pytest.approx(want, abs=1e-12), (fn.__name__, o)


def test_pairs_that_fit_the_cache_exactly_are_kept_for_backward(monkeypatch: pytest.MonkeyPatch) -> None:
    """A chunk's pairs are kept while they fit in ``_CACHE_BYTES`` (size <= what is left): with a cache of
    exactly their size, backward reuses them (no second expansion); one byte less, it recomputes them;
    the gradients agree."""
    from controlgs_adapter.rendering import splatter

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
