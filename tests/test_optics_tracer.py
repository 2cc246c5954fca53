"""Ray tracer and bank generator vs independent calculations (paraxial ABCD, a slab, symmetry)."""

import math

import numpy as np
import pytest
import torch

from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
from controlgs_adapter.downstream.optics.raytrace import chief_ray, paraxial, real_magnification, trace
from controlgs_adapter.errors import InputValueError


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


def test_distortion_and_lateral_colour_at_the_corner():
    rx = Prescription.cardboard()
    m = real_magnification(rx, 550.0)
    corner = 12 * math.sqrt(2)
    land = {lam: chief_ray(rx, lam, np.array([corner]))[1][0] / m / corner * 512 for lam in (486.0, 550.0, 656.0)}
    assert land[550.0] == pytest.approx(611.8, abs=0.5)               # pincushion, ~19.5 %
    assert land[486.0] - land[656.0] == pytest.approx(10.6, abs=0.5)  # per axis (15.0 px along the diagonal)


def test_generated_bank_is_symmetric_and_normalised():
    bank = build_bank(grid=(4, 4), pupil_samples=48, chief_grid=(9, 9))
    psf = bank.psf
    assert torch.allclose(psf.sum((-1, -2)), torch.ones(3, 4, 4), atol=1e-5)
    # mirror symmetry of a rotationally symmetric lens: field (-x, y) has the x-mirrored PSF
    assert torch.allclose(psf[:, :, 0], psf[:, :, 3].flip(-1), atol=2e-3)
    assert torch.allclose(psf[:, 0], psf[:, 3].flip(-2), atol=2e-3)
    assert torch.allclose(bank.chief[:, :, :, 0], -bank.chief[:, :, :, 0].flip(2), atol=1e-6)
    # PSFs grow toward the corner
    assert (bank.psf_pitch_mm[:, 0, 0] > 5 * bank.psf_pitch_mm[:, 1, 1]).all()


def test_bad_prescription_is_named():
    with pytest.raises(InputValueError, match="object_distance_mm"):
        Prescription(dict(CARDBOARD, object_distance_mm=-3))
    with pytest.raises(InputValueError, match="after"):
        Prescription(dict(CARDBOARD, surfaces=[{"radius_mm": 10, "thickness_mm": 1, "after": "glass"}]))
