"""Tests of ``controlgs_adapter.downstream.lens``: the lens pre-warp stage and ``lens_prewarp``. The warp
against brute-force bilinear sampling and whole-pixel shifts in both colour bases, supersampled over each
pixel's footprint; its gradients; the
constructors (radial, LUT, learned, from chief rays and from a PSF bank, for an optics stage) checked
against closed forms and the optics they compensate; LUT files; training-mode skipping; refusals by name.
The stage contract (shapes, dtypes, devices, twin) is checked in ``test_stage_contract.py``."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from helpers.banks import synthetic_bank
from helpers.prewarp_tables import display_tables
from helpers.stage_contract import StageCalls
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import RuntimeState
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
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import read_header, save_tensors

D = torch.float64
CPU = torch.device("cpu")
STATE = RuntimeState()
GEN = torch.Generator().manual_seed(14)


# ----------------------------------------------------------------------------- the warp
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
    img = torch.rand(2, 3, 5, 7, dtype=D, generator=g)
    grid = torch.rand(3, 4, 6, 2, dtype=D, generator=g) * 2.4 - 1.2  # some samples fall outside
    gain = torch.rand(3, 4, 6, dtype=D, generator=g) + 0.5
    out = lens_prewarp(img, grid, gain)
    assert out.shape == (2, 3, 4, 6)
    for b in range(2):
        for c in range(3):
            for i in range(4):
                for j in range(6):
                    ref = gain[c, i, j].item() * _bilinear_reference(img[b, c].numpy(), *grid[c, i, j].tolist())
                    assert out[b, c, i, j].item() == pytest.approx(ref, abs=1e-12)


def test_warp_shifts_each_channel_or_each_primary():
    """Whole-pixel shifts, a different one per channel (zero fill), against slicing: in the RGB basis each
    channel is shifted alone; in the primaries basis each display primary is (converted there and back).
    With a radial grid and a gain, the primaries basis equals a second implementation (explicit matrices,
    one grid_sample per primary); with one grid for all channels both bases agree, with per-channel grids
    they do not."""
    h, w = 5, 6
    img = torch.rand(2, 3, h, w, dtype=D, generator=torch.Generator().manual_seed(7))
    shifts = [(1, 0), (0, -2), (-1, 1)]  # (dy, dx) pixels sampled from: out[y, x] = in[y + dy, x + dx]
    base = pixel_grid((h, w), D)
    grid = torch.stack([base + torch.tensor([2.0 * dx / w, 2.0 * dy / h], dtype=D) for dy, dx in shifts])
    gain = torch.tensor([1.0, 0.5, 2.0], dtype=D)[:, None, None].expand(3, h, w).contiguous()

    def shifted(x: torch.Tensor) -> torch.Tensor:
        out = torch.zeros_like(x)
        for c, (dy, dx) in enumerate(shifts):
            src = F.pad(x[:, c], (2, 2, 2, 2))
            out[:, c] = src[:, 2 + dy:2 + dy + h, 2 + dx:2 + dx + w] * gain[c, 0, 0]
        return out

    assert torch.allclose(lens_prewarp(img, grid, gain, basis="rgb"), shifted(img), atol=1e-12)
    want = primaries_to_rgb(shifted(rgb_to_primaries(img)))
    assert torch.allclose(lens_prewarp(img, grid, gain, basis="primaries"), want, atol=1e-12)
    assert not torch.allclose(want, shifted(img), atol=1e-3)

    image = torch.rand(3, 9, 11, dtype=D, generator=GEN)
    radial, _ = RadialMap(((0.1,), (0.12,), (0.14,))).double()((9, 11), D, CPU)
    gain = 0.5 + torch.rand(3, 9, 11, dtype=D, generator=GEN)
    to_p, to_rgb = rgb_to_primaries_matrix(), primaries_to_rgb_matrix()
    prim = torch.einsum("ij,jhw->ihw", to_p, image)
    warped = torch.stack([F.grid_sample(prim[c][None, None], radial[c][None], align_corners=False)[0, 0] * gain[c]
                          for c in range(3)])
    out = lens_prewarp(image, radial, gain, basis="primaries")
    assert torch.allclose(out, torch.einsum("ij,jhw->ihw", to_rgb, warped), atol=1e-12)
    common = radial[:1].expand(3, -1, -1, -1).contiguous()
    assert torch.allclose(lens_prewarp(image, common, basis="primaries"), lens_prewarp(image, common, basis="rgb"), atol=1e-12)
    assert not torch.allclose(out, lens_prewarp(image, radial, gain, basis="rgb"), atol=1e-3)


def test_supersampling_averages_bilinear_samples_over_each_output_pixels_footprint():
    """``supersample=n``: the mean of ``n x n`` brute-force bilinear samples at ``grid + o_x dx + o_y dy``
    (``dx``, ``dy`` the grid's central differences, one-sided at the border; offsets ``(i + 0.5) / n - 0.5``);
    one sample is the plain warp; anything but an int >= 1 is refused naming it."""
    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, 6, 7, dtype=D, generator=g)
    grid = pixel_grid((4, 5), D).expand(3, -1, -1, -1) * 1.3 + 0.05 * torch.rand(3, 4, 5, 2, dtype=D, generator=g)
    out = lens_prewarp(img, grid, supersample=3)
    offs = [(k + 0.5) / 3 - 0.5 for k in range(3)]
    for c, i, j in ((0, 0, 0), (1, 2, 3), (2, 3, 4), (0, 1, 4)):
        dx = (grid[c, i, min(j + 1, 4)] - grid[c, i, max(j - 1, 0)]) / (min(j + 1, 4) - max(j - 1, 0))
        dy = (grid[c, min(i + 1, 3), j] - grid[c, max(i - 1, 0), j]) / (min(i + 1, 3) - max(i - 1, 0))
        ref = sum(_bilinear_reference(img[c].numpy(), *(grid[c, i, j] + ox * dx + oy * dy).tolist())
                  for oy in offs for ox in offs) / 9
        assert out[c, i, j].item() == pytest.approx(ref, abs=1e-12)
    assert torch.equal(lens_prewarp(img, grid, supersample=1), lens_prewarp(img, grid))
    row = grid[:, :1]  # one output row: no step along y
    step = torch.gradient(row, dim=2)[0]
    want = (lens_prewarp(img, row - 0.25 * step) + lens_prewarp(img, row + 0.25 * step)) / 2
    assert torch.allclose(lens_prewarp(img, row, supersample=2), want, atol=1e-12)
    for bad in (0, 2.0, True):
        with pytest.raises(InputValueError, match=f"supersample must be an int >= 1, got {bad!r}"):
            lens_prewarp(img, grid, supersample=bad)
        with pytest.raises(InputValueError, match=f"supersample must be an int >= 1, got {bad!r}"):
            LensPrewarp(supersample=bad)


def test_supersampling_removes_the_aliasing_of_a_minifying_warp():
    """Columns alternating 1, 0 shown through a warp that takes 2 image columns per output pixel, every
    grid point on a bright column: one sample per pixel shows a flat 1 (the pattern aliased to its
    bright phase), the footprint average shows the pattern's mean 0.5 (2 x 2 exactly, 3 x 3 within 0.06)."""
    img = (torch.arange(64) % 2 == 0).double().expand(3, 4, 64).contiguous()
    grid = pixel_grid((4, 32), D).expand(3, -1, -1, -1).clone()
    grid[..., 0] = (2 * torch.arange(32, dtype=D) + 0.5) / 32 - 1  # image x = 2 j + 0.5 px: column 2 j's centre
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


def test_gradcheck_prewarp():
    """Gradients with respect to the image, the grid and the gain; to radial coefficients through the map;
    to a learned map's bias through the stage."""
    g = torch.Generator().manual_seed(1)
    img = torch.rand(3, 4, 5, dtype=D, generator=g, requires_grad=True)
    grid = (torch.rand(3, 3, 4, 2, dtype=D, generator=g) * 1.6 - 0.8).requires_grad_(True)
    gain = (torch.rand(3, 3, 4, dtype=D, generator=g) + 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(lens_prewarp, (img, grid, gain))
    k = torch.tensor([[0.1], [0.05], [-0.1]], dtype=D, requires_grad=True)
    m = RadialMap(k.detach(), learnable=True).double()

    def radial(image: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
        grid_, _ = torch.func.functional_call(m, {"coefficients": coeffs}, ((4, 5), D, CPU))
        return lens_prewarp(image, grid_)

    assert torch.autograd.gradcheck(radial, (img, k))
    learned = LensPrewarp.learned(hidden=4, layers=1, frequencies=1).double()
    bias = (torch.rand(9, dtype=D, generator=g) * 0.1).requires_grad_(True)

    def mlp_warp(image: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.func.functional_call(learned, {"map.mlp.2.bias": b}, (image, STATE, StageContext((4, 5))))

    assert torch.autograd.gradcheck(mlp_warp, (img, bias))


def test_lens_prewarp_refuses_bad_inputs_by_name():
    img = torch.rand(3, 4, 4)
    ident = pixel_grid((4, 4)).expand(3, -1, -1, -1).contiguous()
    with pytest.raises(ShapeError, match="grid"):
        lens_prewarp(img, torch.zeros(3, 4, 4, 3))
    with pytest.raises(InputValueError, match="grid must have dtype"):
        lens_prewarp(img, torch.zeros(3, 4, 4, 2, dtype=D))
    with pytest.raises(ShapeError, match="gain"):
        lens_prewarp(img, torch.zeros(3, 4, 4, 2), torch.ones(3, 4, 5))
    with pytest.raises(InputValueError, match="gain="):
        lens_prewarp(img, ident, torch.ones(3, 4, 4, device="meta"))
    with pytest.raises(InputValueError, match="grid="):
        lens_prewarp(img, torch.zeros(3, 4, 4, 2, device="meta"))
    with pytest.raises(ShapeError, match="image"):
        lens_prewarp(torch.rand(4, 4, 4), torch.zeros(3, 4, 4, 2))
    with pytest.raises(InputValueError, match="basis must be one of .*'xyz'"):
        lens_prewarp(img, ident, basis="xyz")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- the stage and its constructors
def test_constructors_and_defaults():
    """The default lens is the Cardboard radial map warping the display primaries; ``radial`` gives fixed or
    learnable coefficients; a map and coefficients together, or an unknown basis, are refused; baking keeps
    the basis; a lens on the CPU warps an image on another device there."""
    fixed = LensPrewarp.radial([[0.1], [0.1], [0.1]])
    assert isinstance(fixed.map, RadialMap) and not fixed.map.coefficients.requires_grad
    assert fixed.basis == "primaries" and LensPrewarp().basis == "primaries"
    assert LensPrewarp.radial([[0.1], [0.1], [0.1]], learnable=True).map.coefficients.requires_grad
    assert LensPrewarp(coefficients=[[0.2], [0.2], [0.2]]).map.coefficients.flatten().tolist() == pytest.approx([0.2] * 3)
    for prewarp_map in (RadialMap(), MLPMap()):
        with pytest.raises(InputValueError, match="prewarp_map or coefficients"):
            LensPrewarp(prewarp_map, coefficients=[[0.1]] * 3)
    with pytest.raises(InputValueError, match="basis must be one of .*'xyz'"):
        LensPrewarp(basis="xyz")  # type: ignore[arg-type]
    assert LensPrewarp(basis="rgb").bake((4, 4)).basis == "rgb"
    assert LensPrewarp().bake((4, 4)).basis == "primaries"
    assert LensPrewarp(basis="rgb")(torch.ones(3, 4, 4, device="meta")).device.type == "meta"   # made on the image's device


def test_a_trainable_lens_is_skipped_only_outside_training():
    """A lens with trainable parameters runs in training mode even while it is the identity (so that it gets
    gradients): the pipeline calls it and the gradient reaches the map; in eval mode, or once its parameters
    are frozen, the identity is skipped."""
    learned = LensPrewarp.learned(hidden=8, layers=1, frequencies=0)
    p = Pipeline([learned])
    counter = StageCalls(p)
    image = torch.rand(3, 6, 6)
    p.eval()(image, STATE)
    assert counter.calls["lens"] == 0
    p.train()(image, STATE).sum().backward()
    assert counter.calls["lens"] == 1 and learned.map.mlp[-1].bias.grad is not None
    radial = LensPrewarp.radial([[0.0]] * 3, learnable=True)
    assert not radial.train().is_identity(STATE)
    assert radial.eval().is_identity(STATE)
    radial.map.coefficients.requires_grad_(False)
    assert radial.train().is_identity(STATE)


def test_learned_map_starts_at_the_identity_trains_and_bakes():
    torch.manual_seed(0)
    stage = LensPrewarp.learned(hidden=32, layers=2, frequencies=2).train()
    img = torch.rand(3, 16, 16)
    ctx = StageContext((16, 16))
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


def test_lut_resizes_smoothly():
    small = LensPrewarp.radial(CARDBOARD_RADIAL).bake((24, 24))
    grid, gain = small.map((48, 48), D, CPU)
    exact, _ = RadialMap(CARDBOARD_RADIAL)((48, 48), D, CPU)
    assert float((grid - exact).abs().max()) < 5e-3
    assert torch.allclose(gain, torch.ones_like(gain))


# ----------------------------------------------------------------------------- from chief rays
def _radial_inverse(points: torch.Tensor, k1: float) -> torch.Tensor:
    """Independent inverse of p -> p (1 + k1 |p|^2) on a square image (scalar Newton on the radius)."""
    rho = points.norm(dim=-1, keepdim=True)
    r = rho.clone()
    for _ in range(50):
        r = r - (r + k1 * r**3 - rho) / (1 + 3 * k1 * r**2)
    return torch.where(rho > 0, points * r / rho.clamp(min=1e-300), points)


def test_chief_ray_map_display_to_eye_interpolates_the_bank():
    bank = RadialMap(CARDBOARD_RADIAL)((30, 30), D, CPU)[0]  # [3, 30, 30, 2]
    grid, _ = LensPrewarp.from_chief_ray_map(bank, (64, 64)).map((64, 64), D, CPU)
    exact, _ = RadialMap(CARDBOARD_RADIAL)((64, 64), D, CPU)
    assert float((grid - exact).abs().max()) < 2e-3  # bilinear interpolation of a smooth map (~0.06 px)


def test_chief_ray_map_eye_to_display_is_inverted():
    k = [c[0] for c in CARDBOARD_RADIAL]
    field = pixel_grid((30, 30), D)
    bank = torch.stack([_radial_inverse(field, kc) for kc in k])  # eye position -> display position
    grid, _ = LensPrewarp.from_chief_ray_map(bank, (48, 48), direction="eye_to_display").map((48, 48), D, CPU)
    exact, _ = RadialMap(CARDBOARD_RADIAL)((48, 48), D, CPU)
    covered = exact.abs().amax(-1) < 0.95  # display pixels whose eye position the bank's field grid covers
    assert float((grid - exact)[covered].abs().max()) < 2e-3
    assert float((grid - exact).abs().max()) < 2e-2  # linear extrapolation beyond the bank


def test_prewarp_then_lens_gives_back_the_image():
    """Pre-warp with D, then the lens (eye sees J at D^-1(q)): the eye image is the rendered one."""
    n, k1 = 64, 0.08
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n, dtype=D), torch.linspace(-1, 1, n, dtype=D), indexing="ij")
    smooth = torch.stack([torch.cos(2 * xx + yy), torch.sin(3 * yy) * 0.5 + 0.5, xx * yy * 0.5 + 0.5])
    prewarped = LensPrewarp.radial([[k1]] * 3)(smooth, STATE, StageContext((n, n)))
    lens_grid = _radial_inverse(pixel_grid((n, n), D), k1).expand(3, -1, -1, -1)
    eye = lens_prewarp(prewarped, lens_grid.contiguous())
    centre = (slice(None), slice(8, -8), slice(8, -8))
    assert float((eye - smooth)[centre].abs().max()) < 5e-3
    assert float((prewarped - smooth)[centre].abs().max()) > 5e-2  # the warp itself is not small


def test_jacobian_gain_of_a_radial_map_and_sample_coordinates():
    """The Jacobian gain is the map's area magnification f (f + r f'(r)) for p f(r); the same map given on
    samples that include the edges (as PSF banks store chief rays) gives the same table; non-increasing
    samples and an unknown gain are refused."""
    k1 = 0.1
    bank = RadialMap([[k1]] * 3)((33, 33), D, CPU)[0]  # samples at cell centres
    stage = LensPrewarp.from_chief_ray_map(bank, (40, 40), gain="jacobian")
    r2 = (pixel_grid((40, 40), D) ** 2).sum(-1)
    f = 1 + k1 * r2
    analytic = f * (f + 2 * k1 * r2)  # det d[p f(r)]/dp = f (f + r f'(r))
    inner = (slice(None), slice(1, -1), slice(1, -1))
    assert torch.allclose(stage.map.gain.double()[inner], analytic.expand(3, -1, -1)[inner], rtol=5e-3, atol=2e-3)
    edges = torch.linspace(-1, 1, 33, dtype=D)
    yy, xx = torch.meshgrid(edges, edges, indexing="ij")
    p = torch.stack([xx, yy], -1)
    bank_edges = (p * (1 + k1 * (p**2).sum(-1, keepdim=True))).expand(3, -1, -1, -1)
    other = LensPrewarp.from_chief_ray_map(bank_edges, (40, 40), sample_x=edges, sample_y=edges)
    assert torch.allclose(other.map.displacement, stage.map.displacement, atol=2e-3)
    with pytest.raises(InputValueError, match="sample_x"):
        LensPrewarp.from_chief_ray_map(bank_edges, (8, 8), sample_x=edges.flip(0), sample_y=edges)
    with pytest.raises(InputValueError, match="gain"):
        LensPrewarp.from_chief_ray_map(bank_edges, (8, 8), sample_x=edges, sample_y=edges, gain="area")  # type: ignore[arg-type]
    with pytest.raises(ShapeError, match="chief_ray_map"):
        LensPrewarp.from_chief_ray_map(torch.zeros(3, 1, 5, 2), (4, 4))
    with pytest.raises(InputValueError, match="direction"):
        LensPrewarp.from_chief_ray_map(torch.zeros(3, 4, 4, 2), (4, 4), direction="sideways")  # type: ignore[arg-type]


def test_bank_prewarp_undoes_the_optics_distortion():
    """Pre-warp from the shipped bank's chief rays, with the area-magnification gain, then the optics
    stage's chief-ray warp in the energy form: the eye sees the intended primaries (away from the border),
    where without it they are off by more than 0.1. ``from_psf_bank`` at a size is that LUT (a square image
    spans the display: bit-identical at 27 and 32 px)."""
    n = 64
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    img = torch.stack([torch.cos(3 * xx + yy) * 0.2 + 0.3, torch.sin(2 * yy) * 0.2 + 0.3, xx * yy * 0.2 + 0.3])
    bank = PSFBank.default()
    prewarp = LensPrewarp.from_chief_ray_map(bank.chief, (n, n), sample_x=bank.chief_x, sample_y=bank.chief_y, gain="jacobian")
    prewarp.basis = "rgb"  # applied to primaries below
    assert torch.allclose(LensPrewarp.from_psf_bank(bank, (n, n), gain="jacobian").map.gain, prewarp.map.gain)
    target = rgb_to_primaries(img)  # the optics is separable per primary: warp in that domain
    shown = primaries_to_rgb(prewarp(target, STATE, StageContext((n, n))))
    eye = rgb_to_primaries(psf_optics(shown, bank, mode="distortion", radiometry="energy"))
    plain = rgb_to_primaries(psf_optics(img, bank, mode="distortion", radiometry="energy"))
    centre = (slice(None), slice(8, -8), slice(8, -8))
    assert float((eye - target)[centre].abs().max()) < 0.01
    assert float((plain - target)[centre].abs().max()) > 0.1
    for m in (27, 32):
        a = LensPrewarp.from_psf_bank(bank, (m, m), gain="jacobian").map((m, m), torch.float32, CPU)
        b = LensPrewarp.from_chief_ray_map(bank.chief, (m, m), sample_x=bank.chief_x, sample_y=bank.chief_y,
                                           gain="jacobian").map((m, m), torch.float32, CPU)
        assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])


def test_from_psf_bank_refusals():
    with pytest.raises(InputValueError, match="gain tensor.*size"):
        LensPrewarp.from_psf_bank(PSFBank.default(), gain=torch.ones(3, 4, 4))
    with pytest.raises(InputValueError, match="size"):
        LensPrewarp.from_psf_bank(None, gain=torch.ones(3, 4, 4))
    with pytest.raises(InputValueError, match=r"bank must have 3 wavelengths .*600.0, 500.0"):
        LensPrewarp.from_psf_bank(synthetic_bank(L=2), (4, 4))


# ----------------------------------------------------------------------------- LUT files
def test_lut_file_round_trip_size_and_version(tmp_path):
    """A LUT file (format version 1, its size and source map in the header) reads back as the same warp; a
    map that is not a LUT needs a size to be baked at; a file of another kind, of a newer version or without
    a gain is refused naming the file."""
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
    with pytest.raises(InputValueError, match="size.*RadialMap"):
        LensPrewarp().save_lut(tmp_path / "x.safetensors")
    radial = LensPrewarp.load_lut(LensPrewarp().save_lut(tmp_path / "r.safetensors", (4, 6)))
    assert isinstance(radial.map, LUTMap)
    expect, _ = RadialMap()((4, 6), torch.float32, CPU)
    assert torch.allclose(radial.map((4, 6), torch.float32, CPU)[0], expect, atol=1e-6)
    pixel = pixel_grid((2, 3), torch.float32)[None].expand(3, -1, -1, -1).contiguous()
    header = read_header(LensPrewarp.from_lut(pixel).save_lut(tmp_path / "lut.safetensors"), kind=lens.LUT_KIND, max_version=99)
    assert (header["format_version"], header["size"], header["source"]) == (1, [2, 3], "LUTMap")
    other = save_tensors(tmp_path / "other.safetensors", {"x": torch.zeros(1)}, {}, kind="something-else", format_version=1)
    with pytest.raises(FileFormatError, match="other.safetensors.*'controlgs-prewarp-lut'"):
        LensPrewarp.load_lut(other)
    newer = save_tensors(tmp_path / "newer.safetensors", {"grid": pixel, "gain": torch.ones(3, 2, 3)}, {},
                         kind=lens.LUT_KIND, format_version=2)
    with pytest.raises(FileFormatError, match="newer.safetensors.*newer than this library reads"):
        LensPrewarp.load_lut(newer)
    no_gain = save_tensors(tmp_path / "no_gain.safetensors", {"grid": torch.zeros(3, 2, 2, 2)}, {},
                           kind=lens.LUT_KIND, format_version=1)
    with pytest.raises(FileFormatError, match=r"no_gain.safetensors.*\['gain'\]"):
        LensPrewarp.load_lut(no_gain)


# ----------------------------------------------------------------------------- for an optics stage
class _Optics(torch.nn.Module):
    """An optics stage as ``for_optics`` reads it: a bank, a radiometry, a mode and a placement."""

    def __init__(self, bank: PSFBank | None = None, radiometry: str = "radiance", mode: str = "exact",
                 placement: str = "fit") -> None:
        super().__init__()
        self.bank, self.radiometry, self.mode, self.placement = bank or PSFBank.default(), radiometry, mode, placement


def test_the_fitted_lens_averages_two_by_two_samples_per_display_pixel_the_chief_rays_one():
    """A fitted LUT for optics samples 2 x 2 per display pixel unless told otherwise; the chief rays, and the
    radial lens without optics, one; a configured ``supersample`` is kept."""
    optics = PSFOptics(mode="distortion")
    assert lens.FITTED_SUPERSAMPLE == 2
    assert LensPrewarp.for_optics(optics).supersample == 2
    assert LensPrewarp.for_optics(optics, supersample=1).supersample == 1
    assert LensPrewarp.for_optics(optics, source="chief_rays").supersample == 1
    assert Pipeline.from_config({"lens": True, "optics": {"mode": "distortion"}})["lens"].supersample == 2
    assert Pipeline.from_config({"lens": {"supersample": 3}, "optics": {"mode": "distortion"}})["lens"].supersample == 3
    assert Pipeline.from_config({"lens": True})["lens"].supersample == 1


@pytest.mark.parametrize("basis", ["rgb", "primaries"])
def test_for_optics_passes_the_basis_on_every_path(basis, tmp_path):
    """The chief-ray fallback (no shipped LUT for the radiometry), the chief rays asked for, and a fitted LUT
    file all take the basis; without one the documented default, the primaries."""
    optics = _Optics(radiometry="no-such-radiometry")
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        fallback = LensPrewarp.for_optics(optics, basis=basis)
    assert isinstance(fallback.map, BankMap) and fallback.basis == basis
    chief = LensPrewarp.for_optics(optics, source="chief_rays", basis=basis)
    assert isinstance(chief.map, BankMap) and chief.basis == basis
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        assert LensPrewarp.for_optics(optics).basis == "primaries"
    disp = 0.01 * pixel_grid((5, 4), D).expand(3, -1, -1, -1).clone()
    lut = DisplayLUTMap({"exact": (disp, torch.ones(3, 5, 4, dtype=D))},
                        meta={"bank": bank_fingerprint(optics.bank), "radiometry": "no-such-radiometry"}
                        ).save(tmp_path / "fit.safetensors")
    fitted = LensPrewarp.for_optics(optics, lut=lut, basis=basis)
    assert isinstance(fitted.map, DisplayLUTMap) and fitted.basis == basis
    assert LensPrewarp.for_optics(optics, lut=lut).basis == "primaries"


def test_for_optics_checks_a_fitted_lut_and_falls_back_to_chief_rays(tmp_path):
    """A LUT file fitted for another radiometry or another bank is refused naming the file and both sides;
    the LUT follows the optics' current mode; without a LUT for the bank the chief rays are used, with a
    warning naming the radiometry and the Jacobian gain for the energy form."""
    bank = PSFBank.default()
    disp, gain, _ = display_tables()
    fp = bank_fingerprint(bank)
    lut = DisplayLUTMap({"distortion": (disp, gain), "exact": (disp * 2, gain)},
                        meta={"bank": fp, "radiometry": "energy"}).save(tmp_path / "fit.safetensors")
    with pytest.raises(InputValueError, match="fit.safetensors.*radiometry 'energy'"):
        LensPrewarp.for_optics(_Optics(bank, "radiance"), lut=lut)
    optics = _Optics(bank, "energy", mode="distortion")
    stage = LensPrewarp.for_optics(optics, lut=lut)
    assert isinstance(stage.map, DisplayLUTMap) and stage.map.table_mode() == "distortion"
    optics.mode = "fast"
    assert stage.map.table_mode() == "exact"  # follows the optics' current mode
    other = copy.copy(bank)
    other._cache, other.chief = {}, bank.chief * 1.001  # own cache: the default bank is process-wide
    with pytest.raises(InputValueError, match=f"fit.safetensors.*another PSF bank.*{fp}"):
        LensPrewarp.for_optics(_Optics(other, "energy"), lut=lut)
    for radiometry, fallback in (("energy", "jacobian"), ("radiance", None)):
        with pytest.warns(UserWarning, match=f"no fitted pre-warp LUT.*'{radiometry}'"):
            chief = LensPrewarp.for_optics(_Optics(other, radiometry))
        assert isinstance(chief.map, BankMap) and chief.map.gain == fallback and chief.map.bank is other


def test_for_optics_follows_the_placement_and_refuses_what_it_cannot_use():
    """The chief-ray lens takes the optics' placement, gain and basis; a stage without a PSF bank, an
    unknown source or placement, and a gain with a fitted LUT are refused by name."""
    real = PSFOptics(mode="distortion", placement="stretch")
    lens_ = LensPrewarp.for_optics(real, source="chief_rays")
    assert isinstance(lens_.map, BankMap) and lens_.map.placement == "stretch"
    chief = LensPrewarp.for_optics(_Optics(placement="stretch"), source="chief_rays", gain="jacobian", basis="rgb")
    assert (chief.map.placement, chief.map.gain, chief.basis) == ("stretch", "jacobian", "rgb")
    with pytest.raises(InputValueError, match="optics.*PSFBank.*Identity.*NoneType"):
        LensPrewarp.for_optics(torch.nn.Identity())
    with pytest.raises(InputValueError, match="source.*'traced'"):
        LensPrewarp.for_optics(_Optics(), source="traced")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain applies to source='chief_rays'"):
        LensPrewarp.for_optics(_Optics(), gain="jacobian")
    with pytest.raises(InputValueError, match="optics.placement must be one of .*'crop'"):
        LensPrewarp.for_optics(_Optics(placement="crop"), source="chief_rays")
    real.placement = "tile"
    with pytest.raises(InputValueError, match="placement.*'tile'"):
        LensPrewarp.for_optics(real, source="chief_rays")
    with pytest.raises(InputValueError, match="basis must be one of .* got 'srgb'"):
        LensPrewarp.for_optics(_Optics(), source="chief_rays", basis="srgb")  # type: ignore[arg-type]
