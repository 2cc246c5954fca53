"""Tests of ``controlgs_adapter.downstream.optics.stage``."""

from __future__ import annotations

import dataclasses
import threading
import warnings
from typing import Any, Callable

import pytest
import torch

from controlgs_adapter import RuntimeState, plugins
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics, set_optics_mode
from controlgs_adapter.errors import InputValueError, ShapeError

F64 = torch.float64


def _bank(L: int = 3, **over) -> PSFBank:
    G, K = 2, 3
    psf = torch.zeros(L, G, G, K, K, dtype=F64)
    psf[..., 1, 1] = 1.0  # delta PSFs
    c = torch.linspace(-1, 1, 3, dtype=F64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = torch.tensor([-0.5, 0.5], dtype=F64)
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=F64), field_x=f, field_y=f,
                chief=torch.stack([cx, cy], -1).expand(L, 3, 3, 2).clone(), chief_x=c, chief_y=c,
                wavelengths_nm=(656.0, 550.0, 486.0, 420.0)[:L], display_mm=(10.0, 10.0))
    args.update(over)
    return PSFBank(**args)


def test_optics_needs_three_wavelengths_and_a_positive_zone():
    image = torch.rand(3, 8, 8, dtype=F64)
    with pytest.raises(InputValueError, match="3 wavelengths"):
        psf_optics(image, _bank(4), "distortion")
    with pytest.raises(InputValueError, match="zone"):
        PSFOptics(_bank(), zone=0)
    psf_optics(image, _bank(3), "distortion")  # the same bank with three wavelengths is taken


D64 = torch.float64


def _bank_2(G=5, K=9, L=2, S=32, magnification=None, pincushion=0.0, transmission=None, seed=0):
    """Synthetic bank on a 24 mm display: Gaussian PSFs widening and shifting off-centre across the
    field (so they differ field to field), chief rays ``d * (s + k |d|^2)``."""
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    t = torch.arange(K, dtype=D64) - K // 2
    sig = 0.5 + 0.8 * (fx ** 2 + fy ** 2)
    off = 0.6 * fx                                                            # coma-like shift (px)
    g = torch.exp(-0.5 * (((t[None, :] - off[..., None, None]) ** 2 + t[:, None] ** 2) / sig[..., None, None] ** 2))
    psf = (g / g.sum((-1, -2), keepdim=True)).expand(L, G, G, K, K).clone()
    c = torch.linspace(-1, 1, 17, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    s = (magnification or 1.0) + pincushion * (cx ** 2 + cy ** 2)
    chief = torch.stack([cx * s, cy * s], -1).expand(L, 17, 17, 2).clone()
    meta = {} if transmission is None else {"transmission": transmission.expand(L, G, G).tolist()}
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), 24 / S, dtype=D64), field_x=f, field_y=f, chief=chief,
                   chief_x=c, chief_y=c, wavelengths_nm=(600.0, 500.0)[:L], display_mm=(24.0, 24.0), meta=meta)


def _inner(o: torch.Tensor, frac: float = 0.9) -> torch.Tensor:
    H, W = o.shape[-2:]
    a, b = round(H * (1 - frac) / 2), round(W * (1 - frac) / 2)
    return o[..., a:H - a, b:W - b]


# ----------------------------------------------------------------------------- stage plumbing
def test_radiometry_is_an_explicit_argument():
    bank = PSFBank.default()
    img = torch.full((3, 32, 32), 0.5, dtype=D64)
    st = PSFOptics(mode="distortion")
    assert st.radiometry == "radiance" and "radiometry='radiance'" in repr(st)
    paper = PSFOptics(mode="distortion", radiometry="energy")
    state = RuntimeState(downsample=1.0, power_saving=0.0)
    assert torch.allclose(paper(img, state, None), psf_optics(img, bank, "distortion", radiometry="energy"))
    assert (_inner(st(img, state, None)) - 0.5).abs().max() < 1e-6
    assert bank.resample_to(32, 32) is not bank.resample_to(32, 32, radiometry="energy")
    with pytest.raises(InputValueError, match="radiometry"):
        PSFOptics(radiometry="lumens")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="radiometry"):
        bank.resample_to(8, 8, radiometry="photons")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="transmission"):
        _bank_2(transmission=torch.full((5, 5), 1.5, dtype=D64))


D = torch.float64


# ------------------------------------------------------------------------------ bank pre-warp fit
needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


def _within(seconds: float, fn: Callable[[], Any]) -> Any:
    """``fn()``, run in a daemon thread; a call still running after ``seconds`` fails the test (a hang)."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as e:  # re-raised in the test's thread
            box["error"] = e

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(seconds)
    assert not worker.is_alive(), f"still running after {seconds:g} s"
    if "error" in box:
        raise box["error"]
    return box.get("value")


@needs_optics
def test_fit_bank_prewarp_refuses_a_primary_whose_light_never_reaches_the_eye_frame():
    """A bank whose 550 nm chief rays land 30 x too far out (the green light of every display pixel leaves
    the eye frame) has nothing to fit for that primary: refused in one line naming it, not a fit of the
    other primaries that hangs on the unmeasurable one, whatever the gain iterations (0 included); a
    negative or non-integer ``gain_iterations`` is refused naming it."""
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    bank = PSFBank.default()
    chief = bank.chief.clone()
    chief[1] *= 30.0
    far = PSFOptics(dataclasses.replace(bank, chief=chief, _cache={}))
    for iterations in (0, 2):
        with pytest.raises(InputValueError, match=r"no display pixel could be measured.*channel\(s\) \[1\] of 3"):
            _within(120.0, lambda: fit_bank_prewarp(far, 8, modes=("distortion",), gain_iterations=iterations))
    for bad in (-1, 1.0, True):
        with pytest.raises(InputValueError, match=rf"gain_iterations must be an int >= 0, got {bad!r}"):
            fit_bank_prewarp(PSFOptics(bank), 8, modes=("distortion",), gain_iterations=bad)  # type: ignore[arg-type]
    # 0 iterations: the unit gain, its flat-field residual measured over the pixels seen (the fall-off)
    lut = fit_bank_prewarp(PSFOptics(bank, radiometry="energy"), 8, modes=("distortion",), gain_iterations=0, pool=1)
    _, gain = lut((8, 8), D, "cpu")
    assert torch.equal(gain, torch.ones_like(gain))
    assert 0.0 < lut.meta["residuals"]["distortion"]["flat_max_abs"] < 0.5


def _bank_3(L=3, G=3, K=5, pitch_mm=1.0, chief=lambda d: d, C=9, seed=0, flip_x=False):
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    ch = torch.stack([-chief(cx) if flip_x else chief(cx), chief(cy)], -1).expand(L, C, C, 2).clone()
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


# ----------------------------------------------------------------------------- stage
def test_stage_defaults_by_number():
    """Documented defaults: mode "exact", tol 0.02, zone 5, placement "fit", radiometry "radiance"."""
    from controlgs_adapter.downstream.optics import stage

    st = PSFOptics()
    assert (st.mode, st.tol, st.zone, st.placement, st.radiometry) == ("exact", 0.02, 5, "fit", "radiance")
    assert st.bank is PSFBank.default() and (stage.DEFAULT_TOL, stage.DEFAULT_ZONE) == (0.02, 5)
    assert repr(st).endswith("(mode='exact', placement='fit', radiometry='radiance', tol=0.02, zone=5, "
                             "wavelengths=(656.0, 550.0, 486.0))")
    assert stage.MODES == ("distortion", "fast", "exact")
    assert (PSFOptics.name, PSFOptics.domain) == ("optics", "linear")


def test_psf_optics_defaults_equal_their_explicit_values():
    bank = PSFBank.default()
    img = torch.rand(3, 16, 24, dtype=D64, generator=torch.Generator().manual_seed(2))
    out = psf_optics(img, bank)
    assert torch.equal(out, psf_optics(img, bank, "exact", 0.02, 5, "fit", "radiance"))
    assert torch.equal(psf_optics(img), out)                                       # bank None: the shipped one
    for other in (psf_optics(img, bank, "distortion"), psf_optics(img, bank, placement="stretch"),
                  psf_optics(img, bank, radiometry="energy")):
        assert (out - other).abs().max() > 1e-3
    b8 = _bank_3(G=8)                                                              # random PSFs: every knob shows
    img = img[..., :16, :16]
    fast = psf_optics(img, b8, "fast")
    assert torch.equal(fast, psf_optics(img, b8, "fast", 0.02, 5))
    assert (fast - psf_optics(img, b8, "fast", 0.04, 5)).abs().max() > 1e-6
    assert (fast - psf_optics(img, b8, "fast", 0.02, 6)).abs().max() > 1e-6


def test_stage_passes_every_setting_through():
    bank = PSFBank.default()
    img = torch.rand(3, 18, 32, dtype=D64, generator=torch.Generator().manual_seed(3))
    state = RuntimeState(downsample=1.0, power_saving=0.0)
    st = PSFOptics(bank, mode="fast", tol=0.1, zone=3, placement="stretch", radiometry="energy")
    want = psf_optics(img, bank, "fast", 0.1, 3, "stretch", "energy")
    assert torch.equal(st(img, state, None), want)
    assert not torch.allclose(want, psf_optics(img, bank, "fast", 0.1, 3, "fit", "energy"), atol=1e-6)
    st.mode = "distortion"
    assert torch.equal(st(img, state, None), psf_optics(img, bank, "distortion", placement="stretch", radiometry="energy"))


def test_stage_loads_a_bank_file(tmp_path):
    bank = _bank_3()
    bank.save(tmp_path / "b.safetensors")
    st = PSFOptics(str(tmp_path / "b.safetensors"), mode="distortion")
    assert torch.allclose(st.bank.chief, bank.chief) and st.bank.psf.shape == bank.psf.shape
    st2 = PSFOptics(tmp_path / "b.safetensors")
    assert st2.bank.display_mm == (24.0, 24.0)


@pytest.mark.parametrize("kw, match", [
    (dict(tol=-0.1), r"tol must be in \[0, 1\)"), (dict(tol=1), "tol must be in"), (dict(tol="0"), "tol"),
    (dict(zone=0), "zone must be an int >= 1"), (dict(zone=1.5), "zone"),
    (dict(placement="crop"), "placement must be one of.*'crop'"), (dict(radiometry="flux"), "radiometry must be one of"),
    (dict(mode="blur"), r"mode must be one of \('distortion', 'fast', 'exact'\), got 'blur'"),
])
def test_stage_refuses_bad_settings(kw, match):
    with pytest.raises(InputValueError, match=match):
        PSFOptics(**kw)


def test_stage_mode_setter_and_deprecated_stretch():
    st = PSFOptics(mode="fast", tol=0, zone=1)
    assert st.tol == 0.0 and isinstance(st.tol, float)
    with pytest.raises(InputValueError, match="mode must be one of.*'sharp'"):
        st.mode = "sharp"
    assert st.mode == "fast"
    with pytest.warns(DeprecationWarning, match="stretch"):
        assert PSFOptics(stretch=True).placement == "stretch"
    with pytest.warns(DeprecationWarning, match="stretch"):
        assert PSFOptics(placement="stretch", stretch=False).placement == "fit"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert PSFOptics(placement="stretch").placement == "stretch"


def test_psf_optics_refusals():
    img = torch.rand(3, 8, 8)
    with pytest.raises(InputValueError, match=r"mode must be one of \('distortion', 'fast', 'exact'\), got 'blur'"):
        psf_optics(img, mode="blur")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match=r"needs a bank with 3 wavelengths.*\(656.0, 550.0\)"):
        psf_optics(img, _bank_3(L=2))
    with pytest.raises(ShapeError, match="image must have size 3"):
        psf_optics(torch.rand(2, 8, 8))


def test_set_optics_mode_reaches_the_stage_and_checks_the_mode():
    from controlgs_adapter.downstream.pipeline import Pipeline

    p = Pipeline([PSFOptics(mode="exact")])
    set_optics_mode(p, "distortion")
    assert p["optics"].mode == "distortion"
    with pytest.raises(InputValueError, match="mode must be one of"):
        set_optics_mode(p, "blurry")
