"""PSFBank: every numeric argument is checked, naming it."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.errors import InputValueError

D64 = torch.float64


def _args(**over):
    L, G, K = 3, 2, 3
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=torch.Generator().manual_seed(0))
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 3, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = torch.tensor([-0.5, 0.5], dtype=D64)
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64), field_x=f, field_y=f.clone(),
                chief=torch.stack([cx, cy], -1).expand(L, 3, 3, 2).clone(), chief_x=c, chief_y=c.clone(),
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
    return {**args, **over}


@pytest.mark.parametrize("value", [(math.nan, math.nan), (24.0, math.inf), (24.0, -1.0), (0.0, 24.0), (24.0,),
                                   (24.0, 24.0, 24.0), "24x24", (True, 24.0), ("24", "24"), None, 24.0])
def test_display_mm_must_be_two_finite_positive_numbers(value):
    with pytest.raises(InputValueError, match=r"^PSF bank: display_mm must be"):
        PSFBank(**_args(display_mm=value))


@pytest.mark.parametrize("value", [(656.0, math.nan, 486.0), (656.0, 550.0, -486.0), (656.0, 0.0, 486.0),
                                   (656.0, "550", 486.0), (656.0, math.inf, 486.0), "656", None])
def test_wavelengths_must_be_finite_positive_numbers(value):
    with pytest.raises(InputValueError, match=r"^PSF bank: wavelengths_nm must be"):
        PSFBank(**_args(wavelengths_nm=value))


@pytest.mark.parametrize("name", ["psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y"])
def test_each_tensor_must_be_a_floating_point_tensor(name):
    args = _args()
    with pytest.raises(InputValueError, match=rf"^PSF bank: {name} must be a floating-point torch.Tensor, got torch.int64"):
        PSFBank(**{**args, name: args[name].long()})
    with pytest.raises(InputValueError, match=rf"^PSF bank: {name} must be a floating-point torch.Tensor, got list"):
        PSFBank(**{**args, name: args[name].tolist()})


@pytest.mark.parametrize("name", ["psf_pitch_mm", "field_x", "chief", "chief_y"])
def test_each_tensor_must_be_finite(name):
    args = _args()
    bad = args[name].clone()
    bad.view(-1)[0] = math.nan
    with pytest.raises(InputValueError, match=rf"^PSF bank: {name} holds 1 NaN/Inf"):
        PSFBank(**{**args, name: bad})


def test_numbers_of_any_real_type_are_taken_as_floats():
    bank = PSFBank(**_args(display_mm=[24, 30], wavelengths_nm=[656, 550.5, 486]))
    assert bank.display_mm == (24.0, 30.0) and bank.wavelengths_nm == (656.0, 550.5, 486.0)
    assert all(isinstance(v, float) for v in (*bank.display_mm, *bank.wavelengths_nm))


import copy
from pathlib import Path
from typing import Any, Callable

import numpy as np
from helpers.banks import D64 as D64_2
from helpers.banks import D64 as D64_4
from helpers.banks import tiny_bank
from helpers.pupil import aim_rays
from helpers.rawfiles import write_raw

from controlgs_adapter import plugins
from controlgs_adapter.downstream.lens import bank_fingerprint, pixel_grid
from controlgs_adapter.downstream.optics import resampled
from controlgs_adapter.downstream.optics.bank import BANK_KIND, DEFAULT_BANK_FILE, SUM_TOLERANCE
from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
from controlgs_adapter.downstream.optics.raytrace import chief_ray, real_magnification
from controlgs_adapter.downstream.optics.resampled import quad_overlap
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import ControlGSError, FileFormatError
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors
from controlgs_adapter.state import RuntimeState


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ============================================================================ files: PSF banks
def _bank_file(tmp_path: Path, header: dict[str, Any] | None = None, drop: tuple[str, ...] = (), **tensors: Any) -> Path:
    b = tiny_bank()
    t = {"psf": b.psf.half(), "psf_pitch_mm": b.psf_pitch_mm, "field_x": b.field_x, "field_y": b.field_y,
         "chief": b.chief, "chief_x": b.chief_x, "chief_y": b.chief_y, **tensors}
    for k in drop:
        t.pop(k)
    h = {"wavelengths_nm": [656, 550, 486], "display_mm": [24, 24], **(header or {})}
    h = {k: v for k, v in h.items() if v is not None}
    return write_raw(tmp_path / "bank.safetensors", t, h, kind=BANK_KIND)


BANK_CASES = [
    ("display_mm '66'", {"header": {"display_mm": "66"}}, "display_mm"),
    ("display_mm [24]", {"header": {"display_mm": [24]}}, "display_mm"),
    ("display_mm [0, 24]", {"header": {"display_mm": [0, 24]}}, "display_mm"),
    ("display_mm [true, 24]", {"header": {"display_mm": [True, 24]}}, "display_mm"),
    ("display_mm ['24', '24']", {"header": {"display_mm": ["24", "24"]}}, "display_mm"),
    ("no wavelengths_nm", {"header": {"wavelengths_nm": None}}, "wavelengths_nm"),
    ("wavelengths_nm '656'", {"header": {"wavelengths_nm": "656"}}, "wavelengths_nm"),
    ("wavelengths_nm []", {"header": {"wavelengths_nm": []}}, "wavelengths_nm"),
    ("wavelengths_nm [-1, ...]", {"header": {"wavelengths_nm": [-1, 550, 486]}}, "wavelengths_nm"),
    ("meta a list", {"header": {"meta": [1]}}, "meta"),
    ("empty grid", {"psf": torch.zeros(3, 0, 0, 5, 5), "psf_pitch_mm": torch.zeros(3, 0, 0),
                    "field_x": torch.zeros(0), "field_y": torch.zeros(0)}, "empty grid"),
    ("no psf tensor", {"drop": ("psf",)}, "psf"),
    ("NaN pitch", {"psf_pitch_mm": torch.full((3, 3, 3), math.nan)}, "psf_pitch_mm"),
    ("psf even K", {"psf": torch.full((3, 3, 3, 4, 4), 1 / 16)}, "psf"),
]


@pytest.mark.parametrize("kw, name", [c[1:] for c in BANK_CASES], ids=[c[0] for c in BANK_CASES])
def test_psf_bank_files(tmp_path, kw, name):
    p = _bank_file(tmp_path, **kw)
    _raises(lambda: PSFBank.load(p), FileFormatError, "bank.safetensors", name)


@pytest.mark.parametrize("version", [True, "1", 0, None], ids=repr)
def test_psf_bank_format_version(tmp_path, version):
    b = tiny_bank()
    p = write_raw(tmp_path / "bank.safetensors", {"psf": b.psf}, {"wavelengths_nm": [656, 550, 486]}, kind=BANK_KIND,
                  format_version=version)
    _raises(lambda: PSFBank.load(p), FileFormatError, "bank.safetensors", "format_version")


optics_mod = pytest.importorskip("controlgs_adapter.downstream.optics.stage")


def test_fit_samples_the_bank_at_the_pixels_display_positions():
    """16:9 under "fit": a 27 x 48 image's pixel corners sit at display-normalised
    ``(x, 9/16 y)``; each pixel's footprint is the quad of its corners' chief-ray images, computed
    here by hand from the bank's chief rays (the 48 x 48 image's map, landing points divided by
    the half-extents): its overlap areas add up to the quad's area and sit on the quad;
    the PSFs use the square pixel pitch."""
    bank = PSFBank.default()
    wide, square = bank.resample_to(27, 48, dtype=torch.float64), bank.resample_to(48, 48, dtype=torch.float64)
    ue = torch.linspace(-1, 1, 49, dtype=torch.float64)
    ve = torch.linspace(-1, 1, 28, dtype=torch.float64)
    V, U = torch.meshgrid(ve, ue, indexing="ij")
    ch = square._chief_at(U, V * 27 / 48)                                    # [L, 28, 49, 2]
    X = (ch[..., 0] + 1) * 24 + wide.m
    Y = (ch[..., 1] * 48 / 27 + 1) * 13.5 + wide.m
    qx = torch.stack([X[:, :-1, :-1], X[:, :-1, 1:], X[:, 1:, 1:], X[:, 1:, :-1]]).reshape(4, 3, -1)
    qy = torch.stack([Y[:, :-1, :-1], Y[:, :-1, 1:], Y[:, 1:, 1:], Y[:, 1:, :-1]]).reshape(4, 3, -1)
    cross = [qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4)]
    area = 0.5 * sum(cross)
    cx = sum((qx[e] + qx[(e + 1) % 4]) * cross[e] for e in range(4)) / (6 * area)
    cy = sum((qy[e] + qy[(e + 1) % 4]) * cross[e] for e in range(4)) / (6 * area)
    idx, w = wide.splat_index, wide.splat_weight                             # [L, J, N] (radiance: areas)
    col, row = (idx % wide.Wc).double() + 0.5, (idx // wide.Wc).double() + 0.5
    assert torch.allclose(w.sum(1), area, atol=1e-12)
    assert torch.allclose(wide.area, area, atol=1e-12)
    # first moments by pixel-centre quadrature of the overlaps: within a tenth of a pixel
    assert ((w * col).sum(1) / area - cx).abs().max() < 0.1
    assert ((w * row).sum(1) / area - cy).abs().max() < 0.1
    assert torch.equal(wide.kernels, square.kernels)       # pitch 0.5 mm in both


@pytest.mark.parametrize("h, w, axis", [(54, 96, -2), (96, 54, -1)])
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_fit_simulates_the_image_region_of_a_black_display(h, w, axis, mode):
    """Only the image's region is simulated and the rest of the display is black: the optics of a
    16:9 (9:16) image equals, inside its band, the optics of the square image that holds it in the
    display's central band and black elsewhere (same pixel pitch)."""
    n = max(h, w)
    x = torch.rand(3, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    big = torch.zeros(3, n, n, dtype=torch.float64)
    band = [slice(None)] * 3
    band[axis] = slice((n - min(h, w)) // 2, (n + min(h, w)) // 2)
    big[tuple(band)] = x
    bank = PSFBank.default()
    got = optics_mod.psf_optics(x, bank, mode)
    want = optics_mod.psf_optics(big, bank, mode)[tuple(band)]
    assert torch.allclose(got, want, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- gradients, flat field
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_gradcheck_optics_on_a_non_square_image(mode):
    bank = PSFBank.default()
    x = (torch.rand(3, 5, 9, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: optics_mod.psf_optics(t, bank, mode), (x,))


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


def test_psf_bank_refuses_negative_taps_and_transmission_above_one():
    psf = _bank().psf.clone()
    psf[0, 0, 0, 0, 0], psf[0, 0, 0, 1, 1] = -0.01, 1.01  # still sums to 1
    with pytest.raises(InputValueError, match="non-negative"):
        _bank(psf=psf)
    psf[0, 0, 0, 0, 0], psf[0, 0, 0, 1, 1] = -1e-4, 1.0 + 1e-4  # rounding-size negatives are kept
    _bank(psf=psf)
    for t in (1.5, -0.2):  # checked when the bank is made
        with pytest.raises(InputValueError, match="transmission"):
            _bank(meta={"transmission": torch.full((3, 2, 2), t).tolist()})
    assert torch.equal(_bank(meta={"transmission": [[[0.25] * 2] * 2] * 3}).transmission, torch.full((3, 2, 2), 0.25, dtype=F64))


def test_round_trip(tmp_path):
    bank = tiny_bank(meta={"note": "test"})
    bank.save(tmp_path / "b.safetensors")
    back = PSFBank.load(tmp_path / "b.safetensors")
    assert torch.allclose(back.psf, bank.psf, atol=1e-3)          # PSFs are stored as float16
    assert torch.allclose(back.psf.sum((-1, -2)), torch.ones(3, 3, 3), atol=1e-6)
    assert torch.equal(back.chief, bank.chief) and back.wavelengths_nm == bank.wavelengths_nm
    assert back.meta["note"] == "test"


def test_default_bank_is_the_cardboard_lens():
    bank = PSFBank.default()
    assert bank.wavelengths_nm == (656.0, 550.0, 486.0) and bank.display_mm == (24.0, 24.0)
    assert tuple(bank.psf.shape[:3]) == (3, 30, 30)
    assert bank.meta["prescription"]["surfaces"][0]["radius_mm"] == 290.444
    # corner: pincushion distortion; blue lands further out than red
    corner = bank.chief[:, -1, -1, 0]
    assert 1.15 < corner[1] < 1.25 and corner[2] > corner[1] > corner[0]
    # the corner PSF is ~100x wider than the central one and keeps all its light in the stored window
    px = 24 / 1024
    assert bank.psf_pitch_mm[1, 0, 0] / px > 4 and bank.psf_pitch_mm[1, 15, 15] / px < 0.2
    assert bank.resample_to(64, 64) is bank.resample_to(64, 64)   # cached per resolution


@pytest.mark.parametrize("bad, match", [
    (lambda b: b["psf"].__setitem__((0, 1, 1, 2, 2), math.nan), "NaN"),
    (lambda b: b["psf"].mul_(1.1), "sum to 1"),
    (lambda b: b.__setitem__("field_x", b["field_x"][:2]), "field grid"),
    (lambda b: b.__setitem__("psf_pitch_mm", b["psf_pitch_mm"][:, :2]), "psf_pitch_mm"),
    (lambda b: b.__setitem__("chief_x", torch.linspace(-0.9, 1, 5, dtype=D64_2)), "chief_x"),
    (lambda b: b.__setitem__("wavelengths_nm", (656.0, 550.0)), "wavelengths"),
])
def test_bad_banks_fail_clearly(bad, match):
    args = {k: getattr(tiny_bank(), k) for k in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x",
                                                 "chief_y", "wavelengths_nm", "display_mm")}
    args = {k: v.clone() if isinstance(v, torch.Tensor) else v for k, v in args.items()}
    bad(args)
    with pytest.raises(InputValueError, match=match):
        PSFBank(**args)


def test_bad_files_fail_clearly(tmp_path):
    bank = tiny_bank()
    bank.save(tmp_path / "b.safetensors")
    with pytest.raises(FileFormatError, match="24.0 x 24.0 mm display"):
        PSFBank.load(tmp_path / "b.safetensors", display_mm=(30.0, 20.0))
    save_tensors(tmp_path / "other.safetensors", {"x": torch.zeros(1)}, {}, kind="adapter", format_version=1)
    with pytest.raises(FileFormatError, match="psf_bank"):
        PSFBank.load(tmp_path / "other.safetensors")
    write_raw(tmp_path / "nan.safetensors", {"psf": torch.full((3, 3, 3, 5, 5), math.nan), "psf_pitch_mm": bank.psf_pitch_mm,
                                                "field_x": bank.field_x, "field_y": bank.field_y, "chief": bank.chief,
                                                "chief_x": bank.chief_x, "chief_y": bank.chief_y},
                 {"wavelengths_nm": [656, 550, 486], "display_mm": [24, 24]}, kind="psf_bank", format_version=1)
    with pytest.raises(FileFormatError, match="NaN"):
        PSFBank.load(tmp_path / "nan.safetensors")
    (tmp_path / "trunc.safetensors").write_bytes((tmp_path / "b.safetensors").read_bytes()[:200])
    with pytest.raises(FileFormatError):
        PSFBank.load(tmp_path / "trunc.safetensors")


def test_an_image_of_another_aspect_is_placed_on_the_display():
    bank = tiny_bank()
    fit, stretch = bank.resample_to(48, 64), bank.resample_to(48, 64, placement="stretch")
    assert (fit.region.half_x, fit.region.half_y) == (1.0, 0.75) and fit.W == 64
    assert (stretch.region.half_x, stretch.region.half_y) == (1.0, 1.0)
    with pytest.raises(InputValueError, match="placement"):
        bank.resample_to(48, 64, placement="crop")


@pytest.mark.parametrize("device", ["banana", 3.5])
def test_resample_to_refuses_a_device_that_is_not_one(device):
    with pytest.raises(InputValueError, match=rf"resample_to: device {device!r} is not a usable torch device here"):
        tiny_bank().resample_to(12, 12, device=device)


D64_3 = torch.float64


OPS = {"distortion": psf_distortion, "exact": psf_exact, "fast": lambda x, rb: psf_fast(x, rb, tol=0.05, zone=5)}


def _inner(o: torch.Tensor, frac: float = 0.9) -> torch.Tensor:
    H, W = o.shape[-2:]
    a, b = round(H * (1 - frac) / 2), round(W * (1 - frac) / 2)
    return o[..., a:H - a, b:W - b]


def _steps(o: torch.Tensor) -> float:
    """Largest step between adjacent pixels beyond the local linear trend (first difference minus
    the mean of its two neighbours), both axes."""
    dx, dy = o[..., :, 1:] - o[..., :, :-1], o[..., 1:, :] - o[..., :-1, :]
    sx = dx[..., 1:-1] - 0.5 * (dx[..., 2:] + dx[..., :-2])
    sy = dy[..., 1:-1, :] - 0.5 * (dy[..., 2:, :] + dy[..., :-2, :])
    return max(sx.abs().max().item(), sy.abs().max().item())


# ----------------------------------------------------------------------------- section 1: radiometry
@pytest.mark.parametrize("mode", list(OPS))
def test_flat_field_of_the_cardboard_lens_is_uniform_in_every_mode(mode):
    """Radiance (default): a flat white display is seen flat, up to the pupil transmission (the
    vignetting model: the pupil area on the primary branch; 1 except in the outermost field
    samples of the Cardboard bank, >= 0.98 there, where the lens rim folds part of the pupil
    into the second image). The paper's energy form dims it by the area magnification (~0.8 at
    mid-edge, ~0.6 towards the corner)."""
    bank = PSFBank.default()
    assert bank.transmission.min() > 0.98
    S = 96
    x = torch.ones(3, S, S, dtype=D64_3)
    rb = bank.resample_to(S, S, dtype=D64_3)
    out = OPS[mode](x, rb)
    assert (out - rb.vignetting.reshape(3, S, S))[:, 8:-8, 8:-8].abs().max() < 1e-6
    assert (_inner(out) - 1).abs().max() < 1e-3                               # target: 2 %
    energy = OPS[mode](x, bank.resample_to(S, S, dtype=D64_3, radiometry="energy"))
    assert 0.78 < energy[1, S // 2, 5].item() < 0.86 and energy[1, 5, 5].item() < 0.7


def test_flat_field_of_a_16_9_image_is_uniform():
    bank = PSFBank.default()
    x = torch.ones(1, 3, 27, 48, dtype=D64_3)
    for mode in OPS:
        assert (_inner(psf_optics(x, bank, mode)) - 1).abs().max() < 1e-3


def test_area_magnification_matches_finite_differences_of_the_chief_rays():
    """``rb.area`` (the exact quad areas the radiance form multiplies by, and the energy form
    divides by) against det of the chief-ray Jacobian by central differences at pixel centres;
    the same in both radiometries."""
    bank = PSFBank.default()
    S = 64
    rb = bank.resample_to(S, S, dtype=D64_3)
    u = (2 * torch.arange(S, dtype=D64_3) + 1) / S - 1
    V, U = torch.meshgrid(u, u, indexing="ij")
    h = 1e-5
    ddx = (rb._chief_at(U + h, V) - rb._chief_at(U - h, V)) / (2 * h)
    ddy = (rb._chief_at(U, V + h) - rb._chief_at(U, V - h)) / (2 * h)
    det = (ddx[..., 0] * ddy[..., 1] - ddx[..., 1] * ddy[..., 0]).reshape(3, -1)
    assert ((rb.area / det) - 1).abs().max() < 5e-3                          # O(pixel^2) of the quads
    assert 1.2 < rb.area[1].reshape(S, S)[S // 2, 0].item() < 1.3             # ~1/0.80 at mid-edge
    assert torch.allclose(bank.resample_to(S, S, dtype=D64_3, radiometry="energy").area, rb.area)


def test_radiance_point_source_lands_on_its_chief_ray():
    """A single display pixel: its light is its area magnification (radiance over a larger image),
    centred on the chief ray plus the blended PSF's centroid (within 0.05 px: the blend is taken
    where the light arrives, so it varies a little across the PSF)."""
    bank = PSFBank.default()
    S = 48
    rb = bank.resample_to(S, S, dtype=D64_3)
    iy, ix = 30, 17
    x = torch.zeros(3, S, S, dtype=D64_3)
    x[:, iy, ix] = 1
    out = psf_exact(x, rb)
    e = rb.area[:, iy * S + ix]
    assert torch.allclose(out.sum((-1, -2)), e, rtol=2e-3)
    ref = psf_exact(x, bank.resample_to(S, S, dtype=D64_3, radiometry="energy"))
    yy, xx = torch.meshgrid(torch.arange(S, dtype=D64_3), torch.arange(S, dtype=D64_3), indexing="ij")
    for li in range(3):
        for grid in (xx, yy):
            c = (out[li] * grid).sum() / out[li].sum()
            c_energy = (ref[li] * grid).sum() / ref[li].sum()
            assert abs(c - c_energy).item() < 0.05


# ----------------------------------------------------------------------------- section 3: seams
def test_no_seams_on_the_field_sample_lines_in_exact_mode():
    """Exact mode, flat field: no step above 1e-4 between adjacent pixels in the inner 90 %, rows
    and columns on field-sample lines like the others (the energy form steps there: ~5e-3)."""
    bank = PSFBank.default()
    S = 120                                                                    # 4 px per field cell
    x = torch.ones(3, S, S, dtype=D64_3)
    out = _inner(psf_exact(x, bank.resample_to(S, S, dtype=D64_3)))
    assert _steps(out) < 1e-4
    assert (out - 1).abs().max() < 1e-3
    energy = _inner(psf_exact(x, bank.resample_to(S, S, dtype=D64_3, radiometry="energy")))
    assert _steps(energy) > 1e-3


# ----------------------------------------------------------------------------- section 4: pupil
def test_bank_psf_centroid_matches_a_trace_aimed_uniformly_over_the_pupil():
    """The shipped bank's mid-edge coma centroid (550 nm) against an independent trace: rays
    aimed by Newton at the points of a uniform grid over the 4 mm pupil (equal area each), their
    mean crossing of the virtual image plane relative to the chief ray. Uniform launch slopes gave
    1.20 px at 1024 px; the pupil-uniform value is 0.94 px."""

    bank = PSFBank.default()
    rx = Prescription(CARDBOARD)
    iy, ix, li = 29, 15, 1
    fx, fy = bank.field_x[ix].item() * 12, bank.field_y[iy].item() * 12            # mm on the display
    r = math.hypot(fx, fy)
    lam = bank.wavelengths_nm[li]
    v0, Y0, _ = chief_ray(rx, lam, np.array([r]))
    n = 64
    g = (np.arange(n) + 0.5) / n * 2 - 1
    PX, PY = np.meshgrid(g, g)
    inside = PX ** 2 + PY ** 2 <= 1
    tx, ty = PX[inside] * rx.pupil_radius, PY[inside] * rx.pupil_radius
    xp, yp, _, Y, ok = aim_rays(rx, lam, r, v0[0], tx, ty, 8)                 # Newton per pupil point
    assert ok.all() and np.abs(xp - tx).max() < 1e-9 and np.abs(yp - ty).max() < 1e-9
    px_per_mm = 1024 / 24
    want = (Y - Y0[0]).mean() / real_magnification(rx, rx.reference_wavelength) * px_per_mm   # radial, px at 1024
    K = bank.psf.shape[-1]
    t = torch.arange(K, dtype=D64_3) - K // 2
    p = bank.psf[li, iy, ix].double()
    pitch = bank.psf_pitch_mm[li, iy, ix].item() * px_per_mm
    cx, cy = (p.sum(0) * t).sum().item() * pitch, (p.sum(1) * t).sum().item() * pitch
    got = (cx * fx + cy * fy) / r
    assert got == pytest.approx(want, abs=0.015)
    assert 0.9 < got < 1.0


@pytest.fixture(scope="module")
def cardboard():
    return PSFBank.default()


def test_point_source_lands_at_its_chief_ray_with_the_bank_psf(cardboard):
    """Energy form: unit energy, centroid at the chief ray plus the blended bank PSF's centroid
    (the radiance form: tests/test_optics_fidelity.py)."""
    S = 48
    rb = cardboard.resample_to(S, S, dtype=D64_4, radiometry="energy")
    iy, ix = 30, 17                                   # off-axis pixel
    x = torch.zeros(3, S, S, dtype=D64_4)
    x[:, iy, ix] = 1
    out = psf_exact(x, rb)
    yy, xx = torch.meshgrid(torch.arange(S, dtype=D64_4) + 0.5, torch.arange(S, dtype=D64_4) + 0.5, indexing="ij")
    u, v = (2 * ix + 1) / S - 1, (2 * iy + 1) / S - 1
    chief = rb._chief_at(torch.tensor([u], dtype=D64_4), torch.tensor([v], dtype=D64_4))[:, 0]   # [L, 2]
    for li in range(3):
        o = out[li]
        assert o.sum().item() == pytest.approx(1.0, abs=1e-6)
        cx, cy = (o * xx).sum().item(), (o * yy).sum().item()
        # the bank PSF's own centroid (continuous, from the stored samples) at the blended fields
        w, idx = rb.field_weight[:, iy * S + ix], rb.field_index[:, iy * S + ix]
        K = cardboard.psf.shape[-1]
        t = torch.arange(K, dtype=D64_4) - K // 2
        ps = cardboard.psf[li].reshape(-1, K, K).double()[idx]
        pitch = cardboard.psf_pitch_mm[li].reshape(-1).double()[idx] / (24 / S)
        ox = (w * (ps.sum(1) * t).sum(-1) * pitch).sum().item()
        oy = (w * (ps.sum(2) * t).sum(-1) * pitch).sum().item()
        assert cx == pytest.approx((chief[li, 0].item() + 1) * S / 2 + ox, abs=0.02)
        assert cy == pytest.approx((chief[li, 1].item() + 1) * S / 2 + oy, abs=0.02)
    # lateral colour: blue (486) lands further out than red (656)
    assert abs(chief[2, 0]) > abs(chief[0, 0])


D64_5 = torch.float64


def _pincushion_bank(strength: float) -> PSFBank:
    """Small PSFs (reach 1 px at 24 px) and a strong pincushion: corner quads leave the canvas."""
    K, G = 5, 3
    psf = torch.rand(2, G, G, K, K, generator=torch.Generator().manual_seed(0), dtype=D64_5)
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64_5)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    scale = 1 + strength * (cx ** 2 + cy ** 2)
    f = -1 + (2 * torch.arange(G, dtype=D64_5) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((2, G, G), 0.3 * 24 / 24, dtype=D64_5), field_x=f, field_y=f,
                   chief=torch.stack([cx * scale, cy * scale], -1).expand(2, 9, 9, 2).clone(), chief_x=c, chief_y=c,
                   wavelengths_nm=(600.0, 500.0), display_mm=(24.0, 24.0))


def _copy(bank: PSFBank) -> PSFBank:        # a bank without cached tables
    return PSFBank(**{f: getattr(bank, f) for f in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x",
                                                    "chief_y", "wavelengths_nm", "display_mm", "meta")})


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
@pytest.mark.parametrize("h, w, which", [(40, 40, "cardboard"), (27, 48, "cardboard"), (24, 24, "pincushion"),
                                         (18, 30, "pincushion")])
def test_chunked_footprints_equal_the_literal_ones(cardboard, radiometry, h, w, which, monkeypatch):
    monkeypatch.setattr(resampled, "_FOOTPRINT_CHUNK", 37)          # many chunks of differing extents
    bank = _copy(cardboard) if which == "cardboard" else _pincushion_bank(0.25)
    rb = bank.resample_to(h, w, dtype=D64_5, radiometry=radiometry)
    if which == "pincushion":                                        # some footprint taps fall off the canvas
        assert (rb.splat_index == rb.Hc * rb.Wc).any()
    X, Y = rb.corners()
    qx = torch.stack([X[:, :-1, :-1], X[:, :-1, 1:], X[:, 1:, 1:], X[:, 1:, :-1]]).reshape(4, rb.L, -1)
    qy = torch.stack([Y[:, :-1, :-1], Y[:, :-1, 1:], Y[:, 1:, 1:], Y[:, 1:, :-1]]).reshape(4, rb.L, -1)
    area = 0.5 * sum(qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4))
    x0, y0 = torch.floor(qx.min(0).values), torch.floor(qy.min(0).values)
    J = rb.splat_index.shape[1]
    jx = int((torch.ceil(qx.max(0).values) - x0).max())
    for j in range(J):
        oy, ox = divmod(j, jx)
        px, py = x0 + ox, y0 + oy
        want = quad_overlap(qx, qy, px, py).clamp_min(0)
        if radiometry == "energy":
            want = want / area
        inside = (px >= 0) & (px < rb.Wc) & (py >= 0) & (py < rb.Hc)
        idx = torch.where(inside, py * rb.Wc + px, torch.full_like(px, rb.Hc * rb.Wc)).long()
        assert torch.equal(rb.splat_index[:, j], idx)
        assert (rb.splat_weight[:, j] - torch.where(inside, want, 0)).abs().max() < 1e-13


def test_field_kernels_are_the_crop_of_the_full_table(cardboard):
    rb = cardboard.resample_to(64, 64, dtype=D64_5)
    full = rb.kernels                                                            # [L, G, k, k]
    for li in range(rb.L):
        boxes = rb.box_matrices(li)
        for fields in (torch.tensor([0]), torch.tensor([434, 435, 464]), torch.arange(900)):
            K, r = rb.field_kernels(li, fields)
            assert torch.equal(rb.field_kernels(li, fields, boxes)[0], K)
            m = rb.m
            assert K.shape == (len(fields), 2 * r + 1, 2 * r + 1) and r <= m
            assert (K - full[li, fields, m - r:m + r + 1, m - r:m + r + 1]).abs().max() < 1e-15
            outside = full[li, fields].clone()
            outside[:, m - r:m + r + 1, m - r:m + r + 1] = 0
            assert outside.abs().max() == 0


D64_6 = torch.float64


def _bank_args(psf_min: float) -> dict:
    L, G, K, C = 3, 3, 5, 5
    g = torch.Generator().manual_seed(0)
    psf = torch.rand(L, G, G, K, K, dtype=D64_6, generator=g) + 0.1
    psf /= psf.sum((-1, -2), keepdim=True)
    psf[0, 0, 0, 1, 1] += psf[0, 0, 0, 0, 0].item() - psf_min  # the same sum with psf_min at [0, 0]
    psf[0, 0, 0, 0, 0] = psf_min
    c = torch.linspace(-1, 1, C, dtype=D64_6)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64_6) + 1) / G
    return dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64_6), field_x=f.clone(), field_y=f.clone(),
                chief=torch.stack([cx, cy], -1).expand(L, C, C, 2).clone(), chief_x=c.clone(), chief_y=c.clone(),
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))


def test_bank_accepts_psf_values_down_to_exactly_minus_1e_3():
    bank = PSFBank(**_bank_args(-1e-3))  # the bound itself is rounding, accepted
    assert bank.psf[0, 0, 0, 0, 0].item() == pytest.approx(-1e-3, rel=1e-3)
    with pytest.raises(InputValueError, match="PSF bank: PSFs must be non-negative, min is -0.0011"):
        PSFBank(**_bank_args(-1.1e-3))


def test_psf_bank_repr_shows_the_bank_not_its_resample_cache():
    """A bank's repr names its fields; the resampling cache is not part of what the bank is: the repr is the
    same before and after a resample is cached, and never mentions the cache."""
    torch.manual_seed(0)
    bank = tiny_bank()
    before = repr(bank)
    bank.resample_to(8, 8)
    after = repr(bank)
    assert before.startswith("PSFBank(psf=") and "display_mm=(24.0, 24.0)" in before
    assert after == before and "_cache" not in after


# ------------------------------------------------------------------ PSFBank.transmission
def test_default_transmission_is_float64_ones_like_a_recorded_one():
    """``PSFBank.transmission`` docstring: ``[L, Gy, Gx]`` float64; ones if the bank records none (the
    same dtype as a recorded ``meta["transmission"]`` and as the bank's own tables)."""
    L, G, K = 3, 2, 3
    psf = torch.zeros(L, G, G, K, K, dtype=F64)
    psf[..., K // 2, K // 2] = 1.0
    c = torch.linspace(-1, 1, 3, dtype=F64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = torch.tensor([-0.5, 0.5], dtype=F64)
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=F64), field_x=f, field_y=f,
                chief=torch.stack([cx, cy], -1).expand(L, 3, 3, 2).clone(), chief_x=c, chief_y=c,
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(10.0, 10.0))
    plain = PSFBank(**args).transmission
    assert plain.dtype == F64 and torch.equal(plain, torch.ones(L, G, G, dtype=F64))
    recorded = PSFBank(**args, meta={"transmission": [[[0.5] * G] * G] * L}).transmission
    assert recorded.dtype == plain.dtype == psf.dtype


D = torch.float64


needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")


@needs_optics
def test_psf_centroids_are_the_bilinear_first_moments_of_the_field_psfs():
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.prewarp_fit import _psf_centroids

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


@needs_optics
def test_exact_mode_fit_measures_centroids_and_flattens_by_brute_force():
    from controlgs_adapter.downstream.color import primaries_to_rgb_matrix, rgb_to_primaries_matrix
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp

    bank = PSFBank.default()
    # energy radiometry: the lens's brightness fall-off needs a gain; its mode is replaced by "exact"
    stage = PSFOptics(bank, mode="distortion", radiometry="energy")
    lut = fit_bank_prewarp(stage, 8, modes=("exact",))  # defaults: pool 2, 4 gain iterations
    assert lut.modes == ("exact",) and lut.placement == "fit" and stage.mode == "distortion"
    assert (lut.meta["size"], lut.meta["pool"], lut.meta["gain_iterations"]) == ([8, 8], 2, 4)
    assert lut.meta["radiometry"] == "energy" and set(lut.meta["residuals"]) == {"exact"}
    # measured: the 6 x 6 inner pixels whose light stays inside the frame (36 / 64, a regression pin);
    # the fixed point takes the 7 % fall-off to below 0.2 % at the centroids in 4 iterations
    assert lut.meta["residuals"]["exact"]["measured_fraction"] == 0.5625
    assert lut.meta["residuals"]["exact"]["flat_max_abs"] < 2e-3
    assert 0.0 <= lut.meta["seconds"] < 600.0
    disp, gain = lut.displacement_exact.double(), lut.gain_exact.double()
    assert disp.shape == (3, 4, 4, 2) and gain.shape == (3, 4, 4)
    # brute force: the eye image of every single lit display pixel (one primary at a time)
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


@needs_optics
def test_reach_of_a_display_pixels_light_by_hand():
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.downstream.prewarp_fit import _reach

    bank = PSFBank.default()
    assert bank.psf.shape[-1] == 33 and bank.display_mm == (24.0, 24.0) and bank.field_x.numel() == 30
    # the 30 field samples sit at the pixel centres of a 30-pixel grid: the pitch there is the bank's own;
    # 1.5 x the half-window 33 // 2 + 0.5 = 16.5 samples, over the 12 mm half display
    p = pixel_grid((30, 30), D)
    reach = _reach("exact", bank, p, D)
    # (rtol: the field coordinates are stored in float32, so the samples sit 1e-8 off the pixel centres)
    assert torch.allclose(reach, 1.5 * bank.psf_pitch_mm.double() * 16.5 / 12.0, rtol=1e-5)
    # distortion mode: 3 / min(H, W) = 3 / 30 everywhere
    dist = _reach("distortion", bank, pixel_grid((30, 40), D), D)
    assert dist.shape == (3, 30, 40) and float(dist.min()) == float(dist.max()) == 0.1


D64_7 = torch.float64


def _args_2(L=3, G=3, K=5, C=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64_7, generator=g) + 0.1
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64_7)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64_7) + 1) / G
    return dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64_7), field_x=f.clone(), field_y=f.clone(),
                chief=torch.stack([cx, cy], -1).expand(L, C, C, 2).clone(), chief_x=c.clone(), chief_y=c.clone(),
                wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


def _set(key, value):
    return lambda a: a.__setitem__(key, value(a) if callable(value) else value)


def _put(key, index, value):
    def f(a):
        a[key] = a[key].clone()
        a[key][index] = value
    return f


# ----------------------------------------------------------------------------- files
def _write(path, tensors=None, **header):
    a = _args_2()
    t = {k: a[k] for k in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y")}
    t.update(tensors or {})
    h = {"wavelengths_nm": [656, 550, 486], "display_mm": [24, 24]}
    h.update(header)
    return write_raw(path, {k: v for k, v in t.items() if v is not None}, h, kind="psf_bank", format_version=1)


@pytest.mark.parametrize("edit, match", [
    (_set("psf", lambda a: a["psf"][0]), r"psf must be \[L, Gy, Gx, K, K\] with odd K, got \[3, 3, 5, 5\]"),
    (_set("psf", lambda a: a["psf"][..., :4, :4]), "with odd K, got"),
    (_set("psf", lambda a: a["psf"][..., :3]), "with odd K, got"),
    (_set("psf", lambda a: a["psf"][:, :0]), "empty grid"),
    (_set("psf", lambda a: a["psf"][:2]), "2 PSF channels but 3 wavelengths"),
    (_set("psf_pitch_mm", lambda a: a["psf_pitch_mm"][:2]), r"psf_pitch_mm must be \[3, 3, 3\]"),
    (_set("field_y", lambda a: a["field_y"][:2]), "field grid"),
    (_set("chief", lambda a: a["chief"][0]), r"chief must be \[L, Cy, Cx, 2\] with L = 3"),
    (_set("chief", lambda a: a["chief"][:2]), r"chief must be \[L, Cy, Cx, 2\]"),
    (_set("chief", lambda a: torch.cat([a["chief"], a["chief"][..., :1]], -1)), r"chief must be \[L, Cy, Cx, 2\]"),
    (_set("chief_x", lambda a: a["chief_x"][:4]), "chief grid coordinates do not match"),
    (_set("chief_y", lambda a: a["chief_y"][:4]), "chief grid coordinates do not match"),
    (_put("psf_pitch_mm", (0, 1, 1), math.inf), "psf_pitch_mm holds 1 NaN/Inf"),
    (_put("chief", (1, 2, 2), math.nan), "chief holds 2 NaN/Inf"),
    (_put("field_x", 0, math.nan), "field_x holds 1 NaN"),
    (_put("field_y", 0, math.nan), "field_y holds 1 NaN"),
    (_put("chief_x", 0, math.nan), "chief_x holds 1 NaN"),
    (_put("chief_y", 0, math.nan), "chief_y holds 1 NaN"),
    (_put("psf_pitch_mm", (2, 0, 0), 0.0), "psf_pitch_mm must be positive"),
    (_set("field_x", torch.tensor([-0.5, 0.5, 0.0], dtype=D64_7)), "field_x must be increasing inside"),
    (_set("field_x", torch.tensor([-0.5, 0.0, 0.0], dtype=D64_7)), "field_x must be increasing inside"),
    (_set("field_y", torch.tensor([-0.5, 0.0, 1.5], dtype=D64_7)), "field_y must be increasing inside"),
    (_set("chief_y", torch.tensor([-1.0, -0.4, 0.0, 0.5, 1.0], dtype=D64_7)), r"chief_y must be uniform.*linspace\(-1, 1, 5\)"),
    (_set("display_mm", (24.0, 0.0)), "display_mm must be"),
    (_set("display_mm", (24.0, 24.0, 1.0)), "display_mm must be"),
    (_set("meta", {"transmission": "high"}), "meta.transmission must be numbers"),
    (_set("meta", {"transmission": [[1.0]]}), r"meta.transmission must be \[3, 3, 3\] numbers in \[0, 1\], got shape \[1, 1\]"),
    (_set("meta", {"transmission": torch.full((3, 3, 3), 1.01).tolist()}), r"in \[0, 1\]"),
    (_set("meta", {"transmission": torch.full((3, 3, 3), -0.01).tolist()}), r"in \[0, 1\]"),
    (_set("meta", {"transmission": torch.full((3, 3, 3), math.nan).tolist()}), r"in \[0, 1\]"),
])
def test_bad_banks_are_refused_by_name(edit, match):
    a = _args_2()
    edit(a)
    with pytest.raises(InputValueError, match=match):
        PSFBank(**a)


def test_an_empty_wavelength_list_is_refused():
    a = _args_2()
    a["psf"], a["psf_pitch_mm"], a["chief"], a["wavelengths_nm"] = a["psf"][:0], a["psf_pitch_mm"][:0], a["chief"][:0], ()
    with pytest.raises(InputValueError, match="empty grid.*0 wavelength"):
        PSFBank(**a)


def test_chief_grid_needs_two_samples_per_axis():
    a = _args_2(C=1)
    a["chief_x"] = a["chief_y"] = torch.zeros(1, dtype=D64_7)
    with pytest.raises(InputValueError, match=r"chief_x must be uniform from -1 to 1 \(linspace\(-1, 1, 1\)\)"):
        PSFBank(**a)


def test_sum_and_sign_tolerances_by_number():
    """Each PSF must sum to 1 within SUM_TOLERANCE = 5e-3 (float16 storage), then is renormalised;
    values down to -1e-3 (rounding) are accepted."""
    assert SUM_TOLERANCE == 5e-3
    a = _args_2()
    a["psf"] = a["psf"].clone()
    a["psf"][1, 2, 0] *= 1.004
    a["psf"][0, 0, 0, 1, 1] += a["psf"][0, 0, 0, 0, 0].item() + 9e-4         # the same sum ...
    a["psf"][0, 0, 0, 0, 0] = -9e-4                                           # ... with -9e-4: rounding, kept
    bank = PSFBank(**a)
    assert bank.psf.dtype == torch.float32 and bank.psf_pitch_mm.dtype == torch.float32
    assert bank.chief.dtype == torch.float32
    assert torch.allclose(bank.psf.double().sum((-1, -2)), torch.ones(3, 3, 3, dtype=D64_7), atol=1e-6)
    assert bank.psf[0, 0, 0, 0, 0].item() == pytest.approx(-9e-4, rel=1e-4)
    a = _args_2()
    a["psf"] = a["psf"].clone()
    a["psf"][1, 2, 0] *= 1.006                                                 # flat index 1 * 9 + 2 * 3 + 0 = 15
    with pytest.raises(InputValueError, match=r"sum to 1 \(\+-0.005\); PSF #15 \(flat index over \[L, Gy, Gx\]\) sums to 1.006"):
        PSFBank(**a)
    a = _args_2()
    a["psf"] = a["psf"].clone()
    a["psf"][0, 0, 0, 0, 0] = -2e-3
    with pytest.raises(InputValueError, match="non-negative, min is -0.002"):
        PSFBank(**a)


def test_a_single_field_sample_is_a_valid_bank():
    a = _args_2(G=1)
    bank = PSFBank(**a)
    assert bank.field_x.tolist() == [0.0] and bank.num_wavelengths == 3
    assert torch.equal(bank.transmission, torch.ones(3, 1, 1, dtype=D64_7))   # none recorded: ones


def test_transmission_is_read_from_meta():
    a = _args_2()
    T = torch.linspace(0, 1, 27, dtype=D64_7).reshape(3, 3, 3)
    a["meta"] = {"transmission": T.tolist()}
    bank = PSFBank(**a)
    assert bank.transmission.dtype == D64_7 and torch.equal(bank.transmission, T)   # both ends of [0, 1] allowed


def test_saved_file_holds_float16_psfs_and_its_units(tmp_path):

    bank = PSFBank(**_args_2(), meta={"k": [1, 2]})
    bank.save(tmp_path / "b.safetensors")
    t, h = load_tensors(tmp_path / "b.safetensors", kind="psf_bank", max_version=1)
    assert t["psf"].dtype == torch.float16 and t["chief"].dtype == torch.float32
    assert t["chief_x"].dtype == torch.float64 and t["psf_pitch_mm"].dtype == torch.float32
    assert h["wavelengths_nm"] == [656.0, 550.0, 486.0] and h["display_mm"] == [24.0, 24.0] and h["meta"] == {"k": [1, 2]}
    assert h["shapes"]["psf"] == [3, 3, 3, 5, 5] and "row = y" in h["units"]["psf"]
    back = PSFBank.load(tmp_path / "b.safetensors", display_mm=(24.0, 24.0 * (1 + 5e-7)))   # within 1e-6 relative
    assert back.display_mm == (24.0, 24.0) and back.meta == {"k": [1, 2]}
    with pytest.raises(FileFormatError, match=r"b.safetensors: bank was made for a 24.0 x 24.0 mm display, expected 24.0 x 24.001"):
        PSFBank.load(tmp_path / "b.safetensors", display_mm=(24.0, 24.001))
    with pytest.raises(FileFormatError, match="bank was made for a 24.0 x 24.0 mm display"):
        PSFBank.load(tmp_path / "b.safetensors", display_mm=(24.0 * (1 + 1.5e-6), 24.0))   # beyond 1e-6 relative


@pytest.mark.parametrize("tensors, header, match", [
    ({"chief": None}, {}, r"lacks tensors \['chief'\]"),
    ({"field_x": None, "chief_y": None}, {}, r"lacks tensors \['chief_y', 'field_x'\]"),
    ({}, {"wavelengths_nm": "656"}, "header field 'wavelengths_nm' must be a list of one or more positive numbers"),
    ({}, {"wavelengths_nm": []}, "'wavelengths_nm' must be a list"),
    ({}, {"wavelengths_nm": [656, 550, True]}, "'wavelengths_nm'"),
    ({}, {"wavelengths_nm": [656, 550, -486]}, "'wavelengths_nm'"),
    ({}, {"wavelengths_nm": [656, 550, "486"]}, "'wavelengths_nm'"),
    ({}, {"display_mm": [24, 24, 24]}, "header field 'display_mm' must be a list of 2 positive numbers"),
    ({}, {"display_mm": [24, 0]}, "'display_mm'"),
    ({}, {"meta": [1]}, "header field 'meta' must be a JSON object, got list"),
    ({"psf_pitch_mm": torch.zeros(3, 3, 3)}, {}, r"x.safetensors: PSF bank: psf_pitch_mm must be positive"),
])
def test_bad_bank_files_are_refused_naming_the_file_and_field(tmp_path, tensors, header, match):
    _write(tmp_path / "x.safetensors", tensors, **header)
    with pytest.raises(FileFormatError, match=match):
        PSFBank.load(tmp_path / "x.safetensors")


def test_a_file_without_meta_loads_with_empty_meta(tmp_path):
    bank = PSFBank.load(_write(tmp_path / "x.safetensors"))
    assert bank.meta == {} and bank.wavelengths_nm == (656.0, 550.0, 486.0)


def test_the_default_bank_is_loaded_once_from_the_package():
    assert DEFAULT_BANK_FILE == "cardboard_psf_bank.safetensors"
    assert PSFBank.default() is PSFBank.default()


@pytest.mark.parametrize("h, w", [(1, 8), (8, 1), (8.0, 8), (8, "8")])
def test_resample_to_refuses_bad_sizes(h, w):
    bank = PSFBank(**_args_2())
    with pytest.raises(InputValueError, match="resample_to: height and width must be ints >= 2"):
        bank.resample_to(h, w)


def test_resample_to_caches_per_dtype_and_placement():
    bank = PSFBank(**_args_2())
    a = bank.resample_to(2, 2)
    assert a is bank.resample_to(2, 2) and a.H == 2 and a.W == 2 and a.dtype == torch.float32
    assert bank.resample_to(2, 2, dtype=D64_7) is not a and bank.resample_to(2, 2, dtype=D64_7).dtype == D64_7
    assert bank.resample_to(2, 2, placement="stretch") is not a


def test_build_bank_defaults_made_the_shipped_bank():
    """The shipped bank records the settings it was generated with; they are build_bank's defaults."""
    import inspect

    from controlgs_adapter.downstream.optics.bank import PSFBank

    gen = PSFBank.default().meta["generator"]
    defaults = {k: p.default for k, p in inspect.signature(build_bank).parameters.items()}
    assert gen["grid"] == [30, 30] == list(defaults["grid"])
    assert gen["psf_size"] == 33 == defaults["psf_size"]
    assert gen["pupil_samples"] == 192 == defaults["pupil_samples"]
    assert gen["chief_grid"] == [65, 65] == list(defaults["chief_grid"])
    assert gen["min_pitch_px"] == 0.125 == defaults["min_pitch_px"]
    assert gen["reference_width_px"] == 1024 == defaults["reference_width_px"]


D64_8 = torch.float64


def _bank_2(L=3, G=3, K=5, pitch_mm=1.0, chief=lambda d: d, C=9, seed=0, flip_x=False):
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64_8, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64_8)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64_8) + 1) / G
    ch = torch.stack([-chief(cx) if flip_x else chief(cx), chief(cy)], -1).expand(L, C, C, 2).clone()
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64_8), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


def test_anisotropic_pixels_resample_each_axis_with_its_own_pitch():
    """Stretch placement of a 12 x 24 image on the 24 mm display: pixels 1 mm wide, 2 mm tall. A
    horizontal line PSF (5 cells of 1 mm in the centre row) is 5 taps of 1/5 along x and one tap
    along y; the margin follows the finer axis (m = ceil(1 * 2.5 / 1 - 1/2) = 2)."""
    psf = torch.zeros(3, 1, 1, 5, 5, dtype=D64_8)
    psf[..., 2, :] = 0.2
    c = torch.linspace(-1, 1, 5, dtype=D64_8)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    bank = PSFBank(psf=psf, psf_pitch_mm=torch.ones(3, 1, 1, dtype=D64_8), field_x=torch.zeros(1, dtype=D64_8),
                   field_y=torch.zeros(1, dtype=D64_8), chief=torch.stack([cx, cy], -1).expand(3, 5, 5, 2).clone(),
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
    rb = bank.resample_to(12, 24, dtype=D64_8, placement="stretch", radiometry="energy")
    assert rb.region.pitch_mm == (1.0, 2.0) and (rb.m, rb.k) == (2, 5)
    want = torch.zeros(5, 5, dtype=D64_8)
    want[2] = 0.2
    assert torch.allclose(rb.kernels[1, 0], want, atol=1e-7)
    k, r = rb.field_kernels(1, torch.tensor([0]))
    assert r == 2 and torch.allclose(k[0], want, atol=1e-7)
    k, r = rb.field_kernels(1, torch.tensor([0]), rb.box_matrices(1))
    assert torch.allclose(k[0], want, atol=1e-7)
    # the transposed image (24 x 12): 2 mm wide pixels; the line [-2.5, 2.5] mm covers 1.5 mm of the
    # taps at +-2 mm and all 2 mm of the centre tap: 0.3, 0.4, 0.3 (the PSF is stored as float32)
    rt = bank.resample_to(24, 12, dtype=D64_8, placement="stretch", radiometry="energy")
    assert rt.region.pitch_mm == (2.0, 1.0) and rt.m == 2
    assert rt.kernels[1, 0, 2].tolist() == pytest.approx([0.0, 0.3, 0.4, 0.3, 0.0], abs=1e-7)
    assert rt.kernels[1, 0].sum().item() == pytest.approx(1.0, abs=1e-7)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_fast_mode_rank_is_the_smallest_within_the_relative_residual(radiometry):
    """Per field group, the number of eigen-PSFs is the smallest R whose truncated SVD leaves a
    relative Frobenius residual sqrt(sum_{i > R} s_i^2 / sum s_i^2) <= tol (reference: torch's SVD
    of the group's 4 kernels, float64)."""
    rb = _bank_2(G=2, K=5, seed=3).resample_to(10, 10, dtype=D64_8, radiometry=radiometry)
    K, _ = rb.field_kernels(1, torch.arange(4))
    s = torch.linalg.svdvals(K.reshape(4, -1))
    rel = [(s[r:] ** 2).sum().sqrt().item() / (s ** 2).sum().sqrt().item() for r in range(5)]   # residual of rank r
    seen = set()
    for tol in (0.9, 0.5, 0.3, 0.1, 0.03, 0.01, 0.0):
        want = min(r for r in range(1, 5) if rel[r] <= tol or r == 4)
        (bk,) = rb.zones(2, tol)[1]
        assert bk.kernel_fft.shape[0] == want, (tol, rel)
        seen.add(want)
    assert len(seen) >= 3                                                       # the tolerances reach several ranks


def test_bank_fingerprint_tracks_every_optics_field():
    from controlgs_adapter.downstream.optics.bank import PSFBank

    bank = PSFBank.default()
    fp = bank_fingerprint(bank)
    assert len(fp) == 16 and all(ch in "0123456789abcdef" for ch in fp)
    # copies bypass __init__: PSFBank renormalises its PSFs there, which moves float32 rounding
    def with_fields(**fields: object) -> PSFBank:
        other = copy.copy(bank)
        other._cache = {}  # not shared with the process-wide default bank
        for name, value in fields.items():
            setattr(other, name, value)
        return other

    same = with_fields(psf=bank.psf.clone(), chief=bank.chief.clone(), meta={"other": 1})
    assert bank_fingerprint(same) == fp  # same numbers, other metadata
    changed = {
        "psf": bank.psf.flip(-1), "psf_pitch_mm": bank.psf_pitch_mm * 1.01, "field_x": bank.field_x * 0.99,
        "field_y": bank.field_y * 0.99, "chief": bank.chief * 1.001, "chief_x": bank.chief_x * 0.99,
        "chief_y": bank.chief_y * 0.99, "wavelengths_nm": tuple(w + 1 for w in bank.wavelengths_nm),
        "display_mm": (bank.display_mm[0] + 1, bank.display_mm[1]),
    }
    fps = {name: bank_fingerprint(with_fields(**{name: value})) for name, value in changed.items()}
    assert all(v != fp for v in fps.values()), fps
    assert len(set(fps.values())) == len(fps)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
