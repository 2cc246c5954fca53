"""Sweep 2 (issue 15 section 5), downstream stages: behaviours the large mutation sweep found untested.

Frozen ImageRegion, the RadialMap grid cache, the basis= of every LensPrewarp.for_optics path, the PSF
bank's -1e-3 sign bound at the bound itself, the chief-ray Newton step clamp (+-0.05 per step), the Cauchy
index against the Abbe definition and a catalogue glass, the PSF generator's pupil-grid widening and its
centred convolution."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from controlgs_adapter.downstream.lens import BankMap, LensPrewarp, RadialMap
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.prescription import Prescription
from controlgs_adapter.downstream.optics.raytrace import chief_ray
from controlgs_adapter.downstream.placement import image_region
from controlgs_adapter.errors import InputValueError

CPU = torch.device("cpu")
D64 = torch.float64


# ----------------------------------------------------------------------------- placement


def test_image_region_is_frozen():
    r = image_region(4, 8)  # fit on the 24 x 24 mm display: the width fills it, half_y = 4 / 8
    assert (r.half_x, r.half_y) == (1.0, 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.half_x = 0.25  # type: ignore[misc]
    assert r.half_x == 1.0


# ----------------------------------------------------------------------------- RadialMap cache


def test_radial_map_caches_fixed_coefficients_and_differentiates_learnable_ones():
    coef = [[0.1, 0.0], [0.2, 0.0], [0.3, 0.0]]
    fixed = RadialMap(coef)
    assert torch.is_grad_enabled()
    g1, _ = fixed((5, 7), D64, CPU)
    g2, _ = fixed((5, 7), D64, CPU)
    assert g1 is g2 and len(fixed._cache) == 1  # fixed coefficients: one grid per key, even with grad on
    assert g1.grad_fn is None
    g3, _ = fixed((5, 6), D64, CPU)
    assert g3 is not g1 and len(fixed._cache) == 1  # another size replaces the entry
    g4, _ = fixed((5, 6), torch.float32, CPU)
    assert g4.dtype == torch.float32 and g4 is not g3 and torch.allclose(g4.double(), g3, atol=1e-6)  # per dtype
    # grid_c(p) = p (1 + k_c r^2) by hand at the centre-left pixel of a 1 x 3 image: x = -2/3, y = 0
    # (pixel centres; aspect-corrected r divides x by the larger half-extent 1): R channel 1 + 0.1 * 4/9
    g, _ = fixed((1, 3), D64, CPU)
    assert g[0, 0, 0, 0].item() == pytest.approx(-2 / 3 * (1 + 0.1 * 4 / 9), rel=1e-6)

    learned = RadialMap(coef, learnable=True)
    a, _ = learned((5, 7), D64, CPU)
    b, _ = learned((5, 7), D64, CPU)
    assert a is not b and a.grad_fn is not None and not learned._cache  # a graph each call, nothing cached
    with torch.no_grad():
        c, _ = learned((5, 7), D64, CPU)
        d, _ = learned((5, 7), D64, CPU)
    assert c is d and torch.equal(c, a.detach())  # under no_grad the learnable map caches too
    with torch.no_grad():
        learned.coefficients.mul_(2.0)  # an in-place edit bumps the version: a fresh grid
        e, _ = learned((5, 7), D64, CPU)
    assert e is not c and not torch.equal(e, c)


# ----------------------------------------------------------------------------- for_optics basis


class _Optics(torch.nn.Module):
    def __init__(self, bank: PSFBank, radiometry: str) -> None:
        super().__init__()
        self.bank, self.radiometry, self.mode, self.placement = bank, radiometry, "exact", "fit"


@pytest.mark.parametrize("basis", ["rgb", "primaries"])
def test_for_optics_passes_basis_on_every_path(basis, tmp_path):
    bank = PSFBank.default()
    optics = _Optics(bank, "no-such-radiometry")  # no shipped LUT for it: the chief-ray fallback
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        fallback = LensPrewarp.for_optics(optics, basis=basis)
    assert isinstance(fallback.map, BankMap) and fallback.basis == basis
    chief = LensPrewarp.for_optics(optics, source="chief_rays", basis=basis)
    assert isinstance(chief.map, BankMap) and chief.basis == basis
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        default = LensPrewarp.for_optics(optics)
    assert default.basis == "primaries"  # the documented default
    # a fitted LUT file: the same basis
    from controlgs_adapter.downstream.lens import DisplayLUTMap, bank_fingerprint, pixel_grid

    disp = 0.01 * pixel_grid((5, 4), D64).expand(3, -1, -1, -1).clone()
    gain = torch.ones(3, 5, 4, dtype=D64)
    lut = DisplayLUTMap({"exact": (disp, gain)}, meta={"bank": bank_fingerprint(bank), "radiometry": "no-such-radiometry"}
                        ).save(tmp_path / "fit.safetensors")
    fitted = LensPrewarp.for_optics(optics, lut=lut, basis=basis)
    assert isinstance(fitted.map, DisplayLUTMap) and fitted.basis == basis
    assert LensPrewarp.for_optics(optics, lut=lut).basis == "primaries"
    with pytest.raises(InputValueError, match="basis must be one of .* got 'srgb'"):
        LensPrewarp.for_optics(optics, source="chief_rays", basis="srgb")  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- bank sign bound


def _bank_args(psf_min: float) -> dict:
    L, G, K, C = 3, 3, 5, 5
    g = torch.Generator().manual_seed(0)
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=g) + 0.1
    psf /= psf.sum((-1, -2), keepdim=True)
    psf[0, 0, 0, 1, 1] += psf[0, 0, 0, 0, 0].item() - psf_min  # the same sum with psf_min at [0, 0]
    psf[0, 0, 0, 0, 0] = psf_min
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=D64), field_x=f.clone(), field_y=f.clone(),
                chief=torch.stack([cx, cy], -1).expand(L, C, C, 2).clone(), chief_x=c.clone(), chief_y=c.clone(),
                wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))


def test_bank_accepts_psf_values_down_to_exactly_minus_1e_3():
    bank = PSFBank(**_bank_args(-1e-3))  # the bound itself is rounding, accepted
    assert bank.psf[0, 0, 0, 0, 0].item() == pytest.approx(-1e-3, rel=1e-3)
    with pytest.raises(InputValueError, match="PSF bank: PSFs must be non-negative, min is -0.0011"):
        PSFBank(**_bank_args(-1.1e-3))


# ----------------------------------------------------------------------------- chief-ray Newton clamp


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


# ----------------------------------------------------------------------------- pupil grid widening


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


# ----------------------------------------------------------------------------- Cauchy index


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


def test_conv_same_is_the_centred_crop_of_the_full_convolution():
    """A delta at the centre returns the kernel; a delta one sample right/down shifts it by one (by hand:
    the full (2K-1)^2 convolution cropped at offset K // 2); negative round-off is clipped to 0."""
    from controlgs_adapter.downstream.optics.generate import _conv_same

    K = 5
    b = np.arange(1.0, K * K + 1).reshape(K, K)
    delta = np.zeros((K, K))
    delta[K // 2, K // 2] = 1.0
    assert np.allclose(_conv_same(delta, b), b, atol=1e-12)
    shifted = np.zeros((K, K))
    shifted[K // 2 + 1, K // 2 + 1] = 1.0
    want = np.zeros((K, K))
    want[1:, 1:] = b[:-1, :-1]
    assert np.allclose(_conv_same(shifted, b), want, atol=1e-12)
    brute = np.zeros((2 * K - 1, 2 * K - 1))  # float64 brute force on random inputs
    rng = np.random.default_rng(0)
    a, c = rng.random((K, K)), rng.random((K, K))
    for i in range(K):
        for j in range(K):
            brute[i:i + K, j:j + K] += a[i, j] * c
    assert np.allclose(_conv_same(a, c), brute[K // 2:K // 2 + K, K // 2:K // 2 + K], atol=1e-12)
    assert (_conv_same(-delta, b) == 0).all()  # all-negative result clipped to 0


def test_chief_ray_converged_means_within_1e_9_mm_of_the_pupil_centre():
    """``ok`` is |pupil height| < 1e-9 mm of the returned slope's ray (traced here again): after two Newton
    steps the 5.31 mm ray misses the centre by 1.3e-9 mm (found by a scan): not converged; 1 mm has."""
    from controlgs_adapter.downstream.optics.raytrace import trace

    rx = Prescription.cardboard()
    h = np.array([5.31, 1.0])
    v, _, ok = chief_ray(rx, 550.0, h, iters=2)
    _, yp, _, _, _ = trace(rx, 550.0, 0.0, h, 0.0, v)
    assert 1.2e-9 < abs(yp[0]) < 1.8e-9 and abs(yp[1]) < 1e-12
    assert ok.tolist() == [False, True]
    v, _, ok = chief_ray(rx, 550.0, h)  # the default 40 steps converge both
    assert ok.all()
