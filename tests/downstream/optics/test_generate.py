"""Tests of ``controlgs_adapter.downstream.optics.generate``."""

from __future__ import annotations

import math
from typing import Any, Callable

import numpy as np
import pytest
import torch

from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.errors import ControlGSError, InputValueError


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


BUILD_CASES = [
    ("psf_size=4", {"psf_size": 4}, "psf_size"), ("psf_size=3", {"psf_size": 3}, "psf_size"),
    ("psf_size='33'", {"psf_size": "33"}, "psf_size"), ("grid=(0, 0)", {"grid": (0, 0)}, "grid"),
    ("grid=(3,)", {"grid": (3,)}, "grid"), ("grid=(3, -1)", {"grid": (3, -1)}, "grid"),
    ("pupil_samples=1", {"pupil_samples": 1}, "pupil_samples"), ("min_pitch_px=0", {"min_pitch_px": 0.0}, "min_pitch_px"),
    ("min_pitch_px=nan", {"min_pitch_px": math.nan}, "min_pitch_px"), ("chief_grid=(1, 1)", {"chief_grid": (1, 1)}, "chief_grid"),
]


@pytest.mark.parametrize("kw, name", [c[1:] for c in BUILD_CASES], ids=[c[0] for c in BUILD_CASES])
def test_build_bank_arguments(kw, name):
    _raises(lambda: build_bank(**kw), InputValueError, name)


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


# ----------------------------------------------------------------------------- build_bank: silent by default
def test_build_bank_prints_nothing_unless_progress_is_asked(capsys):
    """``build_bank``'s docstring: ``progress=True`` prints one line per traced wavelength to stdout (the
    ``controlgs optics build-bank`` command turns it on); by default a library call prints nothing. A tiny
    bank (one field, 5 x 5 PSFs) both ways: silent, then one ``traced <nm> nm`` line per wavelength."""
    from controlgs_adapter.downstream.optics.generate import build_bank

    kw = dict(grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(2, 2))
    bank = build_bank(**kw)
    out = capsys.readouterr()
    assert (out.out, out.err) == ("", "")
    assert build_bank(**kw, progress=True).wavelengths_nm == bank.wavelengths_nm
    lines = capsys.readouterr().out.splitlines()
    assert [ln.split(" nm:")[0].split()[-1] for ln in lines] == [f"{w:g}" for w in bank.wavelengths_nm]


# ------------------------------------------------------------------ build_bank: min_pupil_coverage
def test_recorded_pupil_coverage_is_a_fraction_at_most_one_rounded_to_5_decimals():
    """``build_bank`` docstring: ``meta["generator"]["min_pupil_coverage"]`` is at most 1 and rounded to 5
    decimals. On axis with 8 pupil samples the rim-cell quadrature sums to ~1.0005 of the disc (full
    coverage: reads 1.0); with 16 it sums to ~0.99989 (the 6th decimal is not 0, so the rounding shows)."""
    over = build_bank(grid=(1, 1), psf_size=5, pupil_samples=8, chief_grid=(2, 2))
    assert over.meta["generator"]["min_pupil_coverage"] == 1.0
    under = build_bank(grid=(1, 1), psf_size=5, pupil_samples=16, chief_grid=(2, 2))
    cov = under.meta["generator"]["min_pupil_coverage"]
    assert 0.999 < cov < 1.0 and cov == round(cov, 5)


D64 = torch.float64


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
