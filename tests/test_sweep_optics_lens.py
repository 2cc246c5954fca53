"""Lens prescriptions, the ray tracer and the bank generator pinned against hand calculations, a
second (angle-based) meridional tracer, the feasibility notes' optiland/rayoptics figures
(docs: /work/shared/notes/optics.md) and every refusal by its message."""

import math

import numpy as np
import pytest
import torch

from controlgs_adapter.downstream.optics.generate import build_bank, lens_figures
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
from controlgs_adapter.downstream.optics.raytrace import chief_ray, paraxial, real_magnification, trace
from controlgs_adapter.errors import InputValueError
from _pupil import aim_rays

D64 = torch.float64


def _spec(**over):
    spec = {k: (list(v) if isinstance(v, list) else v) for k, v in CARDBOARD.items()}
    spec.update(over)
    return spec


def _lens(surfaces, **over):
    return Prescription(_spec(surfaces=surfaces, **over))


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


# ----------------------------------------------------------------------------- tracer
def _meridional(surfaces, obj, h, slope, lam_index, pupil_gap, image_distance):
    """Independent meridional trace with angles (Snell's law ``n1 sin i = n2 sin r``) through
    spherical surfaces ``(R, thickness_after, n_after)``; returns (pupil height, image-plane height)."""
    z, y, ang, n1 = 0.0, h, math.atan(slope), 1.0                             # angle to the axis
    zv = obj
    for R, t, n2 in surfaces:
        if math.isinf(R):
            zs = zv
            ys = y + math.tan(ang) * (zs - z)
            normal = 0.0                                                         # normal angle to the axis
        else:                                                                    # circle: centre at zv + R
            zc = zv + R
            dz, dy = math.cos(ang), math.sin(ang)
            oz, oy = z - zc, y
            b = oz * dz + oy * dy
            c = oz * oz + oy * oy - R * R
            root = math.sqrt(b * b - c)
            s = -b - root if R > 0 else -b + root                                # the near intersection
            zs, ys = z + s * dz, y + s * dy
            normal = math.atan2(-(ys), -(zs - zc)) if R > 0 else math.atan2(ys, zs - zc)
        i = ang - normal
        r = math.asin(n1 * math.sin(i) / n2)
        ang = normal + r
        z, y, n1 = zs, ys, n2
        zv += t
    zp = zv
    yp = y + math.tan(ang) * (zp - z)
    Y = y + math.tan(ang) * (zp - image_distance - z)
    return yp, Y


@pytest.mark.parametrize("h, slope", [(0.0, 0.1), (3.0, 0.0), (5.0, -0.2), (-2.0, 0.15)])
def test_trace_matches_an_angle_based_meridional_trace(h, slope):
    """A biconvex glass lens with a plane window, non-dispersive (V huge) so n = 1.6 at any wavelength."""
    glass = {"nd": 1.6, "vd": 1e12}
    rx = _lens([{"radius_mm": 40.0, "thickness_mm": 6.0, "after": glass},
                {"radius_mm": -30.0, "thickness_mm": 4.0, "after": "air"},
                {"radius_mm": None, "thickness_mm": 2.0, "after": glass},
                {"radius_mm": None, "thickness_mm": 15.0, "after": "air"}], object_distance_mm=30.0,
               virtual_image_distance_mm=500.0)
    n = cauchy_index(1.6, 1e12, 550.0)
    want_yp, want_Y = _meridional([(40.0, 6.0, n), (-30.0, 4.0, 1.0), (math.inf, 2.0, n), (math.inf, 15.0, 1.0)],
                                  30.0, h, slope, 0, 15.0, 500.0)
    xp, yp, X, Y, ok = trace(rx, 550.0, 0.0, h, 0.0, slope)
    assert ok and xp == pytest.approx(0.0, abs=1e-12) and X == pytest.approx(0.0, abs=1e-12)
    assert yp == pytest.approx(want_yp, abs=1e-9) and Y == pytest.approx(want_Y, abs=1e-7)
    # the same ray turned by 90 degrees about the axis: x and y swap
    xp2, yp2, X2, Y2, _ = trace(rx, 550.0, h, 0.0, slope, 0.0)
    assert (xp2, X2) == pytest.approx((want_yp, want_Y), abs=1e-7) and abs(yp2) < 1e-12 and abs(Y2) < 1e-12


def test_trace_flags_apertures_misses_and_total_internal_reflection():
    rx = Prescription.cardboard()
    # a ray from the display centre at slope v reaches S1 (z = 39.07, sag ~0) at height ~39.07 v; semi-diameter 17
    *_, ok = trace(rx, 550.0, 0.0, 0.0, 0.0, np.array([0.40, 0.45, -0.45]))
    assert ok.tolist() == [True, False, False]
    *_, ok = trace(rx, 550.0, 0.0, 0.0, np.array([0.40, 0.0, 0.3]), np.array([0.0, 0.40, 0.3]))
    assert ok.tolist() == [True, True, False]                                  # the aperture is a disc: |(0.3, 0.3)| = 0.42
    # glass (n = 1.5) -> air through a surface of radius 2 (centre toward the eye): a ray parallel to
    # the axis at height y meets it at incidence asin(y / 2); 1.5 * 0.9 > 1 is total internal
    # reflection, 1.5 * 0.5 < 1 passes; y = 2.5 misses the sphere altogether
    glass = {"nd": 1.5, "vd": 1e12}
    rx = _lens([{"radius_mm": None, "thickness_mm": 1.0, "after": glass},
                {"radius_mm": 2.0, "thickness_mm": 5.0, "after": "air"}], object_distance_mm=1.0)
    *_, ok = trace(rx, 550.0, 0.0, np.array([1.0, 1.8, 2.5, 0.0]), 0.0, 0.0)
    assert ok.tolist() == [True, False, False, True]


def test_slab_paraxial_image_by_hand():
    """A plane-parallel slab has no power: magnification 1; the display is seen at
    object distance + t / n + the air gap from the pupil (apparent depth of the slab)."""
    glass = {"nd": 1.6, "vd": 40.0}
    rx = _lens([{"radius_mm": None, "thickness_mm": 5.0, "after": glass},
                {"radius_mm": None, "thickness_mm": 10.0, "after": "air"}])
    n = cauchy_index(1.6, 40.0, 550.0)
    with np.errstate(divide="ignore"):
        p = paraxial(rx, 550.0)
    assert p.magnification == pytest.approx(1.0, abs=1e-12)
    assert p.image_distance == pytest.approx(39.07 + 5.0 / n + 10.0, abs=1e-9)
    assert math.isinf(p.efl)
    # the chief ray through the pupil centre, projected onto the 667 mm plane: 667 / apparent distance
    assert real_magnification(rx, 550.0) == pytest.approx(667.0 / (39.07 + 5.0 / n + 10.0), rel=1e-6)


@pytest.mark.parametrize("lam, efl, dist, mag", [(486.0, 47.51, 725.6, 15.88), (550.0, 47.91, 650.8, 14.20),
                                                 (656.0, 48.34, 586.9, 12.76)])
def test_paraxial_cardboard_matches_the_notes(lam, efl, dist, mag):
    """Notes (optiland / rayoptics / ABCD, agreeing to 0.2 %): f', virtual image distance, magnification."""
    p = paraxial(Prescription.cardboard(), lam)
    assert p.efl == pytest.approx(efl, abs=0.02)
    assert p.image_distance == pytest.approx(dist, abs=0.6)
    assert p.magnification == pytest.approx(mag, abs=0.02)


def test_chief_ray_crosses_the_pupil_centre_and_reports_convergence():
    rx = Prescription.cardboard()
    h = np.array([0.0, 4.0, 12.0])
    v, Y, ok = chief_ray(rx, 550.0, h)
    assert ok.all() and v[0] == 0.0 and Y[0] == 0.0
    _, yp, _, Y2, _ = trace(rx, 550.0, 0.0, h, 0.0, v)
    assert np.abs(yp).max() < 1e-9 and np.allclose(Y2, Y, atol=0, rtol=0)
    # no Newton step: the paraxial guess -h / pupil_z misses the pupil centre and is reported as such
    v0, _, ok0 = chief_ray(rx, 550.0, h, iters=0)
    assert np.allclose(v0, -h / rx.pupil_z) and ok0.tolist() == [True, False, False]


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


# ----------------------------------------------------------------------------- generator
@pytest.fixture(scope="module")
def small_bank():
    """3 x 3 fields (centre, edges on the axes, corners), K = 9, 1/4 px at 512 px minimum pitch."""
    return build_bank(grid=(3, 3), psf_size=9, pupil_samples=40, chief_grid=(3, 5), min_pitch_px=0.25,
                      reference_width_px=512)


def test_small_bank_grids_pitch_and_meta(small_bank):
    b = small_bank
    assert torch.allclose(b.field_x, torch.tensor([-2 / 3, 0.0, 2 / 3], dtype=D64), atol=1e-12)
    assert torch.allclose(b.field_y, b.field_x) and b.chief_x.tolist() == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert b.chief_y.tolist() == [-1.0, 0.0, 1.0] and tuple(b.chief.shape) == (3, 3, 5, 2)
    assert tuple(b.psf.shape) == (3, 3, 3, 9, 9) and b.wavelengths_nm == (656.0, 550.0, 486.0)
    # the centre PSF is diffraction-limited at 550 and 486 nm: its pitch is the minimum, 0.25 px at
    # 512 px = 0.25 * 24 / 512 mm (656 nm: defocused by the lens's longitudinal colour, coarser)
    assert b.psf_pitch_mm[1:, 1, 1].tolist() == pytest.approx([0.25 * 24 / 512] * 2, rel=1e-6)
    assert b.psf_pitch_mm[0, 1, 1].item() > 1.02 * 0.25 * 24 / 512
    gen = b.meta["generator"]
    assert (gen["grid"], gen["psf_size"], gen["pupil_samples"], gen["chief_grid"]) == ([3, 3], 9, 40, [3, 5])
    assert (gen["min_pitch_px"], gen["reference_width_px"]) == (0.25, 512)
    assert 0.97 < gen["min_pupil_coverage"] <= 1.0
    T = b.transmission
    assert T.shape == (3, 3, 3) and T[:, 1, 1].tolist() == [1.0, 1.0, 1.0] and (T > 0.9).all()
    assert b.meta["figures"]["550nm"]["corner_landing_px_at_1024"] == pytest.approx(611.8, abs=0.3)


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


@pytest.mark.parametrize("kw, match", [
    (dict(psf_size=34), "psf_size must be an odd integer >= 5"),
    (dict(psf_size=3), "psf_size must be an odd integer >= 5"),
    (dict(psf_size=True), "psf_size"),
    (dict(psf_size=33.0), "psf_size"),
    (dict(grid=30), r"grid must be \(Gy, Gx\)"),
    (dict(grid=(3, 3, 3)), r"grid must be \(Gy, Gx\)"),
    (dict(grid=(0, 3)), r"grid\[0\] \(Gy\) must be an integer >= 1"),
    (dict(grid=(3, 0)), r"grid\[1\] \(Gx\)"),
    (dict(chief_grid=[5]), r"chief_grid must be \(Cy, Cx\)"),
    (dict(chief_grid=(1, 5)), r"chief_grid\[0\] must be an integer >= 2"),
    (dict(chief_grid=(5, 1)), r"chief_grid\[1\]"),
    (dict(pupil_samples=3), "pupil_samples must be an integer >= 4"),
    (dict(reference_width_px=0), "reference_width_px must be an integer >= 1"),
    (dict(min_pitch_px=0.0), "min_pitch_px must be a finite number > 0"),
    (dict(min_pitch_px=math.inf), "min_pitch_px"),
    (dict(min_pitch_px=True), "min_pitch_px"),
    (dict(min_pitch_px="0.1"), "min_pitch_px"),
])
def test_build_bank_refuses_bad_settings_by_name(kw, match):
    with pytest.raises(InputValueError, match=match):
        build_bank(**kw)


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
