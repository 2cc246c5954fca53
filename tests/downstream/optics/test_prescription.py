"""Tests of ``controlgs_adapter.downstream.optics.prescription``."""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Callable

import numpy as np
import pytest
import torch
from helpers.pupil import aim_rays

from controlgs_adapter import cli
from controlgs_adapter.downstream.optics.generate import build_bank, lens_figures
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
from controlgs_adapter.downstream.optics.raytrace import chief_ray, paraxial, real_magnification, trace
from controlgs_adapter.errors import ControlGSError, FileFormatError, InputValueError


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


PRESCRIPTION_CASES = [
    ("a list", [1, 2], "mapping"), ("display_mm '66'", {**CARDBOARD, "display_mm": "66"}, "display_mm"),
    ("wavelengths '656'", {**CARDBOARD, "wavelengths_nm": "656"}, "wavelengths_nm"),
    ("surfaces [1]", {**CARDBOARD, "surfaces": [1]}, "surfaces[0]"),
    ("surfaces {}", {**CARDBOARD, "surfaces": {}}, "surfaces"),
    ("radius 'abc'", {**CARDBOARD, "surfaces": [{**CARDBOARD["surfaces"][0], "radius_mm": "abc"}, CARDBOARD["surfaces"][1]]},
     "radius_mm"),
    ("pupil true", {**CARDBOARD, "pupil_diameter_mm": True}, "pupil_diameter_mm"),
    ("no object distance", {k: v for k, v in CARDBOARD.items() if k != "object_distance_mm"}, "object_distance_mm"),
]


# ============================================================================ CLI
def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process: exit code 2, exactly one line on stderr, no traceback; returns it."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture
def files(tmp_path):
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "list.json").write_text("[1, 2]")
    (tmp_path / "field.json").write_text(json.dumps({**CARDBOARD, "display_mm": "66"}))
    (tmp_path / "a_file").write_text("x")
    return tmp_path


CLI_CASES = [
    ("psf-size 4", ["optics", "build-bank", "--psf-size", "4"], "--psf-size"),
    ("psf-size 6", ["optics", "build-bank", "--psf-size", "6"], "--psf-size"),
    ("grid 0 0", ["optics", "build-bank", "--grid", "0", "0"], "--grid"),
    ("grid 3 -1", ["optics", "build-bank", "--grid", "3", "-1"], "--grid"),
    ("pupil-samples 1", ["optics", "build-bank", "--pupil-samples", "1"], "--pupil-samples"),
    ("min-pitch-px 0", ["optics", "build-bank", "--min-pitch-px", "0"], "--min-pitch-px"),
    ("min-pitch-px nan", ["optics", "build-bank", "--min-pitch-px", "nan"], "--min-pitch-px"),
    ("prescription missing", ["optics", "build-bank", "--prescription", "{d}/none.json"], "none.json"),
    ("prescription not JSON", ["optics", "build-bank", "--prescription", "{d}/bad.json"], "bad.json"),
    ("prescription a list", ["optics", "build-bank", "--prescription", "{d}/list.json"], "list.json"),
    ("prescription bad field", ["optics", "build-bank", "--prescription", "{d}/field.json"], "display_mm"),
    ("out a folder", ["optics", "build-bank", "--out", "{d}"], "--out"),
    ("figures prescription missing", ["optics", "figures", "--prescription", "{d}/none.json"], "none.json"),
    ("figures prescription a list", ["optics", "figures", "--prescription", "{d}/list.json"], "list.json"),
    ("demo out under a file", ["demo", "--out", "{d}/a_file/report"], "a_file"),
]


@pytest.mark.parametrize("spec, name", [c[1:] for c in PRESCRIPTION_CASES], ids=[c[0] for c in PRESCRIPTION_CASES])
def test_prescription(spec, name):
    _raises(lambda: Prescription(spec), InputValueError, name)


@pytest.mark.parametrize("argv, name", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli(files, capsys, argv, name):
    line = _cli([a.replace("{d}", str(files)) for a in argv], capsys)
    assert name in line, line


def test_slab_rays_clip_at_the_semi_diameter_and_extend_back_to_the_image_plane():
    """A plane-parallel slab of semi-diameter 2 mm: a ray from the axis with slope u meets the first
    surface at height u d (d the object distance); it passes iff that height (and its exit height)
    is within 2 mm. Its backward extension crosses the image plane at exit + u (z_image - z_exit)."""
    from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
    from controlgs_adapter.downstream.optics.raytrace import trace

    spec = dict(CARDBOARD, surfaces=[
        {"radius_mm": None, "thickness_mm": 5.0, "after": {"nd": 1.6, "vd": 40.0}, "semi_diameter_mm": 2.0},
        {"radius_mm": None, "thickness_mm": 10.0, "after": "air", "semi_diameter_mm": 2.0}])
    rx = Prescription(spec)
    d = rx.object_distance
    u = torch.tensor([0.5, 1.5, 2.5, -1.7]).double().numpy() / d  # first-surface heights 0.5, 1.5, 2.5, -1.7 mm
    _, _, X, _, ok = trace(rx, 550.0, 0.0, 0.0, u, 0.0)
    n = cauchy_index(1.6, 40.0, 550.0)
    slope_glass = torch.tan(torch.asin(torch.from_numpy(u / (1 + u * u) ** 0.5) / n)).numpy()
    exit_x = u * d + slope_glass * 5.0
    assert ok.tolist() == [bool(abs(h) <= 2.0) for h in exit_x]
    assert ok.tolist() == [True, True, False, True]
    want_X = exit_x + u * (rx.image_z - (d + 5.0))
    assert abs(X - want_X).max() < 1e-9


def test_paraxial_figures_of_cardboard():
    """Independent published-by-notes figures: f' 47.91 mm, image at 650.8 mm, m 14.20 at 550 nm."""
    p = paraxial(Prescription.cardboard(), 550.0)
    assert p.efl == pytest.approx(47.91, abs=0.02)
    assert p.image_distance == pytest.approx(650.8, abs=0.5)
    assert p.magnification == pytest.approx(14.20, abs=0.02)
    # thin-lens cross-check of the ABCD focal length: 1/f = (n-1)(1/R1 - 1/R2) + (n-1)^2 t / (n R1 R2)
    n = cauchy_index(1.492, 57.4, 550.0)
    r1, r2, t = 290.444, -25.498, 8.795
    f = 1 / ((n - 1) * (1 / r1 - 1 / r2) + (n - 1) ** 2 * t / (n * r1 * r2))
    assert p.efl == pytest.approx(f, rel=1e-9)


def test_cauchy_pmma_matches_buchdahl_fit_within_2e5():
    for lam, n in ((486.0, 1.49799), (550.0, 1.49383), (656.0, 1.48940)):
        assert cauchy_index(1.492, 57.4, lam) == pytest.approx(n, abs=5e-5)


def test_plane_parallel_slab_keeps_direction():
    spec = dict(CARDBOARD, surfaces=[
        {"radius_mm": None, "thickness_mm": 5.0, "after": {"nd": 1.6, "vd": 40.0}, "semi_diameter_mm": 50},
        {"radius_mm": None, "thickness_mm": 10.0, "after": "air", "semi_diameter_mm": 50}])
    rx = Prescription(spec)
    u = np.array([0.05, -0.1, 0.2])
    xp, yp, _, _, ok = trace(rx, 550.0, 0.0, 0.0, u, 0.0)
    n = cauchy_index(1.6, 40.0, 550.0)
    sin_in = u / np.sqrt(1 + u * u)
    slope_glass = np.tan(np.arcsin(sin_in / n))
    want = u * (rx.object_distance + 10.0) + slope_glass * 5.0      # exits parallel, displaced
    assert ok.all() and np.allclose(xp, want, atol=1e-10)


def test_bad_prescription_is_named():
    with pytest.raises(InputValueError, match="object_distance_mm"):
        Prescription(dict(CARDBOARD, object_distance_mm=-3))
    with pytest.raises(InputValueError, match="after"):
        Prescription(dict(CARDBOARD, surfaces=[{"radius_mm": 10, "thickness_mm": 1, "after": "glass"}]))


def _first_span_covering(rx, lam, r, v0, n):
    """Brute force of the documented rule: the first span of (1.02, 1.2, 1.45, 1.75, 2.1) whose launch
    grid's outline lands outside the pupil, else the widest (an outline ray blocked by an aperture is
    NaN: not outside); returns (span, covered, m, the grid's image-plane Xs)."""
    from controlgs_adapter.downstream.optics.raytrace import trace

    pr, eps = rx.pupil_radius, 1e-6
    xa, ya, _, _, _ = trace(rx, lam, 0.0, r, np.array([0.0, eps, 0.0]), v0 + np.array([0.0, 0.0, eps]))
    jx, jy = (xa[1] - xa[0]) / eps, (ya[2] - ya[0]) / eps
    for span in (1.02, 1.2, 1.45, 1.75, 2.1):
        m = int(round(n * span / 1.02))
        g = ((np.arange(m) + 0.5) / m * 2 - 1) * span * pr
        PX, PY = np.meshgrid(g / jx, v0 + g / jy)
        xp, yp, Xs, _, _ = trace(rx, lam, 0.0, r, PX, PY)
        edge = np.concatenate([np.hypot(xp[[0, -1]], yp[[0, -1]]).ravel(), np.hypot(xp[:, [0, -1]], yp[:, [0, -1]]).ravel()])
        if (edge > pr).all():
            return span, True, m, Xs
    return span, False, m, Xs


@pytest.mark.parametrize("r, want_span, covered", [(0.0, 1.2, True), (15.6, 1.45, True), (16.9, 2.1, False)])
def test_spot_widens_its_launch_grid_to_the_first_span_covering_the_pupil(r, want_span, covered):
    """On the Cardboard lens at 550 nm with n = 16 the axis needs span 1.2, 15.6 mm 1.45 and the display
    corner (16.9 mm) none (vignetted outline: the widest, 2.1); the spot's rays are points of that grid."""
    from controlgs_adapter.downstream.optics.generate import _spot

    rx, lam, n = Prescription.cardboard(), 550.0, 16
    v0, Y0, ok = chief_ray(rx, lam, np.array([r]))
    assert ok[0]
    span, cov_ok, m, Xs = _first_span_covering(rx, lam, r, v0[0], n)
    assert (span, cov_ok) == (want_span, covered)
    sx, sy, w, tr, cov = _spot(rx, lam, r, v0[0], Y0[0], n)
    assert 0 < len(sx) <= m * m and np.isin(sx, Xs).all()
    assert (w > 0).all() and 0.0 < tr <= 1.0
    if covered:
        assert cov == pytest.approx(1.0, abs=0.02)  # the primary branch covers the whole pupil area


@pytest.mark.parametrize("nd, vd", [(1.492, 57.4), (1.5168, 64.17)])  # PMMA (the Cardboard lens), N-BK7
def test_cauchy_index_honours_the_abbe_number_definition(nd, vd):
    """n(d line 587.56 nm) = n_d and n_F - n_C = (n_d - 1) / V_d (F 486.13 nm, C 656.27 nm: the Abbe
    number's definition); between the lines n falls with the wavelength (normal dispersion)."""
    from controlgs_adapter.downstream.optics.prescription import cauchy_index

    assert cauchy_index(nd, vd, 587.56) == pytest.approx(nd, abs=1e-12)
    assert cauchy_index(nd, vd, 486.13) - cauchy_index(nd, vd, 656.27) == pytest.approx((nd - 1) / vd, rel=1e-10)
    # two-term Cauchy n = A + B / lam^2 through those two conditions, solved by hand for N-BK7:
    # B = 0.5168 / 64.17 / (1/0.48613^2 - 1/0.65627^2) = 0.00421731 um^2, A = 1.5168 - B / 0.58756^2 = 1.504584;
    # n(550) = A + B / 0.55^2 = 1.518525
    if nd == 1.5168:
        assert cauchy_index(nd, vd, 550.0) == pytest.approx(1.518525, abs=1e-6)
        # against the SCHOTT catalogue's N-BK7 Sellmeier formula (B1..3, C1..3 in um^2): a two-term Cauchy law
        # is within 5.4e-5 of it from F to C (3e-6 at 550 nm)
        sellmeier = [(1.03961212, 0.00600069867), (0.231792344, 0.0200179144), (1.01046945, 103.560653)]
        for lam in (486.13, 550.0, 587.56, 656.27):
            l2 = (lam * 1e-3) ** 2
            n_cat = (1 + sum(b * l2 / (l2 - c) for b, c in sellmeier)) ** 0.5
            assert cauchy_index(nd, vd, lam) == pytest.approx(n_cat, abs=6e-5)
    assert cauchy_index(nd, vd, 486.0) > cauchy_index(nd, vd, 550.0) > cauchy_index(nd, vd, 656.0)


def test_real_magnification_is_the_tiny_field_limit_of_the_chief_ray_height():
    """``real_magnification`` is ``Y / h`` as the field ``h`` goes to 0 (the ratio the bank's chief rays are
    normalised by). Barrel/pincushion distortion makes ``Y / h = m0 + k h^2``; ``m0`` is extrapolated
    here (Richardson) from two small but finite fields, where tracing noise is negligible."""
    import numpy as np

    from controlgs_adapter.downstream.optics.prescription import Prescription
    from controlgs_adapter.downstream.optics.raytrace import chief_ray, real_magnification

    rx = Prescription.cardboard()
    h = np.array([1e-3, 2e-3])
    for lam in (486.0, 550.0, 656.0):
        _, y, ok = chief_ray(rx, lam, h)
        assert ok.all()
        f1, f2 = y / h
        m0 = (4.0 * f1 - f2) / 3.0
        assert abs(f2 - f1) > 1e-10 * abs(m0)  # the distortion term is really there at these fields
        assert real_magnification(rx, lam) == pytest.approx(m0, rel=6e-12, abs=0)


# ----------------------------------------------------------------------------- prescription
def test_prescription_surfaces_are_immutable_values():
    """A checked prescription's surfaces are frozen dataclasses: not editable after the checks, and
    equal by value."""
    rx, rx2 = Prescription.cardboard(), Prescription(CARDBOARD)
    s = rx.surfaces[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.thickness = 1.0                                                       # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        rx.surfaces[1].radius = math.inf                                        # type: ignore[misc]
    assert (s.thickness, rx.surfaces[1].radius) == (8.795, -25.498) and s == rx2.surfaces[0]


@pytest.mark.parametrize("key, value", [("object_distance_mm", 0), ("pupil_diameter_mm", -4.0),
                                        ("virtual_image_distance_mm", "667")])
def test_a_bad_number_is_refused_with_its_own_message(key, value):
    """A present but non-positive (or non-numeric) field is named by its own message, not reported as
    a missing or malformed field (that message is for absent keys and wrong shapes)."""
    spec = dict(CARDBOARD)
    spec[key] = value
    with pytest.raises(InputValueError) as e:
        Prescription(spec)
    assert str(e.value) == f"prescription[{key!r}] must be a positive number, got {value!r}"


# ----------------------------------------------------------------------------- generate
@pytest.mark.parametrize("r", [0.0, 8.0, 16.0])
def test_spot_weights_cover_the_whole_pupil_disc(r):
    """Generator step 2 (module docstring): each kept ray stands for its pupil area, rim cells by the
    fraction inside the disc, so on the unvignetted Cardboard lens the weights add up to the pupil's
    area pi (2 mm)^2 (transmission and coverage 1) to the grid's sampling error, here < 2e-3 with
    ~40 rays across the pupil; the offsets are finite and the weights positive."""
    import numpy as np

    from controlgs_adapter.downstream.optics import generate
    from controlgs_adapter.downstream.optics.raytrace import chief_ray

    rx = Prescription.cardboard()
    v0, Y0, ok = chief_ray(rx, 550.0, np.array([r]))
    assert ok.all()
    sx, sy, w, tr, cov = generate._spot(rx, 550.0, r, v0[0], Y0[0], 40)
    assert w.sum() == pytest.approx(math.pi * 2.0 ** 2, rel=2e-3)
    assert tr == pytest.approx(1.0, abs=2e-3) and cov == pytest.approx(1.0, abs=2e-3) and tr <= 1.0
    assert (w > 0).all() and np.isfinite(sx).all() and np.isfinite(sy).all() and len(w) > 1000


def test_build_bank_smallest_accepted_values_pass_the_checks(tmp_path):
    from controlgs_adapter.commands.optics import _prescription
    from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription

    assert _prescription(None).spec == Prescription(CARDBOARD).spec
    import json

    p = tmp_path / "rx.json"
    p.write_text(json.dumps(CARDBOARD))
    assert _prescription(p).spec == Prescription(CARDBOARD).spec
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (1 << 20))  # exactly 1 MiB is read (and is not JSON)
    with pytest.raises(FileFormatError, match="not a JSON file"):
        _prescription(big)


D64 = torch.float64


def _spec(**over):
    spec = {k: (list(v) if isinstance(v, list) else v) for k, v in CARDBOARD.items()}
    spec.update(over)
    return spec


def _lens(surfaces, **over):
    return Prescription(_spec(surfaces=surfaces, **over))


# ----------------------------------------------------------------------------- generator
@pytest.fixture(scope="module")
def small_bank():
    """3 x 3 fields (centre, edges on the axes, corners), K = 9, 1/4 px at 512 px minimum pitch."""
    return build_bank(grid=(3, 3), psf_size=9, pupil_samples=40, chief_grid=(3, 5), min_pitch_px=0.25,
                      reference_width_px=512)


def _aimed_at_pupil_grid(rx, lam, r, n=64):
    """Rays from display height ``r`` (on +y) aimed by Newton at a uniform grid over the pupil:
    ``(X, Y, ok)`` on the virtual image plane."""
    v0, _, _ = chief_ray(rx, lam, np.array([r]))
    g = (np.arange(n) + 0.5) / n * 2 - 1
    PX, PY = np.meshgrid(g, g)
    inside = PX ** 2 + PY ** 2 <= 1
    tx, ty = PX[inside] * rx.pupil_radius, PY[inside] * rx.pupil_radius
    xp, yp, X, Y, ok = aim_rays(rx, lam, r, v0[0], tx, ty, 10)
    assert np.abs(xp - tx).max() < 1e-9 and np.abs(yp - ty).max() < 1e-9
    return X, Y, ok


# ----------------------------------------------------------------------------- prescription
def test_cauchy_law_meets_its_two_defining_conditions():
    """n(587.56 nm) = n_d and n_F(486.13) - n_C(656.27) = (n_d - 1) / V_d, exactly (to rounding)."""
    for nd, vd in ((1.492, 57.4), (1.7, 30.0)):
        assert cauchy_index(nd, vd, 587.56) == pytest.approx(nd, abs=1e-13)
        assert cauchy_index(nd, vd, 486.13) - cauchy_index(nd, vd, 656.27) == pytest.approx((nd - 1) / vd, abs=1e-13)
    # two-term law: n(l) - n(inf) falls as 1 / l^2: (n(400) - A) / (n(800) - A) = 4 with A = n at l -> inf
    a = cauchy_index(1.492, 57.4, 1e12)
    assert (cauchy_index(1.492, 57.4, 400.0) - a) / (cauchy_index(1.492, 57.4, 800.0) - a) == pytest.approx(4.0, rel=1e-9)


def test_cardboard_geometry_by_hand():
    rx = Prescription.cardboard()
    assert rx.display_mm == (24.0, 24.0) and rx.pupil_radius == 2.0 and rx.image_distance == 667.0
    assert rx.object_distance == 39.07 and rx.wavelengths == (656.0, 550.0, 486.0) and rx.reference_wavelength == 550.0
    assert rx.vertices == pytest.approx([39.07, 39.07 + 8.795])                  # display -> S1 -> S2
    assert rx.pupil_z == pytest.approx(39.07 + 8.795 + 18.0)                     # 65.865 mm
    assert rx.image_z == pytest.approx(65.865 - 667.0)                           # -601.135 mm: behind the display
    s1, s2 = rx.surfaces
    assert (s1.radius, s1.thickness, s1.semi_diameter) == (290.444, 8.795, 17.0)
    assert (s2.radius, s2.thickness, s2.material) == (-25.498, 18.0, "air")
    assert rx.index("air", 550.0) == 1.0
    assert rx.index(s1.material, 550.0) == cauchy_index(1.492, 57.4, 550.0)


def test_prescription_defaults_and_plane_radius_forms():
    spec = _spec()
    del spec["reference_wavelength_nm"]
    assert Prescription(spec).reference_wavelength == 550.0                     # documented default
    for r in (None, 0, "inf"):
        rx = _lens([{"radius_mm": r, "thickness_mm": 2.0, "after": {"nd": 1.5, "vd": 50.0}},
                    {"thickness_mm": 3.0}])                                     # radius absent: a plane, after: air
        assert math.isinf(rx.surfaces[0].radius) and math.isinf(rx.surfaces[1].radius)
        assert rx.surfaces[1].material == "air"
        assert rx.surfaces[0].semi_diameter == 1e9                              # no aperture by default
    assert _lens([{"radius_mm": -10, "thickness_mm": 1.0}]).surfaces[0].radius == -10.0


def test_prescription_is_a_private_copy():
    spec = _spec(surfaces=[{"radius_mm": 50.0, "thickness_mm": 2.0, "after": "air"}])
    rx = Prescription(spec)
    spec["surfaces"][0]["thickness_mm"] = 99.0
    assert rx.spec["surfaces"][0]["thickness_mm"] == 2.0 and rx.surfaces[0].thickness == 2.0


@pytest.mark.parametrize("spec, match", [
    ([1, 2], "mapping.*list"),
    (_spec(display_mm="24"), r"prescription\['display_mm'\] must be a list"),
    (_spec(wavelengths_nm=550.0), r"prescription\['wavelengths_nm'\] must be a list"),
    (_spec(surfaces={"thickness_mm": 1}), r"prescription\['surfaces'\] must be a list"),
    (_spec(object_distance_mm=True), "object_distance_mm.*positive number"),
    (_spec(object_distance_mm="39"), "object_distance_mm.*positive number"),
    (_spec(object_distance_mm=math.inf), "object_distance_mm.*positive number"),
    (_spec(object_distance_mm=math.nan), "object_distance_mm.*positive number"),
    (_spec(object_distance_mm=0), "object_distance_mm.*positive number"),
    (_spec(display_mm=[24.0, -1.0]), "display_mm.*positive number"),
    (_spec(pupil_diameter_mm=0.0), "pupil_diameter_mm"),
    (_spec(virtual_image_distance_mm=-667.0), "virtual_image_distance_mm"),
    (_spec(wavelengths_nm=[550.0, 0.0]), "wavelengths_nm"),
    (_spec(reference_wavelength_nm=-1.0), "reference_wavelength_nm"),
    ({k: v for k, v in CARDBOARD.items() if k != "pupil_diameter_mm"}, "missing or has a malformed field.*pupil_diameter_mm"),
    (_spec(display_mm=[24.0, 24.0, 1.0]), "missing or has a malformed field"),
    (_spec(surfaces=[]), "at least one surface"),
    (_spec(surfaces=[5]), r"surfaces\[0\] must be an object with 'thickness_mm'"),
    (_spec(surfaces=[{"thickness_mm": 1.0}, {"radius_mm": 5.0}]), r"surfaces\[1\] must be an object with 'thickness_mm'"),
    (_spec(surfaces=[{"radius_mm": True, "thickness_mm": 1.0}]), r"surfaces\[0\].radius_mm must be a number"),
    (_spec(surfaces=[{"radius_mm": "10", "thickness_mm": 1.0}]), r"surfaces\[0\].radius_mm must be a number"),
    (_spec(surfaces=[{"radius_mm": math.nan, "thickness_mm": 1.0}]), r"surfaces\[0\].radius_mm must be a number"),
    (_spec(surfaces=[{"thickness_mm": 1.0, "after": "glass"}, {"thickness_mm": 1.0}]), r"surfaces\[0\]\['after'\]"),
    (_spec(surfaces=[{"thickness_mm": 1.0, "after": {"nd": 1.5}}, {"thickness_mm": 1.0}]), r"surfaces\[0\]\['after'\]"),
    (_spec(surfaces=[{"thickness_mm": 0.0}]), r"surfaces\[0\].thickness_mm"),
    (_spec(surfaces=[{"thickness_mm": 1.0, "semi_diameter_mm": -3.0}]), r"surfaces\[0\].semi_diameter_mm"),
    (_spec(surfaces=[{"thickness_mm": 1.0, "after": {"nd": 1.5, "vd": 50.0}}]), "last surface.*must be 'air'"),
])
def test_bad_prescriptions_are_refused_by_name(spec, match):
    with pytest.raises(InputValueError, match=match):
        Prescription(spec)


@pytest.mark.parametrize("lam, efl, dist, mag", [(486.0, 47.51, 725.6, 15.88), (550.0, 47.91, 650.8, 14.20),
                                                 (656.0, 48.34, 586.9, 12.76)])
def test_paraxial_cardboard_matches_the_notes(lam, efl, dist, mag):
    """Notes (optiland / rayoptics / ABCD, agreeing to 0.2 %): f', virtual image distance, magnification."""
    p = paraxial(Prescription.cardboard(), lam)
    assert p.efl == pytest.approx(efl, abs=0.02)
    assert p.image_distance == pytest.approx(dist, abs=0.6)
    assert p.magnification == pytest.approx(mag, abs=0.02)


def test_lens_figures_match_the_notes():
    """Notes: corner (12, 12) mm lands at 611.8 px (550 nm) of 512, 617.1 (486) and 606.5 (656):
    pincushion 19.5 %; 1 display px (24 / 1024 mm) is 0.3411 mm on the 667 mm plane."""
    f = lens_figures(Prescription.cardboard())
    assert f["550nm"]["corner_landing_px_at_1024"] == pytest.approx(611.8, abs=0.3)
    assert f["486nm"]["corner_landing_px_at_1024"] == pytest.approx(617.1, abs=0.3)
    assert f["656nm"]["corner_landing_px_at_1024"] == pytest.approx(606.5, abs=0.3)
    assert f["550nm"]["corner_distortion_pct"] == pytest.approx(19.5, abs=0.1)
    assert f["550nm"]["corner_distortion_pct"] == pytest.approx((f["550nm"]["corner_landing_px_at_1024"] / 512 - 1) * 100)
    assert f["550nm"]["efl_mm"] == pytest.approx(47.91, abs=0.02)
    assert f["486nm"]["paraxial_image_distance_mm"] == pytest.approx(725.6, abs=0.6)
    assert f["656nm"]["paraxial_magnification"] == pytest.approx(12.76, abs=0.02)
    # paraxial magnification 14.20 at 650.8 mm, scaled to the 667 mm plane: 14.55
    assert f["reference_magnification"] == pytest.approx(14.20 * 667 / 650.8, abs=0.02)
    assert f["550nm"]["chief_magnification_on_image_plane"] == f["reference_magnification"]
    assert f["mm_on_image_plane_per_px_at_1024"] == pytest.approx(0.3411, abs=2e-4)
    assert f["px_per_mm_display_at_1024"] == pytest.approx(1024 / 24) and f["half_width_mm"] == 12.0


def test_small_bank_chief_rays_are_the_traced_landings(small_bank):
    """Chief rays in normalised output coordinates: landing height / reference magnification / 12 mm."""
    rx = Prescription.cardboard()
    m = real_magnification(rx, 550.0)
    for li, lam in enumerate((656.0, 550.0, 486.0)):
        c = small_bank.chief[li].double()
        assert c[1, 2].tolist() == [0.0, 0.0]                                  # display centre
        _, Y, _ = chief_ray(rx, lam, np.array([12.0, 6.0, math.hypot(12.0, 6.0)]))
        assert c[1, 4, 0].item() == pytest.approx(Y[0] / m / 12, abs=1e-6) and abs(c[1, 4, 1].item()) < 1e-7
        assert c[2, 2, 1].item() == pytest.approx(Y[0] / m / 12, abs=1e-6)    # (0, +12): y down the rows
        s = Y[2] / m / math.hypot(12.0, 6.0)                                   # corner (6, 12) mm: radial scale
        assert c[2, 3].tolist() == pytest.approx([6.0 * s / 12, 12.0 * s / 12], abs=1e-6)
    # 550 nm at the right edge: notes' corner of the display diagonal lands at 611.8 / 512
    assert small_bank.chief[1, 2, 4].tolist() == pytest.approx([611.8 / 512] * 2, abs=1e-3)


def test_small_bank_psf_orientation_and_coma_centroid(small_bank):
    """Rotational symmetry: the PSF at (+x, 0) is the transpose of the one at (0, +y) and the mirror of
    (-x, 0); the centroid of the PSF at (0, +8 mm) lies radially outward from its chief ray, at the
    mean of rays aimed by Newton at a uniform grid over the pupil (independent of the generator's
    slope grid and its pupil-area weights)."""
    b = small_bank
    p = b.psf.double()
    assert torch.allclose(p[:, 1, 2], p[:, 2, 1].transpose(-1, -2), atol=2e-3)
    assert torch.allclose(p[:, 1, 0], p[:, 1, 2].flip(-1), atol=2e-3)
    assert torch.allclose(p[:, 0, 1], p[:, 2, 1].flip(-2), atol=2e-3)
    rx = Prescription.cardboard()
    lam, li, r = 550.0, 1, 8.0
    v0, Y0, _ = chief_ray(rx, lam, np.array([r]))
    n = 48
    g = (np.arange(n) + 0.5) / n * 2 - 1
    PX, PY = np.meshgrid(g, g)
    inside = PX ** 2 + PY ** 2 <= 1
    tx, ty = PX[inside] * 2.0, PY[inside] * 2.0
    _, _, X, Y, ok = aim_rays(rx, lam, r, v0[0], tx, ty, 8)
    assert ok.all()
    m = real_magnification(rx, 550.0)
    want = (Y - Y0[0]).mean() / m                                              # display-equivalent mm, radial
    t = torch.arange(9, dtype=D64) - 4
    pitch = b.psf_pitch_mm[li, 2, 1].item()
    q = p[li, 2, 1]
    cy, cx = (q.sum(1) * t).sum().item() * pitch, (q.sum(0) * t).sum().item() * pitch
    assert want > 0.002                                                        # outward coma, several pitches
    assert cy == pytest.approx(want, abs=0.15 * pitch) and abs(cx) < 1e-3 * pitch
    q = p[li, 1, 2]                                                            # (+8, 0) mm: the same, along +x
    cx2 = (q.sum(0) * t).sum().item() * b.psf_pitch_mm[li, 1, 2].item()
    assert cx2 == pytest.approx(want, abs=0.15 * pitch)


def test_centre_psf_is_the_airy_pattern_of_the_pupil():
    """On axis at 550 nm the lens is diffraction-limited (notes: 0.02 wave RMS): the PSF is the Airy
    pattern of the 4 mm pupil seen from the 667 mm plane, first dark ring at 1.21967 lambda z / D,
    divided by the reference magnification (display-equivalent mm). Reference: (2 J1(x) / x)^2 from
    scipy, integrated over the same cells (16 x 16 sub-samples)."""
    sp = pytest.importorskip("scipy.special")
    bank = build_bank(grid=(1, 1), psf_size=33, pupil_samples=16, chief_grid=(2, 2), min_pitch_px=0.01)
    rx = Prescription.cardboard()
    r_airy = 1.21967 * 550e-6 * 667.0 / 4.0 / real_magnification(rx, 550.0)    # 0.00769 mm
    assert r_airy == pytest.approx(0.00769, abs=1e-5)
    p = bank.psf_pitch_mm[1, 0, 0].item()
    assert 3 * r_airy / 15.5 < p < 1.1 * 3 * r_airy / 15.5                  # window: 3 dark-ring radii + the spot
    q = bank.psf[1, 0, 0].double().numpy()
    s = 16
    sub = (np.arange(s) + 0.5) / s - 0.5
    g = ((np.arange(33) - 16)[:, None] + sub[None, :]).ravel() * p
    x = np.maximum(3.8317059702 * np.hypot(g[:, None], g[None, :]) / r_airy, 1e-12)   # first zero of J1
    a = ((2 * sp.j1(x) / x) ** 2).reshape(33, s, 33, s).sum((1, 3))
    a /= a.sum()
    t = np.arange(33) - 16
    R = np.hypot(t[:, None], t[None, :]) * p
    assert q[R <= r_airy].sum() == pytest.approx(a[R <= r_airy].sum(), abs=0.015)   # ~0.87 in the first ring
    assert np.abs(q - a).max() < 0.01 and q.max() > 0.04
    assert (q * t[None, :]).sum() == pytest.approx(0.0, abs=1e-9) and (q * t[:, None]).sum() == pytest.approx(0.0, abs=1e-9)


def test_vignetting_aperture_and_a_non_square_display():
    """An aperture 4 mm before the pupil (semi-diameter 2.3 mm) clips the beams of off-axis fields:
    the bank's transmission at (+-8, 0) mm is the fraction of a uniform pupil grid whose Newton-aimed
    rays pass (~0.89); the centre keeps 1. On a 24 x 16 mm display the chief rays are normalised by
    12 and 8 mm, and the corner (12, 8) mm lands at the traced radial scale."""
    spec = _spec(display_mm=[24.0, 16.0],
                 surfaces=[dict(CARDBOARD["surfaces"][0]), dict(CARDBOARD["surfaces"][1], thickness_mm=14.0),
                           {"radius_mm": None, "thickness_mm": 4.0, "after": "air", "semi_diameter_mm": 2.3}])
    rx = Prescription(spec)
    bank = build_bank(rx, grid=(1, 3), psf_size=9, pupil_samples=40, chief_grid=(3, 3))
    assert bank.field_x.tolist() == pytest.approx([-2 / 3, 0.0, 2 / 3]) and bank.field_y.tolist() == [0.0]
    assert bank.display_mm == (24.0, 16.0)
    T = bank.transmission
    for li, lam in enumerate(rx.wavelengths):
        _, _, ok = _aimed_at_pupil_grid(rx, lam, 8.0)
        assert 0.85 < ok.mean() < 0.93
        assert T[li, 0, 2].item() == pytest.approx(ok.mean(), abs=0.01) and T[li, 0, 0].item() == T[li, 0, 2].item()
        assert T[li, 0, 1].item() == 1.0
    m = real_magnification(rx, 550.0)
    _, Y, _ = chief_ray(rx, 550.0, np.array([math.hypot(12.0, 8.0), 8.0]))
    s = Y[0] / m / math.hypot(12.0, 8.0)
    assert bank.chief[1, 2, 2].tolist() == pytest.approx([s, s], abs=1e-6)         # (12 s / 12, 8 s / 8)
    assert bank.chief[1, 2, 1].tolist() == pytest.approx([0.0, Y[1] / m / 8.0], abs=1e-6)
    assert bank.meta["generator"]["min_pupil_coverage"] == pytest.approx(1.0, abs=0.02)


def test_an_aperture_blocking_the_edge_chief_rays_is_refused():
    spec = _spec(surfaces=[dict(CARDBOARD["surfaces"][0], semi_diameter_mm=5.0), dict(CARDBOARD["surfaces"][1])])
    with pytest.raises(InputValueError, match=r"chief rays of \d+ warp-grid points \(up to 16.97 mm from the display "
                                              r"centre\) at 656 nm are blocked by a lens aperture"):
        build_bank(spec, grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(3, 3))
