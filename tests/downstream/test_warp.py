"""Tests of ``controlgs_adapter.downstream.warp``: inverting a sampled map by Newton's method (exact on
affine maps, on any uniform samples) and the sampling grid of a chief-ray map in both directions,
with its area-magnification gain; the refusals name the argument."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from controlgs_adapter.downstream.lens_maps import RadialMap
from controlgs_adapter.downstream.warp import chief_ray_grid, invert_map, pixel_grid
from controlgs_adapter.errors import InputValueError, ShapeError

D = torch.float64

_A = torch.tensor([[[1.2, 0.1], [-0.05, 0.9]], [[0.8, 0.0], [0.0, 1.1]], [[1.0, -0.2], [0.15, 1.05]]], dtype=D)
_T = torch.tensor([[0.05, -0.1], [0.0, 0.02], [-0.07, 0.03]], dtype=D)


def _affine(a: torch.Tensor, t: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Per channel ``a[c] @ p + t[c]``: ``a`` ``[3, 2, 2]``, ``t`` ``[3, 2]``, ``p`` ``[H, W, 2]`` -> ``[3, H, W, 2]``."""
    return torch.einsum("cij,hwj->chwi", a, p) + t[:, None, None, :]


def test_invert_map_round_trip():
    """On the same sample grid, F(G(q)) = q at the samples (F evaluated at G by bilinear interpolation)."""
    fmap = RadialMap([[0.1], [-0.05], [0.2]])((12, 9), D, torch.device("cpu"))[0]
    inv = invert_map(fmap, (12, 9))
    ident = pixel_grid((12, 9), D).expand(3, -1, -1, -1)
    back = F.grid_sample(fmap.permute(0, 3, 1, 2), inv, align_corners=False, padding_mode="border").permute(0, 2, 3, 1)
    inner = (slice(None), slice(1, -1), slice(1, -1))
    assert torch.allclose(back[inner], ident[inner], atol=1e-8)


def test_one_newton_step_inverts_an_affine_map_exactly():
    """A bilinearly interpolated affine map is affine everywhere, so Newton's method (float64, central
    differences) lands on the analytic inverse ``A^-1 (q - b)`` in one step, for every channel; the y column
    of the Jacobian matters because the map shears y into x."""
    a = torch.tensor([[1.5, 0.6], [0.4, 2.0]], dtype=D)
    b = torch.tensor([0.1, -0.2], dtype=D)
    fmap = (pixel_grid((5, 6), D) @ a.T + b).expand(3, -1, -1, -1).contiguous()
    q = pixel_grid((7, 9), D)
    expected = torch.linalg.solve(a, (q - b).reshape(-1, 2).T).T.reshape(7, 9, 2)
    g = invert_map(fmap, (7, 9), iterations=1, tol=0.0)
    assert g.dtype == D and g.shape == (3, 7, 9, 2)
    assert float((g - expected).abs().max()) < 2e-10


def test_invert_map_of_an_affine_map_on_custom_samples():
    """F_c affine on samples running -1 .. 1 (edges, not cell centres): G_c = A_c^-1 (q - t_c), in the
    map's dtype."""
    sx, sy = torch.linspace(-1, 1, 5, dtype=D), torch.linspace(-1, 1, 4, dtype=D)
    p = torch.stack(torch.meshgrid(sx, sy, indexing="xy"), -1)  # [4, 5, 2]
    fmap = _affine(_A, _T, p)
    q = pixel_grid((6, 7), D)
    want = _affine(torch.linalg.inv(_A), -torch.einsum("cij,cj->ci", torch.linalg.inv(_A), _T), q)
    got = invert_map(fmap, (6, 7), sample_x=sx, sample_y=sy)
    assert got.shape == (3, 6, 7, 2) and got.dtype == D
    assert torch.allclose(got, want, atol=1e-9, rtol=0)
    assert invert_map(fmap.float(), (6, 7), sample_x=sx, sample_y=sy).dtype == torch.float32


def test_invert_map_without_iterations_is_the_first_order_start():
    """No Newton step (iterations=0, or a tolerance every residual meets): G = 2 q - F(q)."""
    a = torch.eye(2, dtype=D).expand(3, 2, 2) * 1.25
    fmap = _affine(a, torch.zeros(3, 2, dtype=D), pixel_grid((3, 3), D))
    q = pixel_grid((4, 5), D)
    start = (2.0 - 1.25) * q.expand(3, -1, -1, -1)
    assert torch.allclose(invert_map(fmap, (4, 5), iterations=0), start, atol=1e-12)
    assert torch.allclose(invert_map(fmap, (4, 5), tol=10.0), start, atol=1e-12)
    assert torch.allclose(invert_map(fmap, (4, 5)), q.expand(3, -1, -1, -1) / 1.25, atol=1e-9)


def test_invert_map_refusals():
    """A map with a zero Jacobian, too few or wrongly shaped samples, and sample coordinates that are not
    uniform to one millionth of their step (or not increasing) are refused by name."""
    with pytest.raises(InputValueError, match="not invertible"):
        invert_map(torch.full((3, 3, 3, 2), 0.3, dtype=D), (2, 2))  # constant: zero Jacobian
    with pytest.raises(ShapeError, match="forward_map needs at least 2x2"):
        invert_map(torch.zeros(3, 2, 1, 2), (2, 2))
    with pytest.raises(ShapeError, match="forward_map"):
        invert_map(torch.zeros(2, 2, 2, 2), (2, 2))
    fmap = pixel_grid((3, 3), D).expand(3, -1, -1, -1)
    with pytest.raises(InputValueError, match="sample_y must be uniformly spaced"):
        invert_map(fmap, (2, 2), sample_y=torch.tensor([-1.0, -0.9, 1.0], dtype=D))
    with pytest.raises(ShapeError, match="sample_x"):
        invert_map(fmap, (2, 2), sample_x=torch.linspace(-1, 1, 4, dtype=D))
    ident = torch.stack(torch.meshgrid(torch.tensor([0.0, 1.0, 2.0], dtype=D), torch.tensor([0.0, 1.0], dtype=D),
                                       indexing="xy"), -1)[None].expand(3, -1, -1, -1).contiguous()
    ys = torch.tensor([0.0, 1.0], dtype=D)
    # steps 1 and 1 + 3e-6: 1.5e-6 from their mean > 1e-6 x mean: refused; 1 and 1 + 1e-6: accepted
    for bad in ([0.0, 1.0, 2.0 + 3e-6], [0.0, 0.0, 0.0], [2.0, 1.0, 0.0]):
        with pytest.raises(InputValueError, match="sample_x.*uniformly spaced"):
            invert_map(ident, (2, 2), sample_x=torch.tensor(bad, dtype=D), sample_y=ys)
    invert_map(ident, (2, 2), sample_x=torch.tensor([0.0, 1.0, 2.0 + 1e-6], dtype=D), sample_y=ys)


def test_chief_ray_grid_display_to_eye_and_jacobian_gain_of_an_affine_map():
    """Display to eye: the grid is the map at the pixel centres (exact for an affine map); the Jacobian gain
    is its constant area magnification |det A_c|; a given gain tensor is passed through."""
    sx, sy = torch.linspace(-1.2, 1.2, 4, dtype=D), torch.linspace(-1, 1, 3, dtype=D)
    chief = _affine(_A, _T, torch.stack(torch.meshgrid(sx, sy, indexing="xy"), -1))
    size = (5, 6)
    grid, gain = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy)
    assert gain is None
    assert torch.allclose(grid, _affine(_A, _T, pixel_grid(size, D)), atol=1e-12, rtol=0)
    _, jac = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain="jacobian")
    assert jac is not None
    assert torch.allclose(jac, torch.linalg.det(_A).abs()[:, None, None].expand(3, *size), atol=1e-12)
    given = torch.rand(3, *size, dtype=D)
    assert chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain=given)[1] is given


def test_chief_ray_grid_eye_to_display_inverts():
    sx = torch.linspace(-1, 1, 4, dtype=D)
    chief = _affine(_A, _T, torch.stack(torch.meshgrid(sx, sx, indexing="xy"), -1))
    grid, _ = chief_ray_grid(chief, (4, 4), direction="eye_to_display", sample_x=sx, sample_y=sx)
    back = torch.einsum("cij,chwj->chwi", _A, grid) + _T[:, None, None, :]  # F_c(G_c(q))
    assert torch.allclose(back, pixel_grid((4, 4), D).expand(3, -1, -1, -1), atol=1e-9)


def test_chief_ray_grid_refusals():
    ok = pixel_grid((3, 3), D).expand(3, -1, -1, -1)
    with pytest.raises(ShapeError, match="chief_ray_map needs at least 2x2"):
        chief_ray_grid(torch.zeros(3, 3, 1, 2), (2, 2))
    with pytest.raises(InputValueError, match="chief_ray_map must have dtype"):
        chief_ray_grid(torch.zeros(3, 2, 2, 2, dtype=torch.int64), (4, 4))
    with pytest.raises(InputValueError, match="direction must be .*'up'"):
        chief_ray_grid(ok, (2, 2), direction="up")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain.*'area'"):
        chief_ray_grid(ok, (2, 2), gain="area")  # type: ignore[arg-type]
