"""Tests of ``controlgs_adapter.downstream.optics.bank``: a PSF bank checks every field when it is made
and when it is read (naming the field, and the file), round-trips through its file, ships the
Cardboard lens, and resamples (cached) onto an image's pixel grid."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.rawfiles import write_raw

from controlgs_adapter.downstream.optics.bank import BANK_KIND, DEFAULT_BANK_FILE, SUM_TOLERANCE, PSFBank
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors

D64 = torch.float64
TENSORS = ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y")


def _bank_args(L=3, G=3, K=5, C=5, seed=0):
    """Valid PSFBank arguments: seeded random PSFs on a G x G field grid, identity chief rays on C x C, 24 mm."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=g) + 0.1
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64), field_x=f.clone(), field_y=f.clone(),
                chief=torch.stack([cx, cy], -1).expand(L, C, C, 2).clone(), chief_x=c.clone(), chief_y=c.clone(),
                wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


def _set(key, value):
    return lambda a: a.__setitem__(key, value(a) if callable(value) else value)


def _put(key, index, value):
    def f(a):
        a[key] = a[key].clone()
        a[key][index] = value
    return f


def _no_wavelengths(a):
    a["psf"], a["psf_pitch_mm"], a["chief"], a["wavelengths_nm"] = a["psf"][:0], a["psf_pitch_mm"][:0], a["chief"][:0], ()


def _one_chief_sample(a):
    a.update(chief=_bank_args(C=1)["chief"], chief_x=torch.zeros(1, dtype=D64), chief_y=torch.zeros(1, dtype=D64))


BAD_BANKS = [
    *[(_set("display_mm", v), r"^PSF bank: display_mm must be") for v in [
        (math.nan, math.nan), (24.0, math.inf), (24.0, -1.0), (0.0, 24.0), (24.0, 0.0), (24.0,), (24.0, 24.0, 24.0),
        (24.0, 24.0, 1.0), "24x24", (True, 24.0), ("24", "24"), None, 24.0]],
    *[(_set("wavelengths_nm", v), r"^PSF bank: wavelengths_nm must be") for v in [
        (656.0, math.nan, 486.0), (656.0, 550.0, -486.0), (656.0, 0.0, 486.0), (656.0, "550", 486.0),
        (656.0, math.inf, 486.0), "656", None]],
    *[(_set(name, lambda a, n=name: a[n].long()), rf"^PSF bank: {name} must be a floating-point torch.Tensor, got torch.int64")
      for name in TENSORS],
    *[(_set(name, lambda a, n=name: a[n].tolist()), rf"^PSF bank: {name} must be a floating-point torch.Tensor, got list")
      for name in TENSORS],
    (_set("psf", lambda a: a["psf"][0]), r"psf must be \[L, Gy, Gx, K, K\] with odd K, got \[3, 3, 5, 5\]"),
    (_set("psf", lambda a: a["psf"][..., :4, :4]), "with odd K, got"),
    (_set("psf", lambda a: a["psf"][..., :3]), "with odd K, got"),
    (_set("psf", lambda a: a["psf"][:, :0]), "empty grid"),
    (_no_wavelengths, "empty grid.*0 wavelength"),
    (_set("psf", lambda a: a["psf"][:2]), "2 PSF channels but 3 wavelengths"),
    (_set("wavelengths_nm", (656.0, 550.0)), "3 PSF channels but 2 wavelengths"),
    (_set("psf_pitch_mm", lambda a: a["psf_pitch_mm"][:2]), r"psf_pitch_mm must be \[3, 3, 3\]"),
    (_set("psf_pitch_mm", lambda a: a["psf_pitch_mm"][:, :2]), r"psf_pitch_mm must be \[3, 3, 3\]"),
    (_set("field_x", lambda a: a["field_x"][:2]), "field grid"),
    (_set("field_y", lambda a: a["field_y"][:2]), "field grid"),
    (_set("chief", lambda a: a["chief"][0]), r"chief must be \[L, Cy, Cx, 2\] with L = 3"),
    (_set("chief", lambda a: a["chief"][:2]), r"chief must be \[L, Cy, Cx, 2\]"),
    (_set("chief", lambda a: torch.cat([a["chief"], a["chief"][..., :1]], -1)), r"chief must be \[L, Cy, Cx, 2\]"),
    (_set("chief_x", lambda a: a["chief_x"][:4]), "chief grid coordinates do not match"),
    (_set("chief_y", lambda a: a["chief_y"][:4]), "chief grid coordinates do not match"),
    (_put("psf", (0, 1, 1, 2, 2), math.nan), "psf holds 1 NaN/Inf"),
    (_put("psf_pitch_mm", (0, 0, 0), math.nan), "^PSF bank: psf_pitch_mm holds 1 NaN/Inf"),
    (_put("psf_pitch_mm", (0, 1, 1), math.inf), "psf_pitch_mm holds 1 NaN/Inf"),
    (_put("chief", (0, 0, 0, 0), math.nan), "^PSF bank: chief holds 1 NaN/Inf"),
    (_put("chief", (1, 2, 2), math.nan), "chief holds 2 NaN/Inf"),
    *[(_put(name, 0, math.nan), rf"^PSF bank: {name} holds 1 NaN/Inf") for name in ("field_x", "field_y", "chief_x", "chief_y")],
    (_put("psf_pitch_mm", (2, 0, 0), 0.0), "psf_pitch_mm must be positive"),
    (_set("psf", lambda a: a["psf"] * 1.1), "sum to 1"),
    (_set("field_x", torch.tensor([-0.5, 0.5, 0.0], dtype=D64)), "field_x must be increasing inside"),
    (_set("field_x", torch.tensor([-0.5, 0.0, 0.0], dtype=D64)), "field_x must be increasing inside"),
    (_set("field_y", torch.tensor([-0.5, 0.0, 1.5], dtype=D64)), "field_y must be increasing inside"),
    (_set("chief_x", torch.linspace(-0.9, 1, 5, dtype=D64)), r"chief_x must be uniform.*linspace\(-1, 1, 5\)"),
    (_set("chief_y", torch.tensor([-1.0, -0.4, 0.0, 0.5, 1.0], dtype=D64)), r"chief_y must be uniform.*linspace\(-1, 1, 5\)"),
    (_one_chief_sample, r"chief_x must be uniform from -1 to 1 \(linspace\(-1, 1, 1\)\)"),
    (_set("meta", {"transmission": "high"}), "meta.transmission must be numbers"),
    (_set("meta", {"transmission": [[1.0]]}), r"meta.transmission must be \[3, 3, 3\] numbers in \[0, 1\], got shape \[1, 1\]"),
    *[(_set("meta", {"transmission": torch.full((3, 3, 3), t).tolist()}), r"transmission must be .* in \[0, 1\]")
      for t in (1.01, 1.5, -0.01, -0.2, math.nan)],
]


@pytest.mark.parametrize("edit, match", BAD_BANKS)
def test_bad_banks_are_refused_by_name(edit, match):
    a = _bank_args()
    edit(a)
    with pytest.raises(InputValueError, match=match):
        PSFBank(**a)


def test_accepted_numbers_grids_and_their_storage():
    """Display size and wavelengths of any real type become floats; one field sample is a valid grid;
    PSFs, pitches and chief rays are held in float32."""
    bank = PSFBank(**{**_bank_args(), "display_mm": [24, 30], "wavelengths_nm": [656, 550.5, 486]})
    assert bank.display_mm == (24.0, 30.0) and bank.wavelengths_nm == (656.0, 550.5, 486.0)
    assert all(isinstance(v, float) for v in (*bank.display_mm, *bank.wavelengths_nm))
    assert bank.psf.dtype == bank.psf_pitch_mm.dtype == bank.chief.dtype == torch.float32
    single = PSFBank(**_bank_args(G=1))
    assert single.field_x.tolist() == [0.0] and single.num_wavelengths == 3


def test_psf_sum_and_sign_tolerances_by_number():
    """Each PSF must sum to 1 within SUM_TOLERANCE = 5e-3 (float16 storage), then is renormalised; values
    down to -1e-3 (rounding) are accepted, the bound itself included."""
    assert SUM_TOLERANCE == 5e-3
    a = _bank_args()
    a["psf"] = a["psf"].clone()
    a["psf"][1, 2, 0] *= 1.004
    a["psf"][0, 0, 0, 1, 1] += a["psf"][0, 0, 0, 0, 0].item() + 9e-4         # the same sum ...
    a["psf"][0, 0, 0, 0, 0] = -9e-4                                           # ... with -9e-4: rounding, kept
    bank = PSFBank(**a)
    assert torch.allclose(bank.psf.double().sum((-1, -2)), torch.ones(3, 3, 3, dtype=D64), atol=1e-6)
    assert bank.psf[0, 0, 0, 0, 0].item() == pytest.approx(-9e-4, rel=1e-4)
    for low, accepted in ((-1e-3, True), (-1.1e-3, False), (-2e-3, False), (-0.01, False)):
        a = _bank_args()
        a["psf"][0, 0, 0, 1, 1] += a["psf"][0, 0, 0, 0, 0].item() - low
        a["psf"][0, 0, 0, 0, 0] = low
        if accepted:
            assert PSFBank(**a).psf[0, 0, 0, 0, 0].item() == pytest.approx(low, rel=1e-3)
        else:
            with pytest.raises(InputValueError, match=rf"PSFs .*non-negative.*{low:.3g}"):
                PSFBank(**a)
    a = _bank_args()
    a["psf"][1, 2, 0] *= 1.006                                                 # flat index 1 * 9 + 2 * 3 + 0 = 15
    with pytest.raises(InputValueError, match=r"\+-0.005.*PSF #15.*1.006"):
        PSFBank(**a)


def test_transmission_is_read_from_meta_else_float64_ones():
    """``PSFBank.transmission``: ``[L, Gy, Gx]`` float64 from ``meta["transmission"]`` (both ends of [0, 1]
    allowed), ones if the bank records none (one field sample included)."""
    plain = PSFBank(**_bank_args()).transmission
    assert plain.dtype == D64 and torch.equal(plain, torch.ones(3, 3, 3, dtype=D64))
    assert torch.equal(PSFBank(**_bank_args(G=1)).transmission, torch.ones(3, 1, 1, dtype=D64))
    T = torch.linspace(0, 1, 27, dtype=D64).reshape(3, 3, 3)
    recorded = PSFBank(**_bank_args(), meta={"transmission": T.tolist()}).transmission
    assert recorded.dtype == D64 and torch.equal(recorded, T)
    quarter = PSFBank(**_bank_args(), meta={"transmission": [[[0.25] * 3] * 3] * 3}).transmission
    assert torch.equal(quarter, torch.full((3, 3, 3), 0.25, dtype=D64))


# ----------------------------------------------------------------------------- files
def _write(path, tensors=None, drop=(), **header):
    """A bank file of :func:`_bank_args` with ``tensors`` replaced, ``drop`` left out, header fields
    replaced (None: left out)."""
    a = _bank_args()
    t = {k: a[k] for k in TENSORS if k not in drop}
    t.update(tensors or {})
    h = {"wavelengths_nm": [656, 550, 486], "display_mm": [24, 24], **header}
    return write_raw(path, t, {k: v for k, v in h.items() if v is not None}, kind=BANK_KIND, format_version=1)


BAD_FILES = [
    ({"drop": ("chief",)}, r"lacks tensors \['chief'\]"),
    ({"drop": ("psf",)}, r"lacks tensors \['psf'\]"),
    ({"drop": ("field_x", "chief_y")}, r"lacks tensors \['chief_y', 'field_x'\]"),
    ({"wavelengths_nm": None}, "'wavelengths_nm'"),
    *[({"wavelengths_nm": v}, "header field 'wavelengths_nm' must be a list of one or more positive numbers")
      for v in ("656", [], [656, 550, True], [-1, 550, 486], [656, 550, -486], [656, 550, "486"])],
    *[({"display_mm": v}, "header field 'display_mm' must be a list of 2 positive numbers")
      for v in ("66", [24], [0, 24], [24, 0], [True, 24], ["24", "24"], [24, 24, 24])],
    ({"meta": [1]}, "header field 'meta' must be a JSON object, got list"),
    ({"tensors": {"psf_pitch_mm": torch.zeros(3, 3, 3)}}, "PSF bank: psf_pitch_mm must be positive"),
    ({"tensors": {"psf_pitch_mm": torch.full((3, 3, 3), math.nan)}}, "psf_pitch_mm holds"),
    ({"tensors": {"psf": torch.full((3, 3, 3, 5, 5), math.nan)}}, "psf holds 675 NaN"),
    ({"tensors": {"psf": torch.full((3, 3, 3, 4, 4), 1 / 16)}}, "psf must be .* with odd K"),
    ({"tensors": {"psf": torch.zeros(3, 0, 0, 5, 5), "psf_pitch_mm": torch.zeros(3, 0, 0), "field_x": torch.zeros(0),
                  "field_y": torch.zeros(0)}}, "empty grid"),
]


@pytest.mark.parametrize("kw, match", BAD_FILES)
def test_bad_bank_files_are_refused_naming_the_file_and_field(tmp_path, kw, match):
    path = _write(tmp_path / "x.safetensors", **kw)
    with pytest.raises(FileFormatError, match=rf"^{path}: .*{match}"):
        PSFBank.load(path)


@pytest.mark.parametrize("version", [True, "1", 0, None], ids=repr)
def test_bank_file_format_version_must_be_one(tmp_path, version):
    path = write_raw(tmp_path / "bank.safetensors", {"psf": _bank_args()["psf"]}, {"wavelengths_nm": [656, 550, 486]},
                     kind=BANK_KIND, format_version=version)
    with pytest.raises(FileFormatError, match=r"bank\.safetensors.*format_version"):
        PSFBank.load(path)


def test_file_round_trip_float16_psfs_units_and_display_check(tmp_path):
    """The file holds float16 PSFs (read back renormalised, to 1e-3), float32 chief rays and pitches,
    float64 grids, the header's wavelengths, display, meta, shapes and units; loading checks the display
    size to 1e-6 relative, the file's kind, and refuses a truncated file. A file without meta loads
    with empty meta."""
    bank = PSFBank(**_bank_args(), meta={"k": [1, 2]})
    path = tmp_path / "b.safetensors"
    bank.save(path)
    t, h = load_tensors(path, kind="psf_bank", max_version=1)
    assert t["psf"].dtype == torch.float16 and t["chief"].dtype == torch.float32
    assert t["chief_x"].dtype == torch.float64 and t["psf_pitch_mm"].dtype == torch.float32
    assert h["wavelengths_nm"] == [656.0, 550.0, 486.0] and h["display_mm"] == [24.0, 24.0] and h["meta"] == {"k": [1, 2]}
    assert h["shapes"]["psf"] == [3, 3, 3, 5, 5] and "row = y" in h["units"]["psf"]
    back = PSFBank.load(path, display_mm=(24.0, 24.0 * (1 + 5e-7)))   # within 1e-6 relative
    assert torch.allclose(back.psf, bank.psf, atol=1e-3)
    assert torch.allclose(back.psf.sum((-1, -2)), torch.ones(3, 3, 3), atol=1e-6)
    assert torch.equal(back.chief, bank.chief) and back.wavelengths_nm == bank.wavelengths_nm
    assert back.display_mm == (24.0, 24.0) and back.meta == {"k": [1, 2]}
    with pytest.raises(FileFormatError, match=r"b\.safetensors.*24\.0 x 24\.0 mm.*24\.0 x 24\.001"):
        PSFBank.load(path, display_mm=(24.0, 24.001))
    for display in ((24.0 * (1 + 1.5e-6), 24.0), (30.0, 20.0)):                  # beyond 1e-6 relative
        with pytest.raises(FileFormatError, match="bank was made for a 24.0 x 24.0 mm display"):
            PSFBank.load(path, display_mm=display)
    other = save_tensors(tmp_path / "other.safetensors", {"x": torch.zeros(1)}, {}, kind="adapter", format_version=1)
    with pytest.raises(FileFormatError, match="other.safetensors.*psf_bank"):
        PSFBank.load(other)
    (tmp_path / "trunc.safetensors").write_bytes(path.read_bytes()[:200])
    with pytest.raises(FileFormatError, match="trunc.safetensors"):
        PSFBank.load(tmp_path / "trunc.safetensors")
    bare = PSFBank.load(_write(tmp_path / "x.safetensors"))
    assert bare.meta == {} and bare.wavelengths_nm == (656.0, 550.0, 486.0)


# ----------------------------------------------------------------------------- the shipped bank
def test_default_bank_is_the_cardboard_lens_loaded_once():
    assert DEFAULT_BANK_FILE == "cardboard_psf_bank.safetensors"
    bank = PSFBank.default()
    assert PSFBank.default() is bank
    assert bank.wavelengths_nm == (656.0, 550.0, 486.0) and bank.display_mm == (24.0, 24.0)
    assert tuple(bank.psf.shape[:3]) == (3, 30, 30)
    assert bank.meta["prescription"]["surfaces"][0]["radius_mm"] == 290.444
    # corner: pincushion distortion; blue lands further out than red
    corner = bank.chief[:, -1, -1, 0]
    assert 1.15 < corner[1] < 1.25 and corner[2] > corner[1] > corner[0]
    # the corner PSF is ~100x wider than the central one and keeps all its light in the stored window
    px = 24 / 1024
    assert bank.psf_pitch_mm[1, 0, 0] / px > 4 and bank.psf_pitch_mm[1, 15, 15] / px < 0.2


# ----------------------------------------------------------------------------- resample_to
def test_resample_to_caches_per_size_dtype_device_placement_and_radiometry():
    """One resampled bank per (size, device, dtype, placement, radiometry): the same object back for the
    same key ("cpu:0" is the tensors' name of "cpu"), float32 by default; the repr names the bank's fields,
    never the cache."""
    bank = PSFBank(**_bank_args())
    before = repr(bank)
    a = bank.resample_to(2, 2)
    assert a is bank.resample_to(2, 2) and a.H == 2 and a.W == 2 and a.dtype == torch.float32
    assert bank.resample_to(2, 2, device="cpu:0") is a
    f64 = bank.resample_to(2, 2, dtype=D64)
    assert f64 is not a and f64.dtype == D64
    assert bank.resample_to(2, 2, placement="stretch") is not a
    assert bank.resample_to(2, 2, radiometry="energy") is not a
    assert bank.resample_to(2, 3) is not a
    assert repr(bank) == before and before.startswith("PSFBank(psf=") and "display_mm=(24.0, 24.0)" in before
    assert "_cache" not in before


def test_resample_to_places_an_image_of_another_aspect():
    bank = PSFBank(**_bank_args())
    fit, stretch = bank.resample_to(48, 64), bank.resample_to(48, 64, placement="stretch")
    assert (fit.region.half_x, fit.region.half_y) == (1.0, 0.75) and fit.W == 64
    assert (stretch.region.half_x, stretch.region.half_y) == (1.0, 1.0)


@pytest.mark.parametrize("kw, match", [
    *[(dict(height=h, width=w), "resample_to: height and width must be ints >= 2") for h, w in [(1, 8), (8, 1), (8.0, 8), (8, "8")]],
    *[(dict(device=d), rf"resample_to: device {d!r} is not a usable torch device here") for d in ("banana", 3.5)],
    (dict(placement="crop"), "placement must be one of .*'crop'"),
    (dict(radiometry="photons"), "radiometry must be one of .*'photons'"),
])
def test_resample_to_refuses_bad_arguments_by_name(kw, match):
    kw = {"height": 8, "width": 8, **kw}
    with pytest.raises(InputValueError, match=match):
        PSFBank(**_bank_args()).resample_to(kw.pop("height"), kw.pop("width"), **kw)
