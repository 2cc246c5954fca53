"""Tests of ``controlgs_adapter.downstream.lens``."""

from __future__ import annotations

import copy
import math
import warnings
from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers.banks import synthetic_bank
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.downstream import lens
from controlgs_adapter.downstream.color import (
    primaries_to_rgb,
    primaries_to_rgb_matrix,
    rgb_to_primaries,
    rgb_to_primaries_matrix,
)
from controlgs_adapter.downstream.lens import (
    CARDBOARD_RADIAL,
    BankMap,
    DisplayLUTMap,
    LensPrewarp,
    LUTMap,
    MLPMap,
    RadialMap,
    bank_fingerprint,
    lens_prewarp,
    pixel_grid,
)
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import read_header, save_tensors

optics_mod = pytest.importorskip("controlgs_adapter.downstream.optics.stage")


# ----------------------------------------------------------------------------- square: bit-identical
@pytest.mark.parametrize("n", [27, 32])
def test_square_images_are_bit_identical_to_the_stretched_display(n):
    bank = PSFBank.default()
    fit = bank.resample_to(n, n, dtype=torch.float64)
    old = bank.resample_to(n, n, dtype=torch.float64, placement="stretch")
    assert fit is not old
    for name in ("field_index", "field_weight", "splat_index", "splat_weight", "kernels"):
        assert torch.equal(getattr(fit, name), getattr(old, name)), name
    x = torch.rand(3, n, n, dtype=torch.float64, generator=torch.Generator().manual_seed(n))
    for mode in ("distortion", "exact"):
        assert torch.equal(optics_mod.psf_optics(x, bank, mode), optics_mod.psf_optics(x, bank, mode, placement="stretch"))
    a = LensPrewarp.from_psf_bank(bank, (n, n), gain="jacobian").map((n, n), torch.float32, torch.device("cpu"))
    b = LensPrewarp.from_chief_ray_map(bank.chief, (n, n), sample_x=bank.chief_x, sample_y=bank.chief_y,
                                       gain="jacobian").map((n, n), torch.float32, torch.device("cpu"))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_the_analytic_radial_map_uses_the_fit_frame():
    """RadialMap's aspect-corrected radius is the display radius under "fit", computed here in mm:
    pixel (i, j) of a 27 x 48 image sits at ((j + 0.5) 0.5 - 12, (i + 0.5) 0.5 - 6.75) mm."""
    k1 = torch.tensor([c[0] for c in CARDBOARD_RADIAL], dtype=torch.float64)
    for h, w in ((27, 48), (48, 27)):
        grid = LensPrewarp().map((h, w), torch.float64, torch.device("cpu"))[0]        # [3, H, W, 2]
        i, j = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
        x_mm, y_mm = (j + 0.5) * 0.5 - w / 4, (i + 0.5) * 0.5 - h / 4
        r2 = (x_mm ** 2 + y_mm ** 2) / 12.0 ** 2                   # display half-width 12 mm
        p = torch.stack([x_mm / (w / 4), y_mm / (h / 4)], -1)      # image-normalised
        want = p[None] * (1 + k1[:, None, None] * r2)[..., None]
        assert torch.allclose(grid, want, atol=1e-6)


def test_optics_stage_placement_argument():
    assert optics_mod.PSFOptics().placement == "fit"
    with pytest.warns(DeprecationWarning, match="placement"):
        assert optics_mod.PSFOptics(stretch=True).placement == "stretch"
    with pytest.raises(InputValueError, match="placement"):
        optics_mod.PSFOptics(placement="crop")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="size"):
        LensPrewarp.from_psf_bank(None, gain=torch.ones(3, 4, 4))


def test_a_stage_without_a_psf_bank_is_refused_by_name():
    with pytest.raises(InputValueError, match="PSFBank.*Identity.*NoneType"):
        LensPrewarp.for_optics(nn.Identity())


@pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")
def test_the_optics_placement_is_checked_and_followed():
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    optics = PSFOptics(mode="distortion", placement="stretch")
    lens = LensPrewarp.for_optics(optics, source="chief_rays")
    assert isinstance(lens.map, BankMap) and lens.map.placement == "stretch"
    optics.placement = "tile"
    with pytest.raises(InputValueError, match="placement.*'tile'"):
        LensPrewarp.for_optics(optics, source="chief_rays")
    with pytest.raises(InputValueError, match="placement.*'tile'"):
        fit_bank_prewarp(optics, 16, modes=("distortion",))


class _Counter:
    """Counts stage calls through forward pre-hooks (the real stages run)."""

    def __init__(self, pipeline: Pipeline) -> None:
        self.calls: Counter[str] = Counter()
        for s in pipeline.stages:
            s.register_forward_pre_hook(lambda mod, args: self.calls.update([mod.name]))


def test_trainable_lens_runs_in_training_even_at_identity():
    lens = LensPrewarp.learned(hidden=8, layers=1, frequencies=0)
    p = Pipeline([lens])
    counter = _Counter(p)
    image = torch.rand(3, 6, 6)
    p.eval()(image, RuntimeState())
    assert counter.calls["lens"] == 0
    out = p.train()(image, RuntimeState())
    out.sum().backward()
    assert counter.calls["lens"] == 1 and lens.map.mlp[-1].bias.grad is not None


needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


GEN = torch.Generator().manual_seed(14)


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


STATE = RuntimeState()


def _bilinear_reference(img: np.ndarray, gx: float, gy: float) -> float:
    """Brute-force bilinear sample of a [H, W] array at normalised (gx, gy), zeros outside."""
    h, w = img.shape
    u, v = (gx + 1) * w / 2 - 0.5, (gy + 1) * h / 2 - 0.5
    x0, y0 = math.floor(u), math.floor(v)
    total = 0.0
    for yy, wy in ((y0, 1 - (v - y0)), (y0 + 1, v - y0)):
        for xx, wx in ((x0, 1 - (u - x0)), (x0 + 1, u - x0)):
            if 0 <= yy < h and 0 <= xx < w:
                total += wy * wx * img[yy, xx]
    return total


def _radial_inverse(points: torch.Tensor, k1: float) -> torch.Tensor:
    """Independent inverse of p -> p (1 + k1 |p|^2) on a square image (scalar Newton on the radius)."""
    rho = points.norm(dim=-1, keepdim=True)
    r = rho.clone()
    for _ in range(50):
        r = r - (r + k1 * r**3 - rho) / (1 + 3 * k1 * r**2)
    return torch.where(rho > 0, points * r / rho.clamp(min=1e-300), points)


def test_prewarp_matches_brute_force_bilinear():
    g = torch.Generator().manual_seed(0)
    img = torch.rand(2, 3, 5, 7, dtype=torch.float64, generator=g)
    grid = torch.rand(3, 4, 6, 2, dtype=torch.float64, generator=g) * 2.4 - 1.2  # some samples fall outside
    gain = torch.rand(3, 4, 6, dtype=torch.float64, generator=g) + 0.5
    out = lens_prewarp(img, grid, gain)
    assert out.shape == (2, 3, 4, 6)
    for b in range(2):
        for c in range(3):
            for i in range(4):
                for j in range(6):
                    ref = gain[c, i, j].item() * _bilinear_reference(img[b, c].numpy(), *grid[c, i, j].tolist())
                    assert out[b, c, i, j].item() == pytest.approx(ref, abs=1e-12)


def test_supersampling_averages_bilinear_samples_over_each_output_pixels_footprint():
    """``supersample=n``: the mean of ``n x n`` brute-force bilinear samples at ``grid + o_x dx + o_y dy``
    (``dx``, ``dy`` the grid's central differences, one-sided at the border; offsets ``(i + 0.5) / n - 0.5``)."""
    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, 6, 7, dtype=torch.float64, generator=g)
    grid = pixel_grid((4, 5), torch.float64).expand(3, -1, -1, -1) * 1.3 + 0.05 * torch.rand(3, 4, 5, 2, dtype=torch.float64, generator=g)
    out = lens_prewarp(img, grid, supersample=3)
    for c, i, j in ((0, 0, 0), (1, 2, 3), (2, 3, 4), (0, 1, 4)):
        dx = grid[c, i, min(j + 1, 4)] - grid[c, i, max(j - 1, 0)]
        dx = dx / (min(j + 1, 4) - max(j - 1, 0))
        dy = grid[c, min(i + 1, 3), j] - grid[c, max(i - 1, 0), j]
        dy = dy / (min(i + 1, 3) - max(i - 1, 0))
        offs = [(k + 0.5) / 3 - 0.5 for k in range(3)]
        ref = sum(_bilinear_reference(img[c].numpy(), *(grid[c, i, j] + ox * dx + oy * dy).tolist()) for oy in offs for ox in offs) / 9
        assert out[c, i, j].item() == pytest.approx(ref, abs=1e-12)
    assert torch.equal(lens_prewarp(img, grid, supersample=1), lens_prewarp(img, grid))
    row = grid[:, :1]  # one output row: no step along y
    step = torch.gradient(row, dim=2)[0]
    want = (lens_prewarp(img, row - 0.25 * step) + lens_prewarp(img, row + 0.25 * step)) / 2
    assert torch.allclose(lens_prewarp(img, row, supersample=2), want, atol=1e-12)
    for bad in (0, 2.0, True):
        with pytest.raises(InputValueError, match=f"supersample must be an int >= 1, got {bad!r}"):
            lens_prewarp(img, grid, supersample=bad)
        with pytest.raises(InputValueError, match="supersample must be an int >= 1"):
            LensPrewarp(supersample=bad)


def test_the_fitted_lens_averages_two_by_two_samples_per_display_pixel_the_chief_rays_one():
    optics = Pipeline.from_config({"optics": {"mode": "distortion"}})["optics"]
    assert lens.FITTED_SUPERSAMPLE == 2
    assert LensPrewarp.for_optics(optics).supersample == 2
    assert LensPrewarp.for_optics(optics, supersample=1).supersample == 1
    assert LensPrewarp.for_optics(optics, source="chief_rays").supersample == 1
    assert Pipeline.from_config({"lens": True, "optics": {"mode": "distortion"}})["lens"].supersample == 2
    assert Pipeline.from_config({"lens": {"supersample": 3}, "optics": {"mode": "distortion"}})["lens"].supersample == 3
    assert Pipeline.from_config({"lens": True})["lens"].supersample == 1  # no optics: the radial map, one sample


def test_supersampling_removes_the_aliasing_of_a_minifying_warp():
    """Columns alternating 1, 0 shown through a warp that takes 2 image columns per output pixel, every
    grid point on a bright column: one sample per pixel shows a flat 1 (the pattern aliased to its
    bright phase), the footprint average shows the pattern's mean 0.5."""
    img = (torch.arange(64) % 2 == 0).double().expand(3, 4, 64).contiguous()
    grid = pixel_grid((4, 32), torch.float64).expand(3, -1, -1, -1).clone()
    grid[..., 0] = (2 * torch.arange(32, dtype=torch.float64) + 0.5) / 32 - 1  # image x = 2 j + 0.5 px: column 2 j's centre
    point, two, three = (lens_prewarp(img, grid, supersample=n)[:, 1:3, 1:-1] for n in (1, 2, 3))
    assert torch.allclose(point, torch.ones_like(point)) and torch.allclose(two, torch.full_like(two, 0.5))
    assert float((three - 0.5).abs().max()) < 0.06
    assert LensPrewarp(supersample=3).supersample == 3 and "supersample=3" in repr(LensPrewarp(supersample=3))


@settings(max_examples=15, deadline=None)
@given(st.integers(2, 12), st.integers(2, 12), st.sampled_from([torch.float32, torch.float64]))
def test_identity_maps_reproduce_input_and_are_identity(h, w, dtype):
    img = torch.rand(3, h, w, dtype=dtype)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    for stage in (LensPrewarp.radial([[0.0], [0.0], [0.0]]), LensPrewarp.from_lut(pixel_grid((h, w), dtype).expand(3, -1, -1, -1))):
        assert stage.is_identity(STATE)
        assert torch.allclose(stage(img, STATE, StageContext((h, w))), img, atol=tol, rtol=0)


def test_integer_pixel_shift():
    img = torch.rand(1, 3, 6, 8, dtype=torch.float64)
    grid = pixel_grid((6, 8), torch.float64).clone()
    grid[..., 0] += 2 * (2.0 / 8)  # read two pixels to the right
    out = lens_prewarp(img, grid.expand(3, -1, -1, -1))
    assert torch.allclose(out[..., :, :6], img[..., :, 2:], atol=1e-12)
    assert torch.all(out[..., :, 6:] == 0)


def test_channels_are_warped_independently():
    img = torch.rand(3, 10, 10, dtype=torch.float64)
    stage = LensPrewarp.radial(torch.tensor(CARDBOARD_RADIAL) * 2)
    stage.basis = "rgb"  # the paper's per-RGB-channel warp (the default warps the display primaries)
    out = stage(img, STATE, StageContext((10, 10)))
    for c in range(3):
        only = torch.zeros_like(img)
        only[c] = img[c]
        assert torch.allclose(stage(only, STATE, StageContext((10, 10)))[c], out[c])


def test_chief_ray_map_display_to_eye_interpolates_the_bank():
    bank = RadialMap(CARDBOARD_RADIAL)((30, 30), torch.float64, torch.device("cpu"))[0]  # [3, 30, 30, 2]
    stage = LensPrewarp.from_chief_ray_map(bank, (64, 64))
    grid, _ = stage.map((64, 64), torch.float64, torch.device("cpu"))
    exact, _ = RadialMap(CARDBOARD_RADIAL)((64, 64), torch.float64, torch.device("cpu"))
    assert float((grid - exact).abs().max()) < 2e-3  # bilinear interpolation of a smooth map (~0.06 px)


def test_chief_ray_map_eye_to_display_is_inverted():
    k = [c[0] for c in CARDBOARD_RADIAL]
    field = pixel_grid((30, 30), torch.float64)
    bank = torch.stack([_radial_inverse(field, kc) for kc in k])  # eye position -> display position
    stage = LensPrewarp.from_chief_ray_map(bank, (48, 48), direction="eye_to_display")
    grid, _ = stage.map((48, 48), torch.float64, torch.device("cpu"))
    exact, _ = RadialMap(CARDBOARD_RADIAL)((48, 48), torch.float64, torch.device("cpu"))
    covered = exact.abs().amax(-1) < 0.95  # display pixels whose eye position the bank's field grid covers
    assert float((grid - exact)[covered].abs().max()) < 2e-3
    assert float((grid - exact).abs().max()) < 2e-2  # linear extrapolation beyond the bank


def test_prewarp_then_lens_gives_back_the_image():
    """Pre-warp with D, then the lens (eye sees J at D^-1(q)): the eye image is the rendered one."""
    n, k1 = 64, 0.08
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n, dtype=torch.float64), torch.linspace(-1, 1, n, dtype=torch.float64), indexing="ij")
    smooth = torch.stack([torch.cos(2 * xx + yy), torch.sin(3 * yy) * 0.5 + 0.5, xx * yy * 0.5 + 0.5])
    prewarped = LensPrewarp.radial([[k1]] * 3)(smooth, STATE, StageContext((n, n)))
    lens_grid = _radial_inverse(pixel_grid((n, n), torch.float64), k1).expand(3, -1, -1, -1)
    eye = lens_prewarp(prewarped, lens_grid.contiguous())
    centre = (slice(None), slice(8, -8), slice(8, -8))
    assert float((eye - smooth)[centre].abs().max()) < 5e-3
    assert float((prewarped - smooth)[centre].abs().max()) > 5e-2  # the warp itself is not small


def test_lut_resizes_smoothly():
    small = LensPrewarp.radial(CARDBOARD_RADIAL).bake((24, 24))
    grid, gain = small.map((48, 48), torch.float64, torch.device("cpu"))
    exact, _ = RadialMap(CARDBOARD_RADIAL)((48, 48), torch.float64, torch.device("cpu"))
    assert float((grid - exact).abs().max()) < 5e-3
    assert torch.allclose(gain, torch.ones_like(gain))


def test_learned_map_identity_at_init_trains_and_bakes():
    torch.manual_seed(0)
    stage = LensPrewarp.learned(hidden=32, layers=2, frequencies=2)
    img = torch.rand(3, 16, 16)
    ctx = StageContext((16, 16))
    stage.eval()
    assert stage.is_identity(STATE)
    stage.train()
    assert not stage.is_identity(STATE)  # trainable: never skipped in training
    assert torch.allclose(stage(img, STATE, ctx), img, atol=1e-6)
    target = LensPrewarp.radial([[0.15], [0.1], [0.05]])(img, STATE, ctx)
    opt = torch.optim.Adam(stage.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        opt.zero_grad()
        loss = (stage(img, STATE, ctx) - target).abs().mean()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]
    baked = stage.bake((16, 16)).eval()
    assert isinstance(baked.map, LUTMap) and not baked.is_identity(STATE)
    with torch.no_grad():
        assert torch.allclose(baked(img, STATE, ctx), stage(img, STATE, ctx), atol=1e-5)


def test_gradcheck_prewarp():
    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, 4, 5, dtype=torch.float64, generator=g, requires_grad=True)
    grid = (torch.rand(3, 3, 4, 2, dtype=torch.float64, generator=g) * 1.6 - 0.8).requires_grad_(True)
    gain = (torch.rand(3, 3, 4, dtype=torch.float64, generator=g) + 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(lens_prewarp, (img, grid, gain))
    k = torch.tensor([[0.1], [0.05], [-0.1]], dtype=torch.float64, requires_grad=True)

    m = RadialMap(k.detach(), learnable=True).double()

    def radial(image: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        grid_, _ = torch.func.functional_call(m, {"coefficients": coeffs}, ((4, 5), torch.float64, torch.device("cpu")))
        return lens_prewarp(image, grid_)

    assert torch.autograd.gradcheck(radial, (img, k))
    learned = LensPrewarp.learned(hidden=4, layers=1, frequencies=1).double()
    bias = (torch.rand(9, dtype=torch.float64, generator=g) * 0.1).requires_grad_(True)

    def mlp_warp(image: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(learned, {"map.mlp.2.bias": b}, (image, STATE, StageContext((4, 5))))

    assert torch.autograd.gradcheck(mlp_warp, (img, bias))


def test_bad_input_names_the_argument():
    img = torch.rand(3, 4, 4)
    with pytest.raises(ShapeError, match="grid"):
        lens_prewarp(img, torch.zeros(3, 4, 4, 3))
    with pytest.raises(InputValueError, match="grid"):
        lens_prewarp(img, torch.zeros(3, 4, 4, 2, dtype=torch.float64))
    with pytest.raises(ShapeError, match="gain"):
        lens_prewarp(img, torch.zeros(3, 4, 4, 2), torch.ones(3, 4, 5))
    with pytest.raises(ShapeError, match="image"):
        lens_prewarp(torch.rand(4, 4, 4), torch.zeros(3, 4, 4, 2))
    with pytest.raises(ShapeError, match="coefficients"):
        RadialMap([[0.1], [0.1]])
    with pytest.raises(ShapeError, match="chief_ray_map"):
        LensPrewarp.from_chief_ray_map(torch.zeros(3, 1, 5, 2), (4, 4))
    with pytest.raises(InputValueError, match="direction"):
        LensPrewarp.from_chief_ray_map(torch.zeros(3, 4, 4, 2), (4, 4), direction="sideways")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="hidden"):
        MLPMap(hidden=0)


def test_bank_prewarp_undoes_the_optics_distortion():
    """Pre-warp from the shipped bank's chief rays, with the area-magnification gain, then the
    optics stage's chief-ray warp: the eye sees the intended primaries (away from the border)."""
    optics_stage = pytest.importorskip("controlgs_adapter.downstream.optics.stage")
    from controlgs_adapter.downstream.optics.bank import PSFBank

    n = 64
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    img = torch.stack([torch.cos(3 * xx + yy) * 0.2 + 0.3, torch.sin(2 * yy) * 0.2 + 0.3, xx * yy * 0.2 + 0.3])
    bank = PSFBank.default()
    prewarp = LensPrewarp.from_chief_ray_map(bank.chief, (n, n), sample_x=bank.chief_x, sample_y=bank.chief_y, gain="jacobian")
    prewarp.basis = "rgb"  # applied to primaries below
    assert torch.allclose(LensPrewarp.from_psf_bank(bank, (n, n), gain="jacobian").map.gain, prewarp.map.gain)
    target = rgb_to_primaries(img)  # the optics is separable per primary: warp in that domain
    shown = primaries_to_rgb(prewarp(target, STATE, StageContext((n, n))))
    # the Jacobian gain undoes the energy-conserving form's 1 / area magnification
    eye = rgb_to_primaries(optics_stage.psf_optics(shown, bank, mode="distortion", radiometry="energy"))
    plain = rgb_to_primaries(optics_stage.psf_optics(img, bank, mode="distortion", radiometry="energy"))
    centre = (slice(None), slice(8, -8), slice(8, -8))
    assert float((eye - target)[centre].abs().max()) < 0.01
    assert float((plain - target)[centre].abs().max()) > 0.1


def test_jacobian_gain_of_a_radial_map_and_sample_coordinates():
    k1 = 0.1
    bank = RadialMap([[k1]] * 3)((33, 33), torch.float64, torch.device("cpu"))[0]  # samples at cell centres
    stage = LensPrewarp.from_chief_ray_map(bank, (40, 40), gain="jacobian")
    r2 = (pixel_grid((40, 40), torch.float64) ** 2).sum(-1)
    f = 1 + k1 * r2
    analytic = f * (f + 2 * k1 * r2)  # det d[p f(r)]/dp = f (f + r f'(r))
    inner = (slice(None), slice(1, -1), slice(1, -1))
    assert torch.allclose(stage.map.gain.double()[inner], analytic.expand(3, -1, -1)[inner], rtol=5e-3, atol=2e-3)
    # the same map given on a grid that includes the edges (-1 .. 1), as PSF banks store chief rays
    edges = torch.linspace(-1, 1, 33, dtype=torch.float64)
    yy, xx = torch.meshgrid(edges, edges, indexing="ij")
    p = torch.stack([xx, yy], -1)
    bank_edges = (p * (1 + k1 * (p**2).sum(-1, keepdim=True))).expand(3, -1, -1, -1)
    other = LensPrewarp.from_chief_ray_map(bank_edges, (40, 40), sample_x=edges, sample_y=edges)
    assert torch.allclose(other.map.displacement, stage.map.displacement, atol=2e-3)
    with pytest.raises(InputValueError, match="sample_x"):
        LensPrewarp.from_chief_ray_map(bank_edges, (8, 8), sample_x=edges.flip(0), sample_y=edges)
    with pytest.raises(InputValueError, match="gain"):
        LensPrewarp.from_chief_ray_map(bank_edges, (8, 8), sample_x=edges, sample_y=edges, gain="area")  # type: ignore[arg-type]


def test_lut_file_round_trip(tmp_path):
    learned = LensPrewarp.learned(hidden=8, layers=1, frequencies=1)
    with torch.no_grad():
        learned.map.mlp[-1].bias.copy_(torch.linspace(-0.05, 0.05, 9))
    path = learned.save_lut(tmp_path / "prewarp.safetensors", (12, 10))
    loaded = LensPrewarp.load_lut(path)
    img = torch.rand(3, 12, 10)
    with torch.no_grad():
        assert torch.allclose(loaded(img, STATE, StageContext((12, 10))), learned(img, STATE, StageContext((12, 10))), atol=1e-5)
    again = loaded.save_lut(tmp_path / "again.safetensors")
    assert torch.equal(LensPrewarp.load_lut(again).map.displacement, loaded.map.displacement)
    with pytest.raises(InputValueError, match="size"):
        LensPrewarp().save_lut(tmp_path / "x.safetensors")
    from controlgs_adapter.errors import FileFormatError
    from controlgs_adapter.formats.safetensors import save_tensors

    other = save_tensors(tmp_path / "other.safetensors", {"x": torch.zeros(1)}, {}, kind="something-else", format_version=1)
    with pytest.raises(FileFormatError, match="expected a 'controlgs-prewarp-lut'"):
        LensPrewarp.load_lut(other)


D64 = torch.float64


class _Optics(torch.nn.Module):
    def __init__(self, bank: PSFBank, radiometry: str) -> None:
        super().__init__()
        self.bank, self.radiometry, self.mode, self.placement = bank, radiometry, "exact", "fit"


@pytest.mark.parametrize("basis", ["rgb", "primaries"])
def test_for_optics_passes_basis_on_every_path(basis, tmp_path):
    bank = PSFBank.default()
    optics = _Optics(bank, "no-such-radiometry")  # no shipped LUT for it: the chief-ray fallback
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        fallback = LensPrewarp.for_optics(optics, basis=basis)
    assert isinstance(fallback.map, BankMap) and fallback.basis == basis
    chief = LensPrewarp.for_optics(optics, source="chief_rays", basis=basis)
    assert isinstance(chief.map, BankMap) and chief.basis == basis
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        default = LensPrewarp.for_optics(optics)
    assert default.basis == "primaries"  # the documented default
    # a fitted LUT file: the same basis
    from controlgs_adapter.downstream.lens import DisplayLUTMap, bank_fingerprint, pixel_grid

    disp = 0.01 * pixel_grid((5, 4), D64).expand(3, -1, -1, -1).clone()
    gain = torch.ones(3, 5, 4, dtype=D64)
    lut = DisplayLUTMap({"exact": (disp, gain)}, meta={"bank": bank_fingerprint(bank), "radiometry": "no-such-radiometry"}
                        ).save(tmp_path / "fit.safetensors")
    fitted = LensPrewarp.for_optics(optics, lut=lut, basis=basis)
    assert isinstance(fitted.map, DisplayLUTMap) and fitted.basis == basis
    assert LensPrewarp.for_optics(optics, lut=lut).basis == "primaries"
    with pytest.raises(InputValueError, match="basis must be one of .* got 'srgb'"):
        LensPrewarp.for_optics(optics, source="chief_rays", basis="srgb")  # type: ignore[arg-type]


D = torch.float64


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


def _display_tables(hd: int = 5, wd: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A display table whose displacement is ``M_c q + t_c`` at display point ``q`` (exact under
    bilinear interpolation) and gain ``1 + 0.1 c``: ``(displacement, gain, M)``."""
    m = torch.tensor([[0.10, -0.05], [0.02, 0.08], [-0.06, 0.04]], dtype=torch.float64)  # diagonal of M_c
    t = torch.tensor([[0.01, 0.02], [-0.03, 0.0], [0.0, -0.01]], dtype=torch.float64)
    q = pixel_grid((hd, wd), torch.float64)
    disp = m[:, None, None, :] * q + t[:, None, None, :]
    gain = (1.0 + 0.1 * torch.arange(3, dtype=torch.float64))[:, None, None].expand(3, hd, wd).clone()
    return disp, gain, torch.cat([m, t], 1)


def test_lens_prewarp_and_bank_map_refusals(tmp_path):
    from controlgs_adapter.downstream.lens import BankMap, lens_prewarp
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.errors import FileFormatError
    from controlgs_adapter.formats.safetensors import save_tensors

    img = torch.rand(3, 4, 4)
    with pytest.raises(InputValueError, match="basis must be one of .*'xyz'"):
        lens_prewarp(img, pixel_grid((4, 4)).expand(3, -1, -1, -1).contiguous(), basis="xyz")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="basis must be one of .*'xyz'"):
        LensPrewarp(basis="xyz")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="either prewarp_map or coefficients, not both"):
        LensPrewarp(MLPMap(), coefficients=[[0.1]] * 3)
    two = synthetic_bank(L=2)
    with pytest.raises(InputValueError, match="bank must have 3 wavelengths .*600.0, 500.0"):
        BankMap(two)
    with pytest.raises(InputValueError, match="bank must have 3 wavelengths"):
        LensPrewarp.from_psf_bank(two, (4, 4))
    bank = PSFBank.default()
    with pytest.raises(InputValueError, match="placement must be one of .*'centre'"):
        BankMap(bank, "centre")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain must be 'jacobian' or None, got 'area'"):
        BankMap(bank, gain="area")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="a gain tensor needs a LUT size"):
        LensPrewarp.from_psf_bank(bank, gain=torch.ones(3, 4, 4))
    with pytest.raises(InputValueError, match="optics must be an optics stage with a PSFBank .*Identity"):
        LensPrewarp.for_optics(torch.nn.Identity())

    class _Optics(torch.nn.Module):
        def __init__(self, placement: str = "fit") -> None:
            super().__init__()
            self.bank, self.placement = bank, placement

    with pytest.raises(InputValueError, match="source must be 'fitted' or 'chief_rays', got 'traced'"):
        LensPrewarp.for_optics(_Optics(), source="traced")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain applies to source='chief_rays'"):
        LensPrewarp.for_optics(_Optics(), gain="jacobian")
    with pytest.raises(InputValueError, match="optics.placement must be one of .*'crop'"):
        LensPrewarp.for_optics(_Optics("crop"), source="chief_rays")
    chief = LensPrewarp.for_optics(_Optics("stretch"), source="chief_rays", gain="jacobian", basis="rgb")
    assert isinstance(chief.map, BankMap) and (chief.map.placement, chief.map.gain, chief.basis) == ("stretch", "jacobian", "rgb")
    no_gain = save_tensors(tmp_path / "lut.safetensors", {"grid": torch.zeros(3, 2, 2, 2)}, {},
                           kind="controlgs-prewarp-lut", format_version=1)
    with pytest.raises(FileFormatError, match=r"lut.safetensors: pre-warp LUT lacks \['gain'\]"):
        LensPrewarp.load_lut(no_gain)


def test_learnable_radial_lens_is_skipped_only_outside_training():
    stage = LensPrewarp.radial([[0.0]] * 3, learnable=True)
    assert not stage.train().is_identity(RuntimeState())  # trainable: runs so that it gets gradients
    assert stage.eval().is_identity(RuntimeState())
    stage.map.coefficients.requires_grad_(False)
    assert stage.train().is_identity(RuntimeState())


def test_for_optics_checks_a_fitted_lut_and_falls_back_to_chief_rays(tmp_path):
    from controlgs_adapter.downstream.lens import BankMap
    from controlgs_adapter.downstream.optics.bank import PSFBank

    bank = PSFBank.default()

    class _Optics(torch.nn.Module):
        def __init__(self, bank_: PSFBank, radiometry: str, mode: str = "exact") -> None:
            super().__init__()
            self.bank, self.radiometry, self.mode, self.placement = bank_, radiometry, mode, "fit"

    disp, gain, _ = _display_tables()
    fp = bank_fingerprint(bank)
    lut = DisplayLUTMap({"distortion": (disp, gain), "exact": (disp * 2, gain)},
                        meta={"bank": fp, "radiometry": "energy"}).save(tmp_path / "fit.safetensors")
    with pytest.raises(InputValueError, match="fit.safetensors: this pre-warp LUT was fitted for radiometry 'energy'"):
        LensPrewarp.for_optics(_Optics(bank, "radiance"), lut=lut)
    optics = _Optics(bank, "energy", mode="distortion")
    stage = LensPrewarp.for_optics(optics, lut=lut)
    assert isinstance(stage.map, DisplayLUTMap) and stage.map.table_mode() == "distortion"
    optics.mode = "fast"
    assert stage.map.table_mode() == "exact"  # follows the optics' current mode
    other = copy.copy(bank)
    other._cache, other.chief = {}, bank.chief * 1.001  # own cache: the default bank is process-wide
    with pytest.raises(InputValueError, match=f"another PSF bank .*{fp}"):
        LensPrewarp.for_optics(_Optics(other, "energy"), lut=lut)
    for radiometry, fallback in (("energy", "jacobian"), ("radiance", None)):
        with pytest.warns(UserWarning, match=f"no fitted pre-warp LUT for this PSF bank and radiometry '{radiometry}'"):
            chief = LensPrewarp.for_optics(_Optics(other, radiometry))
        assert isinstance(chief.map, BankMap) and chief.map.gain == fallback and chief.map.bank is other
