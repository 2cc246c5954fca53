"""Tests of ``controlgs_adapter.downstream.optics.stage``: the optics stage and ``psf_optics`` (defaults,
every setting passed through, bank files, refusals) and ``set_optics_mode``. The stage contract
(shapes, dtypes, gradients, twin) is checked in ``tests/downstream/test_stage_contract.py``."""

from __future__ import annotations

import warnings

import pytest
import torch
from helpers.banks import random_bank

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.optics import stage
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics, set_optics_mode
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError

D64 = torch.float64


def test_stage_defaults_by_number():
    """Documented defaults: the shipped bank, mode "exact", tol 0.02, zone 5, placement "fit", radiometry
    "radiance"; the repr shows them."""
    st = PSFOptics()
    assert (st.mode, st.tol, st.zone, st.placement, st.radiometry) == ("exact", 0.02, 5, "fit", "radiance")
    assert st.bank is PSFBank.default() and (stage.DEFAULT_TOL, stage.DEFAULT_ZONE) == (0.02, 5)
    assert repr(st).endswith("(mode='exact', placement='fit', radiometry='radiance', tol=0.02, zone=5, "
                             "wavelengths=(656.0, 550.0, 486.0))")
    assert stage.MODES == ("distortion", "fast", "exact")
    assert (PSFOptics.name, PSFOptics.domain, PSFOptics.order) == ("optics", "linear", 50.0)


def test_psf_optics_defaults_equal_their_explicit_values():
    bank = PSFBank.default()
    img = torch.rand(3, 16, 24, dtype=D64, generator=torch.Generator().manual_seed(2))
    out = psf_optics(img, bank)
    assert torch.equal(out, psf_optics(img, bank, "exact", 0.02, 5, "fit", "radiance"))
    assert torch.equal(psf_optics(img), out)                                       # bank None: the shipped one
    for other in (psf_optics(img, bank, "distortion"), psf_optics(img, bank, placement="stretch"),
                  psf_optics(img, bank, radiometry="energy")):
        assert (out - other).abs().max() > 1e-3
    b8 = random_bank(G=8)                                                          # random PSFs: every knob shows
    img = img[..., :16, :16]
    fast = psf_optics(img, b8, "fast")
    assert torch.equal(fast, psf_optics(img, b8, "fast", 0.02, 5))
    assert (fast - psf_optics(img, b8, "fast", 0.04, 5)).abs().max() > 1e-6
    assert (fast - psf_optics(img, b8, "fast", 0.02, 6)).abs().max() > 1e-6


def test_stage_passes_every_setting_through():
    """The stage is ``psf_optics`` with its bank, mode, tol, zone, placement and radiometry; the mode is
    settable at any time. In the default radiance form a uniform grey is seen uniform (exact and
    distortion), where the paper's energy form dims it off axis."""
    bank = PSFBank.default()
    img = torch.rand(3, 18, 32, dtype=D64, generator=torch.Generator().manual_seed(3))
    state = RuntimeState(downsample=1.0, power_saving=0.0)
    st = PSFOptics(bank, mode="fast", tol=0.1, zone=3, placement="stretch", radiometry="energy")
    want = psf_optics(img, bank, "fast", 0.1, 3, "stretch", "energy")
    assert torch.equal(st(img, state, None), want)
    assert not torch.allclose(want, psf_optics(img, bank, "fast", 0.1, 3, "fit", "energy"), atol=1e-6)
    st.mode = "distortion"
    assert torch.equal(st(img, state, None), psf_optics(img, bank, "distortion", placement="stretch", radiometry="energy"))
    grey = torch.full((3, 32, 32), 0.5, dtype=D64)
    assert (PSFOptics(mode="distortion")(grey, state, None)[:, 2:-2, 2:-2] - 0.5).abs().max() < 1e-6
    assert (PSFOptics(mode="exact")(grey, state, None)[:, 14:18, 14:18] - 0.5).abs().max() < 0.02
    assert (PSFOptics(mode="distortion", radiometry="energy")(grey, state, None)[:, 2:-2, 2:-2] - 0.5).abs().max() > 0.05


def test_stage_loads_a_bank_file(tmp_path):
    bank = random_bank()
    bank.save(tmp_path / "b.safetensors")
    st = PSFOptics(str(tmp_path / "b.safetensors"), mode="distortion")
    assert torch.allclose(st.bank.chief, bank.chief) and st.bank.psf.shape == bank.psf.shape
    assert PSFOptics(tmp_path / "b.safetensors").bank.display_mm == (24.0, 24.0)


@pytest.mark.parametrize("kw, match", [
    (dict(tol=-0.1), r"tol must be in \[0, 1\)"), (dict(tol=1), "tol must be in"), (dict(tol="0"), "tol"),
    (dict(zone=0), "zone must be an int >= 1"), (dict(zone=1.5), "zone"),
    (dict(placement="crop"), "placement must be one of.*'crop'"),
    (dict(radiometry="flux"), "radiometry must be one of.*'flux'"), (dict(radiometry="lumens"), "radiometry"),
    (dict(mode="blur"), r"mode must be one of \('distortion', 'fast', 'exact'\), got 'blur'"),
])
def test_stage_refuses_bad_settings(kw, match):
    with pytest.raises(InputValueError, match=match):
        PSFOptics(**kw)


def test_stage_mode_setter_and_deprecated_stretch():
    st = PSFOptics(mode="fast", tol=0, zone=1)
    assert st.tol == 0.0 and isinstance(st.tol, float)
    for bad in ("sharp", "blurry"):
        with pytest.raises(InputValueError, match=f"mode must be one of.*'{bad}'"):
            st.mode = bad
    assert st.mode == "fast"
    with pytest.warns(DeprecationWarning, match="stretch"):
        assert PSFOptics(stretch=True).placement == "stretch"
    with pytest.warns(DeprecationWarning, match="stretch"):
        assert PSFOptics(placement="stretch", stretch=False).placement == "fit"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert PSFOptics(placement="stretch").placement == "stretch"


def test_psf_optics_refusals():
    """A bank without exactly 3 wavelengths (the display primaries) is refused naming its wavelengths, an
    unknown mode and an image without 3 channels by name; a 3-wavelength bank is taken."""
    img = torch.rand(3, 8, 8)
    with pytest.raises(InputValueError, match=r"mode.*'blur'"):
        psf_optics(img, mode="blur")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match=r"needs a bank with 3 wavelengths.*\(656.0, 550.0\)"):
        psf_optics(img, random_bank(L=2))
    with pytest.raises(InputValueError, match=r"needs a bank with 3 wavelengths.*420.0"):
        psf_optics(img.double(), random_bank(L=4), "distortion")
    with pytest.raises(ShapeError, match="image must have size 3"):
        psf_optics(torch.rand(2, 8, 8))
    assert psf_optics(img.double(), random_bank(L=3), "distortion").shape == (3, 8, 8)


class _ModelessOptics(Stage):
    """A third-party optics stage with no ``mode``."""

    name = "optics"
    order = 50.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        return image


def test_set_optics_mode_reaches_the_stage_and_refuses_one_without_modes():
    """The pipeline's PSFOptics gets the mode (an unknown mode refused); an optics stage that has no mode
    is refused by type, not silently ignored; a pipeline without optics is left alone."""
    p = Pipeline([PSFOptics(mode="exact")])
    set_optics_mode(p, "distortion")
    assert p["optics"].mode == "distortion"
    with pytest.raises(InputValueError, match="mode must be one of"):
        set_optics_mode(p, "blurry")
    with pytest.raises(InputValueError, match="PSFOptics.*_ModelessOptics"):
        set_optics_mode(Pipeline([_ModelessOptics()]), "fast")
    pipeline = Pipeline.from_config({"resample": True})
    set_optics_mode(pipeline, "fast")
    assert "optics" not in pipeline
