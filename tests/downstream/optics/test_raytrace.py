"""Tests of ``controlgs_adapter.downstream.optics.raytrace``: the real-ray tracer against an independent
angle-based trace, closed forms for slabs and the paraxial ABCD figures; apertures, misses and total
internal reflection; the chief-ray search (clamped Newton steps, convergence) and magnification."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.prescriptions import cardboard_spec, lens

from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
from controlgs_adapter.downstream.optics.raytrace import chief_ray, chief_ray_2d, paraxial, real_magnification, trace, trace_exit
from controlgs_adapter.errors import InputValueError


@pytest.mark.parametrize("lam, efl, dist, mag", [(486.0, 47.51, 725.6, 15.88), (550.0, 47.91, 650.8, 14.20),
                                                 (656.0, 48.34, 586.9, 12.76)])
def test_paraxial_figures_of_the_cardboard_lens(lam, efl, dist, mag):
    """Reference figures (optiland / rayoptics / ABCD, agreeing to 0.2 %): f', virtual image distance and
    magnification; at 550 nm the ABCD focal length is the thick-lens formula
    1/f = (n-1)(1/R1 - 1/R2) + (n-1)^2 t / (n R1 R2)."""
    p = paraxial(Prescription.cardboard(), lam)
    assert p.efl == pytest.approx(efl, abs=0.02)
    assert p.image_distance == pytest.approx(dist, abs=0.6)
    assert p.magnification == pytest.approx(mag, abs=0.02)
    n = cauchy_index(1.492, 57.4, lam)
    r1, r2, t = 290.444, -25.498, 8.795
    assert p.efl == pytest.approx(1 / ((n - 1) * (1 / r1 - 1 / r2) + (n - 1) ** 2 * t / (n * r1 * r2)), rel=1e-9)


@pytest.mark.parametrize("lam", [486.0, 550.0, 656.0])
def test_tracer_matches_paraxial_abcd(lam):
    rx = Prescription.cardboard()
    par = paraxial(rx, lam)
    # near-axis rays from the on-axis display point: their backward extensions cross the axis at the
    # paraxial image; each leaves the lens as Y(z) = Y_i + s (z - zi), s from the pupil-plane height
    zi = rx.image_z
    xp, yp, _, Yi, _ = trace(rx, lam, 0.0, 0.0, 0.0, np.array([1e-5, 2e-5]))
    s = (yp - Yi) / (rx.pupil_z - zi)
    z_cross = zi - Yi / s
    image_distance = rx.pupil_z - z_cross
    assert np.allclose(image_distance, par.image_distance, rtol=1e-4)
    # chief-ray magnification on the 667 mm plane = paraxial magnification scaled to that plane
    m667 = par.magnification * rx.image_distance / par.image_distance
    assert real_magnification(rx, lam) == pytest.approx(m667, rel=1e-4)


def test_distortion_and_lateral_colour_at_the_corner():
    rx = Prescription.cardboard()
    m = real_magnification(rx, 550.0)
    corner = 12 * math.sqrt(2)
    land = {lam: chief_ray(rx, lam, np.array([corner]))[1][0] / m / corner * 512 for lam in (486.0, 550.0, 656.0)}
    assert land[550.0] == pytest.approx(611.8, abs=0.5)               # pincushion, ~19.5 %
    assert land[486.0] - land[656.0] == pytest.approx(10.6, abs=0.5)  # per axis (15.0 px along the diagonal)


def test_trace_computes_in_float64_whatever_the_input_dtype():
    """float32 display points and slopes are traced in float64: the same rays as float64 input, to the
    bit (a float32 trace through the lens differs by ~1e-5 mm), and float64 outputs."""
    rx = Prescription.cardboard()
    h = np.linspace(0.0, 16.0, 9)
    v = np.linspace(-0.3, 0.0, 9)
    ref = trace(rx, 550.0, np.zeros(9), h, np.zeros(9), v)
    low = trace(rx, 550.0, np.zeros(9, np.float32), h.astype(np.float32), np.zeros(9, np.float32), v.astype(np.float32))
    h32, v32 = h.astype(np.float32).astype(np.float64), v.astype(np.float32).astype(np.float64)
    ref32 = trace(rx, 550.0, np.zeros(9), h32, np.zeros(9), v32)  # the float32 inputs' exact values, traced in float64
    for a, b in zip(low, ref32):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert all(a.dtype == np.float64 for a in low[:4])
    assert np.array_equal(low[4], ref[4])


def test_chief_ray_newton_steps_are_clamped_to_0_05():
    """From the paraxial guess v0 = -h / pupil_z, one Newton step moves the slope by at most 0.05 each
    way: at h = 16 mm the full step is +0.057 (the converged slope, 40 steps), at h = 30 mm it is
    negative and larger; one step is then exactly v0 +- 0.05. Near the axis the step is unclamped."""
    rx = Prescription.cardboard()
    h = np.array([16.0, 30.0, 2.0])
    v0 = -h / rx.pupil_z
    v0_back, _, ok0 = chief_ray(rx, 550.0, h, iters=0)
    assert not ok0.any()  # the paraxial guess does not cross the pupil centre within 1e-9 mm
    assert np.array_equal(v0_back, v0)
    v1, _, ok1 = chief_ray(rx, 550.0, h, iters=1)
    assert not ok1[0]  # clamped short of the root: not converged
    assert v1[0] - v0[0] == pytest.approx(0.05, abs=1e-12)
    assert v1[1] - v0[1] == pytest.approx(-0.05, abs=1e-12)
    assert 0.0 < v1[2] - v0[2] < 0.01  # 2 mm: 0.0036, far from the clamp
    v, _, ok = chief_ray(rx, 550.0, h[:1], iters=40)
    assert ok[0] and v[0] - v0[0] > 0.05  # the clamp only slows the approach, the root is further
    v2, _, _ = chief_ray(rx, 550.0, h[:1], iters=2)
    assert v2[0] - v0[0] == pytest.approx((v[0] - v0[0]), abs=1e-3)  # second step: the remaining 0.007


def test_chief_ray_converged_means_within_1e_9_mm_of_the_pupil_centre():
    """``ok`` is |pupil height| < 1e-9 mm of the returned slope's ray (traced here again): after two Newton
    steps the 5.31 mm ray misses the centre by 1.3e-9 mm (found by a scan): not converged; 1 mm has."""
    rx = Prescription.cardboard()
    h = np.array([5.31, 1.0])
    v, _, ok = chief_ray(rx, 550.0, h, iters=2)
    _, yp, _, _, _ = trace(rx, 550.0, 0.0, h, 0.0, v)
    assert 1.2e-9 < abs(yp[0]) < 1.8e-9 and abs(yp[1]) < 1e-12
    assert ok.tolist() == [False, True]
    v, _, ok = chief_ray(rx, 550.0, h)  # the default 40 steps converge both
    assert ok.all()


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
    rx = lens([{"radius_mm": 40.0, "thickness_mm": 6.0, "after": glass},
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
    rx = lens([{"radius_mm": None, "thickness_mm": 1.0, "after": glass},
                {"radius_mm": 2.0, "thickness_mm": 5.0, "after": "air"}], object_distance_mm=1.0)
    *_, ok = trace(rx, 550.0, 0.0, np.array([1.0, 1.8, 2.5, 0.0]), 0.0, 0.0)
    assert ok.tolist() == [True, False, False, True]


def test_plane_parallel_slab_displaces_rays_and_clips_at_its_semi_diameter():
    """A plane-parallel slab (n from the Cauchy law) keeps a ray's direction and displaces it: from the
    display centre with slope u it meets the first surface at height u d (d the object distance) and leaves
    at u d + tan(asin(sin(atan u) / n)) t. With a 2 mm semi-diameter a ray passes iff its heights are within
    2 mm; its backward extension crosses the image plane at exit + u (z_image - z_exit)."""
    n = cauchy_index(1.6, 40.0, 550.0)
    for semi, u_heights in ((50, [0.05, -0.1, 0.2]), (2.0, None)):
        rx = lens([{"radius_mm": None, "thickness_mm": 5.0, "after": {"nd": 1.6, "vd": 40.0}, "semi_diameter_mm": semi},
                   {"radius_mm": None, "thickness_mm": 10.0, "after": "air", "semi_diameter_mm": semi}])
        d = rx.object_distance
        u = np.array(u_heights) if u_heights else np.array([0.5, 1.5, 2.5, -1.7]) / d   # heights 0.5, 1.5, 2.5, -1.7 mm
        xp, _, X, _, ok = trace(rx, 550.0, 0.0, 0.0, u, 0.0)
        slope_glass = np.tan(np.arcsin(u / np.sqrt(1 + u * u) / n))
        exit_x = u * d + slope_glass * 5.0
        if u_heights:
            assert ok.all() and np.allclose(xp, u * (d + 10.0) + slope_glass * 5.0, atol=1e-10)   # exits parallel
        else:
            assert ok.tolist() == [bool(abs(h) <= 2.0) for h in exit_x] == [True, True, False, True]
            assert abs(X - (exit_x + u * (rx.image_z - (d + 5.0)))).max() < 1e-9


def test_slab_paraxial_image_is_the_apparent_depth():
    """A plane-parallel slab has no power: magnification 1; the display is seen at
    object distance + t / n + the air gap from the pupil (apparent depth of the slab)."""
    glass = {"nd": 1.6, "vd": 40.0}
    rx = lens([{"radius_mm": None, "thickness_mm": 5.0, "after": glass},
                {"radius_mm": None, "thickness_mm": 10.0, "after": "air"}])
    n = cauchy_index(1.6, 40.0, 550.0)
    with np.errstate(divide="ignore"):
        p = paraxial(rx, 550.0)
    assert p.magnification == pytest.approx(1.0, abs=1e-12)
    assert p.image_distance == pytest.approx(39.07 + 5.0 / n + 10.0, abs=1e-9)
    assert math.isinf(p.efl)
    # the chief ray through the pupil centre, projected onto the 667 mm plane: 667 / apparent distance
    assert real_magnification(rx, 550.0) == pytest.approx(667.0 / (39.07 + 5.0 / n + 10.0), rel=1e-6)


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


def test_real_magnification_is_the_tiny_field_limit_of_the_chief_ray_height():
    """``real_magnification`` is ``Y / h`` as the field ``h`` goes to 0 (the ratio the bank's chief rays are
    normalised by). Barrel/pincushion distortion makes ``Y / h = m0 + k h^2``; ``m0`` is extrapolated
    here (Richardson) from two small but finite fields, where tracing noise is negligible."""
    rx = Prescription.cardboard()
    h = np.array([1e-3, 2e-3])
    for lam in (486.0, 550.0, 656.0):
        _, y, ok = chief_ray(rx, lam, h)
        assert ok.all()
        f1, f2 = y / h
        m0 = (4.0 * f1 - f2) / 3.0
        assert abs(f2 - f1) > 1e-10 * abs(m0)  # the distortion term is really there at these fields
        assert real_magnification(rx, lam) == pytest.approx(m0, rel=6e-12, abs=0)


# ----------------------------------------------------------------------------- conics, aspheres, mirrors
def _axis_crossings(p, d):
    """Where each ray's line comes closest to the z axis: (z, distance from the axis)."""
    t = -(p[..., 0] * d[..., 0] + p[..., 1] * d[..., 1]) / (d[..., 0] ** 2 + d[..., 1] ** 2)
    q = p + t[..., None] * d
    return q[..., 2], np.hypot(q[..., 0], q[..., 1])


def test_zero_conic_and_zero_aspheric_terms_trace_exactly_like_the_sphere():
    spec = cardboard_spec(surfaces=[dict(CARDBOARD["surfaces"][0], conic=0.0, aspheric=[0.0, 0.0, 0.0]),
                                    dict(CARDBOARD["surfaces"][1], aspheric=[0.0])])
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-14, 14, (2, 2000))
    u, v = rng.uniform(-0.5, 0.5, (2, 2000))
    for a, b in zip(trace(Prescription(spec), 550.0, x, y, u, v), trace(Prescription.cardboard(), 550.0, x, y, u, v)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("f", [25.0, 40.0, 80.0])
def test_a_paraboloid_mirror_focuses_a_collimated_beam_at_half_its_radius(f):
    """A concave paraboloid (k = -1, R = -2f, centre toward the display) at z = 100 mm and a plane fold
    mirror at z = 70 mm: rays parallel to the axis meet the axis at the paraboloid's focus 100 - f
    (exactly, at any height), seen through the fold at 2 * 70 - (100 - f); the paraxial focal length is f."""
    rx = lens([{"radius_mm": -2 * f, "conic": -1.0, "thickness_mm": -30.0, "after": "mirror"},
               {"thickness_mm": 50.0, "after": "mirror"}], object_distance_mm=100.0)
    rng = np.random.default_rng(4)
    r, phi = 20 * np.sqrt(rng.uniform(0, 1, 500)), rng.uniform(0, 2 * math.pi, 500)
    p, d, ok = trace_exit(rx, 550.0, r * np.cos(phi), r * np.sin(phi), 0.0, 0.0)
    z, miss = _axis_crossings(p, d)
    assert ok.all() and d[..., 2].min() > 0
    assert np.abs(z - (140.0 - (100.0 - f))).max() < 1e-9 and miss.max() < 1e-9
    assert paraxial(rx, 550.0).efl == pytest.approx(f, rel=1e-12)
    # the sphere of the same vertex radius has spherical aberration: its marginal rays fall short
    sphere = lens([{"radius_mm": -2 * f, "thickness_mm": -30.0, "after": "mirror"},
                   {"thickness_mm": 50.0, "after": "mirror"}], object_distance_mm=100.0)
    zs, _ = _axis_crossings(*trace_exit(sphere, 550.0, np.array([1e-3, 15.0]), 0.0, 0.0, 0.0)[:2])
    assert zs[0] == pytest.approx(40.0 + f, abs=1e-6) and zs[1] < 40.0 + f - 0.1   # marginal focus nearer the mirror


@pytest.mark.parametrize("a_axis, b_axis", [(60.0, 40.0), (100.0, 30.0)])
def test_an_ellipsoid_mirror_images_one_focus_onto_the_other(a_axis, b_axis):
    """An ellipsoid (R = -b^2 / a, k = -e^2) with its near focus on the display centre: every ray from it
    passes through the far focus (z = vertex - a (1 + e)), here seen through a plane fold mirror."""
    e = math.sqrt(1 - (b_axis / a_axis) ** 2)
    z0 = a_axis * (1 - e)
    fold = z0 / 2
    rx = lens([{"radius_mm": -b_axis ** 2 / a_axis, "conic": -e * e, "thickness_mm": fold - z0, "after": "mirror"},
               {"thickness_mm": 20.0, "after": "mirror"}], object_distance_mm=z0)
    rng = np.random.default_rng(5)
    u, v = rng.uniform(-0.8, 0.8, (2, 300))
    p, d, ok = trace_exit(rx, 550.0, 0.0, 0.0, u, v)
    z, miss = _axis_crossings(p, d)
    assert ok.all() and miss.max() < 1e-9
    assert np.abs(z - (2 * fold - (z0 - a_axis * (1 + e)))).max() < 1e-8


def test_an_asphere_is_hit_on_its_sag():
    """The rays' hits on an even asphere lie on ``z = c r^2 / (1 + sqrt(1 - (1 + k) c^2 r^2)) + A4 r^4 + A6 r^6``
    (one surface: the exit point is the hit)."""
    glass = {"nd": 1.5, "vd": 1e12}
    c, k, a4, a6 = 1 / 30.0, -2.0, 2e-5, -3e-8
    rx = lens([{"radius_mm": 30.0, "conic": k, "aspheric": [a4, a6], "thickness_mm": 10.0, "after": glass,
                "semi_diameter_mm": 12.0}, {"thickness_mm": 5.0}], object_distance_mm=40.0)
    rng = np.random.default_rng(6)
    x, y, u, v = rng.uniform(-3, 3, 400), rng.uniform(-3, 3, 400), rng.uniform(-0.1, 0.1, 400), rng.uniform(-0.1, 0.1, 400)
    one = Prescription(dict(rx.spec, surfaces=[dict(rx.spec["surfaces"][0], after="air")]))
    p, _, ok = trace_exit(one, 550.0, x, y, u, v)
    r2 = p[..., 0] ** 2 + p[..., 1] ** 2
    sag = c * r2 / (1 + np.sqrt(1 - (1 + k) * c * c * r2)) + a4 * r2 ** 2 + a6 * r2 ** 3
    assert ok.all() and np.abs(p[..., 2] - 40.0 - sag).max() < 1e-12


def _folded_aspheric_system(**over):
    """An aspheric glass element (front: decentred, tilted even asphere; back: tilted sphere), then a
    slightly tilted plane fold mirror and a decentred concave conic mirror sending the light on to the
    pupil: every feature of the tracer at once (n = 1.6 at any wavelength)."""
    glass = {"nd": 1.6, "vd": 1e12}
    return lens([{"radius_mm": 35.0, "conic": -1.7, "aspheric": [3e-5, -2e-8], "decenter_mm": [0.4, -0.3],
                  "tilt_deg": [2.0, -1.5], "thickness_mm": 7.0, "after": glass, "semi_diameter_mm": 14.0},
                 {"radius_mm": -40.0, "tilt_deg": [-1.0, 0.5], "thickness_mm": 12.0, "after": "air"},
                 {"tilt_deg": [0.7, 0.3], "thickness_mm": -8.0, "after": "mirror"},
                 {"radius_mm": 150.0, "conic": -0.6, "decenter_mm": [-0.2, 0.5], "thickness_mm": 30.0,
                  "after": "mirror"}], object_distance_mm=30.0, **over)


def _tilted_cardboard():
    """The Cardboard lens with an aspheric, decentred, tilted first surface and a tilted second one."""
    s1, s2 = CARDBOARD["surfaces"]
    return lens([dict(s1, conic=-2.0, aspheric=[1e-6], decenter_mm=[0.4, -0.3], tilt_deg=[2.0, -1.5]),
                 dict(s2, tilt_deg=[-1.0, 0.5])])


def test_trace_matches_an_independent_brute_force_tracer():
    """Random rays through the folded aspheric system: the exit point and direction agree with the
    reference tracer (bisection on the sag, complex-step normals, Snell by angles) to 1e-9 mm / 1e-11."""
    from helpers.reference_tracer import trace_one

    rx = _folded_aspheric_system()
    rng = np.random.default_rng(11)
    x, y, u, v = rng.uniform(-8, 8, 40), rng.uniform(-8, 8, 40), rng.uniform(-0.2, 0.2, 40), rng.uniform(-0.2, 0.2, 40)
    p, d, ok = trace_exit(rx, 550.0, x, y, u, v)
    assert ok.sum() >= 30
    for i in range(40):
        ref = trace_one(rx, 550.0, x[i], y[i], u[i], v[i])
        assert ok[i] == (ref is not None)
        if ref is not None:
            assert np.abs(p[i] - ref[0]).max() < 1e-9 and np.abs(d[i] - ref[1]).max() < 1e-11


def test_a_decentred_lens_is_the_centred_lens_seen_from_a_shifted_field():
    """Decentring every surface by (dx, dy) equals tracing the centred lens from display points shifted by
    (-dx, -dy), with every output shifted back by (dx, dy) (the pupil and image planes are planes)."""
    dx, dy = 0.7, -1.3
    centred = Prescription.cardboard()
    moved = lens([dict(sf, decenter_mm=[dx, dy]) for sf in CARDBOARD["surfaces"]])
    rng = np.random.default_rng(12)
    x, y, u, v = rng.uniform(-10, 10, 500), rng.uniform(-10, 10, 500), rng.uniform(-0.3, 0.3, 500), rng.uniform(-0.3, 0.3, 500)
    xp, yp, X, Y, ok = trace(moved, 550.0, x, y, u, v)
    xp0, yp0, X0, Y0, ok0 = trace(centred, 550.0, x - dx, y - dy, u, v)
    assert np.array_equal(ok, ok0) and ok.mean() > 0.5
    for a, b in ((xp, xp0 + dx), (yp, yp0 + dy), (X, X0 + dx), (Y, Y0 + dy)):
        assert np.abs(a - b)[ok].max() < 1e-9


def test_mirror_symmetry_is_kept_in_x_and_broken_by_a_y_decentre():
    """A lens decentred and tilted only in the y-z plane (decenter [0, dy], tilt about x) stays mirror
    symmetric in x: the ray (-x, y, -u, v) is the mirror image of (x, y, u, v). The y mirror image is
    not a ray of this lens (it is one of the lens decentred by -dy)."""
    over = [{"decenter_mm": [0.0, 0.8], "tilt_deg": [3.0, 0.0]}, {"decenter_mm": [0.0, 0.8]}]
    rx = lens([dict(sf, **o) for sf, o in zip(CARDBOARD["surfaces"], over)])
    flipped = lens([dict(sf, decenter_mm=[0.0, -0.8], tilt_deg=[-o["tilt_deg"][0], 0.0] if "tilt_deg" in o else [0.0, 0.0])
                    for sf, o in zip(CARDBOARD["surfaces"], over)])
    rng = np.random.default_rng(13)
    x, y, u, v = rng.uniform(-10, 10, 300), rng.uniform(-10, 10, 300), rng.uniform(-0.3, 0.3, 300), rng.uniform(-0.3, 0.3, 300)
    xp, yp, X, Y, ok = trace(rx, 550.0, x, y, u, v)
    xm, ym, Xm, Ym, okm = trace(rx, 550.0, -x, y, -u, v)
    assert np.array_equal(ok, okm) and ok.mean() > 0.5
    assert np.abs(xp + xm)[ok].max() < 1e-12 and np.abs(yp - ym)[ok].max() < 1e-12
    assert np.abs(X + Xm)[ok].max() < 1e-10 and np.abs(Y - Ym)[ok].max() < 1e-10
    _, yn, _, Yn, okn = trace(rx, 550.0, x, -y, u, -v)
    both = ok & okn
    assert np.abs(yp + yn)[both].min() > 1e-3                     # y symmetry broken for every ray
    _, yf, _, Yf, okf = trace(flipped, 550.0, x, -y, u, -v)        # ... and restored by the flipped lens
    assert np.array_equal(ok, okf) and np.abs(yp + yf)[ok].max() < 1e-12 and np.abs(Y + Yf)[ok].max() < 1e-10


def test_the_2d_chief_ray_solver_agrees_with_the_meridional_one_on_a_symmetric_lens():
    """On the Cardboard lens the 2-D solver from (x, y) finds the meridional chief ray of radius
    hypot(x, y), turned to the field's direction; on a tilted lens its rays cross the pupil centre."""
    rx = Prescription.cardboard()
    h = np.linspace(0.0, 16.5, 12)
    ang = np.linspace(0.0, 2 * math.pi, 12)
    v, Y, ok = chief_ray(rx, 550.0, h)
    u2, v2, X2, Y2, ok2 = chief_ray_2d(rx, 550.0, h * np.sin(ang), h * np.cos(ang))
    assert ok.all() and ok2.all()
    assert np.abs(u2 - v * np.sin(ang)).max() < 1e-12 and np.abs(v2 - v * np.cos(ang)).max() < 1e-12
    assert np.abs(X2 - Y * np.sin(ang)).max() < 1e-9 and np.abs(Y2 - Y * np.cos(ang)).max() < 1e-9
    tilted = _tilted_cardboard()
    x, y = np.meshgrid(np.linspace(-10, 10, 5), np.linspace(-10, 10, 5))
    u, v, X, Y, ok = chief_ray_2d(tilted, 550.0, x, y)
    xp, yp, X2, Y2, ok2 = trace(tilted, 550.0, x, y, u, v)
    assert ok.all() and np.hypot(xp, yp).max() < 1e-9 and np.array_equal(X, X2) and np.array_equal(Y, Y2)
    _, _, _, _, ok0 = chief_ray_2d(tilted, 550.0, x, y, iters=0)
    assert not ok0.any()                                            # the straight-line guess is not a chief ray


def test_paraxial_refuses_moved_surfaces_and_folds_mirrors():
    tilted = _folded_aspheric_system()
    with pytest.raises(InputValueError, match=r"paraxial: surfaces\[0\] is decentred or tilted"):
        paraxial(tilted, 550.0)
    # a concave mirror of radius R (focal length R / 2) between two plane folds, display 30 mm before it:
    # 1 / s' = 2 / |R| - 1 / 30 (mirror equation), magnification -s' / 30, seen through the last fold
    rx = lens([{"radius_mm": -40.0, "thickness_mm": -10.0, "after": "mirror"},
               {"thickness_mm": 60.0, "after": "mirror"}], object_distance_mm=30.0)
    p = paraxial(rx, 550.0)
    s_img = 1 / (2 / 40.0 - 1 / 30.0)                               # 60 mm in front of the mirror (real)
    assert p.efl == pytest.approx(20.0, rel=1e-12) and p.magnification == pytest.approx(-s_img / 30.0, rel=1e-12)
    assert p.image_distance == pytest.approx(60.0 - (s_img - 10.0), rel=1e-12)   # from the pupil: fold 50 mm before
    m667 = p.magnification * rx.image_distance / p.image_distance
    assert real_magnification(rx, 550.0) == pytest.approx(m667, rel=1e-4)
