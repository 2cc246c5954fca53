"""Tests of ``controlgs_adapter.downstream.bank_maps``."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream import lens
from controlgs_adapter.downstream.lens import DisplayLUTMap, pixel_grid
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import save_tensors


# ------------------------------------------------------------------------------ LUT pre-warp
def test_display_lut_tables_are_held_outside_the_callers_graph():
    """Tables built from tensors that require grad (a fitted table straight from the optimiser) become
    plain buffers: no gradient flows back to the caller's tensors and none is tracked."""
    disp = torch.zeros(3, 4, 5, 2, requires_grad=True)
    gain = torch.ones(3, 4, 5, requires_grad=True)
    lut = DisplayLUTMap({"exact": (disp, gain)})
    for name in ("displacement_exact", "gain_exact"):
        buf = getattr(lut, name)
        assert not buf.requires_grad and buf.grad_fn is None, name
    assert torch.equal(lut.gain_exact, torch.ones(3, 4, 5))


D = torch.float64


# ----------------------------------------------------------------------------- DisplayLUTMap evaluation cache
def test_display_lut_map_evaluates_once_per_size_and_again_after_the_table_changes():
    """``DisplayLUTMap`` (class docstring): the grid and gain are evaluated once per (size, dtype, device,
    table) and returned again as they are; another size, or an in-place change of the table, evaluates
    anew (the change is seen)."""
    from controlgs_adapter.downstream.lens import DisplayLUTMap

    g = torch.Generator().manual_seed(3)
    disp = 0.01 * torch.randn(3, 4, 4, 2, generator=g)
    lut = DisplayLUTMap({"exact": (disp, 1.0 + 0.1 * torch.rand(3, 4, 4, generator=g))}, (10.0, 10.0), "stretch")
    grid1, gain1 = lut((6, 6), D, "cpu")
    grid2, gain2 = lut((6, 6), D, "cpu")
    assert grid2 is grid1 and gain2 is gain1
    other, _ = lut((5, 6), D, "cpu")
    assert other is not grid1 and other.shape == (3, 5, 6, 2)
    before = lut((6, 6), D, "cpu")[0].clone()
    with torch.no_grad():
        lut.displacement_exact += 0.05  # the eye position moves by 0.05 (display-normalised, stretch: grid too)
    after, _ = lut((6, 6), D, "cpu")
    torch.testing.assert_close(after, before + 0.05, rtol=0, atol=1e-6)


def test_display_lut_tables_must_be_finite():
    gain = torch.ones(3, 2, 2)
    gain[1, 0, 1] = float("nan")
    with pytest.raises(InputValueError, match="gain\\['exact'\\]"):
        lens.DisplayLUTMap({"exact": (torch.zeros(3, 2, 2, 2), gain)})
    disp = torch.zeros(3, 2, 2, 2)
    disp[0, 0, 0, 0] = float("inf")
    with pytest.raises(InputValueError, match="displacement\\['exact'\\]"):
        lens.DisplayLUTMap({"exact": (disp, torch.ones(3, 2, 2))})


def _display_tables(hd: int = 5, wd: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A display table whose displacement is ``M_c q + t_c`` at display point ``q`` (exact under
    bilinear interpolation) and gain ``1 + 0.1 c``: ``(displacement, gain, M)``."""
    m = torch.tensor([[0.10, -0.05], [0.02, 0.08], [-0.06, 0.04]], dtype=torch.float64)  # diagonal of M_c
    t = torch.tensor([[0.01, 0.02], [-0.03, 0.0], [0.0, -0.01]], dtype=torch.float64)
    q = pixel_grid((hd, wd), torch.float64)
    disp = m[:, None, None, :] * q + t[:, None, None, :]
    gain = (1.0 + 0.1 * torch.arange(3, dtype=torch.float64))[:, None, None].expand(3, hd, wd).clone()
    return disp, gain, torch.cat([m, t], 1)


def test_display_lut_map_table_choice():
    disp, gain, _ = _display_tables()
    other = (disp * 2.0, gain)
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}).table_mode() == "distortion"  # first
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}, mode="exact").table_mode() == "exact"

    class _Optics(torch.nn.Module):
        mode = "fast"

    optics = _Optics()
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}).follow(optics).table_mode() == "exact"
    only_distortion = DisplayLUTMap({"distortion": (disp, gain)}).follow(optics)
    with pytest.raises(InputValueError, match=r"tables for \('distortion',\), not for optics mode 'fast'"):
        only_distortion.table_mode()
    fast = DisplayLUTMap({"fast": (disp, gain), "exact": other}, mode="fast")
    assert fast.table_mode() == "fast"  # its own fast table wins over the exact one


def test_display_lut_map_refusals(tmp_path):

    disp, gain, _ = _display_tables()
    with pytest.raises(InputValueError, match="tables must hold at least one optics mode"):
        DisplayLUTMap({})
    with pytest.raises(InputValueError, match="placement must be one of .*'centre'"):
        DisplayLUTMap({"exact": (disp, gain)}, placement="centre")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="table modes must be among .*'paraxial'"):
        DisplayLUTMap({"paraxial": (disp, gain)})
    with pytest.raises(ShapeError, match="table 'exact' needs at least 2x2 samples"):
        DisplayLUTMap({"exact": (disp[:, :1], gain[:, :1])})
    with pytest.raises(ShapeError, match=r"gain\['exact'\]"):
        DisplayLUTMap({"exact": (disp, gain[:, :2])})
    kind = {"kind": "controlgs-prewarp-display-lut", "format_version": 1}
    no_modes = save_tensors(tmp_path / "no_modes.safetensors", {"gain_exact": gain.float()}, {}, **kind)
    with pytest.raises(FileFormatError, match="no_modes.safetensors: display LUT header lacks its modes"):
        DisplayLUTMap.load(no_modes)
    lacking = save_tensors(tmp_path / "lacking.safetensors", {"gain_exact": gain.float()}, {"modes": ["exact"]}, **kind)
    with pytest.raises(FileFormatError, match=r"lacking.safetensors: display LUT lacks \['displacement_exact'\]"):
        DisplayLUTMap.load(lacking)
    bad = save_tensors(tmp_path / "bad.safetensors", {"displacement_exact": disp[:, :1].float(), "gain_exact": gain[:, :1].float()},
                       {"modes": ["exact"]}, **kind)
    with pytest.raises(FileFormatError, match="bad.safetensors: table 'exact' needs at least 2x2"):
        DisplayLUTMap.load(bad)
    saved = DisplayLUTMap({"exact": (disp, gain)}, display_mm=(20.0, 10.0), meta={"bank": "x"}).save(tmp_path / "ok.safetensors")
    back = DisplayLUTMap.load(saved, placement="stretch")
    assert back.display_mm == (20.0, 10.0) and back.placement == "stretch" and back.meta == {"bank": "x"}
    assert torch.equal(back.displacement_exact, disp.float())
