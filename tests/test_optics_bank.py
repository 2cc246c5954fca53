"""PSF bank file format: round trip, the shipped default, and bad banks failing clearly."""

import math

import pytest
import torch

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import save_tensors

from _rawfiles import write_raw

D64 = torch.float64


def tiny_bank(**over):
    L, G, K = 3, 3, 5
    psf = torch.rand(L, G, G, K, K, dtype=D64)
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 5, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64), field_x=f, field_y=f,
                chief=torch.stack([cx, cy], -1).expand(L, 5, 5, 2).clone(), chief_x=c, chief_y=c,
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
    args.update(over)
    return PSFBank(**args)


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
    (lambda b: b.__setitem__("chief_x", torch.linspace(-0.9, 1, 5, dtype=D64)), "chief_x"),
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


def test_resample_to_names_the_device_as_tensors_report_it():
    """A device given with an index ("cpu:0"; on a GPU "cuda" vs "cuda:0") is the tensors' device: the
    bank is the cached one and applies to images on it (it was refused as another device)."""
    from controlgs_adapter.downstream.optics.operators import psf_exact

    bank = tiny_bank()
    rb = bank.resample_to(12, 12, device="cpu:0", dtype=torch.float64)
    assert rb is bank.resample_to(12, 12, device="cpu", dtype=torch.float64)
    x = torch.rand(bank.num_wavelengths, 12, 12, dtype=torch.float64)
    torch.testing.assert_close(psf_exact(x, rb), psf_exact(x, bank.resample_to(12, 12, dtype=torch.float64)))


@pytest.mark.parametrize("device", ["banana", 3.5])
def test_resample_to_refuses_a_device_that_is_not_one(device):
    with pytest.raises(InputValueError, match=rf"resample_to: device {device!r} is not a usable torch device here"):
        tiny_bank().resample_to(12, 12, device=device)
