"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001): optics operators and ray generation,
display primaries, each pinned by what the code is for."""

import numpy as np
import pytest
import torch

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_exact, psf_fast

D64 = torch.float64


def _uniform_identity_bank(S: int, K: int = 7, G: int = 4) -> PSFBank:
    """One random PSF everywhere, identity chief rays, one PSF sample per display pixel."""
    g = torch.Generator().manual_seed(3)
    psf = (torch.rand(1, 1, 1, K, K, generator=g, dtype=D64) ** 3).expand(1, G, G, K, K).clone()
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((1, G, G), 24.0 / S, dtype=D64), field_x=f, field_y=f,
                   chief=torch.stack([cx, cy], -1)[None].clone(), chief_x=c, chief_y=c, wavelengths_nm=(550.0,),
                   display_mm=(24.0, 24.0))


@pytest.mark.parametrize("iy, ix", [(3, 3), (3, 12), (16, 16)])
def test_a_lone_lit_pixel_images_to_the_bank_psf_in_the_energy_form(iy, ix):
    # a point source on black (the case the zero-pixel skip is for): under identity chief rays and one
    # PSF everywhere, its image is that PSF centred on the pixel. (3, 3) lies before the first field
    # sample (its blend has one field and its footprint one tap); the others blend 2 and 4 fields.
    S, K = 32, 7
    bank = _uniform_identity_bank(S, K)
    rb = bank.resample_to(S, S, dtype=D64, radiometry="energy")
    x = torch.zeros(1, S, S, dtype=D64)
    x[0, iy, ix] = 2.5
    want = torch.zeros(S, S, dtype=D64)
    want[iy - K // 2:iy + K // 2 + 1, ix - K // 2:ix + K // 2 + 1] = 2.5 * bank.psf[0, 0, 0].double()
    for out in (psf_exact(x, rb), psf_fast(x, rb, tol=0.0, zone=2)):
        assert out[0].sum().item() == pytest.approx(2.5, abs=1e-6)   # the energy form keeps the light (float32 PSF)
        assert torch.allclose(out[0], want, atol=1e-13, rtol=0)


def test_pupil_area_is_the_map_jacobian_times_the_cell():
    from controlgs_adapter.downstream.optics.generate import _pupil_area

    # an affine slope -> pupil map (xp, yp) = A (u, v): every ray stands for det(A) hu hv of pupil,
    # edges included (central and one-sided differences are exact on a linear map); steps differ per axis
    hu, hv = 0.3, 0.7
    a, b, c, d = 2.0, 0.5, -0.4, 1.5
    v, u = np.meshgrid(np.arange(5) * hv, np.arange(6) * hu, indexing="ij")   # u along axis 1, v along 0
    area = _pupil_area(a * u + b * v, c * u + d * v, hu, hv)
    assert area.shape == (5, 6)
    assert np.allclose(area, (a * d - b * c) * hu * hv, rtol=1e-12, atol=0)
    # past a fold the sign flips: yp = v^2 folds at v = 0 (interior rows, where central differences are exact)
    vs = (np.arange(7) - 3.0) * hv
    v, u = np.meshgrid(vs, np.arange(4) * hu, indexing="ij")
    area = _pupil_area(u, v ** 2, hu, hv)
    assert np.allclose(area[1:-1], 2 * v[1:-1] * hu * hv, rtol=1e-12, atol=1e-15)
    assert (area[1:3] < 0).all() and (area[4:6] > 0).all()
    # NaN where a neighbour is not finite
    xp = u.copy()
    xp[3, 2] = np.nan
    area = _pupil_area(xp, v ** 2, hu, hv)
    nan = np.isnan(area)
    assert nan[2, 2] and nan[4, 2] and nan[3, 1] and nan[3, 3] and nan.sum() == 4


def test_primaries_for_other_wavelengths_drive_white_at_one_in_every_primary():
    # the uncached builder (any R, G, B primaries whose gamut holds the sRGB white): each primary's
    # unit is the drive white needs, so linear white (1, 1, 1) -> (1, 1, 1); the second matrix inverts it
    colour = pytest.importorskip("colour")
    from controlgs_adapter.downstream import color

    to_p, to_rgb = color._primaries_matrices_for((638, 532, 465))
    assert to_p @ np.ones(3) == pytest.approx(np.ones(3), abs=1e-12)
    assert to_p @ to_rgb == pytest.approx(np.eye(3), abs=1e-12)
    # the rows are C^-1 M scaled per primary: the primaries' light C diag(u) to_p gives sRGB's XYZ
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"]
    cm = np.stack([np.asarray(cmfs[w]) for w in (638, 532, 465)], axis=1)
    m = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ)
    u = np.linalg.solve(cm, m @ np.ones(3))
    assert np.all(u > 0)
    assert cm @ np.diag(u) @ to_p == pytest.approx(m, abs=1e-12)
