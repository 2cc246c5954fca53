"""Tests of the shipped compact lens (``compact_prescription.json``, its PSF bank and pre-warp LUT): the
prescription against the source design's own surface data, the bank traced from the shipped prescription,
PSFs of unit sum, a flat field seen flat (radiance), no seams between field zones, and the fitted
pre-warp landing every primary of a dot within a tenth of a pixel."""

from __future__ import annotations

import functools

import numpy as np
import pytest
import torch
from helpers.lens_checks import GRID_FIELD, gaussian_dot_errors, inner, steps

from controlgs_adapter.downstream.bank_maps import DisplayLUTMap, bank_fingerprint
from controlgs_adapter.downstream.optics.generate import lens_figures
from controlgs_adapter.downstream.optics.lenses import effects_for_lens, load_lens, shipped_prescription
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast
from controlgs_adapter.downstream.optics.prescription import Prescription
from controlgs_adapter.downstream.optics.raytrace import paraxial, real_magnification
from controlgs_adapter.downstream.pipeline import Pipeline

D64 = torch.float64
OPS = {"distortion": psf_distortion, "exact": psf_exact, "fast": lambda x, rb: psf_fast(x, rb, tol=0.05, zone=5)}

#: the source design as DeepLens stores it (datasets/lenses/pancake/pancake_last.json, Apache-2.0), from the
#: eye pupil toward the display: vertex z (mm), curvature c (1/mm), conic k, [a2, a4, ..., a12] of r^2 .. r^12
#: (r in mm), medium after the surface
DEEPLENS = [
    (14.9021577835083, 0.019480952993035316, 1.4287198781967163,
     [-0.004519629757851362, 8.097344834823161e-05, 1.643850140453651e-07, -2.0891701701941656e-09,
      -2.1087671539521402e-11, 4.59549594016527e-14], "sk16"),
    (16.5, 0.0, 0.0, [], "air"),
    (17.27027130126953, 0.013023302890360355, 0.5660380125045776,
     [0.00580665934830904, -1.7237507563550025e-05, -1.849931834385643e-07, -8.407550211586567e-10,
      -3.534538113580954e-12, 4.220163443962449e-14], "f2"),
    (20.252826690673828, -0.013374259695410728, 0.143933966755867,
     [-0.009519681334495544, 5.9659258113242686e-05, 2.5191539521074446e-07, -2.645139107748662e-10,
      -7.189094697150622e-13, -1.1668887664668167e-14], "air"),
    (21.505802154541016, -0.02432776242494583, 0.7247318625450134,
     [0.006981183774769306, 1.5660494682379067e-05, -5.207366626791554e-08, -9.200843420487104e-10,
      -2.5681863319998444e-12, 4.801934810070088e-14], "sk16"),
    (23.04680824279785, -0.02474612183868885, 0.3857553005218506,
     [0.0020224207546561956, 5.55212318431586e-05, -3.287174195065745e-07, -1.7905238403059798e-09,
      2.3334863555324326e-11, -2.2390943266170638e-14], "air"),
]
GLASS = {"sk16": (1.62041, 60.32), "f2": (1.62004, 36.37)}


def _conic(c: float, k: float, r: np.ndarray) -> np.ndarray:
    return r * r * c / (1 + np.sqrt(1 - (1 + k) * r * r * c * c))


@functools.lru_cache(maxsize=1)
def _lens():
    return load_lens("compact")


@functools.lru_cache(maxsize=None)
def _resampled(S: int):
    return _lens().bank.resample_to(S, S, dtype=D64)


def test_surfaces_are_the_source_design_seen_from_the_display():
    """Reversed order, sag z -> -z: every surface's sag equals minus the source's (its r^2 term folded into the
    vertex radius, r^4 .. r^14 refitted) to 1e-9 mm over the 14 mm semi-diameter; the spacings are the source's
    vertex gaps in reverse (to 0.1 um) and the media the source's media in front of each surface."""
    rx = Prescription(shipped_prescription("compact"))
    r = np.linspace(0.0, 14.0, 1401)
    source = DEEPLENS[::-1]
    assert len(rx.surfaces) == len(source)
    for i, (sf, (z, c, k, ai, _)) in enumerate(zip(rx.surfaces, source)):
        theirs = _conic(c, k, r) + sum(a * r ** (2 * j + 2) for j, a in enumerate(ai))
        ours = _conic(sf.curvature, sf.conic, r) + sum(a * r ** (2 * j + 4) for j, a in enumerate(sf.aspheric))
        assert np.abs(ours + theirs).max() < 1e-9, i
        assert sf.semi_diameter == 14.0
        if i + 1 < len(source):
            assert sf.thickness == pytest.approx(z - source[i + 1][0], abs=1e-7)
            before = source[i + 1][4]
            assert (sf.material == "air") if before == "air" else ((sf.material["nd"], sf.material["vd"]) == GLASS[before])
    assert rx.surfaces[-1].thickness == pytest.approx(DEEPLENS[0][0], abs=1e-7)          # eye relief
    assert rx.surfaces[-1].material == "air"


def test_the_display_sits_where_the_virtual_image_is_at_667_mm():
    """At 550 nm the paraxial virtual image is 667 mm from the eye (to the display distance's 1 um rounding),
    the focal length is the source's traced one (21.64 mm, not the 19.56 mm its file states) and the chief-ray
    magnification on that plane is the paraxial one."""
    rx = Prescription(shipped_prescription("compact"))
    p = paraxial(rx, 550.0)
    assert p.image_distance == pytest.approx(667.0, abs=0.5)
    assert p.efl == pytest.approx(21.637, abs=0.002)
    assert real_magnification(rx, 550.0) == pytest.approx(p.magnification, rel=1e-3)
    assert rx.efficiency == 1.0 and rx.display_mm == (8.77, 8.77) and rx.pupil_radius == 2.0


def test_the_shipped_bank_is_traced_from_the_shipped_prescription():
    """The bank records the shipped prescription and its figures (so it is not stale), holds no vignetting
    (28 mm apertures), and every PSF is non-negative with unit sum."""
    bank = _lens().bank
    spec = shipped_prescription("compact")
    assert bank.meta["prescription"] == spec
    figures = lens_figures(Prescription(spec))
    assert bank.meta["figures"]["550nm"]["corner_distortion_pct"] == pytest.approx(
        figures["550nm"]["corner_distortion_pct"], abs=1e-9)
    assert bank.psf.shape == (3, 30, 30, 33, 33) and bank.display_mm == (8.77, 8.77)
    assert float(bank.psf.min()) >= 0
    assert torch.allclose(bank.psf.double().sum((-1, -2)), torch.ones(3, 30, 30, dtype=D64), atol=1e-6)
    assert torch.equal(bank.transmission, torch.ones_like(bank.transmission))


@pytest.mark.parametrize("mode", list(OPS))
def test_flat_field_is_seen_flat_up_to_the_transmission(mode):
    """Radiance: a flat white display is seen as the vignetting (the pupil transmission, here 1) to 1e-6
    away from the frame's edge, and flat to 1e-3 over the inner 90 %."""
    S = 96
    rb = _resampled(S)
    out = OPS[mode](torch.ones(3, S, S, dtype=D64), rb)
    assert (out - rb.vignetting.reshape(3, S, S))[:, 8:-8, 8:-8].abs().max() < 1e-6
    assert (inner(out) - 1).abs().max() < 1e-3


def test_no_seams_between_field_zones_in_exact_mode():
    """Exact mode, flat field at 4 px per field cell: no step above 1e-4 between adjacent pixels in the
    inner 90 %; the energy form, which steps on the field-sample lines, shows the check can fail."""
    S = 120
    x = torch.ones(3, S, S, dtype=D64)
    assert steps(inner(psf_exact(x, _resampled(S)))) < 1e-4
    energy = psf_exact(x, _lens().bank.resample_to(S, S, dtype=D64, radiometry="energy"))
    assert steps(inner(energy)) > 1e-4


def test_the_shipped_lut_is_fitted_for_the_shipped_bank():
    lens = _lens()
    lut = DisplayLUTMap.load(lens.prewarp)
    assert lut.meta["bank"] == bank_fingerprint(lens.bank)
    assert lut.sizes == {"distortion": (64, 96, 128, 192, 256), "exact": (64, 96, 128, 192, 256)}
    assert lut.meta["radiometry"] == "radiance"


@pytest.mark.parametrize("mode", ["distortion", "exact"])
@pytest.mark.parametrize("size", [(96, 96), (54, 96)])
def test_the_prewarp_lands_every_primary_of_a_dot_within_a_tenth_of_a_pixel(mode, size):
    """Through the compact lens's fitted pre-warp and optics, each primary of a white dot on a 0.1 grid over
    the field is seen within 0.1 px of where it was rendered; without the pre-warp lateral colour and
    distortion move some primary by more than 0.3 px."""
    config = effects_for_lens({"lens": True, "optics": {"mode": mode}}, _lens())
    pipe = Pipeline.from_config(config).double()
    assert isinstance(pipe["lens"].map, DisplayLUTMap)
    field = GRID_FIELD if size[0] == size[1] else [(u, v * size[0] / size[1]) for u, v in GRID_FIELD]
    err = gaussian_dot_errors(pipe, size, field)
    worst = int(err.amax(1).argmax())
    assert float(err.max()) < 0.1, (field[worst], err[worst])
    plain = Pipeline.from_config(effects_for_lens({"optics": {"mode": mode}}, _lens())).double()
    assert float(gaussian_dot_errors(plain, size, field).max()) > 0.3
