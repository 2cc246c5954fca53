"""Tests of ``controlgs_adapter.downstream.prewarp_fit``: training a learned pre-warp through the pipeline
(the paper's loss and recipe, baking), and fitting a bank's display pre-warp table through the optics
(centroids measured by brute force, the flat-field gain, the map beyond the measured pixels, refusals),
with its helpers checked on worked-out values."""

from __future__ import annotations

import dataclasses
import inspect
import re
from pathlib import Path

import pytest
import torch

from controlgs_adapter.downstream.color import primaries_to_rgb_matrix, rgb_to_primaries_matrix
from controlgs_adapter.downstream.lens import BankMap, DisplayLUTMap, LensPrewarp, LUTMap, bank_fingerprint, chief_ray_grid, pixel_grid
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.stage import PSFOptics
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.prewarp_fit import FIT_SIZES, _fill_invalid, _psf_centroids, _reach, fit_bank_prewarp, fit_prewarp
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.losses import image_loss
from controlgs_adapter.metrics import ssim
from controlgs_adapter.state import RuntimeState

D = torch.float64
ROOT = Path(__file__).resolve().parents[2]


# ----------------------------------------------------------------------------- fit_prewarp
class _Lens(Stage):
    """A lens stage adding a trainable offset per channel."""

    name, domain, order = "lens", "linear", 10.0

    def __init__(self) -> None:
        super().__init__()
        self.offset = torch.nn.Parameter(torch.zeros(3, dtype=D))

    def process(self, image, state, ctx):
        return image + self.offset[:, None, None]


def test_fit_prewarp_refuses_what_it_cannot_fit():
    images = torch.rand(2, 3, 16, 16)
    with pytest.raises(InputValueError, match=r"'lens'.*\['resample', 'oled'\]"):
        fit_prewarp(Pipeline.from_config(["resample"]), images, steps=1)
    with pytest.raises(InputValueError, match="lens stage has no trainable parameters"):
        fit_prewarp(Pipeline.from_config(["lens"]), images, steps=1)
    pipe = Pipeline([LensPrewarp.learned(hidden=4, layers=1)])
    with pytest.raises(ShapeError, match="targets"):
        fit_prewarp(pipe, images, torch.rand(3, 3, 16, 16), steps=1)
    with pytest.raises(InputValueError, match="targets must have dtype"):
        fit_prewarp(pipe, images, images.double(), steps=1)
    for kwargs, shown in (({"lr": 0.0}, "lr=0.0"), ({"lr": -1.0}, "lr=-1.0"), ({"steps": 0}, "steps=0")):
        with pytest.raises(InputValueError, match=rf"steps must be >= 1 and lr > 0, got .*{shown}"):
            fit_prewarp(pipe, images, **kwargs)


def test_fit_prewarp_default_length_is_the_documented_recipe():
    """docs/explanation/pipeline.md documents ``fit_prewarp(..., steps=10_000, lr=1e-3)``, the paper's recipe
    (Supp. B.1); the function's defaults are those (10,000 steps take minutes here, so read, not run)."""
    doc = (ROOT / "docs" / "explanation" / "pipeline.md").read_text()
    m = re.search(r"fit_prewarp\(pipeline, images, targets, steps=([0-9_]+), lr=([0-9.e-]+)\)", doc)
    assert m is not None
    params = inspect.signature(fit_prewarp).parameters
    assert params["steps"].default == int(m.group(1)) == 10_000
    assert params["lr"].default == float(m.group(2)) == 1e-3


def test_fit_prewarp_loss_learning_rate_and_mode():
    """The loss is the paper's 3DGS loss 0.8 L1 + 0.2 (1 - SSIM), no MSE (the lens is the identity at step
    1); Adam's first step moves every parameter with a gradient by the learning rate (default 1e-3); the
    pipeline's train/eval mode comes back; the loss list has one entry per step."""
    g = torch.Generator().manual_seed(5)
    images = torch.rand(1, 3, 16, 16, generator=g, dtype=D) * 0.5 + 0.25
    targets = (images + 0.1 * torch.rand(1, 3, 16, 16, generator=g, dtype=D)).clamp(0, 1)
    pipe = Pipeline([_Lens()]).eval()
    losses = fit_prewarp(pipe, images, targets, steps=1)
    l1 = float((images[0] - targets[0]).abs().mean())
    expect = 0.8 * l1 + 0.2 * (1.0 - float(ssim(images[0], targets[0], data_range=1.0).mean()))
    assert losses == [pytest.approx(expect, rel=1e-6)]
    assert pipe["lens"].offset.abs().tolist() == pytest.approx([1e-3] * 3, rel=1e-4)
    assert not pipe.training
    fast = Pipeline([_Lens()])
    fit_prewarp(fast, images, targets, steps=1, lr=0.02)
    assert fast["lens"].offset.abs().tolist() == pytest.approx([0.02] * 3, rel=1e-4)
    assert fast.training
    assert len(fit_prewarp(pipe, images, steps=3, lr=1e-2)) == 3


def _smooth_images(n: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    a = torch.stack([torch.cos(4 * xx + yy), torch.sin(3 * yy - xx), xx * yy]) * 0.3 + 0.45
    return torch.stack([a, a.flip(-1)])


def test_fit_reduces_the_eye_loss_and_bakes():
    """A learned pre-warp fitted through the distortion optics lowers the eye loss by a fifth within 60
    steps; baked into a LUT at the image size it gives the same eye loss."""
    torch.manual_seed(0)
    images = _smooth_images(32)
    pipe = Pipeline.from_config({"lens": LensPrewarp.learned(hidden=32, layers=2, frequencies=2),
                                 "optics": {"mode": "distortion"}})

    def eye_loss() -> float:
        with torch.no_grad():
            return sum(float(image_loss(pipe(img, RuntimeState(), reference=img), img)) for img in images) / 2

    before = eye_loss()
    losses = fit_prewarp(pipe, images, steps=60, lr=1e-2, generator=torch.Generator().manual_seed(0))
    assert len(losses) == 60 and pipe.training  # the pipeline's mode is restored
    after = eye_loss()
    assert after < 0.8 * before
    baked = pipe["lens"].bake((32, 32))
    assert isinstance(baked.map, LUTMap)
    pipe.stages[pipe.names.index("lens")] = baked
    assert abs(eye_loss() - after) < 1e-3


# ----------------------------------------------------------------------------- fit_bank_prewarp
def test_fit_bank_prewarp_refusals_name_the_argument():
    with pytest.raises(InputValueError, match="optics.*PSFBank.*Identity"):
        fit_bank_prewarp(torch.nn.Identity())
    optics = PSFOptics()
    for size in (7, 8.0, "16"):
        with pytest.raises(InputValueError, match=rf"size must be an int >= 8 .*got {size!r}"):
            fit_bank_prewarp(optics, size)  # type: ignore[arg-type]
    for size, pool in [(16, 0), (16, 3), (8, 4), (16, 2.0)]:  # 8 / 4 = 2 samples < 4
        with pytest.raises(InputValueError, match=rf"pool.*got {pool!r}"):
            fit_bank_prewarp(optics, size, pool=pool)  # type: ignore[arg-type]
    for modes in ((), ("blur",)):
        with pytest.raises(InputValueError, match=r"modes must be a non-empty subset"):
            fit_bank_prewarp(optics, 16, modes=modes)
    for bad in (-1, 1.0, True):
        with pytest.raises(InputValueError, match=rf"gain_iterations.*{bad!r}"):
            fit_bank_prewarp(optics, 8, modes=("distortion",), gain_iterations=bad)  # type: ignore[arg-type]
    for bank in (PSFBank.default(), None):  # a bank or None is made an optics stage first
        with pytest.raises(InputValueError, match="size must be an int >= 8"):
            fit_bank_prewarp(bank, 7)
    stretched = PSFOptics(mode="distortion", placement="stretch")
    stretched.placement = "tile"
    with pytest.raises(InputValueError, match="placement.*'tile'"):
        fit_bank_prewarp(stretched, 16, modes=("distortion",))


def test_fit_bank_prewarp_refuses_a_primary_whose_light_never_reaches_the_eye_frame():
    """A bank whose 550 nm chief rays land 30 x too far out (the green light of every display pixel leaves
    the eye frame) has nothing to fit for that primary: refused in one line naming it, whatever the gain
    iterations (0 included). With 0 iterations on a valid bank the gain is 1, its flat-field residual
    measured over the pixels seen (the energy form's fall-off)."""
    bank = PSFBank.default()
    chief = bank.chief.clone()
    chief[1] *= 30.0
    far = PSFOptics(dataclasses.replace(bank, chief=chief, _cache={}))
    for iterations in (0, 2):
        with pytest.raises(InputValueError, match=r"measured.*\[1\] of 3"):
            fit_bank_prewarp(far, 8, modes=("distortion",), gain_iterations=iterations)
    lut = fit_bank_prewarp(PSFOptics(bank, radiometry="energy"), 8, modes=("distortion",), gain_iterations=0, pool=1)
    _, gain = lut((8, 8), D, "cpu")
    assert torch.equal(gain, torch.ones_like(gain))
    assert 0.0 < lut.meta["residuals"]["distortion"]["flat_max_abs"] < 0.5


def test_distortion_fit_follows_the_chief_rays_flattens_and_round_trips(tmp_path):
    """Distortion mode at 16 px: the LUT records the bank's fingerprint, brings a flat field back within 1 %,
    and in the display's centre region its map is the chief rays (an independent evaluation: BankMap) to a
    tenth of a pixel; saved and read back for the same optics it gives the same grid."""
    optics = PSFOptics(mode="distortion")
    lut = fit_bank_prewarp(optics, 16, modes=("distortion",), pool=1, gain_iterations=3)
    assert lut.meta["bank"] == bank_fingerprint(optics.bank) and lut.meta["residuals"]["distortion"]["flat_max_abs"] < 1e-2
    grid, _ = lut((16, 16), D, "cpu")
    chief, _ = BankMap(optics.bank).double()((16, 16), D, "cpu")
    inner = (pixel_grid((16, 16), D).abs() < 0.6).all(-1)
    assert float((grid - chief)[:, inner].abs().max()) * 8 < 0.1       # px at 16 px
    path = lut.save(tmp_path / "lut.safetensors")
    assert torch.equal(LensPrewarp.for_optics(optics, lut=path).map((16, 16), D, "cpu")[0], grid)


def test_exact_mode_fit_measures_centroids_and_flattens_by_brute_force():
    """Exact mode at 8 px (defaults: pool 2, 4 gain iterations) through energy optics whose own mode is left
    alone: the table holds, where measured, the centroid of every single lit display pixel's eye image
    (brute force, one primary at a time, pooled 2 x 2); the gain flattens a flat field."""
    bank = PSFBank.default()
    stage = PSFOptics(bank, mode="distortion", radiometry="energy")
    lut = fit_bank_prewarp(stage, 8, modes=("exact",))
    assert lut.modes == ("exact",) and lut.placement == "fit" and stage.mode == "distortion"
    assert (lut.meta["size"], lut.meta["pool"], lut.meta["gain_iterations"]) == ([8, 8], 2, 4)
    assert lut.meta["radiometry"] == "energy" and set(lut.meta["residuals"]) == {"exact"}
    # measured: the 6 x 6 inner pixels whose light stays inside the frame (36 / 64); the fixed point takes
    # the 7 % fall-off to below 0.2 % at the centroids in 4 iterations
    assert lut.meta["residuals"]["exact"]["measured_fraction"] == 0.5625
    assert lut.meta["residuals"]["exact"]["flat_max_abs"] < 2e-3
    assert lut.meta["seconds"] >= 0.0
    disp, gain = lut.displacement_exact.double(), lut.gain_exact.double()
    assert disp.shape == (3, 4, 4, 2) and gain.shape == (3, 4, 4)
    optics = PSFOptics(bank, mode="exact", placement="stretch", radiometry="energy").double()
    to_p, to_rgb = rgb_to_primaries_matrix(), primaries_to_rgb_matrix()

    def op(s: torch.Tensor) -> torch.Tensor:  # primaries [B, 3, 8, 8] -> primaries
        out = optics(torch.einsum("ij,bjhw->bihw", to_rgb, s), RuntimeState(), StageContext((8, 8)))
        return torch.einsum("ij,bjhw->bihw", to_p, out)

    p = pixel_grid((8, 8), D)
    ones = torch.eye(3 * 64, dtype=D).reshape(3 * 64, 3, 8, 8)
    eye = op(ones).reshape(3, 8, 8, 3, 8, 8)  # [lit primary, lit y, lit x, eye primary, y, x]
    light = eye.sum(dim=(3, 4, 5))
    cx = (eye.sum(3) * p[..., 0]).sum(dim=(3, 4)) / light
    cy = (eye.sum(3) * p[..., 1]).sum(dim=(3, 4)) / light
    centroid_disp = torch.stack([cx, cy], -1) - p  # [3, 8, 8, 2]
    pooled = centroid_disp.reshape(3, 4, 2, 4, 2, 2).mean(dim=(2, 4))
    # the central 2 x 2 cells (pixels 2..5) are measured: the table holds the centroids there
    assert torch.allclose(disp[:, 1:3, 1:3], pooled[:, 1:3, 1:3], atol=1e-5)
    # the gain brings a flat field back to flat at the centre: within 3.5 % (pooled 2 x 2 at 8 px)
    # where the uncorrected energy fall-off reaches 7 %
    flat = op(lut((8, 8), D, "cpu")[1][None])[0]
    assert float((flat[:, 2:6, 2:6] - 1.0).abs().max()) < 0.035
    assert float((op(torch.ones(1, 3, 8, 8, dtype=D))[0, :, 2:6, 2:6] - 1.0).abs().max()) > 0.06
    assert float(gain.min()) > 1.0  # brightens everywhere against the fall-off


def test_fit_bank_prewarp_fits_a_table_per_display_size():
    """Several sizes: one table per size and mode, each the single-size fit's; the largest is the main
    table (``size``, ``meta["size"]``); the residuals of every size are kept. Repeated or too small sizes, and
    a pool that does not divide every size, are refused."""
    optics = PSFOptics(mode="distortion")
    lut = fit_bank_prewarp(optics, [32, 16], modes=("distortion",), gain_iterations=1)
    assert (lut.size, lut.sizes, lut.meta["size"], lut.meta["sizes"]) == (32, {"distortion": (16, 32)}, [32, 32], [16, 32])
    assert sorted(lut.meta["residuals_by_size"]) == ["16", "32"] and lut.meta["residuals"] == lut.meta["residuals_by_size"]["32"]
    for n, sfx in ((16, "_16"), (32, "")):
        alone = fit_bank_prewarp(optics, n, modes=("distortion",), gain_iterations=1)
        assert alone.sizes == {"distortion": (n,)} and "sizes" not in alone.meta
        assert torch.equal(getattr(lut, f"displacement_distortion{sfx}"), alone.displacement_distortion)
        assert torch.equal(getattr(lut, f"gain_distortion{sfx}"), alone.gain_distortion)
    for size in ([16, 16], [], [16, 7]):
        with pytest.raises(InputValueError, match=r"size.*got \["):
            fit_bank_prewarp(optics, size)
    with pytest.raises(InputValueError, match=r"pool.*\[16, 18\]\), got 4"):
        fit_bank_prewarp(optics, [16, 18], pool=4)


def test_the_shipped_lut_holds_a_table_per_fitted_size_for_the_shipped_bank():
    """The LUT shipped for the Cardboard bank (its fingerprint) has distortion and exact tables at every
    default fit size (64 to 256 px, pooled 2 x 2: 128 x 128 samples at 256 px, 32 x 32 at 64 px)."""
    assert FIT_SIZES == (64, 96, 128, 192, 256)
    lut = LensPrewarp.for_optics(PSFOptics(mode="exact")).map
    assert isinstance(lut, DisplayLUTMap) and lut.meta["bank"] == bank_fingerprint(PSFBank.default())
    assert lut.sizes == {"distortion": FIT_SIZES, "exact": FIT_SIZES} and lut.meta["pool"] == 2
    assert lut.displacement_exact.shape == (3, 128, 128, 2) and lut.displacement_exact_64.shape == (3, 32, 32, 2)


def test_fit_continues_the_measured_residual_beyond_the_psf_centroids_where_the_frame_cuts_the_light():
    """Where a display pixel's light leaves the eye frame its centroid cannot be measured, and the map there
    is the chief ray plus the bank PSF's own centroid offset plus the *measured* discretisation residual
    (map - chief - PSF centroid on the measured pixels) continued outwards. At 8 px the measured pixels are
    the inner 6 x 6 (36 / 64); the outer ring must be that continuation, not the chief ray minus the offset
    (which lands up to 0.03 px off at 8 px)."""
    optics = PSFOptics()
    bank = optics.bank
    lut = fit_bank_prewarp(optics, 8, modes=("exact",), pool=1, gain_iterations=0)
    assert lut.meta["residuals"]["exact"]["measured_fraction"] == 36 / 64
    p = pixel_grid((8, 8), D)
    target = lut.displacement_exact.double() + p  # eye position of every display pixel
    chief, _ = chief_ray_grid(bank.chief.double(), (8, 8), sample_x=bank.chief_x, sample_y=bank.chief_y)
    offset = _psf_centroids(bank, p, D)
    assert float(offset[:, 0].abs().max()) * 4 > 1e-3  # the edge pixels' PSFs are off-centre (px at 8 px)
    residual = target - chief - offset
    inner = torch.zeros(3, 8, 8, dtype=torch.bool)
    inner[:, 1:-1, 1:-1] = True
    expected = _fill_invalid(torch.where(inner[..., None], residual, torch.zeros_like(residual)), inner)
    assert float((residual - expected).abs().max()) * 4 < 1e-5  # px at 8 px (float32 tables)


# ----------------------------------------------------------------------------- helpers of the fit
def test_fill_invalid_spreads_the_measured_values_outwards():
    """3 x 3, valid (0, 0) = 1 and (0, 2) = 3. Round 1 (3 x 3 means of valid neighbours): (0, 1) = 2,
    (1, 0) = 1, (1, 1) = 2, (1, 2) = 3; round 2: (2, 0) = (1 + 2) / 2, (2, 1) = (1 + 2 + 3) / 3, (2, 2) = 2.5;
    an invalid pixel's value is never used; channels and components are filled independently."""
    values = torch.zeros(1, 3, 3, 1, dtype=D)
    values[0, 0, 0, 0], values[0, 0, 2, 0] = 1.0, 3.0
    values[0, 1, 1, 0] = 99.0
    valid = torch.zeros(1, 3, 3, dtype=torch.bool)
    valid[0, 0, 0] = valid[0, 0, 2] = True
    flat = [1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 1.5, 2.0, 2.5]
    assert _fill_invalid(values, valid)[0, ..., 0].flatten().tolist() == pytest.approx(flat)
    both = torch.cat([values, -values], dim=-1).expand(2, 3, 3, 2)
    out = _fill_invalid(both, valid.expand(2, 3, 3))
    assert out[1, ..., 1].flatten().tolist() == pytest.approx([-v for v in flat])
    with pytest.raises(InputValueError, match="no display pixel could be measured"):
        _fill_invalid(values, torch.zeros_like(valid))


def test_psf_centroids_are_the_bilinear_first_moments_of_the_field_psfs():
    bank = PSFBank.default()
    k = bank.psf.shape[-1]

    def moment(l_: int, gy: int, gx: int) -> tuple[float, float]:  # brute force, float64
        psf = bank.psf[l_, gy, gx].double()
        taps = torch.arange(k, dtype=D) - k // 2
        pitch = float(bank.psf_pitch_mm[l_, gy, gx])
        return (float((psf * taps[None, :]).sum()) * pitch / (bank.display_mm[0] / 2),
                float((psf * taps[:, None]).sum()) * pitch / (bank.display_mm[1] / 2))

    fx, fy = bank.field_x.double(), bank.field_y.double()
    pts = torch.tensor([[[float(fx[3]), float(fy[5])],                                       # a field sample
                         [0.5 * float(fx[7] + fx[8]), 0.5 * float(fy[10] + fy[11])],          # a cell centre
                         [1.5, -1.5]]], dtype=D)                                              # beyond: clamped
    c = _psf_centroids(bank, pts, D)
    assert c.shape == (3, 1, 3, 2)
    for l_ in range(3):
        assert c[l_, 0, 0].tolist() == pytest.approx(moment(l_, 5, 3), abs=1e-9)
        corners = [moment(l_, gy, gx) for gy in (10, 11) for gx in (7, 8)]
        assert c[l_, 0, 1].tolist() == pytest.approx([sum(v[i] for v in corners) / 4 for i in range(2)], abs=1e-9)
        assert c[l_, 0, 2].tolist() == pytest.approx(moment(l_, 0, len(fx) - 1), abs=1e-9)
    assert float(c.abs().max()) > 1e-4  # the moments are not all zero (coma off axis)


def test_reach_of_a_display_pixels_light():
    """Exact mode: 1.5 x the PSF window's half-width (33 // 2 + 0.5 = 16.5 samples at the bank's pitch) over
    the 12 mm half display, at the 30 field samples (the pixel centres of a 30-pixel grid); distortion mode:
    3 / min(H, W) everywhere."""
    bank = PSFBank.default()
    assert bank.psf.shape[-1] == 33 and bank.display_mm == (24.0, 24.0) and bank.field_x.numel() == 30
    reach = _reach("exact", bank, pixel_grid((30, 30), D), D)
    # (rtol: the field coordinates are stored in float32, so the samples sit 1e-8 off the pixel centres)
    assert torch.allclose(reach, 1.5 * bank.psf_pitch_mm.double() * 16.5 / 12.0, rtol=1e-5)
    dist = _reach("distortion", bank, pixel_grid((30, 40), D), D)
    assert dist.shape == (3, 30, 40) and float(dist.min()) == float(dist.max()) == 0.1
