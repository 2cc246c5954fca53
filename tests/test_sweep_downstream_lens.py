"""Mutation-sweep tests of the lens pre-warp: documented defaults through the public API, sample
spacing tolerance, file-format versions and refusals, against numbers worked out by hand."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream import lens
from controlgs_adapter.downstream.lens import LensPrewarp, LUTMap, MLPMap, PrewarpMap, RadialMap, invert_map
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import Stage
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import read_header, save_tensors

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


def test_radial_constructor_defaults():
    fixed = LensPrewarp.radial([[0.1], [0.1], [0.1]])
    assert isinstance(fixed.map, RadialMap) and not fixed.map.coefficients.requires_grad
    assert fixed.basis == "primaries"
    learn = LensPrewarp.radial([[0.1], [0.1], [0.1]], learnable=True)
    assert learn.map.coefficients.requires_grad
    assert LensPrewarp(coefficients=[[0.2], [0.2], [0.2]]).map.coefficients.flatten().tolist() == pytest.approx([0.2] * 3)
    with pytest.raises(InputValueError, match="either prewarp_map or coefficients"):
        LensPrewarp(RadialMap(), coefficients=[[0.1]] * 3)
    with pytest.raises(InputValueError, match="basis must be one of"):
        LensPrewarp(basis="xyz")  # type: ignore[arg-type]


def test_learned_map_defaults():
    for m in (MLPMap(), LensPrewarp.learned().map):
        linears = [x for x in m.mlp if isinstance(x, torch.nn.Linear)]
        # 2 hidden layers of 64 and the 9-wide output; input 2 + 4 x 4 Fourier features (4 octaves)
        assert [(x.in_features, x.out_features) for x in linears] == [(18, 64), (64, 64), (64, 9)]
        assert m.frequencies == 4 and m.is_identity()
    small = LensPrewarp.learned(hidden=5, layers=1, frequencies=0).map
    assert [(x.in_features, x.out_features) for x in small.mlp if isinstance(x, torch.nn.Linear)] == [(2, 5), (5, 9)]


def test_the_prewarp_map_base_class_is_abstract():
    with pytest.raises(NotImplementedError):
        PrewarpMap().is_identity()
    with pytest.raises(NotImplementedError):
        PrewarpMap()((2, 2), D, torch.device("cpu"))


def test_lens_runs_at_order_ten():
    def at(order: float) -> Stage:
        return type("S", (Stage,), {"name": f"s{order}", "order": order, "process": lambda self, i, s, c: i})()

    assert Pipeline([at(10.1), LensPrewarp(), at(9.9)]).names == ["s9.9", "lens", "s10.1"]


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


def test_lut_files_carry_format_version_one_and_refuse_newer(tmp_path):
    pixel = lens.pixel_grid((2, 3), torch.float32)
    stage = LensPrewarp.from_lut(pixel[None].expand(3, -1, -1, -1).contiguous())
    path = stage.save_lut(tmp_path / "lut.safetensors")
    header = read_header(path, kind=lens.LUT_KIND, max_version=99)
    assert (header["format_version"], header["size"], header["source"]) == (1, [2, 3], "LUTMap")
    newer = save_tensors(tmp_path / "newer.safetensors", {"grid": pixel[None].expand(3, -1, -1, -1).contiguous(),
                                                         "gain": torch.ones(3, 2, 3)},
                         {}, kind=lens.LUT_KIND, format_version=2)
    with pytest.raises(FileFormatError, match="newer than this library reads"):
        LensPrewarp.load_lut(newer)
    table = {"exact": (torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 2))}
    dpath = lens.DisplayLUTMap(table).save(tmp_path / "display.safetensors")
    assert read_header(dpath, kind=lens.DISPLAY_LUT_KIND, max_version=99)["format_version"] == 1
    dnewer = save_tensors(tmp_path / "dnewer.safetensors", {"displacement_exact": torch.zeros(3, 2, 2, 2),
                                                           "gain_exact": torch.ones(3, 2, 2)},
                          {"modes": ["exact"]}, kind=lens.DISPLAY_LUT_KIND, format_version=2)
    with pytest.raises(FileFormatError, match="newer than this library reads"):
        lens.DisplayLUTMap.load(dnewer)


def test_save_lut_needs_a_size_unless_the_map_is_a_lut(tmp_path):
    with pytest.raises(InputValueError, match="size is required to save a RadialMap as a LUT"):
        LensPrewarp().save_lut(tmp_path / "x.safetensors")
    path = LensPrewarp().save_lut(tmp_path / "r.safetensors", (4, 6))
    again = LensPrewarp.load_lut(path)
    assert isinstance(again.map, LUTMap)
    expect, _ = RadialMap()((4, 6), torch.float32, torch.device("cpu"))
    assert torch.allclose(again.map((4, 6), torch.float32, torch.device("cpu"))[0], expect, atol=1e-6)


def test_bake_keeps_the_basis_and_refusals_of_the_warp_inputs():
    assert LensPrewarp(basis="rgb").bake((4, 4)).basis == "rgb"
    assert LensPrewarp().bake((4, 4)).basis == "primaries"
    image = torch.rand(3, 4, 4, dtype=D)
    grid = lens.pixel_grid((4, 4), D)[None].expand(3, -1, -1, -1).contiguous()
    with pytest.raises(InputValueError, match="grid must have dtype"):
        lens.lens_prewarp(image, grid.float())
    with pytest.raises(InputValueError, match="gain="):
        lens.lens_prewarp(image, grid, torch.ones(3, 4, 4, dtype=D, device="meta"))
    with pytest.raises(InputValueError, match="chief_ray_map must have dtype"):
        lens.chief_ray_grid(torch.zeros(3, 2, 2, 2, dtype=torch.int64), (4, 4))


def test_maps_are_evaluated_on_the_requested_device():
    # "meta" stands in for a second device on a machine without a GPU
    meta = torch.device("meta")
    table = {"exact": (torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 2))}
    grid = lens.pixel_grid((2, 2))[None].expand(3, -1, -1, -1).contiguous()
    for m in (lens.DisplayLUTMap(table), LUTMap(grid), RadialMap(), MLPMap(hidden=4, layers=1)):
        g, gain = m.to(meta)((4, 6), torch.float32, meta)
        assert g.device.type == "meta" and (gain is None or gain.device.type == "meta")


def test_a_lut_is_evaluated_in_the_requested_dtype_at_its_own_size_and_another():
    grid = lens.pixel_grid((3, 4))[None].expand(3, -1, -1, -1).contiguous() + 0.01
    gain = torch.full((3, 3, 4), 1.5)
    lut = LUTMap(grid, gain)
    for size in ((3, 4), (6, 8)):
        g, k = lut(size, D, torch.device("cpu"))
        assert g.dtype == D and k.dtype == D
        assert float(k.min()) == 1.5 and float(k.max()) == 1.5
    out = LensPrewarp.from_lut(grid, gain)(torch.ones(3, 3, 4, dtype=D))
    assert out.dtype == D


def test_display_lut_tables_must_be_finite():
    gain = torch.ones(3, 2, 2)
    gain[1, 0, 1] = float("nan")
    with pytest.raises(InputValueError, match="gain\\['exact'\\]"):
        lens.DisplayLUTMap({"exact": (torch.zeros(3, 2, 2, 2), gain)})
    disp = torch.zeros(3, 2, 2, 2)
    disp[0, 0, 0, 0] = float("inf")
    with pytest.raises(InputValueError, match="displacement\\['exact'\\]"):
        lens.DisplayLUTMap({"exact": (disp, torch.ones(3, 2, 2))})
