"""Lens pre-warp P_lens: per-channel bilinear warp + gain, radial / LUT / chief-ray / learned maps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.lens import (
    CARDBOARD_RADIAL, LensPrewarp, LUTMap, MLPMap, RadialMap, invert_map, lens_prewarp, pixel_grid,
)
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import RuntimeState

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


def test_channels_are_warped_independently():
    img = torch.rand(3, 10, 10, dtype=torch.float64)
    stage = LensPrewarp.radial(torch.tensor(CARDBOARD_RADIAL) * 2)
    stage.basis = "rgb"  # the paper's per-RGB-channel warp (the default warps the display primaries)
    out = stage(img, STATE, StageContext((10, 10)))
    for c in range(3):
        only = torch.zeros_like(img)
        only[c] = img[c]
        assert torch.allclose(stage(only, STATE, StageContext((10, 10)))[c], out[c])


def _radial_inverse(points: torch.Tensor, k1: float) -> torch.Tensor:
    """Independent inverse of p -> p (1 + k1 |p|^2) on a square image (scalar Newton on the radius)."""
    rho = points.norm(dim=-1, keepdim=True)
    r = rho.clone()
    for _ in range(50):
        r = r - (r + k1 * r**3 - rho) / (1 + 3 * k1 * r**2)
    return torch.where(rho > 0, points * r / rho.clamp(min=1e-300), points)


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


def test_invert_map_round_trip():
    fmap = RadialMap([[0.1], [-0.05], [0.2]])((12, 9), torch.float64, torch.device("cpu"))[0]
    inv = invert_map(fmap, (12, 9))  # same sample grid: F(G(q)) = q exactly at the samples
    ident = pixel_grid((12, 9), torch.float64).expand(3, -1, -1, -1)
    back = torch.nn.functional.grid_sample(  # F at G via bilinear interpolation of F (channels as batch)
        fmap.permute(0, 3, 1, 2), inv, align_corners=False, padding_mode="border"
    ).permute(0, 2, 3, 1)
    inner = (slice(None), slice(1, -1), slice(1, -1))
    assert torch.allclose(back[inner], ident[inner], atol=1e-8)


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
    from controlgs_adapter.downstream.color import primaries_to_rgb, rgb_to_primaries
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
