"""Tests of ``controlgs_adapter.downstream.prewarp_fit``."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest
import torch

from controlgs_adapter import plugins
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.prewarp_fit import fit_prewarp
from controlgs_adapter.downstream.stage import Stage
from controlgs_adapter.errors import InputValueError, ShapeError


def test_fit_rejects_what_it_cannot_fit():
    images = torch.rand(2, 3, 16, 16)
    with pytest.raises(InputValueError, match="no 'lens'"):
        fit_prewarp(Pipeline.from_config(["resample"]), images, steps=1)
    with pytest.raises(InputValueError, match="trainable"):
        fit_prewarp(Pipeline.from_config(["lens"]), images, steps=1)
    pipe = Pipeline([LensPrewarp.learned(hidden=4, layers=1)])
    with pytest.raises(ShapeError, match="targets"):
        fit_prewarp(pipe, images, torch.rand(3, 3, 16, 16), steps=1)
    with pytest.raises(InputValueError, match="steps"):
        fit_prewarp(pipe, images, steps=0)


ROOT = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------ fit_prewarp
def test_fit_prewarp_default_length_is_the_documented_recipe():
    """docs/pipeline.md documents ``fit_prewarp(..., steps=10_000, lr=1e-3)``, the paper's recipe (Supp. B.1);
    the function's defaults are those (10,000 steps take minutes here, so read, not run)."""
    from controlgs_adapter.downstream.prewarp_fit import fit_prewarp

    doc = (ROOT / "docs" / "pipeline.md").read_text()
    m = re.search(r"fit_prewarp\(pipeline, images, targets, steps=([0-9_]+), lr=([0-9.e-]+)\)", doc)
    assert m is not None
    params = inspect.signature(fit_prewarp).parameters
    assert params["steps"].default == int(m.group(1)) == 10_000
    assert params["lr"].default == float(m.group(2)) == 1e-3


D = torch.float64


needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


# ----------------------------------------------------------------------------- pre-warp fit beyond the frame
@needs_optics
def test_fit_continues_the_measured_residual_beyond_the_psf_centroids_where_the_frame_cuts_the_light():
    """``fit_bank_prewarp`` (module docstring of prewarp_fit): where a display pixel's light leaves the eye
    frame its centroid cannot be measured, and the map there is the chief ray plus the bank PSF's own
    centroid offset plus the *measured* discretisation residual (map - chief - PSF centroid on the measured
    pixels) continued outwards. At 8 px the measured pixels are the inner 6 x 6 (36 / 64, pinned in
    test_sweep_downstream_pipeline); the outer ring must be that continuation, not the chief ray minus the
    offset (which lands up to 0.03 px off at 8 px)."""
    from controlgs_adapter.downstream.lens import chief_ray_grid, pixel_grid
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import _fill_invalid, _psf_centroids, fit_bank_prewarp

    optics = PSFOptics()
    bank = optics.bank
    lut = fit_bank_prewarp(optics, 8, modes=("exact",), pool=1, gain_iterations=0)
    assert lut.meta["residuals"]["exact"]["measured_fraction"] == 36 / 64
    p = pixel_grid((8, 8), D)
    target = lut.displacement_exact.double() + p  # eye position of every display pixel
    chief, _ = chief_ray_grid(bank.chief.double(), (8, 8), sample_x=bank.chief_x, sample_y=bank.chief_y)
    offset = _psf_centroids(bank, p, D)  # the PSFs' first moments (brute-forced in test_sweep_downstream_pipeline)
    assert float(offset[:, 0].abs().max()) * 4 > 1e-3  # the edge pixels' PSFs are off-centre (px at 8 px)
    residual = target - chief - offset
    inner = torch.zeros(3, 8, 8, dtype=torch.bool)
    inner[:, 1:-1, 1:-1] = True
    expected = _fill_invalid(torch.where(inner[..., None], residual, torch.zeros_like(residual)), inner)
    assert float((residual - expected).abs().max()) * 4 < 1e-5  # px at 8 px (float32 tables)


def _fill_by_hand() -> tuple[torch.Tensor, torch.Tensor, list[list[float]]]:
    # 3 x 3, valid (0, 0) = 1 and (0, 2) = 3. Round 1 (3 x 3 means of valid neighbours): (0, 1) = 2,
    # (1, 0) = 1, (1, 1) = 2, (1, 2) = 3; round 2: (2, 0) = (1 + 2) / 2, (2, 1) = (1 + 2 + 3) / 3, (2, 2) = 2.5
    values = torch.zeros(1, 3, 3, 1, dtype=D)
    values[0, 0, 0, 0], values[0, 0, 2, 0] = 1.0, 3.0
    values[0, 1, 1, 0] = 99.0  # an invalid pixel's value is never used
    valid = torch.zeros(1, 3, 3, dtype=torch.bool)
    valid[0, 0, 0] = valid[0, 0, 2] = True
    return values, valid, [[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [1.5, 2.0, 2.5]]


class _Lens(Stage):
    name, domain, order = "lens", "linear", 10.0

    def __init__(self) -> None:
        super().__init__()
        self.offset = torch.nn.Parameter(torch.zeros(3, dtype=D))

    def process(self, image, state, ctx):
        return image + self.offset[:, None, None]


def test_fit_bank_prewarp_refusals_name_the_argument():
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    with pytest.raises(InputValueError, match="optics must be an optics stage or a PSFBank, got Identity"):
        fit_bank_prewarp(torch.nn.Identity())
    if "optics" not in plugins.stages():
        return
    from controlgs_adapter.downstream.optics.stage import PSFOptics

    optics = PSFOptics()
    for size in (7, 8.0, "16"):
        with pytest.raises(InputValueError, match="size must be an int >= 8"):
            fit_bank_prewarp(optics, size)  # type: ignore[arg-type]
    for size, pool in [(16, 0), (16, 3), (8, 4), (16, 2.0)]:  # 8 / 4 = 2 samples < 4
        with pytest.raises(InputValueError, match="pool must be an int >= 1 dividing size into >= 4 samples"):
            fit_bank_prewarp(optics, size, pool=pool)  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="modes must be a non-empty subset"):
        fit_bank_prewarp(optics, 16, modes=())
    from controlgs_adapter.downstream.optics.bank import PSFBank

    for bank in (PSFBank.default(), None):  # a bank or None is made an optics stage first
        with pytest.raises(InputValueError, match="size must be an int >= 8"):
            fit_bank_prewarp(bank, 7)


def test_fill_invalid_by_hand_and_nothing_measured():
    from controlgs_adapter.downstream.prewarp_fit import _fill_invalid

    values, valid, expect = _fill_by_hand()
    flat = [v for row in expect for v in row]
    assert _fill_invalid(values, valid)[0, ..., 0].flatten().tolist() == pytest.approx(flat)
    # two channels x two components are filled independently
    both = torch.cat([values, -values], dim=-1).expand(2, 3, 3, 2)
    out = _fill_invalid(both, valid.expand(2, 3, 3))
    assert out[1, ..., 1].flatten().tolist() == pytest.approx([-v for v in flat])
    with pytest.raises(InputValueError, match="no display pixel could be measured"):
        _fill_invalid(values, torch.zeros_like(valid))


def test_fit_prewarp_loss_and_learning_rate_defaults():
    from controlgs_adapter.downstream.prewarp_fit import fit_prewarp
    from controlgs_adapter.metrics import ssim

    g = torch.Generator().manual_seed(5)
    images = torch.rand(1, 3, 16, 16, generator=g, dtype=D) * 0.5 + 0.25
    targets = (images + 0.1 * torch.rand(1, 3, 16, 16, generator=g, dtype=D)).clamp(0, 1)
    pipe = Pipeline([_Lens()]).eval()
    losses = fit_prewarp(pipe, images, targets, steps=1)
    # the paper's 3DGS loss 0.8 L1 + 0.2 (1 - SSIM), no MSE; the lens is the identity at step 1
    l1 = float((images[0] - targets[0]).abs().mean())
    expect = 0.8 * l1 + 0.2 * (1.0 - float(ssim(images[0], targets[0], data_range=1.0).mean()))
    assert losses == [pytest.approx(expect, rel=1e-6)]
    # Adam's first step moves every parameter with a gradient by lr = 1e-3
    assert pipe["lens"].offset.abs().tolist() == pytest.approx([1e-3] * 3, rel=1e-4)
    assert not pipe.training  # the caller's mode comes back
    fast = Pipeline([_Lens()])
    fit_prewarp(fast, images, targets, steps=1, lr=0.02)
    assert fast["lens"].offset.abs().tolist() == pytest.approx([0.02] * 3, rel=1e-4)
    assert fast.training
    assert len(fit_prewarp(pipe, images, steps=3, lr=1e-2)) == 3
    for kwargs in ({"lr": 0.0}, {"lr": -1.0}, {"steps": 0}):
        with pytest.raises(InputValueError, match="steps must be >= 1 and lr > 0"):
            fit_prewarp(pipe, images, **kwargs)
    with pytest.raises(InputValueError, match="targets must have dtype"):
        fit_prewarp(pipe, images, targets.float(), steps=1)
