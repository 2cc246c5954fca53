"""Tests of ``controlgs_adapter.downstream.lens_maps``: the stand-alone pre-warp maps. The radial
polynomial (the Cardboard default, its radius in the display frame, caching), the lookup table
(bilinear interpolation and extrapolation, dtype, edits, refusals) and the learned MLP (layout, Fourier
features, identity at init), evaluated on the requested dtype and device."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.downstream.bank_maps import DisplayLUTMap
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.lens_maps import CARDBOARD_RADIAL, LUTMap, MLPMap, PrewarpMap, RadialMap
from controlgs_adapter.downstream.warp import pixel_grid
from controlgs_adapter.errors import InputValueError, ShapeError

D = torch.float64
CPU = torch.device("cpu")


# ----------------------------------------------------------------------------- RadialMap
def test_cardboard_radial_default():
    """1 + 2 k1 = landing / 512 at the display corner (r^2 = 2): k1 = (landing - 512) / 1024 for the
    606.5 / 611.8 / 617.1 px landings of 656 / 550 / 486 nm (of a 1024 px display); the default map and the
    default lens use them, fixed; the grid at the corner pixel centre of a 2 x 2 image (p = (0.5, 0.5),
    r^2 = 0.5) is p (1 + k1 / 2), without a gain."""
    expect = [(606.5 - 512) / 1024, (611.8 - 512) / 1024, (617.1 - 512) / 1024]
    assert expect == pytest.approx([0.0922852, 0.0974609, 0.1026367], abs=1e-7)
    assert RadialMap().coefficients.tolist() == RadialMap(CARDBOARD_RADIAL).coefficients.tolist()
    for stage_map in (RadialMap(), LensPrewarp().map):
        assert stage_map.coefficients.flatten().tolist() == pytest.approx(expect, rel=1e-6)
        assert not stage_map.coefficients.requires_grad
    grid, gain = RadialMap()((2, 2), D, CPU)
    assert gain is None
    assert grid[:, 1, 1, 0].tolist() == pytest.approx([0.5 * (1 + k / 2) for k in expect], rel=1e-6)


def test_radial_map_higher_orders_on_a_square_image():
    """``grid_c(p) = p (1 + k_c1 r^2 + k_c2 r^4)``, r = |p| on a square image; an in-place change of the
    coefficients is followed; zero coefficients are the identity."""
    k = [[0.1, 0.02], [0.0, -0.03], [-0.05, 0.0]]
    m = RadialMap(k)
    grid, gain = m((4, 4), D, CPU)
    assert gain is None
    p = pixel_grid((4, 4), D)
    r2 = (p ** 2).sum(-1)
    for c, (k1, k2) in enumerate(k):
        want = p * (1 + k1 * r2 + k2 * r2 ** 2)[..., None]
        assert torch.allclose(grid[c], want, atol=1e-7, rtol=0)  # coefficients are stored as float32
    with torch.no_grad():
        m.coefficients[1, 1] = 0.0  # in place: the cached grid must follow
    assert torch.allclose(m((4, 4), D, CPU)[0][1], p, atol=1e-12)
    assert not m.is_identity() and RadialMap([[0.0, 0.0]] * 3).is_identity()


def test_the_radial_radius_is_the_display_radius_under_fit():
    """On a non-square image r is the radius in display-normalised coordinates of the image placed on the
    square display with "fit" (the longer axis spans [-1, 1]). Worked out: the top-right pixel centre of a
    4 x 8 image, (7/8, -3/4) with aspect (1, 1/2); the centre-left pixel of a 1 x 3 image, x = -2/3; and in
    mm for 27 x 48 and 48 x 27: pixel (i, j) of a 27 x 48 image sits at ((j + 0.5) 0.5 - 12, (i + 0.5) 0.5
    - 6.75) mm on the 24 mm display."""
    k = torch.tensor([[0.1, 0.02], [0.0, 0.0], [-0.05, 0.0]])
    grid, gain = RadialMap(k)((4, 8), D, CPU)
    assert gain is None
    x, y = 7 / 8, -3 / 4
    r2 = x**2 + (y / 2) ** 2
    for c in range(3):
        f = 1 + float(k[c, 0]) * r2 + float(k[c, 1]) * r2**2
        assert grid[c, 0, 7].tolist() == pytest.approx([x * f, y * f], abs=1e-6)
    g, _ = RadialMap([[0.1, 0.0], [0.2, 0.0], [0.3, 0.0]])((1, 3), D, CPU)
    assert g[0, 0, 0, 0].item() == pytest.approx(-2 / 3 * (1 + 0.1 * 4 / 9), rel=1e-6)
    k1 = torch.tensor([c[0] for c in CARDBOARD_RADIAL], dtype=D)
    for h, w in ((27, 48), (48, 27)):
        grid = LensPrewarp().map((h, w), D, CPU)[0]                             # [3, H, W, 2]
        i, j = torch.meshgrid(torch.arange(h, dtype=D), torch.arange(w, dtype=D), indexing="ij")
        x_mm, y_mm = (j + 0.5) * 0.5 - w / 4, (i + 0.5) * 0.5 - h / 4
        r2 = (x_mm ** 2 + y_mm ** 2) / 12.0 ** 2                   # display half-width 12 mm
        p = torch.stack([x_mm / (w / 4), y_mm / (h / 4)], -1)      # image-normalised
        assert torch.allclose(grid, p[None] * (1 + k1[:, None, None] * r2)[..., None], atol=1e-6)


def test_radial_map_caches_fixed_coefficients_and_differentiates_learnable_ones():
    """Fixed coefficients: one grid per (size, dtype, device) key, kept even with grad on and replaced by
    another key. Learnable ones: a fresh graph every call, cached only under no_grad, and an in-place edit
    gives a fresh grid."""
    coef = [[0.1, 0.0], [0.2, 0.0], [0.3, 0.0]]
    fixed = RadialMap(coef)
    assert torch.is_grad_enabled()
    g1, _ = fixed((5, 7), D, CPU)
    g2, _ = fixed((5, 7), D, CPU)
    assert g1 is g2 and len(fixed._cache) == 1 and g1.grad_fn is None
    g3, _ = fixed((5, 6), D, CPU)
    assert g3 is not g1 and len(fixed._cache) == 1
    g4, _ = fixed((5, 6), torch.float32, CPU)
    assert g4.dtype == torch.float32 and g4 is not g3 and torch.allclose(g4.double(), g3, atol=1e-6)
    learned = RadialMap(coef, learnable=True)
    a, _ = learned((5, 7), D, CPU)
    b, _ = learned((5, 7), D, CPU)
    assert a is not b and a.grad_fn is not None and not learned._cache
    with torch.no_grad():
        c, _ = learned((5, 7), D, CPU)
        d, _ = learned((5, 7), D, CPU)
    assert c is d and torch.equal(c, a.detach())
    with torch.no_grad():
        learned.coefficients.mul_(2.0)
        e, _ = learned((5, 7), D, CPU)
    assert e is not c and not torch.equal(e, c)


def test_radial_coefficients_are_checked_as_stored():
    """Coefficients are ``[3, K]``, stored as float32 (integers accepted): a value finite in float64 but
    infinite in float32 is refused."""
    with pytest.raises(ShapeError, match="coefficients"):
        RadialMap([[0.1], [0.1]])
    with pytest.raises(InputValueError, match="coefficients"):
        RadialMap([[1e39], [0.0], [0.0]])
    assert RadialMap([[1], [0], [0]]).coefficients.dtype == torch.float32


# ----------------------------------------------------------------------------- LUTMap
def _bilinear_field(p: torch.Tensor, coef: torch.Tensor) -> torch.Tensor:
    """``coef`` ``[3, D, 4]`` (1, x, y, x y) evaluated at points ``p`` ``[H, W, 2]`` -> ``[3, H, W, D]`` (float64)."""
    x, y = p[..., 0].double(), p[..., 1].double()
    basis = torch.stack([torch.ones_like(x), x, y, x * y], -1)
    return torch.einsum("cdk,hwk->chwd", coef, basis)


@pytest.mark.parametrize("size", [(7, 5), (2, 9), (4, 3)])
def test_lut_map_interpolates_and_extrapolates_a_bilinear_table_exactly(size):
    """Bilinear interpolation reproduces a bilinear function exactly, and so does linear extrapolation past
    the table's outer pixel centres (the border pixels of a larger image); grid and gain alike."""
    grid_coef = torch.tensor([
        [[0.05, 1.10, 0.10, 0.20], [-0.02, 0.05, 0.90, -0.10]],
        [[-0.03, 0.95, -0.05, 0.00], [0.04, 0.02, 1.05, 0.15]],
        [[0.00, 1.20, 0.00, -0.05], [0.01, -0.10, 1.15, 0.00]],
    ], dtype=D)
    gain_coef = torch.tensor([[[1.0, 0.2, -0.1, 0.05]], [[0.8, 0.0, 0.3, 0.0]], [[1.2, -0.2, 0.0, 0.1]]], dtype=D)
    table = pixel_grid((4, 3), D)
    got_grid, got_gain = LUTMap(_bilinear_field(table, grid_coef), _bilinear_field(table, gain_coef)[..., 0])(size, D, CPU)
    p = pixel_grid(size, D)
    assert got_grid.shape == (3, *size, 2) and got_gain.shape == (3, *size)
    assert torch.allclose(got_grid, _bilinear_field(p, grid_coef), atol=1e-6, rtol=0)  # buffers are float32
    assert torch.allclose(got_gain, _bilinear_field(p, gain_coef)[..., 0], atol=1e-6, rtol=0)


def test_lut_map_at_its_own_size_and_in_the_requested_dtype():
    """At its own size the table itself comes back; no gain means a gain of one; a constant gain stays
    constant at another size; the grid and gain are in the requested dtype, and so is a stage's output."""
    g = torch.Generator().manual_seed(3)
    grid = pixel_grid((3, 4), D) + 0.1 * torch.rand(3, 3, 4, 2, dtype=D, generator=g)
    out_grid, out_gain = LUTMap(grid)((3, 4), D, CPU)
    assert torch.allclose(out_grid, grid, atol=1e-7, rtol=0)
    assert torch.equal(out_gain, torch.ones(3, 3, 4, dtype=D)) and out_grid.dtype == D
    assert LUTMap(grid)((3, 4), torch.float32, CPU)[0].dtype == torch.float32
    shifted = pixel_grid((3, 4))[None].expand(3, -1, -1, -1).contiguous() + 0.01
    lut = LUTMap(shifted, torch.full((3, 3, 4), 1.5))
    for size in ((3, 4), (6, 8)):
        g, k = lut(size, D, CPU)
        assert g.dtype == D and k.dtype == D
        assert float(k.min()) == 1.5 and float(k.max()) == 1.5
    assert LensPrewarp.from_lut(shifted, torch.full((3, 3, 4), 1.5))(torch.ones(3, 3, 4, dtype=D)).dtype == D


def test_lut_map_follows_in_place_edits_of_its_buffers():
    """Evaluation and ``is_identity`` see in-place changes of the displacement and gain buffers."""
    ident = pixel_grid((3, 3), D).expand(3, -1, -1, -1).clone()
    m = LUTMap(ident)
    assert m.is_identity()
    first, _ = m((5, 5), D, CPU)
    assert torch.allclose(first, pixel_grid((5, 5), D).expand(3, -1, -1, -1), atol=1e-7)
    m.gain[1, 2, 0] = 1.5
    assert not m.is_identity()
    m.gain[1, 2, 0] = 1.0
    assert m.is_identity()
    m.displacement[:, :, :, 0] += 0.25  # a uniform shift in x
    assert not m.is_identity()
    moved, _ = m((5, 5), D, CPU)
    assert torch.allclose(moved[..., 0] - first[..., 0], torch.full((3, 5, 5), 0.25, dtype=D), atol=1e-7)
    assert not LUTMap(ident, torch.full((3, 3, 3), 2.0, dtype=D)).is_identity()


def test_lut_map_refusals_name_the_argument():
    for bad in (torch.zeros(3, 1, 4, 2), torch.zeros(3, 4, 1, 2)):
        with pytest.raises(ShapeError, match="grid needs at least 2x2"):
            LUTMap(bad)
    with pytest.raises(ShapeError, match="grid"):
        LUTMap(torch.zeros(2, 2, 2, 2))
    with pytest.raises(ShapeError, match="gain"):
        LUTMap(torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 3))
    grid = torch.rand(3, 4, 5, 2)
    LUTMap(grid)  # finite: accepted
    for bad in (math.nan, math.inf):  # it would sample NaN everywhere it reaches
        g = grid.clone()
        g[1, 2, 3, 0] = bad
        with pytest.raises(InputValueError, match="grid"):
            LUTMap(g)


# ----------------------------------------------------------------------------- MLPMap
def test_mlp_map_layers_and_fourier_features():
    """Default: 2 hidden layers of 64 and a 9-wide output, input 2 + 4 x 4 Fourier features (4 octaves),
    identity at init (also as the learned lens's map). The features of (x, y) are (x, y, sin, cos of
    pi 2^k x and pi 2^k y); without frequencies the input is (x, y) itself."""
    for m in (MLPMap(), LensPrewarp.learned().map):
        linears = [x for x in m.mlp if isinstance(x, torch.nn.Linear)]
        assert [(x.in_features, x.out_features) for x in linears] == [(18, 64), (64, 64), (64, 9)]
        assert m.frequencies == 4 and m.is_identity()
    small = LensPrewarp.learned(hidden=5, layers=1, frequencies=0).map
    assert [(x.in_features, x.out_features) for x in small.mlp if isinstance(x, torch.nn.Linear)] == [(2, 5), (5, 9)]
    m = MLPMap(hidden=3, layers=3, frequencies=2)
    assert m.mlp[0].in_features == 2 + 4 * 2
    assert [type(x).__name__ for x in m.mlp] == ["Linear", "SiLU"] * 3 + ["Linear"]
    assert m.mlp[2].in_features == 3 and m.mlp[-1].out_features == 9
    p = torch.tensor([[0.25, -0.5]], dtype=D)
    x, y = 0.25, -0.5
    ang = torch.tensor([torch.pi * x, 2 * torch.pi * x, torch.pi * y, 2 * torch.pi * y], dtype=D)
    want = torch.cat([torch.tensor([x, y], dtype=D), ang.sin(), ang.cos()])
    assert torch.allclose(m._encode(p)[0], want, atol=1e-15)
    raw = MLPMap(hidden=3, layers=1, frequencies=0)
    assert raw.mlp[0].in_features == 2 and torch.equal(raw._encode(p), p)


def test_mlp_map_output_is_displacement_and_log_gain_per_channel():
    """With a zero last weight the output is the bias: channel c reads (dx, dy, log gain) from
    bias[3c : 3c + 3]; any non-zero last weight makes it not the identity."""
    m = MLPMap(hidden=5, layers=2, frequencies=1).double()
    assert m.is_identity()
    bias = torch.tensor([0.1, -0.2, 0.3, 0.0, 0.05, -0.4, -0.1, 0.0, 0.7], dtype=D)
    with torch.no_grad():
        m.mlp[-1].bias.copy_(bias)
    assert not m.is_identity()
    grid, gain = m((3, 4), D, CPU)
    p = pixel_grid((3, 4), D)
    b = bias.reshape(3, 3)
    for c in range(3):
        assert torch.allclose(grid[c], p + b[c, :2], atol=1e-15)
        assert torch.allclose(gain[c], torch.full((3, 4), float(torch.exp(b[c, 2])), dtype=D), atol=1e-15)
    with torch.no_grad():
        m.mlp[-1].bias.zero_()
        m.mlp[-1].weight[4, 0] = 1e-3
    assert not m.is_identity()


@pytest.mark.parametrize("kwargs", [dict(hidden=0), dict(layers=0), dict(frequencies=-1)])
def test_mlp_map_refuses_bad_sizes_and_accepts_the_bounds(kwargs):
    with pytest.raises(InputValueError, match="hidden, layers.*frequencies"):
        MLPMap(**kwargs)
    m = MLPMap(hidden=1, layers=1, frequencies=0)
    assert m.is_identity() and m((2, 2), torch.float32, CPU)[0].shape == (3, 2, 2, 2)


# ----------------------------------------------------------------------------- every map
def test_the_prewarp_map_base_class_is_abstract():
    with pytest.raises(NotImplementedError):
        PrewarpMap().is_identity()
    with pytest.raises(NotImplementedError):
        PrewarpMap()((2, 2), D, CPU)


def test_maps_are_evaluated_on_the_requested_device():
    """"meta" stands in for a second device on a machine without a GPU."""
    meta = torch.device("meta")
    table = {"exact": (torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 2))}
    grid = pixel_grid((2, 2))[None].expand(3, -1, -1, -1).contiguous()
    for m in (DisplayLUTMap(table), LUTMap(grid), RadialMap(), MLPMap(hidden=4, layers=1)):
        g, gain = m.to(meta)((4, 6), torch.float32, meta)
        assert g.device.type == "meta" and (gain is None or gain.device.type == "meta")
