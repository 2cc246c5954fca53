"""Fidelity of the default pre-warp and display mapping (issue 14, sections 1-2): a perfect render
comes back as itself, dots of every primary land where they were rendered, and a perfect render
gets display scale 1. References are independent: float64 functional re-implementations, the
analytic value 1, and centroids measured on the eye image."""

from __future__ import annotations

import warnings
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F

from controlgs_adapter import plugins
from controlgs_adapter.downstream.color import (linear_to_srgb, primaries_to_rgb_matrix, rgb_to_primaries,
                                                rgb_to_primaries_matrix, srgb_to_linear)
from controlgs_adapter.downstream.display import display_power
from controlgs_adapter.downstream.lens import (BankMap, DisplayLUTMap, LensPrewarp, RadialMap, bank_fingerprint,
                                               lens_prewarp, pixel_grid)
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import RuntimeState

needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")
GEN = torch.Generator().manual_seed(14)
FIELD = [(0.0, 0.0), (0.85, 0.85), (-0.85, -0.85), (0.85, -0.85), (-0.85, 0.0), (0.0, 0.85), (0.5, 0.5)]


# ----------------------------------------------------------------------------- warp in the primaries basis
def _reference_warp(image: torch.Tensor, grid: torch.Tensor, gain: torch.Tensor) -> torch.Tensor:
    """Second implementation: primaries by an explicit matrix product, one grid_sample per primary."""
    to_p, to_rgb = rgb_to_primaries_matrix(), primaries_to_rgb_matrix()
    prim = torch.einsum("ij,jhw->ihw", to_p, image)
    warped = torch.stack([F.grid_sample(prim[c][None, None], grid[c][None], align_corners=False)[0, 0] * gain[c]
                          for c in range(3)])
    return torch.einsum("ij,jhw->ihw", to_rgb, warped)


def test_primaries_basis_equals_a_second_implementation_and_rgb_for_a_common_grid():
    image = torch.rand(3, 9, 11, dtype=torch.float64, generator=GEN)
    grid, _ = RadialMap(((0.1,), (0.12,), (0.14,))).double()((9, 11), torch.float64, "cpu")
    gain = 0.5 + torch.rand(3, 9, 11, dtype=torch.float64, generator=GEN)
    out = lens_prewarp(image, grid, gain, basis="primaries")
    assert torch.allclose(out, _reference_warp(image, grid, gain), atol=1e-12)
    common = grid[:1].expand(3, -1, -1, -1).contiguous()
    assert torch.allclose(lens_prewarp(image, common, basis="primaries"), lens_prewarp(image, common, basis="rgb"), atol=1e-12)
    assert not torch.allclose(out, lens_prewarp(image, grid, gain, basis="rgb"), atol=1e-3)
    with pytest.raises(InputValueError, match="basis"):
        lens_prewarp(image, grid, basis="xyz")
    with pytest.raises(InputValueError, match="basis"):
        LensPrewarp(basis="xyz")


def test_gradcheck_changed_stages():
    image = (0.2 + torch.rand(3, 6, 7, dtype=torch.float64, generator=GEN)).requires_grad_(True)
    grid, _ = RadialMap(((0.1,), (0.12,), (0.14,))).double()((6, 7), torch.float64, "cpu")
    gain = 0.5 + torch.rand(3, 6, 7, dtype=torch.float64, generator=GEN)
    assert torch.autograd.gradcheck(lambda x: lens_prewarp(x, grid, gain, basis="primaries"), (image,))
    lut = DisplayLUTMap({"exact": (0.01 * torch.randn(3, 5, 5, 2, generator=GEN), 1 + 0.1 * torch.rand(3, 5, 5, generator=GEN))})
    stage = LensPrewarp(lut).double()
    assert torch.autograd.gradcheck(lambda x: stage(x, RuntimeState(), StageContext((6, 7))), (image,))
    # the display stage with the ground truth as displayed, through lens and resampling
    gt = torch.rand(3, 8, 8, dtype=torch.float64, generator=GEN)
    x = (0.1 + 0.8 * torch.rand(3, 8, 8, dtype=torch.float64, generator=GEN)).requires_grad_(True)
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True}).double()
    for state in (RuntimeState(2.0, 0.3), RuntimeState(1.0, 0.0)):
        assert torch.autograd.gradcheck(lambda t: pipe(t, state, reference=gt), (x,))


# ----------------------------------------------------------------------------- P_ref on the displayed GT
@pytest.mark.parametrize("d", [1.0, 2.5])
def test_a_perfect_render_gets_display_scale_one_at_every_rho(d):
    gt = torch.rand(3, 20, 20, dtype=torch.float64, generator=GEN)
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True}).double()
    grid, _ = pipe["lens"].map((20, 20), torch.float64, "cpu")
    shown = area_resample(lens_prewarp(srgb_to_linear(gt), grid, basis="primaries"), d)   # float64 functional reference
    for rho in (0.0, 0.2, 0.4, 0.6, 0.8):
        _, inter = pipe.run_recorded(gt, RuntimeState(d, rho), reference=gt)
        diag = inter["diagnostics"]
        assert float(diag["display.scale"]) == pytest.approx(1.0 - rho, abs=1e-12)
        assert float(diag["display.power_ref"]) == pytest.approx(float(display_power(shown)), rel=1e-12)
    old = Pipeline.from_config({"lens": True, "resample": True, "display": {"p_ref": "ground_truth"}}).double()
    _, inter = old.run_recorded(gt, RuntimeState(d, 0.0), reference=gt)
    assert float(inter["diagnostics"]["display.scale"]) > 1.02       # the former rule brightens a perfect render
    with pytest.raises(InputValueError, match="p_ref"):
        Pipeline.from_config({"display": {"p_ref": "gt"}})


def test_active_sees_the_reference():
    pipe = Pipeline.from_config({"resample": True, "display": True})
    gt = torch.rand(3, 8, 8)
    assert pipe.active(RuntimeState()) == []
    assert pipe.active(RuntimeState(), reference=gt) == ["display"]


# ----------------------------------------------------------------------------- dots per primary
def _dot_centroid_errors(pipe: Pipeline, size: tuple[int, int], field=FIELD) -> torch.Tensor:
    """``[dots, 3]`` distance (px) of each primary's eye centroid from the rendered dot's centre."""
    h, w = size
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64) + 0.5, torch.arange(w, dtype=torch.float64) + 0.5,
                            indexing="ij")
    centres = [((u + 1) / 2 * w, (v + 1) / 2 * h) for u, v in field]
    dots = torch.stack([0.5 * torch.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 2).expand(3, h, w) for cx, cy in centres])
    with torch.no_grad():
        prim = rgb_to_primaries(srgb_to_linear(pipe(linear_to_srgb(dots), RuntimeState())))   # [dots, 3, H, W]
    r = max(6, min(h, w) // 8)
    errs = []
    for k, (cx, cy) in enumerate(centres):
        m = prim[k] * (((xx - cx).abs() < r) & ((yy - cy).abs() < r))
        s = m.sum((1, 2))
        errs.append(torch.hypot((m * xx).sum((1, 2)) / s - cx, (m * yy).sum((1, 2)) / s - cy))
    return torch.stack(errs)


@needs_optics
@pytest.mark.parametrize("mode", ["distortion", "exact"])
@pytest.mark.parametrize("size", [(96, 96), (54, 96)])
def test_every_primary_of_a_white_dot_lands_within_a_tenth_of_a_pixel(mode, size):
    pipe = Pipeline.from_config({"lens": True, "optics": {"mode": mode}}).double()
    assert isinstance(pipe["lens"].map, DisplayLUTMap) and pipe["lens"].basis == "primaries"
    field = FIELD if size[0] == size[1] else [(u, v * 0.5) for u, v in FIELD]
    err = _dot_centroid_errors(pipe, size, field)
    assert float(err.max()) < 0.1, err


@needs_optics
def test_the_paper_per_rgb_chief_ray_warp_misses_by_lateral_colour():
    """Sensitivity: the per-RGB warp of the bank's chief rays (the former default) puts the primaries
    of a dot at (0.85, 0.85) apart by more than a pixel at 256 px in exact mode (here at 96 px)."""
    pipe = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": {"mode": "exact"}}).double()
    assert isinstance(pipe["lens"].map, BankMap)
    err = _dot_centroid_errors(pipe, (96, 96), [(0.85, 0.85)])
    assert float(err.max()) > 0.3


# ----------------------------------------------------------------------------- a perfect render comes back
def _patch(x: torch.Tensor, u: float, v: float, r: int) -> torch.Tensor:
    h, w = x.shape[-2:]
    i, j = int((v + 1) / 2 * h), int((u + 1) / 2 * w)
    return x[..., i - r:i + r, j - r:j + r].mean()


@needs_optics
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_ground_truth_through_the_default_pipeline_comes_back_within_three_percent(mode):
    h = 96
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, h, dtype=torch.float64), torch.linspace(-1, 1, h, dtype=torch.float64),
                            indexing="ij")
    smooth = torch.stack([0.5 + 0.2 * torch.cos(2 * xx + yy), 0.45 + 0.2 * torch.sin(xx - 2 * yy), 0.4 + 0.1 * xx * yy])
    pipe = Pipeline.from_config({"lens": True, "resample": True, "display": True, "optics": {"mode": mode}}).double()
    for gt in (torch.full((3, h, h), 0.6, dtype=torch.float64), smooth):
        eye = srgb_to_linear(pipe(gt, RuntimeState(), reference=gt))
        ref = srgb_to_linear(gt)
        for u, v in ((0.0, 0.0), (0.8, 0.8), (-0.8, -0.8), (0.8, -0.8), (-0.8, 0.8)):
            ratio = float(_patch(eye, u, v, 3) / _patch(ref, u, v, 3))
            assert abs(ratio - 1.0) < 0.03, (u, v, ratio)


# ----------------------------------------------------------------------------- the fit, the file, the fallback
@needs_optics
def test_fit_bank_prewarp_places_and_flattens_and_round_trips(tmp_path):
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    optics = PSFOptics(mode="distortion")
    lut = fit_bank_prewarp(optics, 16, modes=("distortion",), pool=1, gain_iterations=3)
    assert lut.meta["bank"] == bank_fingerprint(optics.bank) and lut.meta["residuals"]["distortion"]["flat_max_abs"] < 1e-2
    # the map at the display centre region follows the chief rays (an independent evaluation: BankMap)
    grid, gain = lut((16, 16), torch.float64, "cpu")
    chief, _ = BankMap(optics.bank).double()((16, 16), torch.float64, "cpu")
    inner = (pixel_grid((16, 16), torch.float64).abs() < 0.6).all(-1)
    assert float((grid - chief)[:, inner].abs().max()) * 8 < 0.1       # px at 16 px
    path = lut.save(tmp_path / "lut.safetensors")
    again = LensPrewarp.for_optics(optics, lut=path)
    assert torch.equal(again.map((16, 16), torch.float64, "cpu")[0], grid)
    with pytest.raises(InputValueError, match="radiometry"):
        LensPrewarp.for_optics(PSFOptics(mode="distortion", radiometry="energy"), lut=path)
    other = PSFOptics(replace(optics.bank, chief=optics.bank.chief * 1.001, _cache={}))
    with pytest.raises(InputValueError, match="another PSF bank"):
        LensPrewarp.for_optics(other, lut=path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fallback = LensPrewarp.for_optics(other)
    assert isinstance(fallback.map, BankMap) and any("fit-prewarp" in str(w.message) for w in caught)
    (tmp_path / "bad.safetensors").write_bytes(b"nonsense")
    with pytest.raises(FileFormatError):
        DisplayLUTMap.load(tmp_path / "bad.safetensors")
    with pytest.raises(InputValueError, match="modes"):
        fit_bank_prewarp(optics, 16, modes=("blur",))


@needs_optics
def test_the_lut_follows_the_optics_mode():
    pipe = Pipeline.from_config({"lens": True, "optics": {"mode": "distortion"}})
    lut = pipe["lens"].map
    assert lut.table_mode() == "distortion"
    pipe["optics"].mode = "fast"
    assert lut.table_mode() == "exact"
