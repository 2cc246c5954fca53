"""Tests of ``controlgs_adapter.downstream.bank_maps``: the pre-warp maps tied to a PSF bank. The display
LUT map (its tables, evaluation over the image region, tables fitted at several display sizes served by
pixel pitch, cache, mode choice, file format and refusals),
the chief-ray map, the bank fingerprint, and both compensating the optics: the dots of an image land
where they were rendered."""

from __future__ import annotations

import copy

import pytest
import torch
from helpers.banks import synthetic_bank
from helpers.lens_checks import GRID_FIELD, gaussian_dot_errors
from helpers.prewarp_tables import display_tables

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.bank_maps import DISPLAY_LUT_KIND
from controlgs_adapter.downstream.color import primaries_to_rgb, rgb_to_primaries
from controlgs_adapter.downstream.lens import BankMap, DisplayLUTMap, LensPrewarp, bank_fingerprint, pixel_grid
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.stage import psf_optics
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import StageContext
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import read_header, save_tensors

D = torch.float64
CPU = torch.device("cpu")
STATE = RuntimeState()


# ----------------------------------------------------------------------------- DisplayLUTMap
@pytest.mark.parametrize("placement, size, half", [("stretch", (4, 8), (1.0, 1.0)), ("fit", (4, 8), (1.0, 0.5)),
                                                  ("fit", (6, 3), (0.5, 1.0))])
def test_display_lut_map_samples_the_image_region_of_the_display(placement, size, half):
    """grid(u) = (u h + disp(u h)) / h on a square display: a 4 x 8 image fit on it spans the full
    width and half the height (h = (1, 0.5))."""
    disp, gain, mt = display_tables()
    lut = DisplayLUTMap({"exact": (disp, gain)}, display_mm=(24.0, 24.0), placement=placement)
    grid, got_gain = lut(size, D, CPU)
    h = torch.tensor(half, dtype=D)
    q = pixel_grid(size, D) * h  # display-normalised
    want = (q + mt[:, None, None, :2] * q + mt[:, None, None, 2:]) / h
    assert torch.allclose(grid, want, atol=1e-6, rtol=0)  # tables are stored as float32
    assert torch.allclose(got_gain, gain[:, :1, :1].expand(3, *size), atol=1e-6)
    assert not lut.is_identity()


def test_display_lut_tables_are_held_outside_the_callers_graph():
    """Tables built from tensors that require grad (a fitted table straight from the optimiser) become
    plain buffers: no gradient flows back to the caller's tensors and none is tracked."""
    disp = torch.zeros(3, 4, 5, 2, requires_grad=True)
    gain = torch.ones(3, 4, 5, requires_grad=True)
    lut = DisplayLUTMap({"exact": (disp, gain)})
    for name in ("displacement_exact", "gain_exact"):
        buf = getattr(lut, name)
        assert not buf.requires_grad and buf.grad_fn is None, name
    assert torch.equal(lut.gain_exact, torch.ones(3, 4, 5))


def test_display_lut_map_evaluates_once_per_size_and_again_after_the_table_changes():
    """The grid and gain are evaluated once per (size, dtype, device, table) and returned again as they
    are; another size, or an in-place change of the table, evaluates anew (the change is seen)."""
    g = torch.Generator().manual_seed(3)
    disp = 0.01 * torch.randn(3, 4, 4, 2, generator=g)
    lut = DisplayLUTMap({"exact": (disp, 1.0 + 0.1 * torch.rand(3, 4, 4, generator=g))}, (10.0, 10.0), "stretch")
    grid1, gain1 = lut((6, 6), D, "cpu")
    grid2, gain2 = lut((6, 6), D, "cpu")
    assert grid2 is grid1 and gain2 is gain1
    other, _ = lut((5, 6), D, "cpu")
    assert other is not grid1 and other.shape == (3, 5, 6, 2)
    before = lut((6, 6), D, "cpu")[0].clone()
    with torch.no_grad():
        lut.displacement_exact += 0.05  # the eye position moves by 0.05 (display-normalised, stretch: grid too)
    after, _ = lut((6, 6), D, "cpu")
    torch.testing.assert_close(after, before + 0.05, rtol=0, atol=1e-6)


def test_display_lut_map_table_choice():
    """The first table by default or the given mode; following an optics stage, its current mode's table
    (fast falls back to exact, a missing one is refused naming the modes)."""
    disp, gain, _ = display_tables()
    other = (disp * 2.0, gain)
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}).table_mode() == "distortion"  # first
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}, mode="exact").table_mode() == "exact"

    class _Optics(torch.nn.Module):
        mode = "fast"

    optics = _Optics()
    assert DisplayLUTMap({"distortion": (disp, gain), "exact": other}).follow(optics).table_mode() == "exact"
    only_distortion = DisplayLUTMap({"distortion": (disp, gain)}).follow(optics)
    with pytest.raises(InputValueError, match=r"\('distortion',\).*'fast'"):
        only_distortion.table_mode()
    fast = DisplayLUTMap({"fast": (disp, gain), "exact": other}, mode="fast")
    assert fast.table_mode() == "fast"  # its own fast table wins over the exact one


def test_display_lut_map_refusals():
    disp, gain, _ = display_tables()
    with pytest.raises(InputValueError, match="tables must hold at least one optics mode"):
        DisplayLUTMap({})
    with pytest.raises(InputValueError, match="placement must be one of .*'centre'"):
        DisplayLUTMap({"exact": (disp, gain)}, placement="centre")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="table modes must be among .*'paraxial'"):
        DisplayLUTMap({"paraxial": (disp, gain)})
    with pytest.raises(ShapeError, match="table 'exact' needs at least 2x2 samples"):
        DisplayLUTMap({"exact": (disp[:, :1], gain[:, :1])})
    with pytest.raises(ShapeError, match=r"gain\['exact'\]"):
        DisplayLUTMap({"exact": (disp, gain[:, :2])})
    nan_gain = torch.ones(3, 2, 2)
    nan_gain[1, 0, 1] = float("nan")
    with pytest.raises(InputValueError, match=r"gain\['exact'\]"):
        DisplayLUTMap({"exact": (torch.zeros(3, 2, 2, 2), nan_gain)})
    inf_disp = torch.zeros(3, 2, 2, 2)
    inf_disp[0, 0, 0, 0] = float("inf")
    with pytest.raises(InputValueError, match=r"displacement\['exact'\]"):
        DisplayLUTMap({"exact": (inf_disp, torch.ones(3, 2, 2))})


def test_display_lut_file_round_trip_version_and_refusals(tmp_path):
    """A display LUT file carries format version 1, the display size, the tables and the meta (the placement is chosen when reading);
    a newer version, a header without modes, a missing table, a table below 2 x 2 and a file that is not a
    LUT are refused naming the file."""
    disp, gain, _ = display_tables()
    saved = DisplayLUTMap({"exact": (disp, gain)}, display_mm=(20.0, 10.0), meta={"bank": "x"}).save(tmp_path / "ok.safetensors")
    assert read_header(saved, kind=DISPLAY_LUT_KIND, max_version=99)["format_version"] == 1
    back = DisplayLUTMap.load(saved, placement="stretch")
    assert back.display_mm == (20.0, 10.0) and back.placement == "stretch" and back.meta == {"bank": "x"}
    assert torch.equal(back.displacement_exact, disp.float())
    kind = {"kind": DISPLAY_LUT_KIND}
    newer = save_tensors(tmp_path / "newer.safetensors", {"displacement_exact": torch.zeros(3, 2, 2, 2),
                                                         "gain_exact": torch.ones(3, 2, 2)},
                         {"modes": ["exact"]}, format_version=2, **kind)
    with pytest.raises(FileFormatError, match="newer.safetensors.*newer than this library reads"):
        DisplayLUTMap.load(newer)
    no_modes = save_tensors(tmp_path / "no_modes.safetensors", {"gain_exact": gain.float()}, {}, format_version=1, **kind)
    with pytest.raises(FileFormatError, match="no_modes.safetensors.*modes"):
        DisplayLUTMap.load(no_modes)
    lacking = save_tensors(tmp_path / "lacking.safetensors", {"gain_exact": gain.float()}, {"modes": ["exact"]},
                           format_version=1, **kind)
    with pytest.raises(FileFormatError, match=r"lacking.safetensors.*\['displacement_exact'\]"):
        DisplayLUTMap.load(lacking)
    bad = save_tensors(tmp_path / "bad.safetensors", {"displacement_exact": disp[:, :1].float(), "gain_exact": gain[:, :1].float()},
                       {"modes": ["exact"]}, format_version=1, **kind)
    with pytest.raises(FileFormatError, match="bad.safetensors.*'exact'.*2x2"):
        DisplayLUTMap.load(bad)
    (tmp_path / "nonsense.safetensors").write_bytes(b"nonsense")
    with pytest.raises(FileFormatError, match="nonsense.safetensors"):
        DisplayLUTMap.load(tmp_path / "nonsense.safetensors")


# ----------------------------------------------------------------------------- BankMap and the fingerprint
def test_bank_map_refusals():
    with pytest.raises(InputValueError, match=r"bank must have 3 wavelengths .*600.0, 500.0"):
        BankMap(synthetic_bank(L=2))
    bank = PSFBank.default()
    with pytest.raises(InputValueError, match="placement must be one of .*'centre'"):
        BankMap(bank, "centre")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="gain must be 'jacobian' or None, got 'area'"):
        BankMap(bank, gain="area")  # type: ignore[arg-type]


def test_bank_fingerprint_tracks_every_optics_field():
    """16 hex digits; the same numbers with other metadata give the same fingerprint, a change of any field
    that shapes the optics gives a new one (each a different one)."""
    bank = PSFBank.default()
    fp = bank_fingerprint(bank)
    assert len(fp) == 16 and all(ch in "0123456789abcdef" for ch in fp)

    def with_fields(**fields: object) -> PSFBank:  # copies bypass __init__, which renormalises the PSFs
        other = copy.copy(bank)
        other._cache = {}  # not shared with the process-wide default bank
        for name, value in fields.items():
            setattr(other, name, value)
        return other

    same = with_fields(psf=bank.psf.clone(), chief=bank.chief.clone(), meta={"other": 1})
    assert bank_fingerprint(same) == fp
    changed = {
        "psf": bank.psf.flip(-1), "psf_pitch_mm": bank.psf_pitch_mm * 1.01, "field_x": bank.field_x * 0.99,
        "field_y": bank.field_y * 0.99, "chief": bank.chief * 1.001, "chief_x": bank.chief_x * 0.99,
        "chief_y": bank.chief_y * 0.99, "wavelengths_nm": tuple(w + 1 for w in bank.wavelengths_nm),
        "display_mm": (bank.display_mm[0] + 1, bank.display_mm[1]),
    }
    fps = {name: bank_fingerprint(with_fields(**{name: value})) for name, value in changed.items()}
    assert all(v != fp for v in fps.values()), fps
    assert len(set(fps.values())) == len(fps)


# ----------------------------------------------------------------------------- compensating the optics
DOTS = ((0.0, 0.0), (0.6, 0.5), (-0.6, -0.5), (0.75, -0.6), (-0.45, 0.7), (0.85, 0.0), (0.0, -0.8))


def _pixel_dots(h: int, w: int) -> tuple[torch.Tensor, list[tuple[int, int]]]:
    """A black image with one white pixel at each of :data:`DOTS` (image-normalised) and their (row, col)."""
    img = torch.zeros(3, h, w, dtype=D)
    where = []
    for x, y in DOTS:
        i, j = int((y + 1) / 2 * h), int((x + 1) / 2 * w)
        img[:, i, j] = 1.0
        where.append((i, j))
    return img, where


def _pixel_dot_errors(eye_primaries: torch.Tensor, where: list[tuple[int, int]], r: int = 4) -> torch.Tensor:
    """``[dots, 3]`` distance (px) of each primary's light centroid, in a window around each dot, from the dot."""
    out = []
    for i, j in where:
        win = eye_primaries[:, max(i - r, 0):i + r + 1, max(j - r, 0):j + r + 1].clamp_min(0)
        rows = torch.arange(max(i - r, 0), max(i - r, 0) + win.shape[1], dtype=D)
        cols = torch.arange(max(j - r, 0), max(j - r, 0) + win.shape[2], dtype=D)
        s = win.sum((1, 2))
        out.append(torch.stack([(win.sum(2) * rows).sum(1) / s - i, (win.sum(1) * cols).sum(1) / s - j], -1).norm(dim=-1))
    return torch.stack(out)


@pytest.mark.parametrize("h, w", [(48, 48), (27, 48), (48, 27)])
def test_chief_ray_prewarp_then_optics_lands_dots_where_they_started(h, w):
    """The pipeline's lens built from the optics' bank chief rays for the same region (each primary warped),
    then the optics' chief-ray warp: each white dot is seen where it was rendered, to a quarter pixel, where
    without the pre-warp the outer dots move by more than 0.8 px."""
    p = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": {"mode": "distortion"}}).double()
    assert isinstance(p["lens"].map, BankMap)
    target, where = _pixel_dots(h, w)
    prim = rgb_to_primaries(target)                 # the optics is separable per primary: warp in that domain
    shown = primaries_to_rgb(p["lens"](prim, STATE, StageContext((h, w))))
    eye = rgb_to_primaries(psf_optics(shown, p["optics"].bank, mode="distortion"))
    plain = rgb_to_primaries(psf_optics(target, p["optics"].bank, mode="distortion"))
    assert float(_pixel_dot_errors(eye, where).max()) < 0.25
    assert float(_pixel_dot_errors(plain, where).max()) > 0.8


def test_a_chief_ray_prewarp_for_the_wrong_region_misses():
    """Sensitivity of the dot test: a pre-warp built as if the 27 x 48 image spanned the display
    (stretch) does not land the dots under the "fit" optics."""
    bank = PSFBank.default()
    target, where = _pixel_dots(27, 48)
    wrong = LensPrewarp.from_psf_bank(bank, placement="stretch").double()
    wrong.basis = "rgb"  # applied to primaries below
    shown = primaries_to_rgb(wrong(rgb_to_primaries(target), STATE, StageContext((27, 48))))
    eye = rgb_to_primaries(psf_optics(shown, bank, mode="distortion"))
    assert float(_pixel_dot_errors(eye, where).max()) > 0.3


@pytest.mark.parametrize("mode", ["distortion", "exact"])
@pytest.mark.parametrize("size", [(96, 96), (54, 96)])
def test_the_shipped_display_lut_lands_every_primary_of_a_dot_within_a_tenth_of_a_pixel(mode, size):
    """The default lens with optics is the display LUT fitted for the shipped bank, warping the primaries:
    over the whole field (a 0.1 grid, (0.6, -0.5) included) each primary's eye centroid of a white dot is
    within 0.1 px of where it was rendered, so no two primaries are 0.2 px apart anywhere."""
    pipe = Pipeline.from_config({"lens": True, "optics": {"mode": mode}}).double()
    assert isinstance(pipe["lens"].map, DisplayLUTMap) and pipe["lens"].basis == "primaries"
    field = GRID_FIELD if size[0] == size[1] else [(u, v * 0.5) for u, v in GRID_FIELD]
    assert ((0.6, -0.5) if size[0] == size[1] else (0.6, -0.25)) in field
    err = gaussian_dot_errors(pipe, size, field)
    worst = int(err.amax(1).argmax())
    assert float(err.max()) < 0.1, (field[worst], err[worst])


@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_one_sample_per_display_pixel_and_one_fitted_size_miss_the_tenth_of_a_pixel(mode):
    """Sensitivity: point-sampling the image at each display pixel (supersample 1) and the table of one
    fitted size (256) leave a primary of some dot on the grid more than 0.1 px off at 96 px."""
    pipe = Pipeline.from_config({"lens": {"supersample": 1}, "optics": {"mode": mode}}).double()
    lut = pipe["lens"].map
    assert pipe["lens"].supersample == 1 and lut.sizes[mode] == (64, 96, 128, 192, 256)
    main = {mode: (getattr(lut, f"displacement_{mode}"), getattr(lut, f"gain_{mode}"))}  # fitted at 256 px
    pipe["lens"].map = DisplayLUTMap(main, lut.display_mm, meta=lut.meta).follow(pipe["optics"]).double()
    assert float(gaussian_dot_errors(pipe, (96, 96), GRID_FIELD).max()) > 0.1


def test_the_paper_per_rgb_chief_ray_warp_misses_by_lateral_colour():
    """Sensitivity: the per-RGB warp of the bank's chief rays puts the primaries of a dot at (0.85, 0.85)
    apart by more than a pixel at 256 px in exact mode (here more than 0.3 px at 96 px)."""
    pipe = Pipeline.from_config({"lens": {"source": "chief_rays", "basis": "rgb"}, "optics": {"mode": "exact"}}).double()
    assert isinstance(pipe["lens"].map, BankMap)
    err = gaussian_dot_errors(pipe, (96, 96), [(0.85, 0.85)])
    assert float(err.max()) > 0.3


# ----------------------------------------------------------------------------- tables fitted at several display sizes
def _sized_lut(**kw):
    """Distortion tables fitted at display sizes 16 (displacement 0.01), 32 (main, 0.03) and 64 (0.05) of
    a 24 mm square display; gains 1, 2, 3."""
    def table(v: float, g: float, n: int = 4):
        return torch.full((3, n, n, 2), v), torch.full((3, n, n), g)

    return DisplayLUTMap({"distortion": table(0.03, 2.0)}, (24.0, 24.0), size=32,
                         sizes={"distortion": {16: table(0.01, 1.0, 3), 64: table(0.05, 3.0, 5)}}, **kw)


@pytest.mark.parametrize("n, disp, gain", [(8, 0.01, 1.0), (16, 0.01, 1.0), (32, 0.03, 2.0), (64, 0.05, 3.0), (128, 0.05, 3.0),
                                           (24, 0.01 + 0.02 * 0.5849625007211562, 1.5849625007211562),
                                           (48, 0.03 + 0.02 * 0.5849625007211562, 2.5849625007211562)])
def test_an_image_gets_the_tables_whose_pitch_brackets_its_own(n, disp, gain):
    """Between two fitted sizes the tables blend linearly in log pitch; beyond them the nearest serves."""
    lut = _sized_lut()
    assert lut.sizes == {"distortion": (16, 32, 64)} and lut.size == 32
    grid, g = lut((n, n), D, "cpu")
    assert torch.allclose(grid - pixel_grid((n, n), D), torch.full_like(grid, disp), atol=1e-6)
    assert torch.allclose(g, torch.full_like(g, gain), atol=1e-6)
    wide, _ = lut((n // 2, n), D, "cpu")  # the same pitch in a wide image ("fit": the width spans the display)
    assert torch.allclose(wide[..., 0] - pixel_grid((n // 2, n), D)[..., 0], torch.full_like(wide[..., 0], disp), atol=1e-6)


def test_tables_of_several_sizes_round_trip_and_are_checked(tmp_path):
    lut = _sized_lut(meta={"bank": "b"})
    path = lut.save(tmp_path / "lut.safetensors")
    back = DisplayLUTMap.load(path)
    assert back.sizes == lut.sizes and back.size == 32 and back.meta == {"bank": "b"}
    for n in (12, 24, 32, 48, 90):
        assert torch.equal(back((n, n), D, "cpu")[0], lut((n, n), D, "cpu")[0])
    assert "sizes={'distortion': [16, 32, 64]}" in repr(back)
    disp, gain = torch.zeros(3, 2, 2, 2), torch.ones(3, 2, 2)
    with pytest.raises(InputValueError, match="sizes needs the size of the main tables"):
        DisplayLUTMap({"exact": (disp, gain)}, sizes={"exact": {16: (disp, gain)}})
    with pytest.raises(InputValueError, match="sizes needs .* a table of the same mode"):
        DisplayLUTMap({"exact": (disp, gain)}, size=32, sizes={"distortion": {16: (disp, gain)}})
    with pytest.raises(InputValueError, match=r"sizes\['exact'\].*size=32, got 32"):
        DisplayLUTMap({"exact": (disp, gain)}, size=32, sizes={"exact": {32: (disp, gain)}})
    with pytest.raises(InputValueError, match="size must be an int >= 1"):
        DisplayLUTMap({"exact": (disp, gain)}, size=0)
    with pytest.raises(ShapeError, match=r"gain\['exact'\]"):
        DisplayLUTMap({"exact": (disp, gain)}, size=32, sizes={"exact": {16: (disp, gain[:, :1])}})
    kind = {"kind": DISPLAY_LUT_KIND, "format_version": 1}
    lacking = save_tensors(tmp_path / "lacking.safetensors", {"displacement_exact": disp, "gain_exact": gain},
                           {"modes": ["exact"], "size": 32, "sizes": {"exact": [16]}}, **kind)
    with pytest.raises(FileFormatError, match=r"lacking.safetensors.*\['displacement_exact_16', 'gain_exact_16'\]"):
        DisplayLUTMap.load(lacking)
    bad = save_tensors(tmp_path / "bad.safetensors", {"displacement_exact": disp, "gain_exact": gain},
                       {"modes": ["exact"], "size": 32, "sizes": {"exact": ["16"]}}, **kind)
    with pytest.raises(FileFormatError, match="bad.safetensors.*'sizes'"):
        DisplayLUTMap.load(bad)


def test_one_table_serves_every_pitch():
    disp = 0.02 * torch.ones(3, 4, 4, 2)
    lut = DisplayLUTMap({"exact": (disp, torch.ones(3, 4, 4))}, (24.0, 24.0), meta={"size": [256, 256]})
    assert lut.size == 256 and lut.sizes == {"exact": (256,)}
    for n in (8, 96, 512):
        grid, _ = lut((n, n), D, "cpu")
        assert torch.allclose(grid - pixel_grid((n, n), D), torch.full_like(grid, 0.02), atol=1e-6)
