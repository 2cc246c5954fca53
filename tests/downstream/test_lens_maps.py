"""Tests of ``controlgs_adapter.downstream.lens_maps``."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.downstream import lens
from controlgs_adapter.downstream.lens import CARDBOARD_RADIAL, LensPrewarp, LUTMap, MLPMap, PrewarpMap, RadialMap, pixel_grid
from controlgs_adapter.errors import InputValueError, ShapeError


def test_radial_map_formula_on_a_non_square_image():
    k = torch.tensor([[0.1, 0.02], [0.0, 0.0], [-0.05, 0.0]])
    grid, gain = RadialMap(k)((4, 8), torch.float64, torch.device("cpu"))
    assert gain is None
    i, j = 0, 7  # top-right pixel centre: x = 2 * 7.5 / 8 - 1, y = 2 * 0.5 / 4 - 1; aspect (1, 1/2)
    x, y = 7 / 8, -3 / 4
    r2 = x**2 + (y / 2) ** 2
    for c in range(3):
        f = 1 + float(k[c, 0]) * r2 + float(k[c, 1]) * r2**2
        assert grid[c, i, j].tolist() == pytest.approx([x * f, y * f], abs=1e-6)


CPU = torch.device("cpu")


D64 = torch.float64


def test_radial_map_caches_fixed_coefficients_and_differentiates_learnable_ones():
    coef = [[0.1, 0.0], [0.2, 0.0], [0.3, 0.0]]
    fixed = RadialMap(coef)
    assert torch.is_grad_enabled()
    g1, _ = fixed((5, 7), D64, CPU)
    g2, _ = fixed((5, 7), D64, CPU)
    assert g1 is g2 and len(fixed._cache) == 1  # fixed coefficients: one grid per key, even with grad on
    assert g1.grad_fn is None
    g3, _ = fixed((5, 6), D64, CPU)
    assert g3 is not g1 and len(fixed._cache) == 1  # another size replaces the entry
    g4, _ = fixed((5, 6), torch.float32, CPU)
    assert g4.dtype == torch.float32 and g4 is not g3 and torch.allclose(g4.double(), g3, atol=1e-6)  # per dtype
    # grid_c(p) = p (1 + k_c r^2) by hand at the centre-left pixel of a 1 x 3 image: x = -2/3, y = 0
    # (pixel centres; aspect-corrected r divides x by the larger half-extent 1): R channel 1 + 0.1 * 4/9
    g, _ = fixed((1, 3), D64, CPU)
    assert g[0, 0, 0, 0].item() == pytest.approx(-2 / 3 * (1 + 0.1 * 4 / 9), rel=1e-6)

    learned = RadialMap(coef, learnable=True)
    a, _ = learned((5, 7), D64, CPU)
    b, _ = learned((5, 7), D64, CPU)
    assert a is not b and a.grad_fn is not None and not learned._cache  # a graph each call, nothing cached
    with torch.no_grad():
        c, _ = learned((5, 7), D64, CPU)
        d, _ = learned((5, 7), D64, CPU)
    assert c is d and torch.equal(c, a.detach())  # under no_grad the learnable map caches too
    with torch.no_grad():
        learned.coefficients.mul_(2.0)  # an in-place edit bumps the version: a fresh grid
        e, _ = learned((5, 7), D64, CPU)
    assert e is not c and not torch.equal(e, c)


def test_lut_map_refuses_a_grid_that_is_not_finite():
    """A LUT grid holding NaN or inf is refused, naming ``grid`` (it would sample NaN everywhere it reaches)."""
    grid = torch.rand(3, 4, 5, 2)
    LUTMap(grid)  # finite: accepted
    for bad in (math.nan, math.inf):
        g = grid.clone()
        g[1, 2, 3, 0] = bad
        with pytest.raises(InputValueError, match="grid"):
            LUTMap(g)


def test_radial_coefficients_are_checked_as_stored_in_float32():
    from controlgs_adapter.downstream.lens import RadialMap

    with pytest.raises(InputValueError, match="coefficients"):
        RadialMap([[1e39], [0.0], [0.0]])  # finite in float64, inf in the float32 buffer
    assert RadialMap([[1], [0], [0]]).coefficients.dtype == torch.float32  # integers are accepted


D = torch.float64


def test_cardboard_radial_default_by_hand():
    # 1 + 2 k1 = landing / 512 at the display corner (r^2 = 2): k1 = (landing - 512) / 1024 for the
    # 606.5 / 611.8 / 617.1 px landings of 656 / 550 / 486 nm
    expect = [(606.5 - 512) / 1024, (611.8 - 512) / 1024, (617.1 - 512) / 1024]
    assert expect == pytest.approx([0.0922852, 0.0974609, 0.1026367], abs=1e-7)
    for stage_map in (RadialMap(), LensPrewarp().map):
        assert stage_map.coefficients.flatten().tolist() == pytest.approx(expect, rel=1e-6)
        assert not stage_map.coefficients.requires_grad
    # the grid at the corner pixel centre of a 2 x 2 image (p = (0.5, 0.5), r^2 = 0.5): p (1 + k1 / 2)
    grid, gain = RadialMap()((2, 2), D, torch.device("cpu"))
    assert gain is None
    assert grid[:, 1, 1, 0].tolist() == pytest.approx([0.5 * (1 + k / 2) for k in expect], rel=1e-6)


def test_the_prewarp_map_base_class_is_abstract():
    with pytest.raises(NotImplementedError):
        PrewarpMap().is_identity()
    with pytest.raises(NotImplementedError):
        PrewarpMap()((2, 2), D, torch.device("cpu"))


def test_maps_are_evaluated_on_the_requested_device():
    # "meta" stands in for a second device on a machine without a GPU
    meta = torch.device("meta")
    table = {"exact": (torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 2))}
    grid = lens.pixel_grid((2, 2))[None].expand(3, -1, -1, -1).contiguous()
    for m in (lens.DisplayLUTMap(table), LUTMap(grid), RadialMap(), MLPMap(hidden=4, layers=1)):
        g, gain = m.to(meta)((4, 6), torch.float32, meta)
        assert g.device.type == "meta" and (gain is None or gain.device.type == "meta")


def test_lut_map_same_size_returns_the_table_and_no_gain_means_one():
    g = torch.Generator().manual_seed(3)
    grid = pixel_grid((3, 4), torch.float64) + 0.1 * torch.rand(3, 3, 4, 2, dtype=torch.float64, generator=g)
    out_grid, out_gain = LUTMap(grid)((3, 4), torch.float64, CPU)
    assert torch.allclose(out_grid, grid, atol=1e-7, rtol=0)
    assert torch.equal(out_gain, torch.ones(3, 3, 4, dtype=torch.float64))
    assert out_grid.dtype == torch.float64
    assert LUTMap(grid)((3, 4), torch.float32, CPU)[0].dtype == torch.float32


def test_lut_map_is_identity_follows_its_buffers():
    ident = pixel_grid((3, 3), torch.float64).expand(3, -1, -1, -1).clone()
    m = LUTMap(ident)
    assert m.is_identity()
    m.gain[1, 2, 0] = 1.5  # in-place edit after the first answer
    assert not m.is_identity()
    m.gain[1, 2, 0] = 1.0
    assert m.is_identity()
    m.displacement[0, 0, 0, 1] = 1e-3
    assert not m.is_identity()
    assert not LUTMap(ident, torch.full((3, 3, 3), 2.0, dtype=torch.float64)).is_identity()


def test_lut_map_refusals_name_the_argument():
    with pytest.raises(ShapeError, match="grid needs at least 2x2"):
        LUTMap(torch.zeros(3, 1, 4, 2))
    with pytest.raises(ShapeError, match="grid needs at least 2x2"):
        LUTMap(torch.zeros(3, 4, 1, 2))
    with pytest.raises(ShapeError, match="gain"):
        LUTMap(torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 3))
    with pytest.raises(ShapeError, match="grid"):
        LUTMap(torch.zeros(2, 2, 2, 2))


def test_mlp_map_fourier_features_by_hand():
    m = MLPMap(hidden=3, layers=3, frequencies=2)
    assert m.mlp[0].in_features == 2 + 4 * 2
    assert [type(x).__name__ for x in m.mlp] == ["Linear", "SiLU"] * 3 + ["Linear"]
    assert m.mlp[2].in_features == 3 and m.mlp[-1].out_features == 9
    p = torch.tensor([[0.25, -0.5]], dtype=torch.float64)
    x, y = 0.25, -0.5
    pi = torch.pi
    ang = torch.tensor([pi * x, 2 * pi * x, pi * y, 2 * pi * y], dtype=torch.float64)
    want = torch.cat([torch.tensor([x, y], dtype=torch.float64), ang.sin(), ang.cos()])
    assert torch.allclose(m._encode(p)[0], want, atol=1e-15)
    raw = MLPMap(hidden=3, layers=1, frequencies=0)
    assert raw.mlp[0].in_features == 2 and torch.equal(raw._encode(p), p)


@pytest.mark.parametrize("kwargs", [dict(hidden=0), dict(layers=0), dict(frequencies=-1)])
def test_mlp_map_refuses_bad_sizes(kwargs):
    with pytest.raises(InputValueError, match="hidden, layers must be >= 1 and frequencies >= 0"):
        MLPMap(**kwargs)


def test_mlp_map_accepts_the_bounds():
    m = MLPMap(hidden=1, layers=1, frequencies=0)
    assert m.is_identity() and m((2, 2), torch.float32, CPU)[0].shape == (3, 2, 2, 2)


def test_radial_map_default_and_higher_orders_by_hand():
    from controlgs_adapter.downstream.lens import RadialMap

    landing = (606.5, 611.8, 617.1)  # px from the centre of a 1024 px display, corner (r^2 = 2)
    assert torch.allclose(RadialMap().coefficients, torch.tensor([[(d / 512 - 1) / 2] for d in landing]))
    assert RadialMap().coefficients.tolist() == RadialMap(CARDBOARD_RADIAL).coefficients.tolist()
    k = [[0.1, 0.02], [0.0, -0.03], [-0.05, 0.0]]
    m = RadialMap(k)
    grid, gain = m((4, 4), torch.float64, CPU)  # square image on the square display: r = |p|
    assert gain is None
    p = pixel_grid((4, 4), torch.float64)
    r2 = (p ** 2).sum(-1)
    for c, (k1, k2) in enumerate(k):
        want = p * (1 + k1 * r2 + k2 * r2 ** 2)[..., None]
        assert torch.allclose(grid[c], want, atol=1e-7, rtol=0)  # coefficients are stored as float32
    with torch.no_grad():
        m.coefficients[1, 1] = 0.0  # in place: the cached grid must follow
    assert torch.allclose(m((4, 4), torch.float64, CPU)[0][1], p, atol=1e-12)
    assert not m.is_identity() and RadialMap([[0.0, 0.0]] * 3).is_identity()
