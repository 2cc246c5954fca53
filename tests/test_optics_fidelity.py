"""Fidelity of the optics operators against independent references (issue 14, sections 1, 3, 4):
radiometry (a lossless lens conserves radiance), seams, footprints, the area magnification, the
pupil sampling of the bank. float64 throughout; every reference is analytic or a second
implementation (conv2d + hand-made weights, finite differences, a re-aimed ray trace)."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast, psf_reference
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import RuntimeState
from _pupil import aim_rays

D64 = torch.float64
OPS = {"distortion": psf_distortion, "exact": psf_exact, "fast": lambda x, rb: psf_fast(x, rb, tol=0.05, zone=5)}


def _bank(G=5, K=9, L=2, S=32, magnification=None, pincushion=0.0, transmission=None, seed=0):
    """Synthetic bank on a 24 mm display: Gaussian PSFs widening and shifting off-centre across the
    field (so they differ field to field), chief rays ``d * (s + k |d|^2)``."""
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    t = torch.arange(K, dtype=D64) - K // 2
    sig = 0.5 + 0.8 * (fx ** 2 + fy ** 2)
    off = 0.6 * fx                                                            # coma-like shift (px)
    g = torch.exp(-0.5 * (((t[None, :] - off[..., None, None]) ** 2 + t[:, None] ** 2) / sig[..., None, None] ** 2))
    psf = (g / g.sum((-1, -2), keepdim=True)).expand(L, G, G, K, K).clone()
    c = torch.linspace(-1, 1, 17, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    s = (magnification or 1.0) + pincushion * (cx ** 2 + cy ** 2)
    chief = torch.stack([cx * s, cy * s], -1).expand(L, 17, 17, 2).clone()
    meta = {} if transmission is None else {"transmission": transmission.expand(L, G, G).tolist()}
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), 24 / S, dtype=D64), field_x=f, field_y=f, chief=chief,
                   chief_x=c, chief_y=c, wavelengths_nm=(600.0, 500.0)[:L], display_mm=(24.0, 24.0), meta=meta)


def _inner(o: torch.Tensor, frac: float = 0.9) -> torch.Tensor:
    H, W = o.shape[-2:]
    a, b = round(H * (1 - frac) / 2), round(W * (1 - frac) / 2)
    return o[..., a:H - a, b:W - b]


def _steps(o: torch.Tensor) -> float:
    """Largest step between adjacent pixels beyond the local linear trend (first difference minus
    the mean of its two neighbours), both axes."""
    dx, dy = o[..., :, 1:] - o[..., :, :-1], o[..., 1:, :] - o[..., :-1, :]
    sx = dx[..., 1:-1] - 0.5 * (dx[..., 2:] + dx[..., :-2])
    sy = dy[..., 1:-1, :] - 0.5 * (dy[..., 2:, :] + dy[..., :-2, :])
    return max(sx.abs().max().item(), sy.abs().max().item())


# ----------------------------------------------------------------------------- section 1: radiometry
@pytest.mark.parametrize("mode", list(OPS))
def test_flat_field_of_the_cardboard_lens_is_uniform_in_every_mode(mode):
    """Radiance (default): a flat white display is seen flat, up to the pupil transmission (the
    vignetting model: the pupil area on the primary branch; 1 except in the outermost field
    samples of the Cardboard bank, >= 0.98 there, where the lens rim folds part of the pupil
    into the second image). The paper's energy form dims it by the area magnification (~0.8 at
    mid-edge, ~0.6 towards the corner)."""
    bank = PSFBank.default()
    assert bank.transmission.min() > 0.98
    S = 96
    x = torch.ones(3, S, S, dtype=D64)
    rb = bank.resample_to(S, S, dtype=D64)
    out = OPS[mode](x, rb)
    assert (out - rb.vignetting.reshape(3, S, S))[:, 8:-8, 8:-8].abs().max() < 1e-6
    assert (_inner(out) - 1).abs().max() < 1e-3                               # target: 2 %
    energy = OPS[mode](x, bank.resample_to(S, S, dtype=D64, radiometry="energy"))
    assert 0.78 < energy[1, S // 2, 5].item() < 0.86 and energy[1, 5, 5].item() < 0.7


def test_flat_field_of_a_16_9_image_is_uniform():
    bank = PSFBank.default()
    x = torch.ones(1, 3, 27, 48, dtype=D64)
    for mode in OPS:
        assert (_inner(psf_optics(x, bank, mode)) - 1).abs().max() < 1e-3


def test_pure_magnification_gives_a_uniform_flat_field_analytically():
    """Chief rays ``1.1 d``: every display pixel's image is 1.21 output pixels. Radiance: the
    covered frame is exactly 1; energy: exactly 1 / 1.21 (both where the footprints cover whole
    output pixels, i.e. away from the border; to the float32 storage of the bank)."""
    S = 40
    bank = _bank(S=S, magnification=1.1)
    x = torch.ones(2, S, S, dtype=D64)
    for radiometry, want in (("radiance", 1.0), ("energy", 1 / 1.21)):
        rb = bank.resample_to(S, S, dtype=D64, radiometry=radiometry)
        assert torch.allclose(rb.area, torch.full_like(rb.area, 1.21), atol=1e-6)
        assert (_inner(psf_distortion(x, rb), 0.8) - want).abs().max() < 1e-6
        if radiometry == "radiance":                                          # PSFs stored as float32 sums
            for mode in ("exact", "fast"):
                assert (_inner(OPS[mode](x, rb), 0.5) - want).abs().max() < 1e-7


def test_vignetting_is_the_traced_transmission_blended_where_the_light_arrives():
    """A distortion-free bank with transmission falling towards the edge: a flat field equals the
    bilinear interpolation of the transmission at the output pixel centres (computed here by hand)."""
    G, S = 5, 30
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    T = 1 - 0.2 * (f[:, None] ** 2 + f[None, :] ** 2)
    bank = _bank(G=G, S=S, transmission=T)
    u = (2 * torch.arange(S, dtype=D64) + 1) / S - 1
    pos = ((u + 1) / 2 * G - 0.5).clamp(0, G - 1)                             # field-grid coordinate
    i0 = pos.floor().clamp(max=G - 2).long()
    a = pos - i0
    Ty = T[i0] * (1 - a)[:, None] + T[i0 + 1] * a[:, None]                    # rows interpolated
    want = Ty[:, i0] * (1 - a) + Ty[:, i0 + 1] * a
    rb = bank.resample_to(S, S, dtype=D64)
    x = torch.ones(2, S, S, dtype=D64)
    assert torch.allclose(psf_distortion(x, rb), want.expand(2, S, S), atol=1e-12)
    for mode in ("exact", "fast"):
        assert (_inner(OPS[mode](x, rb), 0.6) - want[6:-6, 6:-6]).abs().max() < 1e-7
    assert torch.allclose(psf_distortion(x, bank.resample_to(S, S, dtype=D64, radiometry="energy")), x)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_distortion_free_bank_is_a_blend_of_convolutions(radiometry):
    """Identity chief rays and PSFs varying across the field: radiance is each field PSF's
    convolution (conv2d) blended with the bilinear weights of the output pixel; energy is the
    convolution of each field's weighted image (the weights of the source pixel)."""
    G, K, S = 4, 7, 24
    bank = _bank(G=G, K=K, S=S)
    rb = bank.resample_to(S, S, dtype=D64, radiometry=radiometry)
    x = torch.rand(2, S, S, dtype=D64, generator=torch.Generator().manual_seed(3))
    u = (2 * torch.arange(S, dtype=D64) + 1) / S - 1
    pos = ((u + 1) / 2 * G - 0.5).clamp(0, G - 1)
    i0 = pos.floor().clamp(max=G - 2).long()
    a = pos - i0
    w1 = torch.zeros(G, S, dtype=D64)                                          # 1-D hat weights [field, pixel]
    w1[i0, torch.arange(S)] += 1 - a
    w1[i0 + 1, torch.arange(S)] += a
    want = torch.zeros(2, S, S, dtype=D64)
    for fy in range(G):
        for fx in range(G):
            w = w1[fy][:, None] * w1[fx][None, :]
            k = bank.psf[:, fy, fx].double().flip(-1, -2)[:, None]             # conv2d correlates
            src = x * w if radiometry == "energy" else x
            conv = F.conv2d(F.pad(src[None], (K // 2,) * 4), k, groups=2)[0]
            want += conv if radiometry == "energy" else conv * w
    for op in (psf_exact, psf_reference, lambda v, r: psf_fast(v, r, tol=0.0, zone=2)):
        assert torch.allclose(op(x, rb), want, atol=1e-12)


def test_area_magnification_matches_finite_differences_of_the_chief_rays():
    """``rb.area`` (the exact quad areas the radiance form multiplies by, and the energy form
    divides by) against det of the chief-ray Jacobian by central differences at pixel centres;
    the same in both radiometries."""
    bank = PSFBank.default()
    S = 64
    rb = bank.resample_to(S, S, dtype=D64)
    u = (2 * torch.arange(S, dtype=D64) + 1) / S - 1
    V, U = torch.meshgrid(u, u, indexing="ij")
    h = 1e-5
    ddx = (rb._chief_at(U + h, V) - rb._chief_at(U - h, V)) / (2 * h)
    ddy = (rb._chief_at(U, V + h) - rb._chief_at(U, V - h)) / (2 * h)
    det = (ddx[..., 0] * ddy[..., 1] - ddx[..., 1] * ddy[..., 0]).reshape(3, -1)
    assert ((rb.area / det) - 1).abs().max() < 5e-3                          # O(pixel^2) of the quads
    assert 1.2 < rb.area[1].reshape(S, S)[S // 2, 0].item() < 1.3             # ~1/0.80 at mid-edge
    assert torch.allclose(bank.resample_to(S, S, dtype=D64, radiometry="energy").area, rb.area)


def test_radiance_point_source_lands_on_its_chief_ray():
    """A single display pixel: its light is its area magnification (radiance over a larger image),
    centred on the chief ray plus the blended PSF's centroid (within 0.05 px: the blend is taken
    where the light arrives, so it varies a little across the PSF)."""
    bank = PSFBank.default()
    S = 48
    rb = bank.resample_to(S, S, dtype=D64)
    iy, ix = 30, 17
    x = torch.zeros(3, S, S, dtype=D64)
    x[:, iy, ix] = 1
    out = psf_exact(x, rb)
    e = rb.area[:, iy * S + ix]
    assert torch.allclose(out.sum((-1, -2)), e, rtol=2e-3)
    ref = psf_exact(x, bank.resample_to(S, S, dtype=D64, radiometry="energy"))
    yy, xx = torch.meshgrid(torch.arange(S, dtype=D64), torch.arange(S, dtype=D64), indexing="ij")
    for li in range(3):
        for grid in (xx, yy):
            c = (out[li] * grid).sum() / out[li].sum()
            c_energy = (ref[li] * grid).sum() / ref[li].sum()
            assert abs(c - c_energy).item() < 0.05


# ----------------------------------------------------------------------------- section 3: seams
def test_no_seams_on_the_field_sample_lines_in_exact_mode():
    """Exact mode, flat field: no step above 1e-4 between adjacent pixels in the inner 90 %, rows
    and columns on field-sample lines like the others (the energy form steps there: ~5e-3)."""
    bank = PSFBank.default()
    S = 120                                                                    # 4 px per field cell
    x = torch.ones(3, S, S, dtype=D64)
    out = _inner(psf_exact(x, bank.resample_to(S, S, dtype=D64)))
    assert _steps(out) < 1e-4
    assert (out - 1).abs().max() < 1e-3
    energy = _inner(psf_exact(x, bank.resample_to(S, S, dtype=D64, radiometry="energy")))
    assert _steps(energy) > 1e-3


def test_a_ramp_through_field_varying_psfs_has_no_seams():
    """No distortion (so no box-pixel resampling), PSFs widening from 0.5 to 2 px and shifting by up
    to 1.5 px quadratically across a 6 x 6 field grid, a horizontal ramp: the radiance form's
    output has no step beyond the trend above 1e-4 (its blend is continuous, with kinks only);
    the energy form's scatter steps by ~4e-3 on the sample lines."""
    G, K, S = 6, 15, 96
    bank = _bank(G=G, K=K, S=S)
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    t = torch.arange(K, dtype=D64) - K // 2
    sig, off = 0.5 + 1.5 * (fx ** 2 + fy ** 2), 1.5 * fx ** 2 * torch.sign(fx)
    g = torch.exp(-0.5 * (((t[None, :] - off[..., None, None]) ** 2 + t[:, None] ** 2) / sig[..., None, None] ** 2))
    bank.psf = (g / g.sum((-1, -2), keepdim=True)).expand(2, G, G, K, K).clone()
    bank.validate()
    x = torch.linspace(0.1, 0.9, S, dtype=D64).expand(2, S, S).clone()
    rb = bank.resample_to(S, S, dtype=D64)
    assert _steps(_inner(psf_exact(x, rb), 0.7)) < 1e-4
    assert _steps(_inner(psf_fast(x, rb, tol=0.02, zone=3), 0.7)) < 1e-4
    assert _steps(_inner(psf_exact(x, bank.resample_to(S, S, dtype=D64, radiometry="energy")), 0.7)) > 1e-3


def test_fast_mode_converges_to_the_radiance_exact_operator_and_keeps_flat_fields():
    bank = PSFBank.default()
    rb = bank.resample_to(48, 48, dtype=D64)
    g = torch.Generator().manual_seed(0)
    x = F.avg_pool2d(torch.rand(3, 96, 96, generator=g, dtype=D64)[None], 2)[0]
    ref = psf_exact(x, rb)
    errs = [((psf_fast(x, rb, tol=t, zone=5) - ref).norm() / ref.norm()).item() for t in (0.3, 0.1, 0.03, 0.0)]
    assert errs[0] > errs[1] > errs[2] and errs[3] < 1e-9
    flat = psf_fast(torch.ones(3, 48, 48, dtype=D64), rb, tol=0.3, zone=6)
    assert (flat - rb.vignetting.reshape(3, 48, 48))[:, 4:-4, 4:-4].abs().max() < 1e-6   # kernel sums kept


# ----------------------------------------------------------------------------- stage plumbing
def test_radiometry_is_an_explicit_argument():
    bank = PSFBank.default()
    img = torch.full((3, 32, 32), 0.5, dtype=D64)
    st = PSFOptics(mode="distortion")
    assert st.radiometry == "radiance" and "radiometry='radiance'" in repr(st)
    paper = PSFOptics(mode="distortion", radiometry="energy")
    state = RuntimeState(downsample=1.0, power_saving=0.0)
    assert torch.allclose(paper(img, state, None), psf_optics(img, bank, "distortion", radiometry="energy"))
    assert (_inner(st(img, state, None)) - 0.5).abs().max() < 1e-6
    assert bank.resample_to(32, 32) is not bank.resample_to(32, 32, radiometry="energy")
    with pytest.raises(InputValueError, match="radiometry"):
        PSFOptics(radiometry="lumens")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="radiometry"):
        bank.resample_to(8, 8, radiometry="photons")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="transmission"):
        _bank(transmission=torch.full((5, 5), 1.5, dtype=D64))


# ----------------------------------------------------------------------------- section 4: pupil
def test_bank_psf_centroid_matches_a_trace_aimed_uniformly_over_the_pupil():
    """The shipped bank's mid-edge coma centroid (550 nm) against an independent trace: rays
    aimed by Newton at the points of a uniform grid over the 4 mm pupil (equal area each), their
    mean crossing of the virtual image plane relative to the chief ray. Uniform launch slopes gave
    1.20 px at 1024 px; the pupil-uniform value is 0.94 px."""
    from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
    from controlgs_adapter.downstream.optics.raytrace import chief_ray, real_magnification

    bank = PSFBank.default()
    rx = Prescription(CARDBOARD)
    iy, ix, li = 29, 15, 1
    fx, fy = bank.field_x[ix].item() * 12, bank.field_y[iy].item() * 12            # mm on the display
    r = math.hypot(fx, fy)
    lam = bank.wavelengths_nm[li]
    v0, Y0, _ = chief_ray(rx, lam, np.array([r]))
    n = 64
    g = (np.arange(n) + 0.5) / n * 2 - 1
    PX, PY = np.meshgrid(g, g)
    inside = PX ** 2 + PY ** 2 <= 1
    tx, ty = PX[inside] * rx.pupil_radius, PY[inside] * rx.pupil_radius
    xp, yp, _, Y, ok = aim_rays(rx, lam, r, v0[0], tx, ty, 8)                 # Newton per pupil point
    assert ok.all() and np.abs(xp - tx).max() < 1e-9 and np.abs(yp - ty).max() < 1e-9
    px_per_mm = 1024 / 24
    want = (Y - Y0[0]).mean() / real_magnification(rx, rx.reference_wavelength) * px_per_mm   # radial, px at 1024
    K = bank.psf.shape[-1]
    t = torch.arange(K, dtype=D64) - K // 2
    p = bank.psf[li, iy, ix].double()
    pitch = bank.psf_pitch_mm[li, iy, ix].item() * px_per_mm
    cx, cy = (p.sum(0) * t).sum().item() * pitch, (p.sum(1) * t).sum().item() * pitch
    got = (cx * fx + cy * fy) / r
    assert got == pytest.approx(want, abs=0.015)
    assert 0.9 < got < 1.0
