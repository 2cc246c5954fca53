"""Tests of ``controlgs_adapter.downstream.optics.generate``: building a PSF bank from a prescription by
ray tracing (argument checks, grids and pitches, chief rays against the tracer, PSF symmetry, centroids
against rays aimed over the pupil, the Airy pattern on axis, vignetting), the spots it is built from,
the lens figures, and the shipped bank's settings."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest
import torch
from helpers.prescriptions import cardboard_spec
from helpers.pupil import aim_at_pupil_grid

from controlgs_adapter.downstream.optics import generate
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.generate import build_bank, lens_figures
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
from controlgs_adapter.downstream.optics.raytrace import chief_ray, real_magnification, trace
from controlgs_adapter.errors import InputValueError

D64 = torch.float64


@pytest.mark.parametrize("kw, match", [
    *[(dict(psf_size=v), "psf_size must be an odd integer >= 5") for v in (3, 4, 34, "33")],
    (dict(psf_size=True), "psf_size"), (dict(psf_size=33.0), "psf_size"),
    (dict(grid=30), r"grid must be \(Gy, Gx\)"), (dict(grid=(3,)), r"grid must be \(Gy, Gx\)"),
    (dict(grid=(3, 3, 3)), r"grid must be \(Gy, Gx\)"),
    (dict(grid=(0, 0)), r"grid\[0\] \(Gy\) must be an integer >= 1"), (dict(grid=(0, 3)), r"grid\[0\] \(Gy\)"),
    (dict(grid=(3, 0)), r"grid\[1\] \(Gx\)"), (dict(grid=(3, -1)), r"grid\[1\] \(Gx\) must be an integer >= 1, got -1"),
    (dict(chief_grid=[5]), r"chief_grid must be \(Cy, Cx\)"),
    (dict(chief_grid=(1, 1)), r"chief_grid\[0\] must be an integer >= 2"), (dict(chief_grid=(1, 5)), r"chief_grid\[0\]"),
    (dict(chief_grid=(5, 1)), r"chief_grid\[1\]"),
    *[(dict(pupil_samples=v), "pupil_samples must be an integer >= 4") for v in (1, 3)],
    (dict(reference_width_px=0), "reference_width_px must be an integer >= 1"),
    *[(dict(min_pitch_px=v), "min_pitch_px must be a finite number > 0") for v in (0.0, math.nan)],
    (dict(min_pitch_px=math.inf), "min_pitch_px"), (dict(min_pitch_px=True), "min_pitch_px"),
    (dict(min_pitch_px="0.1"), "min_pitch_px"),
    *[(dict(use_symmetry=v), "use_symmetry must be True or False") for v in (1, None, "no")],
    *[(kw, rf"^{name}.* must be an.* integer >= \d+ and <= 2147483647, got ")   # counts beyond int32
      for kw, name in [(dict(pupil_samples=10**400), "pupil_samples"), (dict(psf_size=2**31 + 1), "psf_size"),
                       (dict(grid=(2**40, 2)), r"grid\[0\]")]],
])
def test_build_bank_refuses_bad_settings_by_name(kw, match):
    with pytest.raises(InputValueError, match=match):
        build_bank(**kw)


def test_an_aperture_blocking_the_edge_chief_rays_is_refused():
    spec = cardboard_spec(surfaces=[dict(CARDBOARD["surfaces"][0], semi_diameter_mm=5.0), dict(CARDBOARD["surfaces"][1])])
    with pytest.raises(InputValueError, match=r"chief rays.*16\.97 mm.*656 nm.*aperture"):
        build_bank(spec, grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(3, 3))


def test_build_bank_prints_nothing_unless_progress_is_asked(capsys):
    """``progress=True`` prints one line per traced wavelength to stdout (the ``controlgs optics build-bank``
    command turns it on); by default a library call prints nothing. A tiny bank (one field, 5 x 5 PSFs)
    both ways: silent, then one ``traced <nm> nm`` line per wavelength."""
    kw = dict(grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(2, 2))
    bank = build_bank(**kw)
    out = capsys.readouterr()
    assert (out.out, out.err) == ("", "")
    assert build_bank(**kw, progress=True).wavelengths_nm == bank.wavelengths_nm
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split(" nm:")[0].split()[-1] for ln in lines] == [f"{w:g}" for w in bank.wavelengths_nm]


def test_recorded_pupil_coverage_is_a_fraction_at_most_one_rounded_to_5_decimals():
    """``meta["generator"]["min_pupil_coverage"]`` is at most 1 and rounded to 5 decimals. On axis with 8
    pupil samples the rim-cell quadrature sums to ~1.0005 of the disc (full coverage: reads 1.0); with 16
    it sums to ~0.99989 (the 6th decimal is not 0, so the rounding shows)."""
    over = build_bank(grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(2, 2))
    assert over.meta["generator"]["min_pupil_coverage"] == 1.0
    under = build_bank(grid=(1, 1), psf_size=5, pupil_samples=16, chief_grid=(2, 2))
    cov = under.meta["generator"]["min_pupil_coverage"]
    assert 0.999 < cov < 1.0 and cov == round(cov, 5)


# ----------------------------------------------------------------------------- a small traced bank
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
    assert torch.allclose(b.psf.sum((-1, -2)), torch.ones(3, 3, 3), atol=1e-5)
    # the centre PSF is diffraction-limited at 550 and 486 nm: its pitch is the minimum, 0.25 px at
    # 512 px = 0.25 * 24 / 512 mm (656 nm: defocused by the lens's longitudinal colour, coarser);
    # the corner PSFs are more than 5 x coarser
    assert b.psf_pitch_mm[1:, 1, 1].tolist() == pytest.approx([0.25 * 24 / 512] * 2, rel=1e-6)
    assert b.psf_pitch_mm[0, 1, 1].item() > 1.02 * 0.25 * 24 / 512
    assert (b.psf_pitch_mm[:, 0, 0] > 5 * b.psf_pitch_mm[:, 1, 1]).all()
    gen = b.meta["generator"]
    assert (gen["grid"], gen["psf_size"], gen["pupil_samples"], gen["chief_grid"]) == ([3, 3], 9, 40, [3, 5])
    assert (gen["min_pitch_px"], gen["reference_width_px"]) == (0.25, 512)
    assert 0.97 < gen["min_pupil_coverage"] <= 1.0
    T = b.transmission
    assert T.shape == (3, 3, 3) and T[:, 1, 1].tolist() == [1.0, 1.0, 1.0] and (T > 0.9).all()
    assert b.meta["figures"]["550nm"]["corner_landing_px_at_1024"] == pytest.approx(611.8, abs=0.3)


def test_small_bank_chief_rays_are_the_traced_landings(small_bank):
    """Chief rays in normalised output coordinates: landing height / reference magnification / 12 mm;
    mirror-symmetric in x."""
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
    # 550 nm at the right edge: the display diagonal's corner lands at 611.8 / 512
    assert small_bank.chief[1, 2, 4].tolist() == pytest.approx([611.8 / 512] * 2, abs=1e-3)
    assert torch.allclose(small_bank.chief[..., 0], -small_bank.chief[..., 0].flip(2), atol=1e-6)


def test_psf_centroids_are_the_mean_of_rays_aimed_uniformly_over_the_pupil(small_bank):
    """Rotational symmetry: the small bank's PSF at (+x, 0) is the transpose of the one at (0, +y) and the
    mirror of (-x, 0). Coma: the centroid of a PSF lies radially outward from its chief ray, at the mean
    crossing of rays aimed by Newton at a uniform grid over the pupil (equal area each; independent of the
    generator's slope grid and its pupil-area weights): the small bank at (0, +8 mm) and (+8, 0) mm, and the
    shipped bank at mid-edge (550 nm: 0.94 px at 1024 px; uniform launch slopes would give 1.20 px)."""
    p = small_bank.psf.double()
    assert torch.allclose(p[:, 1, 2], p[:, 2, 1].transpose(-1, -2), atol=2e-3)
    assert torch.allclose(p[:, 1, 0], p[:, 1, 2].flip(-1), atol=2e-3)
    assert torch.allclose(p[:, 0, 1], p[:, 2, 1].flip(-2), atol=2e-3)
    rx = Prescription.cardboard()
    m = real_magnification(rx, rx.reference_wavelength)
    lam, li, r = 550.0, 1, 8.0
    _, Y0, _ = chief_ray(rx, lam, np.array([r]))
    _, _, _, Y, ok = aim_at_pupil_grid(rx, lam, r, n=48, iterations=8)
    assert ok.all()
    want = (Y - Y0[0]).mean() / m                                              # display-equivalent mm, radial
    t = torch.arange(9, dtype=D64) - 4
    pitch = small_bank.psf_pitch_mm[li, 2, 1].item()
    q = p[li, 2, 1]
    cy, cx = (q.sum(1) * t).sum().item() * pitch, (q.sum(0) * t).sum().item() * pitch
    assert want > 0.002                                                        # outward coma, several pitches
    assert cy == pytest.approx(want, abs=0.15 * pitch) and abs(cx) < 1e-3 * pitch
    q = p[li, 1, 2]                                                            # (+8, 0) mm: the same, along +x
    cx2 = (q.sum(0) * t).sum().item() * small_bank.psf_pitch_mm[li, 1, 2].item()
    assert cx2 == pytest.approx(want, abs=0.15 * pitch)

    bank = PSFBank.default()
    iy, ix = 29, 15
    fx, fy = bank.field_x[ix].item() * 12, bank.field_y[iy].item() * 12            # mm on the display
    r = math.hypot(fx, fy)
    lam = bank.wavelengths_nm[li]
    _, Y0, _ = chief_ray(rx, lam, np.array([r]))
    _, _, _, Y, ok = aim_at_pupil_grid(rx, lam, r, n=64, iterations=8)
    assert ok.all()
    px_per_mm = 1024 / 24
    want = (Y - Y0[0]).mean() / m * px_per_mm                                  # radial, px at 1024
    K = bank.psf.shape[-1]
    t = torch.arange(K, dtype=D64) - K // 2
    q = bank.psf[li, iy, ix].double()
    pitch = bank.psf_pitch_mm[li, iy, ix].item() * px_per_mm
    cx, cy = (q.sum(0) * t).sum().item() * pitch, (q.sum(1) * t).sum().item() * pitch
    got = (cx * fx + cy * fy) / r
    assert got == pytest.approx(want, abs=0.015)
    assert 0.9 < got < 1.0


def test_centre_psf_is_the_airy_pattern_of_the_pupil():
    """On axis at 550 nm the lens is diffraction-limited (0.02 wave RMS): the PSF is the Airy pattern of the
    4 mm pupil seen from the 667 mm plane, first dark ring at 1.21967 lambda z / D, divided by the reference
    magnification (display-equivalent mm). Reference: (2 J1(x) / x)^2 from scipy, integrated over the same
    cells (16 x 16 sub-samples)."""
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
    spec = cardboard_spec(display_mm=[24.0, 16.0],
                          surfaces=[dict(CARDBOARD["surfaces"][0]), dict(CARDBOARD["surfaces"][1], thickness_mm=14.0),
                                    {"radius_mm": None, "thickness_mm": 4.0, "after": "air", "semi_diameter_mm": 2.3}])
    rx = Prescription(spec)
    bank = build_bank(rx, grid=(1, 3), psf_size=9, pupil_samples=40, chief_grid=(3, 3))
    assert bank.field_x.tolist() == pytest.approx([-2 / 3, 0.0, 2 / 3]) and bank.field_y.tolist() == [0.0]
    assert bank.display_mm == (24.0, 16.0)
    T = bank.transmission
    for li, lam in enumerate(rx.wavelengths):
        *_, ok = aim_at_pupil_grid(rx, lam, 8.0)
        assert 0.85 < ok.mean() < 0.93
        assert T[li, 0, 2].item() == pytest.approx(ok.mean(), abs=0.01) and T[li, 0, 0].item() == T[li, 0, 2].item()
        assert T[li, 0, 1].item() == 1.0
    m = real_magnification(rx, 550.0)
    _, Y, _ = chief_ray(rx, 550.0, np.array([math.hypot(12.0, 8.0), 8.0]))
    s = Y[0] / m / math.hypot(12.0, 8.0)
    assert bank.chief[1, 2, 2].tolist() == pytest.approx([s, s], abs=1e-6)         # (12 s / 12, 8 s / 8)
    assert bank.chief[1, 2, 1].tolist() == pytest.approx([0.0, Y[1] / m / 8.0], abs=1e-6)
    assert bank.meta["generator"]["min_pupil_coverage"] == pytest.approx(1.0, abs=0.02)


def test_build_bank_defaults_made_the_shipped_bank():
    """The shipped bank records the settings it was generated with; they are build_bank's defaults."""
    gen = PSFBank.default().meta["generator"]
    defaults = {k: p.default for k, p in inspect.signature(build_bank).parameters.items()}
    assert gen["grid"] == [30, 30] == list(defaults["grid"])
    assert gen["psf_size"] == 33 == defaults["psf_size"]
    assert gen["pupil_samples"] == 192 == defaults["pupil_samples"]
    assert gen["chief_grid"] == [65, 65] == list(defaults["chief_grid"])
    assert gen["min_pitch_px"] == 0.125 == defaults["min_pitch_px"]
    assert gen["reference_width_px"] == 1024 == defaults["reference_width_px"]


# ----------------------------------------------------------------------------- spots
def _first_span_covering(rx, lam, r, v0, n):
    """Brute force of the documented rule: the first span of (1.02, 1.2, 1.45, 1.75, 2.1) whose launch
    grid's outline lands outside the pupil, else the widest (an outline ray blocked by an aperture is
    NaN: not outside); returns (span, covered, m, the grid's image-plane Xs)."""
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
    rx, lam, n = Prescription.cardboard(), 550.0, 16
    v0, Y0, ok = chief_ray(rx, lam, np.array([r]))
    assert ok[0]
    span, cov_ok, m, Xs = _first_span_covering(rx, lam, r, v0[0], n)
    assert (span, cov_ok) == (want_span, covered)
    sx, sy, w, tr, cov = generate._spot(rx, lam, r, v0[0], Y0[0], n)
    assert 0 < len(sx) <= m * m and np.isin(sx, Xs).all()
    assert (w > 0).all() and 0.0 < tr <= 1.0
    if covered:
        assert cov == pytest.approx(1.0, abs=0.02)  # the primary branch covers the whole pupil area


@pytest.mark.parametrize("r", [0.0, 8.0, 16.0])
def test_spot_weights_cover_the_whole_pupil_disc(r):
    """Each kept ray stands for its pupil area, rim cells by the fraction inside the disc, so on the
    unvignetted Cardboard lens the weights add up to the pupil's area pi (2 mm)^2 (transmission and
    coverage 1) to the grid's sampling error, here < 2e-3 with ~40 rays across the pupil; the offsets
    are finite and the weights positive."""
    rx = Prescription.cardboard()
    v0, Y0, ok = chief_ray(rx, 550.0, np.array([r]))
    assert ok.all()
    sx, sy, w, tr, cov = generate._spot(rx, 550.0, r, v0[0], Y0[0], 40)
    assert w.sum() == pytest.approx(math.pi * 2.0 ** 2, rel=2e-3)
    assert tr == pytest.approx(1.0, abs=2e-3) and cov == pytest.approx(1.0, abs=2e-3) and tr <= 1.0
    assert (w > 0).all() and np.isfinite(sx).all() and np.isfinite(sy).all() and len(w) > 1000


def test_pupil_area_is_the_map_jacobian_times_the_cell():
    # an affine slope -> pupil map (xp, yp) = A (u, v): every ray stands for det(A) hu hv of pupil,
    # edges included (central and one-sided differences are exact on a linear map); steps differ per axis
    hu, hv = 0.3, 0.7
    a, b, c, d = 2.0, 0.5, -0.4, 1.5
    v, u = np.meshgrid(np.arange(5) * hv, np.arange(6) * hu, indexing="ij")   # u along axis 1, v along 0
    area = generate._pupil_area(a * u + b * v, c * u + d * v, hu, hv)
    assert area.shape == (5, 6)
    assert np.allclose(area, (a * d - b * c) * hu * hv, rtol=1e-12, atol=0)
    # past a fold the sign flips: yp = v^2 folds at v = 0 (interior rows, where central differences are exact)
    vs = (np.arange(7) - 3.0) * hv
    v, u = np.meshgrid(vs, np.arange(4) * hu, indexing="ij")
    area = generate._pupil_area(u, v ** 2, hu, hv)
    assert np.allclose(area[1:-1], 2 * v[1:-1] * hu * hv, rtol=1e-12, atol=1e-15)
    assert (area[1:3] < 0).all() and (area[4:6] > 0).all()
    # NaN where a neighbour is not finite
    xp = u.copy()
    xp[3, 2] = np.nan
    nan = np.isnan(generate._pupil_area(xp, v ** 2, hu, hv))
    assert nan[2, 2] and nan[4, 2] and nan[3, 1] and nan[3, 3] and nan.sum() == 4


def test_conv_same_is_the_centred_crop_of_the_full_convolution():
    """A delta at the centre returns the kernel; a delta one sample right/down shifts it by one (the full
    (2K-1)^2 convolution cropped at offset K // 2); negative round-off is clipped to 0."""
    K = 5
    b = np.arange(1.0, K * K + 1).reshape(K, K)
    delta = np.zeros((K, K))
    delta[K // 2, K // 2] = 1.0
    assert np.allclose(generate._conv_same(delta, b), b, atol=1e-12)
    shifted = np.zeros((K, K))
    shifted[K // 2 + 1, K // 2 + 1] = 1.0
    want = np.zeros((K, K))
    want[1:, 1:] = b[:-1, :-1]
    assert np.allclose(generate._conv_same(shifted, b), want, atol=1e-12)
    brute = np.zeros((2 * K - 1, 2 * K - 1))  # float64 brute force on random inputs
    rng = np.random.default_rng(0)
    a, c = rng.random((K, K)), rng.random((K, K))
    for i in range(K):
        for j in range(K):
            brute[i:i + K, j:j + K] += a[i, j] * c
    assert np.allclose(generate._conv_same(a, c), brute[K // 2:K // 2 + K, K // 2:K // 2 + K], atol=1e-12)
    assert (generate._conv_same(-delta, b) == 0).all()  # all-negative result clipped to 0


# ----------------------------------------------------------------------------- figures
def test_lens_figures_of_the_cardboard_lens():
    """Reference figures (optiland / rayoptics / ABCD, agreeing to 0.2 %): corner (12, 12) mm lands at
    611.8 px (550 nm) of 512, 617.1 (486) and 606.5 (656): pincushion 19.5 %; 1 display px (24 / 1024 mm)
    is 0.3411 mm on the 667 mm plane."""
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


# ----------------------------------------------------------------------------- lenses that are not rotationally symmetric
_SMALL = dict(grid=(3, 3), psf_size=9, pupil_samples=24, chief_grid=(5, 5), min_pitch_px=0.25, reference_width_px=512)


def _centroid(bank):
    """PSF centroids (mm) about each field's centre sample ``[L, Gy, Gx]`` in x and y."""
    K = bank.psf.shape[-1]
    g = (torch.arange(K, dtype=D64) - K // 2)
    p = bank.psf.double()
    return (p * g).sum((-1, -2)) * bank.psf_pitch_mm, (p * g[:, None]).sum((-1, -2)) * bank.psf_pitch_mm


def test_the_2d_path_on_a_symmetric_lens_agrees_with_the_rotation_shortcut():
    """Cardboard traced field point by field point (``use_symmetry=False``) vs its meridional spots rotated
    to each field: the same chief rays (to 1e-9), transmissions, PSF centroids within 2e-4 mm (0.004 px at
    1024 px) and PSFs within 2 % in L1 (a grid aimed along the field's direction vs along the axes)."""
    a = build_bank(**_SMALL)
    b = build_bank(**_SMALL, use_symmetry=False)
    assert (a.chief - b.chief).abs().max() < 1e-9
    assert np.abs(np.array(a.meta["transmission"]) - np.array(b.meta["transmission"])).max() <= 1e-4
    assert max((x - y).abs().max().item() for x, y in zip(_centroid(a), _centroid(b))) < 2e-4
    assert (a.psf - b.psf).abs().sum((-1, -2)).max() < 0.02
    assert ((a.psf_pitch_mm - b.psf_pitch_mm) / a.psf_pitch_mm).abs().max() < 0.01
    assert a.meta["lens"] == b.meta["lens"] == {"axis": [0.0, 0.0], "rotationally_symmetric": True, "psf": True,
                                                "kind": "prescription"}
    # the shortcut really is a different computation: the diagonal fields' PSFs are not bit-equal
    assert not torch.equal(a.psf[:, 0, 0], b.psf[:, 0, 0])


def test_a_y_decentred_lens_keeps_x_mirror_symmetry_and_breaks_y():
    """Both Cardboard surfaces decentred by 0.6 mm in y: PSFs mirror in x (field -x is field +x flipped
    left-right, to 1e-5 in L1), chief rays antisymmetric in x; top and bottom rows differ; the lens frame is recorded;
    the efficiency scales every transmission."""
    spec = cardboard_spec(surfaces=[dict(sf, decenter_mm=[0.0, 0.6]) for sf in CARDBOARD["surfaces"]], efficiency=0.5)
    b = build_bank(spec, **_SMALL)
    assert b.meta["lens"] == {"axis": [0.0, 0.0], "rotationally_symmetric": False, "psf": True, "kind": "prescription"}
    assert not b.rotationally_symmetric and b.axis == (0.0, 0.0)
    # (to the float32 storage and the forward-difference aims, taken on the same side of each chief ray)
    assert (b.psf - b.psf.flip(2).flip(-1)).abs().sum((-1, -2)).max() < 1e-5
    assert ((b.psf_pitch_mm - b.psf_pitch_mm.flip(2)) / b.psf_pitch_mm).abs().max() < 1e-5
    assert torch.allclose(b.chief[..., 0], -b.chief[..., 0].flip(2), atol=1e-9)
    assert torch.allclose(b.chief[..., 1], b.chief[..., 1].flip(2), atol=1e-9)
    assert (b.psf[:, 0, 1] - b.psf[:, 2, 1].flip(-2)).abs().sum((-1, -2)).min() > 0.05
    assert (b.chief[..., 1] + b.chief[..., 1].flip(1)).abs().max() > 1e-3
    T = np.array(b.meta["transmission"])
    centred = np.array(build_bank(cardboard_spec(surfaces=spec["surfaces"]), **_SMALL).meta["transmission"])
    assert np.array_equal(T, (centred * 0.5).round(4)) and T.max() == 0.5


def test_an_offset_display_is_the_centred_lens_seen_from_shifted_points():
    """``display_offset_mm`` (ox, oy): the lens axis meets the display there; a display point P is the centred
    lens's point P - o, so its chief ray lands at axis + (its meridional landing) / m_ref in normalised
    coordinates (meridional search on the centred lens at radius |P - o|). The PSF at a field point is the
    centred lens's at P - o (on a 12 mm display, 3 x 3 fields at 0 and +-4 mm, offset 4 mm: field (4, 0)
    of the offset lens is the centred lens's axis point)."""
    ox, oy = 0.9, -0.6
    b = build_bank(cardboard_spec(display_offset_mm=[ox, oy]), **_SMALL)
    assert b.axis == pytest.approx((0.075, -0.05), abs=1e-15) and not b.rotationally_symmetric
    rx = Prescription.cardboard()
    m = real_magnification(rx, 550.0)
    CX, CY = np.meshgrid(np.linspace(-12, 12, 5), np.linspace(-12, 12, 5))
    lx, ly = CX - ox, CY - oy
    r = np.hypot(lx, ly)
    _, Y, ok = chief_ray(rx, 550.0, r.ravel())
    s = np.where(r > 0, Y.reshape(r.shape) / np.maximum(r, 1e-12), m) / m
    assert ok.all()
    assert np.abs(b.chief[1, ..., 0].numpy() - (ox + lx * s) / 12).max() < 1e-7      # float32 storage
    assert np.abs(b.chief[1, ..., 1].numpy() - (oy + ly * s) / 12).max() < 1e-7
    c = build_bank(cardboard_spec(display_offset_mm=[4.0, 0.0], display_mm=[12.0, 12.0]), **_SMALL)
    a = build_bank(cardboard_spec(display_mm=[12.0, 12.0]), **_SMALL)
    assert (c.psf[:, 1, 2] - a.psf[:, 1, 1]).abs().sum((-1, -2)).max() < 1e-4
    assert (c.psf[:, 1, 1] - a.psf[:, 1, 1]).abs().sum((-1, -2)).min() > 0.1       # the display centre is off-axis


def test_lens_figures_of_asymmetric_lenses_at_the_four_corners():
    """A display offset alone: each corner's distortion is the centred lens's radial distortion at the
    corner's distance from the axis; an x-symmetric lens (y decentre) has mirrored +-x corners; a tilted
    lens has no paraxial figures."""
    rx = Prescription.cardboard()
    m = real_magnification(rx, 550.0)
    f = lens_figures(Prescription(cardboard_spec(display_offset_mm=[0.8, 0.5])))["550nm"]
    cx, cy = np.array([-12.0, 12.0, -12.0, 12.0]) - 0.8, np.array([-12.0, -12.0, 12.0, 12.0]) - 0.5
    r = np.hypot(cx, cy)
    _, Y, _ = chief_ray(rx, 550.0, r)
    assert f["corner_distortion_pct"] == pytest.approx(list((Y / m / r - 1) * 100), abs=1e-7)
    want = [[(0.8 + x * y / m / rr) / 12 * 512, (0.5 + yy * y / m / rr) / 12 * 512] for x, yy, y, rr in zip(cx, cy, Y, r)]
    assert np.abs(np.array(f["corner_landing_px_at_1024"]) - want).max() < 1e-6
    assert f["efl_mm"] == pytest.approx(47.91, abs=0.02)                  # paraxial figures: the lens is centred
    spec = cardboard_spec(surfaces=[dict(sf, decenter_mm=[0.0, 0.6]) for sf in CARDBOARD["surfaces"]])
    g = lens_figures(Prescription(spec))["550nm"]
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = g["corner_landing_px_at_1024"]
    assert (x0, y0) == pytest.approx((-x1, y1), abs=1e-9) and (x2, y2) == pytest.approx((-x3, y3), abs=1e-9)
    assert abs(y0 + y2) > 1 and g["efl_mm"] is None and g["paraxial_magnification"] is None


def test_a_folded_mirror_magnifier_builds_a_bank():
    """A pancake-like double pass in air: a window, a plane fold mirror 10 mm on, back to a concave mirror
    (R = 70, f = 35) at the window, forward through the fold plane to the pupil. The display is 30 mm from
    the mirror along the path: magnification 35 / (35 - 30) = 7 at 210 mm behind the mirror, 235 mm from the
    pupil (mirror equation); on the 667 mm plane the chief rays scale that by 667 / 235. Efficiency 0.25 (two
    half-mirror passes) is the transmission; both bank paths agree on the chief rays and the PSF centroids."""
    sd = 20.0
    spec = cardboard_spec(object_distance_mm=10.0, efficiency=0.25, display_mm=[10.0, 10.0],
                          surfaces=[{"thickness_mm": 10.0, "semi_diameter_mm": sd},
                                    {"thickness_mm": -10.0, "after": "mirror", "semi_diameter_mm": sd},
                                    {"radius_mm": 70.0, "thickness_mm": 10.0, "after": "mirror", "semi_diameter_mm": sd},
                                    {"thickness_mm": 15.0, "semi_diameter_mm": sd}])
    rx = Prescription(spec)
    assert real_magnification(rx, 550.0) == pytest.approx(7.0 * 667.0 / 235.0, rel=1e-8)
    a = build_bank(rx, **_SMALL)
    b = build_bank(rx, **_SMALL, use_symmetry=False)
    assert np.array(a.meta["transmission"]).tolist() == [[[0.25] * 3] * 3] * 3
    assert a.meta["lens"]["rotationally_symmetric"] and a.meta["figures"]["550nm"]["efl_mm"] == pytest.approx(35.0)
    assert (a.chief - b.chief).abs().max() < 1e-6
    assert max((x - y).abs().max().item() for x, y in zip(_centroid(a), _centroid(b))) < 2e-4


def test_a_decentred_lens_bank_sees_a_flat_field_flat_without_seams():
    """The invariants of the shipped banks hold for a bank traced in 2-D: its PSFs sum to 1, under radiance a flat
    display is seen as the pupil transmission (here a 1.5 mm display offset with 50 % path efficiency: 0.5) over the
    inner 90 %, and exact mode shows no step above 1e-4 between adjacent pixels; the energy form, which steps at
    the field-sample lines, shows the seam check can fail."""
    from helpers.lens_checks import inner, steps

    from controlgs_adapter.downstream.optics.operators import psf_exact

    bank = build_bank(cardboard_spec(display_offset_mm=[1.5, 0.0], efficiency=0.5),
                      **{**_SMALL, "grid": (6, 6), "psf_size": 15, "chief_grid": (17, 17)})
    assert not bank.rotationally_symmetric and bank.axis == pytest.approx((0.125, 0.0))
    assert torch.allclose(bank.psf.double().sum((-1, -2)), torch.ones(3, 6, 6, dtype=torch.float64), atol=1e-6)
    S = 48
    x = torch.ones(3, S, S, dtype=torch.float64)
    out = psf_exact(x, bank.resample_to(S, S, dtype=torch.float64))
    assert (inner(out) - 0.5).abs().max() < 3e-4
    assert steps(inner(out)) < 1e-4
    energy = psf_exact(x, bank.resample_to(S, S, dtype=torch.float64, radiometry="energy"))
    assert steps(inner(energy)) > 1e-4
