"""Tests of ``controlgs_adapter.downstream.optics.prescription``: a lens prescription is checked (every
refusal names the field and the value), copied and frozen; the Cardboard geometry; the Cauchy
dispersion law against its defining conditions and catalogue data."""

from __future__ import annotations

import dataclasses
import math

import pytest
from helpers.prescriptions import cardboard_spec, lens

from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
from controlgs_adapter.errors import InputValueError


def _surface(i, **over):
    return dict(CARDBOARD["surfaces"][i], **over)


@pytest.mark.parametrize("spec, match", [
    ([1, 2], "mapping.*list"),
    (cardboard_spec(display_mm="24"), r"prescription\['display_mm'\] must be a list"),
    (cardboard_spec(display_mm="66"), r"prescription\['display_mm'\] must be a list"),
    (cardboard_spec(wavelengths_nm=550.0), r"prescription\['wavelengths_nm'\] must be a list"),
    (cardboard_spec(wavelengths_nm="656"), r"prescription\['wavelengths_nm'\] must be a list"),
    (cardboard_spec(surfaces={"thickness_mm": 1}), r"prescription\['surfaces'\] must be a list"),
    (cardboard_spec(surfaces={}), r"prescription\['surfaces'\] must be a list"),
    *[(cardboard_spec(**{key: value}), rf"prescription\['{key}'\] must be a positive number, got {value!r}")
      for key, value in [("object_distance_mm", True), ("object_distance_mm", "39"), ("object_distance_mm", math.inf),
                         ("object_distance_mm", math.nan), ("object_distance_mm", 0), ("object_distance_mm", -3),
                         ("pupil_diameter_mm", 0.0), ("pupil_diameter_mm", -4.0), ("pupil_diameter_mm", True),
                         ("virtual_image_distance_mm", -667.0), ("virtual_image_distance_mm", "667"),
                         ("reference_wavelength_nm", -1.0)]],
    (cardboard_spec(display_mm=[24.0, -1.0]), "display_mm.*positive number"),
    (cardboard_spec(wavelengths_nm=[550.0, 0.0]), "wavelengths_nm"),
    ({k: v for k, v in CARDBOARD.items() if k != "pupil_diameter_mm"}, "missing or has a malformed field.*pupil_diameter_mm"),
    ({k: v for k, v in CARDBOARD.items() if k != "object_distance_mm"}, "missing or has a malformed field.*object_distance_mm"),
    (cardboard_spec(display_mm=[24.0, 24.0, 1.0]), "missing or has a malformed field"),
    (cardboard_spec(surfaces=[]), "at least one surface"),
    (cardboard_spec(surfaces=[1]), r"surfaces\[0\] must be an object with 'thickness_mm'"),
    (cardboard_spec(surfaces=[5]), r"surfaces\[0\] must be an object with 'thickness_mm'"),
    (cardboard_spec(surfaces=[{"thickness_mm": 1.0}, {"radius_mm": 5.0}]), r"surfaces\[1\] must be an object with 'thickness_mm'"),
    *[(cardboard_spec(surfaces=[{"radius_mm": r, "thickness_mm": 1.0}]), r"surfaces\[0\].radius_mm must be a number")
      for r in (True, "10", math.nan)],
    (cardboard_spec(surfaces=[_surface(0, radius_mm="abc"), _surface(1)]), r"surfaces\[0\].radius_mm must be a number"),
    (cardboard_spec(surfaces=[{"thickness_mm": 1.0, "after": "glass"}, {"thickness_mm": 1.0}]), r"surfaces\[0\]\['after'\]"),
    (cardboard_spec(surfaces=[{"radius_mm": 10, "thickness_mm": 1, "after": "glass"}]), r"surfaces\[0\]\['after'\]"),
    (cardboard_spec(surfaces=[{"thickness_mm": 1.0, "after": {"nd": 1.5}}, {"thickness_mm": 1.0}]), r"surfaces\[0\]\['after'\]"),
    (cardboard_spec(surfaces=[{"thickness_mm": 0.0}]), r"surfaces\[0\].thickness_mm"),
    (cardboard_spec(surfaces=[{"thickness_mm": 1.0, "semi_diameter_mm": -3.0}]), r"surfaces\[0\].semi_diameter_mm"),
    (cardboard_spec(surfaces=[{"thickness_mm": 1.0, "after": {"nd": 1.5, "vd": 50.0}}]), "last surface.*must be 'air'"),
])
def test_bad_prescriptions_are_refused_by_name(spec, match):
    with pytest.raises(InputValueError, match=match):
        Prescription(spec)


def test_cardboard_geometry():
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
    spec = cardboard_spec()
    del spec["reference_wavelength_nm"]
    assert Prescription(spec).reference_wavelength == 550.0                     # documented default
    for r in (None, 0, "inf"):
        rx = lens([{"radius_mm": r, "thickness_mm": 2.0, "after": {"nd": 1.5, "vd": 50.0}},
                   {"thickness_mm": 3.0}])                                      # radius absent: a plane, after: air
        assert math.isinf(rx.surfaces[0].radius) and math.isinf(rx.surfaces[1].radius)
        assert rx.surfaces[1].material == "air"
        assert rx.surfaces[0].semi_diameter == 1e9                              # no aperture by default
    assert lens([{"radius_mm": -10, "thickness_mm": 1.0}]).surfaces[0].radius == -10.0


def test_prescription_is_a_private_frozen_copy():
    """A checked prescription keeps its own copy of the spec, and its surfaces are frozen dataclasses:
    not editable after the checks, and equal by value."""
    spec = cardboard_spec(surfaces=[{"radius_mm": 50.0, "thickness_mm": 2.0, "after": "air"}])
    rx = Prescription(spec)
    spec["surfaces"][0]["thickness_mm"] = 99.0
    assert rx.spec["surfaces"][0]["thickness_mm"] == 2.0 and rx.surfaces[0].thickness == 2.0
    rx, rx2 = Prescription.cardboard(), Prescription(CARDBOARD)
    s = rx.surfaces[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.thickness = 1.0                                                       # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        rx.surfaces[1].radius = math.inf                                        # type: ignore[misc]
    assert (s.thickness, rx.surfaces[1].radius) == (8.795, -25.498) and s == rx2.surfaces[0]


@pytest.mark.parametrize("nd, vd", [(1.492, 57.4), (1.5168, 64.17), (1.7, 30.0)])  # PMMA (the Cardboard lens), N-BK7
def test_cauchy_index_meets_the_abbe_number_definition(nd, vd):
    """n(d line 587.56 nm) = n_d and n_F - n_C = (n_d - 1) / V_d (F 486.13 nm, C 656.27 nm: the Abbe
    number's definition); a two-term law: n(l) - n(inf) falls as 1 / l^2; between the lines n falls with
    the wavelength (normal dispersion)."""
    assert cauchy_index(nd, vd, 587.56) == pytest.approx(nd, abs=1e-13)
    assert cauchy_index(nd, vd, 486.13) - cauchy_index(nd, vd, 656.27) == pytest.approx((nd - 1) / vd, abs=1e-13, rel=1e-10)
    a = cauchy_index(nd, vd, 1e12)
    assert (cauchy_index(nd, vd, 400.0) - a) / (cauchy_index(nd, vd, 800.0) - a) == pytest.approx(4.0, rel=1e-9)
    assert cauchy_index(nd, vd, 486.0) > cauchy_index(nd, vd, 550.0) > cauchy_index(nd, vd, 656.0)


def test_cauchy_index_against_catalogue_data():
    """PMMA: within 5e-5 of a Buchdahl fit at 486 / 550 / 656 nm. N-BK7: two-term Cauchy through the
    two conditions, solved here: B = 0.5168 / 64.17 / (1/0.48613^2 - 1/0.65627^2) = 0.00421731 um^2,
    A = 1.5168 - B / 0.58756^2 = 1.504584, n(550) = A + B / 0.55^2 = 1.518525; within 6e-5 of the SCHOTT
    catalogue's Sellmeier formula (B1..3, C1..3 in um^2) from F to C (3e-6 at 550 nm)."""
    for lam, n in ((486.0, 1.49799), (550.0, 1.49383), (656.0, 1.48940)):
        assert cauchy_index(1.492, 57.4, lam) == pytest.approx(n, abs=5e-5)
    assert cauchy_index(1.5168, 64.17, 550.0) == pytest.approx(1.518525, abs=1e-6)
    sellmeier = [(1.03961212, 0.00600069867), (0.231792344, 0.0200179144), (1.01046945, 103.560653)]
    for lam in (486.13, 550.0, 587.56, 656.27):
        l2 = (lam * 1e-3) ** 2
        n_cat = (1 + sum(b * l2 / (l2 - c) for b, c in sellmeier)) ** 0.5
        assert cauchy_index(1.5168, 64.17, lam) == pytest.approx(n_cat, abs=6e-5)




# ----------------------------------------------------------------------------- conics, aspheres, moves, mirrors
_MIRROR_PAIR = [{"radius_mm": -80.0, "thickness_mm": -30.0, "after": "mirror"}, {"thickness_mm": 50.0, "after": "mirror"}]


@pytest.mark.parametrize("surfaces, over, match", [
    ([_surface(0, semi_diameter_mm=0.0), _surface(1)], {}, r"surfaces\[0\].semi_diameter_mm.*positive number, got 0.0"),
    ([_surface(0), _surface(1, semi_diameter_mm=-2.0)], {}, r"surfaces\[1\].semi_diameter_mm.*positive number, got -2.0"),
    # sphere R = 10 cannot reach 11 mm; an ellipsoid k = 1 (oblate) of R = 20 reaches 20 / sqrt(2) = 14.1 mm only
    ([{"radius_mm": 10.0, "thickness_mm": 2.0, "semi_diameter_mm": 11.0}], {}, r"surfaces\[0\]: the conic .*no sag at its semi_diameter_mm 11"),
    ([{"radius_mm": 20.0, "conic": 1.0, "thickness_mm": 2.0, "semi_diameter_mm": 14.2}], {}, r"surfaces\[0\]: the conic"),
    ([_surface(0), _surface(1, conic=math.nan)], {}, r"surfaces\[1\].conic must be a finite number, got nan"),
    ([_surface(0, conic=math.inf), _surface(1)], {}, r"surfaces\[0\].conic"),
    ([_surface(0, conic="1"), _surface(1)], {}, r"surfaces\[0\].conic"),
    ([_surface(0, aspheric=[1e-5, math.inf]), _surface(1)], {}, r"surfaces\[0\].aspheric must be a list of finite numbers"),
    ([_surface(0), _surface(1, aspheric=1e-5)], {}, r"surfaces\[1\].aspheric must be a list"),
    ([_surface(0, decenter_mm=[1.0]), _surface(1)], {}, r"surfaces\[0\].decenter_mm must be \[x, y\]"),
    ([_surface(0), _surface(1, tilt_deg=[0.0, math.nan])], {}, r"surfaces\[1\].tilt_deg must be \[x, y\]"),
    ([_surface(0, radius=5.0), _surface(1)], {}, r"surfaces\[0\] has unknown keys \['radius'\]"),
    ([_surface(0), _surface(1, after="Mirror")], {}, r"surfaces\[1\]\['after'\] must be 'air', 'mirror'"),
    # mirrors: an odd number leaves the light travelling away from the eye; thickness signs follow the direction
    ([_MIRROR_PAIR[0], {"thickness_mm": -5.0}], {}, r"1 mirrors.*even number"),
    ([_MIRROR_PAIR[0], {"thickness_mm": 5.0}, _MIRROR_PAIR[1]], {}, r"surfaces\[1\].thickness_mm.*negative"),
    ([dict(_MIRROR_PAIR[0], thickness_mm=30.0), _MIRROR_PAIR[1]], {}, r"surfaces\[0\].thickness_mm.*negative"),
    ([_MIRROR_PAIR[0], dict(_MIRROR_PAIR[1], thickness_mm=-50.0)], {}, r"surfaces\[1\].thickness_mm.*must be a positive"),
    ([_surface(0), _surface(1)], {"display_offset_mm": [1.0, math.inf]}, r"display_offset_mm'\] must be \[x, y\]"),
    ([_surface(0), _surface(1)], {"display_offset_mm": 1.0}, r"display_offset_mm'\] must be \[x, y\]"),
    *[([_surface(0), _surface(1)], {"efficiency": e}, r"efficiency'\] must be a number in \(0, 1\]") for e in (0.0, 1.5, True, math.nan)],
    ([_surface(0), _surface(1)], {"focal_mm": 40.0}, r"prescription has unknown keys \['focal_mm'\]"),
])
def test_bad_surfaces_and_system_keys_are_refused_by_name(surfaces, over, match):
    with pytest.raises(InputValueError, match=match):
        lens(surfaces, **over)


def test_new_keys_are_read_with_defaults_that_keep_today_s_lenses():
    rx = Prescription.cardboard()
    assert rx.rotationally_symmetric and rx.display_offset == (0.0, 0.0) and rx.efficiency == 1.0
    assert all(sf.conic == 0.0 and sf.aspheric == () and not sf.moved and not sf.mirror for sf in rx.surfaces)
    assert rx.path_length == rx.pupil_z
    rx = lens([_surface(0, conic=-1, aspheric=[1e-5, 0], decenter_mm=[0.5, 0]), _surface(1, tilt_deg=[0, 2])],
              display_offset_mm=[1.0, -2.0], efficiency=0.25)
    s1, s2 = rx.surfaces
    assert (s1.conic, s1.aspheric, s1.decenter, s1.tilt) == (-1.0, (1e-5, 0.0), (0.5, 0.0), (0.0, 0.0))
    assert s2.tilt == (0.0, 2.0) and s1.moved and s2.moved
    assert rx.display_offset == (1.0, -2.0) and rx.efficiency == 0.25 and not rx.rotationally_symmetric
    assert not lens([_surface(0), _surface(1)], display_offset_mm=[0.0, 0.5]).rotationally_symmetric
    assert lens([_surface(0, decenter_mm=[0, 0], tilt_deg=[-0.0, 0]), _surface(1)]).rotationally_symmetric
    # a mirror keeps the medium before it; thicknesses after it are negative, the path is unfolded
    glass = {"nd": 1.5, "vd": 50.0}
    rx = lens([{"radius_mm": 100.0, "thickness_mm": 3.0, "after": glass}, {"thickness_mm": -2.0, "after": "mirror"},
               {"radius_mm": 100.0, "thickness_mm": 2.0, "after": "mirror"}, {"thickness_mm": 10.0}],
              object_distance_mm=30.0)
    assert [sf.mirror for sf in rx.surfaces] == [False, True, True, False]
    assert rx.surfaces[1].material == glass and rx.surfaces[2].material == glass   # the medium before each mirror
    assert rx.vertices == pytest.approx([30.0, 33.0, 31.0, 33.0]) and rx.pupil_z == pytest.approx(43.0)
    assert rx.path_length == pytest.approx(30.0 + 3 + 2 + 2 + 10)
