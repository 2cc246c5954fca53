"""Tests of ``controlgs_adapter.downstream.warp``."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream.lens import DisplayLUTMap, LUTMap, MLPMap, RadialMap, chief_ray_grid, invert_map, pixel_grid
from controlgs_adapter.errors import InputValueError, ShapeError


def test_invert_map_round_trip():
    fmap = RadialMap([[0.1], [-0.05], [0.2]])((12, 9), torch.float64, torch.device("cpu"))[0]
    inv = invert_map(fmap, (12, 9))  # same sample grid: F(G(q)) = q exactly at the samples
    ident = pixel_grid((12, 9), torch.float64).expand(3, -1, -1, -1)
    back = torch.nn.functional.grid_sample(  # F at G via bilinear interpolation of F (channels as batch)
        fmap.permute(0, 3, 1, 2), inv, align_corners=False, padding_mode="border"
    ).permute(0, 2, 3, 1)
    inner = (slice(None), slice(1, -1), slice(1, -1))
    assert torch.allclose(back[inner], ident[inner], atol=1e-8)


# ------------------------------------------------------------------------------ lens: invert_map
def test_one_newton_step_inverts_an_affine_map_exactly():
    """A bilinearly interpolated affine map is affine everywhere, so Newton's method (float64, central
    differences) lands on the analytic inverse ``A^-1 (q - b)`` in one step, for every channel; the y column
    of the Jacobian matters because the map shears y into x."""
    a = torch.tensor([[1.5, 0.6], [0.4, 2.0]], dtype=torch.float64)
    b = torch.tensor([0.1, -0.2], dtype=torch.float64)
    gh, gw = 5, 6
    ys = (torch.arange(gh, dtype=torch.float64) + 0.5) * (2.0 / gh) - 1.0
    xs = (torch.arange(gw, dtype=torch.float64) + 0.5) * (2.0 / gw) - 1.0
    p = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # [Gh, Gw, 2] (x, y)
    fmap = (p @ a.T + b).expand(3, -1, -1, -1).contiguous()
    h, w = 7, 9
    qy = (torch.arange(h, dtype=torch.float64) + 0.5) * (2.0 / h) - 1.0
    qx = (torch.arange(w, dtype=torch.float64) + 0.5) * (2.0 / w) - 1.0
    q = torch.stack(torch.meshgrid(qx, qy, indexing="xy"), dim=-1)
    expected = torch.linalg.solve(a, (q - b).reshape(-1, 2).T).T.reshape(h, w, 2)
    g = invert_map(fmap, (h, w), iterations=1, tol=0.0)
    assert g.dtype == torch.float64 and g.shape == (3, h, w, 2)
    assert float((g - expected).abs().max()) < 2e-10


D = torch.float64


def test_sample_coordinates_must_be_uniform_within_one_millionth():
    fmap = torch.stack(torch.meshgrid(torch.tensor([0.0, 1.0, 2.0], dtype=D), torch.tensor([0.0, 1.0], dtype=D),
                                      indexing="xy"), -1)[None].expand(3, -1, -1, -1).contiguous()  # identity
    ys = torch.tensor([0.0, 1.0], dtype=D)
    # steps 1 and 1 + 3e-6: 1.5e-6 from their mean > 1e-6 x mean: refused
    with pytest.raises(InputValueError, match="sample_x must be uniformly spaced and increasing"):
        invert_map(fmap, (2, 2), sample_x=torch.tensor([0.0, 1.0, 2.0 + 3e-6], dtype=D), sample_y=ys)
    # steps 1 and 1 + 1e-6: 0.5e-6 from their mean: accepted
    invert_map(fmap, (2, 2), sample_x=torch.tensor([0.0, 1.0, 2.0 + 1e-6], dtype=D), sample_y=ys)
    for bad in ([0.0, 0.0, 0.0], [2.0, 1.0, 0.0]):
        with pytest.raises(InputValueError, match="sample_x must be uniformly spaced and increasing"):
            invert_map(fmap, (2, 2), sample_x=torch.tensor(bad, dtype=D), sample_y=ys)


CPU = torch.device("cpu")


# per channel c: F_c(x, y) = (a0 + a1 x + a2 y + a3 x y, b0 + b1 x + b2 y + b3 x y)
_COEF = torch.tensor([
    [[0.05, 1.10, 0.10, 0.20], [-0.02, 0.05, 0.90, -0.10]],
    [[-0.03, 0.95, -0.05, 0.00], [0.04, 0.02, 1.05, 0.15]],
    [[0.00, 1.20, 0.00, -0.05], [0.01, -0.10, 1.15, 0.00]],
], dtype=torch.float64)  # [3, 2 (out x, y), 4]


def _bilinear_field(p: torch.Tensor, coef: torch.Tensor = _COEF) -> torch.Tensor:
    """``coef`` ``[3, D, 4]`` evaluated at points ``p`` ``[H, W, 2]`` -> ``[3, H, W, D]`` (float64)."""
    x, y = p[..., 0].double(), p[..., 1].double()
    basis = torch.stack([torch.ones_like(x), x, y, x * y], -1)  # [H, W, 4]
    return torch.einsum("cdk,hwk->chwd", coef, basis)


def _affine(a: torch.Tensor, t: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """Per channel ``a[c] @ p + t[c]``: ``a`` ``[3, 2, 2]``, ``t`` ``[3, 2]``, ``p`` ``[H, W, 2]`` -> ``[3, H, W, 2]``."""
    return torch.einsum("cij,hwj->chwi", a, p) + t[:, None, None, :]


_A = torch.tensor([[[1.2, 0.1], [-0.05, 0.9]], [[0.8, 0.0], [0.0, 1.1]], [[1.0, -0.2], [0.15, 1.05]]], dtype=torch.float64)


_T = torch.tensor([[0.05, -0.1], [0.0, 0.02], [-0.07, 0.03]], dtype=torch.float64)


def _display_tables(hd: int = 5, wd: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A display table whose displacement is ``M_c q + t_c`` at display point ``q`` (exact under
    bilinear interpolation) and gain ``1 + 0.1 c``: ``(displacement, gain, M)``."""
    m = torch.tensor([[0.10, -0.05], [0.02, 0.08], [-0.06, 0.04]], dtype=torch.float64)  # diagonal of M_c
    t = torch.tensor([[0.01, 0.02], [-0.03, 0.0], [0.0, -0.01]], dtype=torch.float64)
    q = pixel_grid((hd, wd), torch.float64)
    disp = m[:, None, None, :] * q + t[:, None, None, :]
    gain = (1.0 + 0.1 * torch.arange(3, dtype=torch.float64))[:, None, None].expand(3, hd, wd).clone()
    return disp, gain, torch.cat([m, t], 1)


@pytest.mark.parametrize("size", [(7, 5), (2, 9), (4, 3)])
def test_lut_map_interpolates_and_extrapolates_a_bilinear_table_exactly(size):
    """Bilinear interpolation reproduces a bilinear function exactly, and so does linear
    extrapolation past the table's outer pixel centres (the border pixels of a larger image)."""
    table_size = (4, 3)
    grid = _bilinear_field(pixel_grid(table_size, torch.float64))  # [3, 4, 3, 2]
    gain_coef = torch.tensor([[[1.0, 0.2, -0.1, 0.05]], [[0.8, 0.0, 0.3, 0.0]], [[1.2, -0.2, 0.0, 0.1]]],
                             dtype=torch.float64)
    gain = _bilinear_field(pixel_grid(table_size, torch.float64), gain_coef)[..., 0]  # [3, 4, 3]
    got_grid, got_gain = LUTMap(grid, gain)(size, torch.float64, CPU)
    p = pixel_grid(size, torch.float64)
    assert got_grid.shape == (3, *size, 2) and got_gain.shape == (3, *size)
    assert torch.allclose(got_grid, _bilinear_field(p), atol=1e-6, rtol=0)  # buffers are float32
    assert torch.allclose(got_gain, _bilinear_field(p, gain_coef)[..., 0], atol=1e-6, rtol=0)


def test_mlp_map_output_layout_by_hand():
    """With a zero last weight the output is the bias: channel c reads (dx, dy, log gain) from
    bias[3c : 3c + 3]."""
    m = MLPMap(hidden=5, layers=2, frequencies=1).double()
    assert m.is_identity()
    bias = torch.tensor([0.1, -0.2, 0.3, 0.0, 0.05, -0.4, -0.1, 0.0, 0.7], dtype=torch.float64)
    with torch.no_grad():
        m.mlp[-1].bias.copy_(bias)
    assert not m.is_identity()
    grid, gain = m((3, 4), torch.float64, CPU)
    p = pixel_grid((3, 4), torch.float64)
    b = bias.reshape(3, 3)
    for c in range(3):
        assert torch.allclose(grid[c], p + b[c, :2], atol=1e-15)
        assert torch.allclose(gain[c], torch.full((3, 4), float(torch.exp(b[c, 2])), dtype=torch.float64), atol=1e-15)
    with torch.no_grad():
        m.mlp[-1].bias.zero_()
        m.mlp[-1].weight[4, 0] = 1e-3
    assert not m.is_identity()


def test_invert_map_of_an_affine_map_on_custom_samples():
    """F_c affine on samples running -1 .. 1 (edges, not cell centres): G_c = A_c^-1 (q - t_c)."""
    sx, sy = torch.linspace(-1, 1, 5, dtype=torch.float64), torch.linspace(-1, 1, 4, dtype=torch.float64)
    p = torch.stack(torch.meshgrid(sx, sy, indexing="xy"), -1)  # [4, 5, 2]
    fmap = _affine(_A, _T, p)
    q = pixel_grid((6, 7), torch.float64)
    want = _affine(torch.linalg.inv(_A), -torch.einsum("cij,cj->ci", torch.linalg.inv(_A), _T), q)
    got = invert_map(fmap, (6, 7), sample_x=sx, sample_y=sy)
    assert got.shape == (3, 6, 7, 2) and got.dtype == torch.float64
    assert torch.allclose(got, want, atol=1e-9, rtol=0)
    assert invert_map(fmap.float(), (6, 7), sample_x=sx, sample_y=sy).dtype == torch.float32


def test_invert_map_without_iterations_is_the_first_order_start():
    """No Newton step (iterations=0, or a tolerance every residual meets): G = 2 q - F(q)."""
    a = torch.eye(2, dtype=torch.float64).expand(3, 2, 2) * 1.25
    fmap = _affine(a, torch.zeros(3, 2, dtype=torch.float64), pixel_grid((3, 3), torch.float64))
    q = pixel_grid((4, 5), torch.float64)
    start = (2.0 - 1.25) * q.expand(3, -1, -1, -1)
    assert torch.allclose(invert_map(fmap, (4, 5), iterations=0), start, atol=1e-12)
    assert torch.allclose(invert_map(fmap, (4, 5), tol=10.0), start, atol=1e-12)
    assert torch.allclose(invert_map(fmap, (4, 5)), q.expand(3, -1, -1, -1) / 1.25, atol=1e-9)


def test_invert_map_refusals():
    with pytest.raises(InputValueError, match="not invertible"):
        invert_map(torch.full((3, 3, 3, 2), 0.3, dtype=torch.float64), (2, 2))  # constant: zero Jacobian
    with pytest.raises(ShapeError, match="forward_map needs at least 2x2"):
        invert_map(torch.zeros(3, 2, 1, 2), (2, 2))
    with pytest.raises(ShapeError, match="forward_map"):
        invert_map(torch.zeros(2, 2, 2, 2), (2, 2))
    fmap = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1)
    with pytest.raises(InputValueError, match="sample_y must be uniformly spaced"):
        invert_map(fmap, (2, 2), sample_y=torch.tensor([-1.0, -0.9, 1.0], dtype=torch.float64))
    with pytest.raises(ShapeError, match="sample_x"):
        invert_map(fmap, (2, 2), sample_x=torch.linspace(-1, 1, 4, dtype=torch.float64))


def test_chief_ray_grid_display_to_eye_and_jacobian_gain_of_an_affine_map():
    sx, sy = torch.linspace(-1.2, 1.2, 4, dtype=torch.float64), torch.linspace(-1, 1, 3, dtype=torch.float64)
    chief = _affine(_A, _T, torch.stack(torch.meshgrid(sx, sy, indexing="xy"), -1))
    size = (5, 6)
    grid, gain = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy)
    assert gain is None
    assert torch.allclose(grid, _affine(_A, _T, pixel_grid(size, torch.float64)), atol=1e-12, rtol=0)
    _, jac = chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain="jacobian")
    assert jac is not None
    det = torch.linalg.det(_A).abs()  # constant area magnification of an affine map
    assert torch.allclose(jac, det[:, None, None].expand(3, *size), atol=1e-12)
    given = torch.rand(3, *size, dtype=torch.float64)
    assert chief_ray_grid(chief, size, sample_x=sx, sample_y=sy, gain=given)[1] is given


def test_chief_ray_grid_eye_to_display_inverts():
    sx = torch.linspace(-1, 1, 4, dtype=torch.float64)
    chief = _affine(_A, _T, torch.stack(torch.meshgrid(sx, sx, indexing="xy"), -1))
    grid, _ = chief_ray_grid(chief, (4, 4), direction="eye_to_display", sample_x=sx, sample_y=sx)
    back = torch.einsum("cij,chwj->chwi", _A, grid) + _T[:, None, None, :]  # F_c(G_c(q))
    assert torch.allclose(back, pixel_grid((4, 4), torch.float64).expand(3, -1, -1, -1), atol=1e-9)


def test_chief_ray_grid_refusals():
    ok = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1)
    with pytest.raises(ShapeError, match="chief_ray_map needs at least 2x2"):
        chief_ray_grid(torch.zeros(3, 3, 1, 2), (2, 2))
    with pytest.raises(InputValueError, match="direction must be"):
        chief_ray_grid(ok, (2, 2), direction="up")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain must be a tensor, 'jacobian' or None"):
        chief_ray_grid(ok, (2, 2), gain="area")  # type: ignore[arg-type]


@pytest.mark.parametrize("placement, size, half", [("stretch", (4, 8), (1.0, 1.0)), ("fit", (4, 8), (1.0, 0.5)),
                                                  ("fit", (6, 3), (0.5, 1.0))])
def test_display_lut_map_samples_the_image_region_of_the_display(placement, size, half):
    """grid(u) = (u h + disp(u h)) / h on a square display: a 4 x 8 image fit on it spans the full
    width and half the height (h = (1, 0.5))."""
    disp, gain, mt = _display_tables()
    lut = DisplayLUTMap({"exact": (disp, gain)}, display_mm=(24.0, 24.0), placement=placement)
    grid, got_gain = lut(size, torch.float64, CPU)
    h = torch.tensor(half, dtype=torch.float64)
    q = pixel_grid(size, torch.float64) * h  # display-normalised
    want = (q + mt[:, None, None, :2] * q + mt[:, None, None, 2:]) / h
    assert torch.allclose(grid, want, atol=1e-6, rtol=0)  # tables are stored as float32
    assert torch.allclose(got_gain, gain[:, :1, :1].expand(3, *size), atol=1e-6)
    assert not lut.is_identity()


def test_lut_map_evaluation_follows_in_place_edits():
    grid = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1).clone()
    m = LUTMap(grid)
    first, _ = m((5, 5), torch.float64, CPU)
    assert torch.allclose(first, pixel_grid((5, 5), torch.float64).expand(3, -1, -1, -1), atol=1e-7)
    m.displacement[:, :, :, 0] += 0.25  # a uniform shift in x
    moved, _ = m((5, 5), torch.float64, CPU)
    assert torch.allclose(moved[..., 0] - first[..., 0], torch.full((3, 5, 5), 0.25, dtype=torch.float64), atol=1e-7)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
