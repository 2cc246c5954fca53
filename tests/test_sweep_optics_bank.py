"""PSFBank checks, file header checks and tolerances pinned by number; every refusal triggered and its
message (field, file) checked."""

import math

import pytest
import torch

from controlgs_adapter.downstream.optics.bank import DEFAULT_BANK_FILE, SUM_TOLERANCE, PSFBank
from controlgs_adapter.errors import FileFormatError, InputValueError

from _rawfiles import write_raw

D64 = torch.float64


def _args(L=3, G=3, K=5, C=5, seed=0):
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
    (_set("field_x", torch.tensor([-0.5, 0.5, 0.0], dtype=D64)), "field_x must be increasing inside"),
    (_set("field_x", torch.tensor([-0.5, 0.0, 0.0], dtype=D64)), "field_x must be increasing inside"),
    (_set("field_y", torch.tensor([-0.5, 0.0, 1.5], dtype=D64)), "field_y must be increasing inside"),
    (_set("chief_y", torch.tensor([-1.0, -0.4, 0.0, 0.5, 1.0], dtype=D64)), r"chief_y must be uniform.*linspace\(-1, 1, 5\)"),
    (_set("display_mm", (24.0, 0.0)), "display_mm must be"),
    (_set("display_mm", (24.0, 24.0, 1.0)), "display_mm must be"),
    (_set("meta", {"transmission": "high"}), "meta.transmission must be numbers"),
    (_set("meta", {"transmission": [[1.0]]}), r"meta.transmission must be \[3, 3, 3\] numbers in \[0, 1\], got shape \[1, 1\]"),
    (_set("meta", {"transmission": torch.full((3, 3, 3), 1.01).tolist()}), r"in \[0, 1\]"),
    (_set("meta", {"transmission": torch.full((3, 3, 3), -0.01).tolist()}), r"in \[0, 1\]"),
    (_set("meta", {"transmission": torch.full((3, 3, 3), math.nan).tolist()}), r"in \[0, 1\]"),
])
def test_bad_banks_are_refused_by_name(edit, match):
    a = _args()
    edit(a)
    with pytest.raises(InputValueError, match=match):
        PSFBank(**a)


def test_an_empty_wavelength_list_is_refused():
    a = _args()
    a["psf"], a["psf_pitch_mm"], a["chief"], a["wavelengths_nm"] = a["psf"][:0], a["psf_pitch_mm"][:0], a["chief"][:0], ()
    with pytest.raises(InputValueError, match="empty grid.*0 wavelength"):
        PSFBank(**a)


def test_chief_grid_needs_two_samples_per_axis():
    a = _args(C=1)
    a["chief_x"] = a["chief_y"] = torch.zeros(1, dtype=D64)
    with pytest.raises(InputValueError, match=r"chief_x must be uniform from -1 to 1 \(linspace\(-1, 1, 1\)\)"):
        PSFBank(**a)


def test_sum_and_sign_tolerances_by_number():
    """Each PSF must sum to 1 within SUM_TOLERANCE = 5e-3 (float16 storage), then is renormalised;
    values down to -1e-3 (rounding) are accepted."""
    assert SUM_TOLERANCE == 5e-3
    a = _args()
    a["psf"] = a["psf"].clone()
    a["psf"][1, 2, 0] *= 1.004
    a["psf"][0, 0, 0, 1, 1] += a["psf"][0, 0, 0, 0, 0].item() + 9e-4         # the same sum ...
    a["psf"][0, 0, 0, 0, 0] = -9e-4                                           # ... with -9e-4: rounding, kept
    bank = PSFBank(**a)
    assert bank.psf.dtype == torch.float32 and bank.psf_pitch_mm.dtype == torch.float32
    assert bank.chief.dtype == torch.float32
    assert torch.allclose(bank.psf.double().sum((-1, -2)), torch.ones(3, 3, 3, dtype=D64), atol=1e-6)
    assert bank.psf[0, 0, 0, 0, 0].item() == pytest.approx(-9e-4, rel=1e-4)
    a = _args()
    a["psf"] = a["psf"].clone()
    a["psf"][1, 2, 0] *= 1.006                                                 # flat index 1 * 9 + 2 * 3 + 0 = 15
    with pytest.raises(InputValueError, match=r"sum to 1 \(\+-0.005\); PSF #15 \(flat index over \[L, Gy, Gx\]\) sums to 1.006"):
        PSFBank(**a)
    a = _args()
    a["psf"] = a["psf"].clone()
    a["psf"][0, 0, 0, 0, 0] = -2e-3
    with pytest.raises(InputValueError, match="non-negative, min is -0.002"):
        PSFBank(**a)


def test_a_single_field_sample_is_a_valid_bank():
    a = _args(G=1)
    bank = PSFBank(**a)
    assert bank.field_x.tolist() == [0.0] and bank.num_wavelengths == 3
    assert torch.equal(bank.transmission, torch.ones(3, 1, 1, dtype=D64))   # none recorded: ones


def test_transmission_is_read_from_meta():
    a = _args()
    T = torch.linspace(0, 1, 27, dtype=D64).reshape(3, 3, 3)
    a["meta"] = {"transmission": T.tolist()}
    bank = PSFBank(**a)
    assert bank.transmission.dtype == D64 and torch.equal(bank.transmission, T)   # both ends of [0, 1] allowed


# ----------------------------------------------------------------------------- files
def _write(path, tensors=None, **header):
    a = _args()
    t = {k: a[k] for k in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x", "chief_y")}
    t.update(tensors or {})
    h = {"wavelengths_nm": [656, 550, 486], "display_mm": [24, 24]}
    h.update(header)
    return write_raw(path, {k: v for k, v in t.items() if v is not None}, h, kind="psf_bank", format_version=1)


def test_saved_file_holds_float16_psfs_and_its_units(tmp_path):
    from controlgs_adapter.formats.safetensors import load_tensors

    bank = PSFBank(**_args(), meta={"k": [1, 2]})
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
    bank = PSFBank(**_args())
    with pytest.raises(InputValueError, match="resample_to: height and width must be ints >= 2"):
        bank.resample_to(h, w)


def test_resample_to_caches_per_dtype_and_placement():
    bank = PSFBank(**_args())
    a = bank.resample_to(2, 2)
    assert a is bank.resample_to(2, 2) and a.H == 2 and a.W == 2 and a.dtype == torch.float32
    assert bank.resample_to(2, 2, dtype=D64) is not a and bank.resample_to(2, 2, dtype=D64).dtype == D64
    assert bank.resample_to(2, 2, placement="stretch") is not a
