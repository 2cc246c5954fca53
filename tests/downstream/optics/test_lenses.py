"""Choosing the lens (``downstream/optics/lenses.py``): every spec form of ``load_lens`` against the bank built
directly from the same source, the pre-warp LUT found by bank fingerprint (beside a bank file, among the
shipped ones), ``effects_for_lens`` against the stages built by hand, and the refusals naming the file."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from helpers.banks import random_bank
from helpers.prescriptions import cardboard_spec

from controlgs_adapter.downstream.bank_maps import BankMap, DisplayLUTMap, bank_fingerprint
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.lens_maps import RadialMap
from controlgs_adapter.downstream.optics import lenses
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.lenses import (Lens, ShippedLens, check_lens_spec, effects_for_lens, load_lens,
                                                        prewarp_for_bank, shipped_prescription)
from controlgs_adapter.downstream.optics.prescription import CARDBOARD
from controlgs_adapter.downstream.optics.profiles import bank_from_profile, load_profile
from controlgs_adapter.downstream.optics.stage import PSFOptics
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import RuntimeState

#: a bank traced in a second: few fields, pupil rays and chief rays
SMALL_TRACE = dict(grid=(2, 2), psf_size=5, pupil_samples=8, chief_grid=(5, 5))
#: an OpenCV-form distortion profile with lateral colour (pincushion, as a magnifier's display -> eye map)
PROFILE = {"kind": "opencv", "display_px": [64, 64], "display_mm": [24.0, 24.0], "k1": 0.12, "radius_px": 32,
           "channel_scales": [0.99, 1.0, 1.01]}


def _write_json(path: Path, obj: object) -> Path:
    path.write_text(json.dumps(obj))
    return path


def _lut_for(bank: PSFBank, path: Path, radiometry: str = "radiance") -> Path:
    """A display LUT (zero displacement, unit gain) whose header names ``bank``."""
    tables = {"distortion": (torch.zeros(3, 4, 4, 2), torch.ones(3, 4, 4))}
    DisplayLUTMap(tables, bank.display_mm, meta={"bank": bank_fingerprint(bank), "radiometry": radiometry}).save(path)
    return path


def _same_bank(a: PSFBank, b: PSFBank) -> bool:
    return bank_fingerprint(a) == bank_fingerprint(b)


def test_the_shipped_cardboard_lens_is_the_default_bank_and_its_fitted_lut():
    for spec in (None, "cardboard"):
        lens = load_lens(spec)
        assert (lens.spec, lens.kind, lens.is_default) == ("cardboard", "shipped", True)
        assert lens.bank is PSFBank.default()
        assert lens.prewarp is not None and lens.prewarp.name == "cardboard_prewarp_lut.safetensors"
        assert DisplayLUTMap.load(lens.prewarp).meta["bank"] == bank_fingerprint(lens.bank)
    assert load_lens(lens) is lens
    assert shipped_prescription("cardboard") == CARDBOARD


def test_a_bank_file_finds_the_lut_beside_it_else_a_shipped_one_by_fingerprint(tmp_path):
    random_bank(C=5).save(tmp_path / "mine_psf_bank.safetensors")
    bank = PSFBank.load(tmp_path / "mine_psf_bank.safetensors")  # as stored (PSFs in float16)
    lens = load_lens(str(tmp_path / "mine_psf_bank.safetensors"))
    assert (lens.kind, lens.spec, lens.prewarp) == ("bank", str(tmp_path / "mine_psf_bank.safetensors"), None)
    assert _same_bank(lens.bank, bank) and not lens.is_default
    # both namings beside the file; a LUT fitted for another bank is passed over
    _lut_for(random_bank(C=5, seed=1), tmp_path / "mine_psf_bank_prewarp_lut.safetensors")
    assert load_lens(tmp_path / "mine_psf_bank.safetensors").prewarp is None
    beside = _lut_for(bank, tmp_path / "mine_prewarp_lut.safetensors")
    assert load_lens(tmp_path / "mine_psf_bank.safetensors").prewarp == beside
    # a copy of the shipped bank anywhere finds the shipped LUT through its fingerprint
    copy = tmp_path / "copy.safetensors"
    shutil.copy(lenses._data_file("cardboard_psf_bank.safetensors"), copy)
    assert load_lens(copy).prewarp == load_lens("cardboard").prewarp
    # a bank object
    obj = load_lens(bank)
    assert obj.bank is bank and obj.kind == "bank" and obj.spec == f"psf-bank:{bank_fingerprint(bank)}"


def test_a_prescription_is_traced_on_load_with_one_line_naming_build_bank(tmp_path, monkeypatch, capsys):
    traced: list[dict] = []

    def small(rx, **kw):  # the real tracer at a cheap sampling
        traced.append(kw)
        return build_bank(rx, **SMALL_TRACE)

    monkeypatch.setattr(lenses, "build_bank", small)
    spec = cardboard_spec(name="mine", object_distance_mm=38.0)
    path = _write_json(tmp_path / "mine.json", spec)
    lens = load_lens(path)
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and "controlgs optics build-bank --lens" in out[0] and str(path) in out[0]
    assert traced == [{}] and (lens.kind, lens.prewarp) == ("prescription", None)
    direct = build_bank(spec, **SMALL_TRACE)
    torch.testing.assert_close(lens.bank.chief, direct.chief, rtol=0, atol=0)
    assert lens.bank.meta["prescription"]["object_distance_mm"] == 38.0


def test_a_distortion_profile_becomes_its_chief_ray_bank(tmp_path):
    path = _write_json(tmp_path / "hmd.json", PROFILE)
    lens = load_lens(path)
    direct = bank_from_profile(load_profile(path))
    assert lens.kind == "profile" and not lens.bank.has_psf and lens.prewarp is None
    torch.testing.assert_close(lens.bank.chief, direct.chief, rtol=0, atol=0)
    _lut_for(direct, tmp_path / "hmd_prewarp_lut.safetensors")  # a LUT fitted for it, beside the profile
    assert load_lens(path).prewarp == tmp_path / "hmd_prewarp_lut.safetensors"


@pytest.mark.parametrize("content, suffix, error, names", [
    (None, ".json", InputValueError, "no such file"),
    ("[1, 2]", ".json", FileFormatError, "JSON list"),
    ("{", ".json", FileFormatError, "not a JSON lens file"),
    ('{"kind": "fisheye"}', ".json", FileFormatError, "neither a prescription"),
    ('{"surfaces": [], "display_mm": [24, 24]}', ".json", FileFormatError, "prescription"),
    ('{"kind": "opencv", "display_px": [64, 64], "display_mm": [24, 24]}', ".json", FileFormatError, "k1"),
    ("not a bank", ".safetensors", FileFormatError, "safetensors"),
    ("{}", ".txt", FileFormatError, "not a lens file"),
])
def test_a_bad_lens_file_is_refused_naming_the_file(tmp_path, content, suffix, error, names):
    path = tmp_path / f"lens{suffix}"
    if content is not None:
        path.write_text(content)
    with pytest.raises(error) as e:
        load_lens(path)
    assert str(path) in str(e.value) and names in str(e.value) and "\n" not in str(e.value)


def test_names_that_are_not_shipped_or_not_installed_are_refused(monkeypatch):
    with pytest.raises(InputValueError, match=r"^lens cardbaord: not a shipped lens \(cardboard, compact\) nor a file$"):
        load_lens("cardbaord")
    monkeypatch.setitem(lenses.SHIPPED_LENSES, "absent", ShippedLens("absent_psf_bank.safetensors", "absent.lut",
                                                                      "absent.json"))
    with pytest.raises(InputValueError, match="^lens absent: its PSF bank absent_psf_bank.safetensors is not installed$"):
        load_lens("absent")
    with pytest.raises(InputValueError, match="^--lens absent: its PSF bank"):
        check_lens_spec("absent", "--lens")
    with pytest.raises(InputValueError, match="its prescription absent.json is not installed"):
        shipped_prescription("absent")
    with pytest.raises(InputValueError, match="lens must be"):
        load_lens(3.0)  # type: ignore[arg-type]


def test_a_shipped_lut_is_found_by_the_fingerprint_of_the_optics_bank(tmp_path, monkeypatch):
    bank = random_bank(C=5)
    files = {"other.lut": _lut_for(random_bank(C=5, seed=2), tmp_path / "other.lut"),
             "mine.lut": _lut_for(bank, tmp_path / "mine.lut")}
    monkeypatch.setattr(lenses, "_data_file", lambda name: files.get(name, tmp_path / "missing" / name))
    monkeypatch.setattr(lenses, "SHIPPED_LENSES", {"a": ShippedLens("a.bank", "other.lut", None),
                                                    "b": ShippedLens("b.bank", "mine.lut", None)})
    assert prewarp_for_bank(bank) == files["mine.lut"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # found: no chief-ray fallback
        stage = LensPrewarp.for_optics(PSFOptics(bank))
    assert isinstance(stage.map, DisplayLUTMap) and stage.map.meta["bank"] == bank_fingerprint(bank)
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):  # another radiometry than the LUT's
        stage = LensPrewarp.for_optics(PSFOptics(bank, radiometry="energy"))
    assert isinstance(stage.map, BankMap)


def test_effects_for_lens_puts_the_bank_in_the_optics_and_its_lut_in_the_lens(tmp_path):
    path = tmp_path / "b.safetensors"
    random_bank(C=5).save(path)
    lut = _lut_for(PSFBank.load(path), tmp_path / "b_prewarp_lut.safetensors")
    lens = load_lens(path)
    effects = {"lens": {"basis": "rgb"}, "optics": {"radiometry": "radiance"}, "resample": True}
    got = effects_for_lens(effects, lens)
    assert effects == {"lens": {"basis": "rgb"}, "optics": {"radiometry": "radiance"}, "resample": True}  # unchanged
    assert got == {"lens": {"basis": "rgb", "lut": str(lut)}, "optics": {"radiometry": "radiance", "bank": lens.bank},
                   "resample": True}
    pipe = Pipeline.from_config(got)
    assert pipe["optics"].bank is lens.bank and pipe["lens"].basis == "rgb"
    assert pipe["lens"].map.meta["bank"] == bank_fingerprint(lens.bank)
    assert effects_for_lens(effects, None) == effects and effects_for_lens(["lens"], None) == {"lens": True}
    # chief rays asked for: no LUT added; the default lens: the optics' default bank
    assert effects_for_lens({"lens": {"source": "chief_rays"}, "optics": True}, lens)["lens"] == {"source": "chief_rays"}
    assert effects_for_lens({"optics": True}, "cardboard")["optics"]["bank"] is PSFBank.default()
    with pytest.raises(InputValueError, match=r"effects\['optics'\] already names its PSF bank"):
        effects_for_lens({"optics": PSFOptics(random_bank(C=5, seed=3))}, lens)
    same = PSFOptics(lens.bank)
    assert effects_for_lens({"optics": same}, lens)["optics"] is same


def test_without_optics_the_lens_stage_follows_the_banks_chief_rays():
    bank = random_bank(C=9, pincushion=0.05)
    got = Pipeline.from_config(effects_for_lens({"lens": True}, bank))
    want = LensPrewarp.from_psf_bank(bank)  # the same map, built by hand
    image = torch.rand(3, 12, 16, dtype=torch.float64)
    state = RuntimeState()
    assert isinstance(got["lens"].map, BankMap)
    torch.testing.assert_close(got["lens"](image, state), want(image, state), rtol=0, atol=0)
    # Cardboard keeps the analytic radial map; a map given in the options is kept
    assert isinstance(Pipeline.from_config(effects_for_lens({"lens": True}, "cardboard"))["lens"].map, RadialMap)
    assert effects_for_lens({"lens": {"coefficients": [[0.1]] * 3}}, bank)["lens"] == {"coefficients": [[0.1]] * 3}


def test_a_lens_records_what_names_it():
    lens = Lens("x.json", random_bank(C=5), None, "profile")
    assert not lens.is_default and load_lens(lens) is lens


def test_a_folder_or_device_is_not_a_lens_file_and_an_untraceable_prescription_names_its_file(tmp_path):
    """A path that exists but is not a regular file is said to be one (not 'no such file'); a prescription whose
    chief rays cannot be traced is refused naming the file, not the prescription in the abstract."""
    for spec in (str(tmp_path), "/dev/null"):
        with pytest.raises(InputValueError, match=r": not a regular file$"):
            check_lens_spec(spec)
    with pytest.raises(InputValueError, match=r": no such file$"):
        check_lens_spec(str(tmp_path / "gone.json"))
    bad = tmp_path / "far.json"
    bad.write_text(json.dumps(cardboard_spec(display_offset_mm=[9.0, 0.0])))   # the far corners have no chief ray
    with pytest.raises(FileFormatError, match=rf"^{bad}: prescription: the chief rays of \d+ warp-grid points"):
        load_lens(bad)
