"""Tests of ``controlgs_adapter.downstream.optics.operators``: the shift-variant PSF operators (exact,
fast, distortion-only and the literal reference) in both radiometries: closed forms on synthetic banks,
agreement with the reference, flat fields, point sources and seams on the Cardboard bank, linearity,
adjointness and gradients, black-pixel skipping, and their refusals."""

from __future__ import annotations

import functools

import pytest
import torch
import torch.nn.functional as F
from helpers.banks import random_bank, synthetic_bank
from helpers.lens_checks import inner as _inner
from helpers.lens_checks import steps as _steps
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.optics import operators
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast, psf_reference
from controlgs_adapter.downstream.optics.stage import psf_optics
from controlgs_adapter.errors import InputValueError, ShapeError

D64 = torch.float64
RADIOMETRIES = ("radiance", "energy")
OPS = {"distortion": psf_distortion, "exact": psf_exact, "fast": lambda x, rb: psf_fast(x, rb, tol=0.05, zone=5)}
#: every operator, fast with small groups
ALL_OPS = {"distortion": psf_distortion, "exact": psf_exact, "reference": psf_reference,
           "fast": lambda x, rb: psf_fast(x, rb, 0.05, 2)}


def _gaussian_bank(G=5, K=9, L=2, S=32, magnification=None, pincushion=0.0, transmission=None):
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


@functools.lru_cache(maxsize=1)
def _rb8():
    return random_bank().resample_to(8, 8)                                       # float32


# ----------------------------------------------------------------------------- closed forms
def test_pure_magnification_gives_a_uniform_flat_field_analytically():
    """Chief rays ``1.1 d``: every display pixel's image is 1.21 output pixels. Radiance: the
    covered frame is exactly 1; energy: exactly 1 / 1.21 (both where the footprints cover whole
    output pixels, i.e. away from the border; to the float32 storage of the bank)."""
    S = 40
    bank = _gaussian_bank(S=S, magnification=1.1)
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
    bilinear interpolation of the transmission at the output pixel centres (computed here);
    the energy form has no vignetting."""
    G, S = 5, 30
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    T = 1 - 0.2 * (f[:, None] ** 2 + f[None, :] ** 2)
    bank = _gaussian_bank(G=G, S=S, transmission=T)
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


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_distortion_free_bank_is_a_blend_of_convolutions(radiometry):
    """Identity chief rays and PSFs varying across the field: radiance is each field PSF's
    convolution (conv2d) blended with the bilinear weights of the output pixel; energy is the
    convolution of each field's weighted image (the weights of the source pixel)."""
    G, K, S = 4, 7, 24
    bank = _gaussian_bank(G=G, K=K, S=S)
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


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_uniform_psf_field_is_a_single_convolution(radiometry):
    bank = synthetic_bank()
    rb = bank.resample_to(16, 16, dtype=D64, radiometry=radiometry)
    x = torch.rand(3, 2, 16, 16, dtype=D64)
    k = bank.psf[0, 0, 0].double()
    ref = F.conv2d(F.pad(x.reshape(-1, 1, 16, 16), (3, 3, 3, 3)), k.flip(0, 1)[None, None]).reshape(3, 2, 16, 16)
    for op in (psf_exact, psf_reference, lambda a, r: psf_fast(a, r, tol=0.5, zone=4)):
        assert (op(x, rb) - ref).abs().max() < 1e-6


@pytest.mark.parametrize("iy, ix", [(3, 3), (3, 12), (16, 16)])
def test_a_lone_lit_pixel_images_to_the_bank_psf_in_the_energy_form(iy, ix):
    """A point source on black: under identity chief rays and one PSF everywhere, its image is that PSF
    centred on the pixel. (3, 3) lies before the first field sample (its blend has one field and its
    footprint one tap); the others blend 2 and 4 fields."""
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


# ----------------------------------------------------------------------------- agreement with the reference
@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_exact_and_fast_equal_the_reference_on_the_cardboard_bank(radiometry):
    """Square and wide images: exact equals the brute-force splat; fast with one field per group is
    exact at any tol (the one-field eigen-PSF is the field's kernel itself); several fields per group at
    tol 0 are the full eigen-expansion (eigh of K K^T: to 1e-9)."""
    bank = PSFBank.default()
    x = torch.rand(3, 24, 24, dtype=D64)
    rb = bank.resample_to(24, 24, dtype=D64, radiometry=radiometry)
    assert torch.allclose(psf_exact(x, rb), psf_reference(x, rb), atol=1e-12, rtol=0)
    rb = bank.resample_to(18, 32, dtype=D64, radiometry=radiometry)
    x = torch.rand(2, 3, 18, 32, dtype=D64, generator=torch.Generator().manual_seed(1))
    ref = psf_reference(x, rb)
    assert torch.allclose(psf_exact(x, rb), ref, atol=1e-12, rtol=0)
    assert torch.allclose(psf_fast(x, rb, tol=0.3, zone=1), ref, atol=1e-12, rtol=0)
    assert ((psf_fast(x, rb, tol=0.0, zone=3) - ref).norm() / ref.norm()) < 1e-9


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_fast_operator_converges_to_exact_and_keeps_flat_fields(radiometry):
    """On the Cardboard bank the fast operator's error falls with tol (below 1 % at 0.03) and vanishes at
    0 (zones of 5 and 6), beating the distortion-only operator; its kernels keep their sums: a flat field
    is the vignetting (radiance)."""
    bank = PSFBank.default()
    rb = bank.resample_to(48, 48, dtype=D64, radiometry=radiometry)
    for zone, seed in ((5, 0), (6, 1)):
        x = F.avg_pool2d(torch.rand(3, 96, 96, generator=torch.Generator().manual_seed(seed), dtype=D64)[None], 2)[0]
        ref = psf_exact(x, rb)
        errs = [((psf_fast(x, rb, tol=t, zone=zone) - ref).norm() / ref.norm()).item() for t in (0.3, 0.1, 0.03, 0.0)]
        assert errs[0] > errs[1] > errs[2] and errs[2] < 0.01 and errs[3] < 1e-8, (zone, errs)
        assert ((psf_distortion(x, rb) - ref).norm() / ref.norm()).item() > errs[2]
    if radiometry == "radiance":
        flat = psf_fast(torch.ones(3, 48, 48, dtype=D64), rb, tol=0.3, zone=6)
        assert (flat - rb.vignetting.reshape(3, 48, 48))[:, 4:-4, 4:-4].abs().max() < 1e-6


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_fast_is_exact_at_tol_zero_for_any_zone_and_rank_one_at_extreme_tol(radiometry):
    """A 4 x 4 field grid of different PSFs: zones of 1 (any tol), 3 (not dividing 4), 4 and 10 (larger than
    the grid) at tol=0 all equal the brute-force splat; tol near 1 keeps one eigen-PSF per group: the same
    operator as max_rank=1, and not exact."""
    bank = synthetic_bank(K=5, G=4, L=2, uniform=False, identity=False, seed=2)
    rb = bank.resample_to(12, 10, dtype=D64, radiometry=radiometry)
    x = torch.rand(2, 12, 10, dtype=D64, generator=torch.Generator().manual_seed(4))
    ref = psf_reference(x, rb)
    for zone, tol in ((1, 0.9), (3, 0.0), (10, 0.0), (4, 0.0)):
        assert torch.allclose(psf_fast(x, rb, tol=tol, zone=zone), ref, atol=1e-10, rtol=0), (zone, tol)
    x = torch.rand(2, 12, 10, dtype=D64, generator=torch.Generator().manual_seed(5))
    rank_one = psf_fast(x, rb, tol=0.999, zone=4)
    assert torch.allclose(rank_one, psf_fast(x, rb, tol=0.0, zone=4, max_rank=1), atol=1e-12, rtol=0)
    ref = psf_reference(x, rb)
    assert float((rank_one - ref).norm() / ref.norm()) > 1e-3


def test_fast_defaults_and_an_integer_zero_tolerance():
    rb = random_bank(G=8).resample_to(16, 16, dtype=D64)
    x = torch.rand(3, 16, 16, dtype=D64, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(psf_fast(x, rb, tol=0, zone=1), psf_exact(x, rb), atol=1e-12)   # tol 0 as an int
    assert torch.equal(psf_fast(x, rb), psf_fast(x, rb, 0.02, 6))             # operator defaults: tol 0.02, zone 6
    assert not torch.allclose(psf_fast(x, rb, 0.02, 6), psf_fast(x, rb, 0.04, 6), atol=1e-9)
    assert not torch.allclose(psf_fast(x, rb, 0.02, 6), psf_fast(x, rb, 0.02, 7), atol=1e-9)
    one = synthetic_bank(K=3, G=2, L=1).resample_to(6, 6, dtype=D64)               # one wavelength, one-field zones
    assert psf_fast(torch.rand(1, 6, 6, dtype=D64), one, tol=0.0, zone=1).shape == (1, 6, 6)


def _padded_means(buckets):
    return [sum((bh + 2 * mz) * (bw + 2 * mz) for _, _, bh, bw, mz in bk.boxes) / len(bk.boxes)
            for bks in buckets for bk in bks]


@pytest.mark.parametrize("rule", ["slices", "mixed", "tables"])
@pytest.mark.parametrize("op", ["exact", "fast"])
def test_tables_and_slices_match_the_reference(monkeypatch, rule, op):
    """Radiance buckets move their boxes by slices or by index tables (a size threshold): either way, or
    mixed, outputs and gradients equal the per-pixel reference."""
    rb = PSFBank.default().resample_to(24, 24, dtype=D64, radiometry="radiance")
    buckets = rb.zones(1, 0.0) if op == "exact" else rb.zones(2, 0.0)   # fast at tol 0: exact, ranks 1..4
    means = sorted(_padded_means(buckets))
    assert means[0] < means[-1]                                  # a threshold between them splits the buckets
    thr = {"slices": 0, "mixed": means[len(means) // 2], "tables": means[-1]}[rule]
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", thr)
    used = {operators._use_tables(bk) for bks in buckets for bk in bks}
    assert used == {"slices": {False}, "mixed": {False, True}, "tables": {True}}[rule]

    run = (lambda a: psf_exact(a, rb)) if op == "exact" else (lambda a: psf_fast(a, rb, tol=0.0, zone=2))
    x = torch.rand(2, 3, 24, 24, dtype=D64, requires_grad=True)
    w = torch.rand(2, 3, 24, 24, dtype=D64)
    out = run(x)
    (g,) = torch.autograd.grad((out * w).sum(), x)
    ref = psf_reference(x, rb)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    tol = 1e-12 if op == "exact" else 1e-9     # fast: its eigen-split drops singular values at rounding level (4e-10 here)
    assert torch.allclose(out, ref, atol=tol, rtol=0)
    assert torch.allclose(g, g_ref, atol=tol, rtol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: the CUDA table rule not run")
def test_cuda_uses_tables_for_every_bucket_and_matches_the_cpu_reference(monkeypatch):
    """On CUDA every bucket moves its boxes through index tables (a Python step per box is ~10 kernel
    launches there), even where the CPU rule picks slices; outputs and gradients equal the float64
    per-pixel reference computed on the CPU."""
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", 0)            # the CPU rule: slices for every bucket
    bank = PSFBank.default()
    cpu = bank.resample_to(24, 24, dtype=D64, radiometry="radiance")
    x = torch.rand(2, 3, 24, 24, dtype=D64, requires_grad=True)
    xg = x.detach().cuda().requires_grad_(True)
    gpu = bank.resample_to(24, 24, device=xg.device, dtype=D64, radiometry="radiance")   # cuda:0, as the stage does
    assert {operators._use_tables(bk) for bks in cpu.zones(1, 0.0) for bk in bks} == {False}
    assert {operators._use_tables(bk) for bks in gpu.zones(1, 0.0) for bk in bks} == {True}
    w = torch.rand(2, 3, 24, 24, dtype=D64)
    out = psf_exact(xg, gpu)
    (g,) = torch.autograd.grad((out * w.cuda()).sum(), xg)
    ref = psf_reference(x, cpu)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    assert torch.allclose(out.cpu(), ref, atol=1e-12, rtol=0)
    assert torch.allclose(g.cpu(), g_ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("chunk", [1, 300])
def test_energy_reference_is_independent_of_its_tap_chunks(monkeypatch, chunk):
    """The energy reference walks the kernel taps in chunks of at most ``_CHUNK_ELEMS`` elements (a
    memory bound); whatever the chunk, it equals the per-field FFT operator (and its gradient the
    FFT operator's exact adjoint)."""
    rb = random_bank(G=4, pitch_mm=2.0, pincushion=0.1).resample_to(10, 10, dtype=D64, radiometry="energy")
    assert rb.k > 2
    x = torch.rand(2, 3, 10, 10, dtype=D64, generator=torch.Generator().manual_seed(4), requires_grad=True)
    w = torch.rand(2, 3, 10, 10, dtype=D64, generator=torch.Generator().manual_seed(5))
    want = psf_exact(x, rb)
    (g_want,) = torch.autograd.grad((want * w).sum(), x)
    monkeypatch.setattr(operators, "_CHUNK_ELEMS", chunk)
    got = psf_reference(x, rb)
    (g_got,) = torch.autograd.grad((got * w).sum(), x)
    assert torch.allclose(got, want, atol=1e-12, rtol=0) and torch.allclose(g_got, g_want, atol=1e-12, rtol=0)


def test_energy_operators_on_a_batch_with_several_eigen_psfs():
    """Energy form, a batch of 2 and field groups of several eigen-PSFs (``psf_fast`` at tol 0,
    zone 2: exact): outputs and gradients equal the brute-force reference item by item."""
    rb = random_bank(G=4, pitch_mm=2.0, pincushion=0.1).resample_to(12, 12, dtype=D64, radiometry="energy")
    assert max(b.kernel_fft.shape[0] for bks in rb.zones(2, 0.0) for b in bks) > 1
    x = torch.rand(2, 3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(8), requires_grad=True)
    w = torch.rand(2, 3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(9))
    for op in (lambda a: psf_fast(a, rb, 0.0, 2), lambda a: psf_exact(a, rb)):
        out = op(x)
        (g,) = torch.autograd.grad((out * w).sum(), x)
        for i in range(2):
            xi = x[i].detach().clone().requires_grad_(True)
            ref = psf_reference(xi, rb)
            (gi,) = torch.autograd.grad((ref * w[i]).sum(), xi)
            assert torch.allclose(out[i], ref, atol=1e-10, rtol=0) and torch.allclose(g[i], gi, atol=1e-10, rtol=0)


# ----------------------------------------------------------------------------- linearity and gradients
@settings(max_examples=10, deadline=None)
@given(a=st.floats(-3, 3), b=st.floats(-3, 3), seed=st.integers(0, 100), radiometry=st.sampled_from(RADIOMETRIES))
def test_linearity(a, b, seed, radiometry):
    bank = synthetic_bank(uniform=False, identity=False, seed=seed % 3)
    rb = bank.resample_to(12, 12, dtype=D64, radiometry=radiometry)
    g = torch.Generator().manual_seed(seed)
    x, y = torch.rand(2, 12, 12, generator=g, dtype=D64), torch.rand(2, 12, 12, generator=g, dtype=D64)
    for op in (psf_exact, psf_distortion, lambda v, r: psf_fast(v, r, tol=0.1, zone=2)):
        assert torch.allclose(op(a * x + b * y, rb), a * op(x, rb) + b * op(y, rb), atol=1e-12)


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_adjointness_and_gradcheck(radiometry):
    bank = synthetic_bank(uniform=False, identity=False, K=5)
    rb = bank.resample_to(8, 8, dtype=D64, radiometry=radiometry)
    x = torch.rand(1, 2, 8, 8, dtype=D64, requires_grad=True)
    y = torch.rand(1, 2, 8, 8, dtype=D64)
    for op in (psf_reference, psf_exact, psf_distortion, lambda a, r: psf_fast(a, r, tol=0.05, zone=2)):
        out = op(x, rb)
        (g,) = torch.autograd.grad((out * y).sum(), x)
        assert (out * y).sum().item() == pytest.approx((x * g).sum().item(), rel=1e-12)
        assert torch.autograd.gradcheck(lambda a: op(a, rb), (x,))


@pytest.mark.parametrize("rule", [0, 10 ** 9])
def test_gradcheck_both_branches(monkeypatch, rule):
    """Exact and fast (ranks > 1) pass gradcheck on the Cardboard bank with boxes moved by slices and by tables."""
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", rule)
    rb = PSFBank.default().resample_to(6, 6, dtype=D64, radiometry="radiance")
    x = torch.rand(1, 3, 6, 6, dtype=D64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: psf_exact(a, rb), (x,))
    assert torch.autograd.gradcheck(lambda a: psf_fast(a, rb, tol=0.0, zone=3), (x,))


# ----------------------------------------------------------------------------- black-pixel skipping
def _sparse_images(S=12):
    """Images that black-pixel skipping must treat exactly like dense ones.

    ``a``: batch of 2; a block of exactly 1.0 in every channel of both items (40 % of the pixels),
    item 1 adds random pixels lit in channel 0 only and a lone pixel lit in channel 2 only.
    ``b``: channel 1 black everywhere, a few pixels in channels 0 and 2.
    ``c``: one lone pixel of value 1 in one channel."""
    g = torch.Generator().manual_seed(11)
    a = torch.zeros(2, 3, S, S, dtype=D64)
    a[:, :, 2:8, 1:9] = 1.0                                                     # 48 of 144 pixels, = 1 exactly
    a[1, 0, 9:11, 2:10] = torch.rand(2, 8, dtype=D64, generator=g) + 0.5          # channel 0 of item 1 only
    a[1, 2, 10, 11] = 0.7                                                         # a lone pixel, channel 2 of item 1
    b = torch.zeros(1, 3, S, S, dtype=D64)
    b[0, 0, 3:6, 3:6] = torch.rand(3, 3, dtype=D64, generator=g) + 0.5
    b[0, 2, 8, 9] = 1.0
    c = torch.zeros(1, 3, S, S, dtype=D64)
    c[0, 1, 9, 3] = 1.0
    return a, b, c


@pytest.mark.parametrize(("radiometry", "table_area"), [("radiance", None), ("radiance", 0), ("energy", None)])
def test_black_pixel_skipping_is_exact_for_awkward_sparse_images(monkeypatch, radiometry, table_area):
    """Module docstring: pixels black in every channel are skipped when no gradient is needed. The
    result must equal the dense path (an input that requires a gradient: nothing is skipped) for
    every operator, with lit values of exactly 1, pixels lit in one channel or one batch item only,
    a black channel, and a lone lit pixel; radiance both with index tables and with box slices; and on
    the Cardboard bank, a block on black through the fast operator."""
    if table_area is not None:  # the table / slice rule is the radiance operator's
        monkeypatch.setattr(operators, "_TABLE_MAX_AREA", table_area)  # every bucket by slices
    rb = random_bank(G=4, pitch_mm=2.0, pincushion=0.1).resample_to(12, 12, dtype=D64, radiometry=radiometry)
    cases = [(x, name, op, rb) for x in _sparse_images() for name, op in ALL_OPS.items()]
    block = torch.zeros(1, 3, 32, 32, dtype=D64)
    block[..., 10:14, 5:9] = 1.0
    cardboard = PSFBank.default().resample_to(32, 32, dtype=D64, radiometry=radiometry)
    cases.append((block, "fast on the Cardboard bank", lambda x, r: psf_fast(x, r, tol=0.05), cardboard))
    for x, name, op, r in cases:
        with torch.no_grad():
            skipped = op(x, r)
        dense = op(x.clone().requires_grad_(True), r).detach()
        assert dense.abs().sum() > 0.1, name
        assert torch.allclose(skipped, dense, atol=1e-12, rtol=0), (name, (skipped - dense).abs().max())


def test_a_lone_pixel_is_not_skipped_where_it_is_a_groups_only_tap():
    """Distortion-free lens, one lit pixel between field samples: in the energy operator's per-field
    groups it is the one active tap of several groups. Skipping black pixels (no gradient) must keep
    those groups: the result equals the dense path and carries the pixel's light (energy form: the
    PSFs sum to 1, held as float32, and nothing leaves the 12 x 12 image from its centre)."""
    rb = random_bank(G=4, pitch_mm=2.0).resample_to(12, 12, dtype=D64, radiometry="energy")
    x = torch.zeros(1, 3, 12, 12, dtype=D64)
    x[0, 1, 5, 6] = 1.0
    with torch.no_grad():
        skipped = psf_exact(x, rb)
    dense = psf_exact(x.clone().requires_grad_(True), rb).detach()
    assert dense[0, 1].sum().item() == pytest.approx(1.0, abs=1e-6)          # PSFs held as float32
    assert torch.allclose(skipped, dense, atol=1e-12, rtol=0)


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_gradient_at_a_sparse_image_is_the_dense_one(radiometry):
    """Every operator is linear: d<A x, w>/dx = A^T w whatever x. Pixels that are zero may be skipped
    only without a gradient; with one, the gradient at a mostly black image equals the one at a
    dense image (where nothing is skipped), and the skipping forward is exact."""
    rb = random_bank(G=4, pitch_mm=2.0, chief=lambda d: d * (1 + 0.1 * d * d)).resample_to(12, 12, dtype=D64,
                                                                                          radiometry=radiometry)
    w = torch.rand(3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(5))
    sparse = torch.zeros(3, 12, 12, dtype=D64)
    sparse[:, 3:5, 6:8] = 1.0
    dense = torch.rand(3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(6)) + 0.5
    for op in ALL_OPS.values():
        grads = []
        for x in (sparse, dense):
            xr = x.clone().requires_grad_(True)
            (g,) = torch.autograd.grad((op(xr, rb) * w).sum(), xr)
            grads.append(g)
        assert grads[0].abs().sum() > 1 and torch.allclose(grads[0], grads[1], atol=1e-12)
        with torch.no_grad():
            assert torch.allclose(op(sparse, rb), op(sparse.clone().requires_grad_(True), rb), atol=1e-12)


# ----------------------------------------------------------------------------- the Cardboard lens
@pytest.mark.parametrize("mode", list(OPS))
def test_flat_field_of_the_cardboard_lens_is_uniform_in_every_mode(mode):
    """Radiance (default): a flat white display is seen flat, up to the pupil transmission (the
    vignetting model: the pupil area on the primary branch; 1 except in the outermost field
    samples of the Cardboard bank, >= 0.98 there, where the lens rim folds part of the pupil
    into the second image), for a square image and a 16:9 one. The paper's energy form dims it by the
    area magnification (~0.8 at mid-edge, ~0.6 towards the corner)."""
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
    wide = psf_optics(torch.ones(1, 3, 27, 48, dtype=D64), bank, mode)
    assert (_inner(wide) - 1).abs().max() < 1e-3


def test_light_is_conserved_where_none_leaves():
    """Energy form: every display pixel's light is kept. Radiance form: each pixel's light is
    multiplied by its area magnification (its image is that much larger at the same radiance)."""
    bank = PSFBank.default()
    x = torch.zeros(3, 64, 64, dtype=D64)
    x[:, 20:44, 20:44] = torch.rand(3, 24, 24, dtype=D64)
    rb = bank.resample_to(64, 64, dtype=D64, radiometry="energy")
    for op in (psf_exact, psf_distortion):
        out = op(x, rb)
        assert ((out.sum((-1, -2)) - x.sum((-1, -2))).abs() / x.sum((-1, -2))).max() < 1e-5
    rb = bank.resample_to(64, 64, dtype=D64)
    want = (x.reshape(3, -1) * rb.area).sum(-1)
    assert torch.allclose(psf_distortion(x, rb).sum((-1, -2)), want, rtol=1e-12, atol=0)


def test_a_point_source_lands_on_its_chief_ray_with_the_bank_psf():
    """A single off-axis display pixel. Energy form: unit light, centroid at the chief ray plus the blended
    bank PSF's own centroid (continuous, from the stored samples) to 0.02 px; lateral colour puts blue
    (486 nm) further out than red. Radiance form: its light is its area magnification (radiance over a
    larger image), centred where the energy form's is (within 0.05 px: the blend is taken where the light
    arrives, so it varies a little across the PSF)."""
    bank = PSFBank.default()
    S = 48
    rb = bank.resample_to(S, S, dtype=D64, radiometry="energy")
    iy, ix = 30, 17
    x = torch.zeros(3, S, S, dtype=D64)
    x[:, iy, ix] = 1
    energy = psf_exact(x, rb)
    yy, xx = torch.meshgrid(torch.arange(S, dtype=D64) + 0.5, torch.arange(S, dtype=D64) + 0.5, indexing="ij")
    u, v = (2 * ix + 1) / S - 1, (2 * iy + 1) / S - 1
    chief = rb._chief_at(torch.tensor([u], dtype=D64), torch.tensor([v], dtype=D64))[:, 0]   # [L, 2]
    K = bank.psf.shape[-1]
    t = torch.arange(K, dtype=D64) - K // 2
    w, idx = rb.field_weight[:, iy * S + ix], rb.field_index[:, iy * S + ix]
    for li in range(3):
        o = energy[li]
        assert o.sum().item() == pytest.approx(1.0, abs=1e-6)
        ps = bank.psf[li].reshape(-1, K, K).double()[idx]
        pitch = bank.psf_pitch_mm[li].reshape(-1).double()[idx] / (24 / S)
        ox = (w * (ps.sum(1) * t).sum(-1) * pitch).sum().item()
        oy = (w * (ps.sum(2) * t).sum(-1) * pitch).sum().item()
        assert (o * xx).sum().item() == pytest.approx((chief[li, 0].item() + 1) * S / 2 + ox, abs=0.02)
        assert (o * yy).sum().item() == pytest.approx((chief[li, 1].item() + 1) * S / 2 + oy, abs=0.02)
    assert abs(chief[2, 0]) > abs(chief[0, 0])
    rr = bank.resample_to(S, S, dtype=D64)
    radiance = psf_exact(x, rr)
    assert torch.allclose(radiance.sum((-1, -2)), rr.area[:, iy * S + ix], rtol=2e-3)
    for li in range(3):
        for grid in (xx, yy):
            c = (radiance[li] * grid).sum() / radiance[li].sum()
            assert abs(c - (energy[li] * grid).sum() / energy[li].sum()).item() < 0.05


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
    bank = _gaussian_bank(G=G, K=K, S=S)
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


def _flat_field_d2(rb):
    o = psf_exact(torch.ones(2, rb.H, rb.W, dtype=D64), rb)[:, 8:-8, 8:-8]
    return max((o[:, :, 2:] - 2 * o[:, :, 1:-1] + o[:, :, :-2]).abs().max().item(),
               (o[:, 2:] - 2 * o[:, 1:-1] + o[:, :-2]).abs().max().item())


def test_no_seams_in_a_flat_field_of_the_energy_form():
    """Energy form (the paper's scatter). Gaussian PSFs widening from 0.6 to 2 px across a 6 x 6
    field grid, on a flat field: no step at field-cell borders. The remaining smooth curvature (1/2
    laplacian of the PSF variance, a property of any shift-variant scatter) stays < 3e-3, while blending
    with the nearest field instead (patch-wise PSFs) makes steps of ~0.17."""
    G, K, S = 6, 15, 96
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    sig = 0.6 + 0.7 * (fx ** 2 + fy ** 2)
    t = torch.arange(K, dtype=D64) - K // 2
    g = torch.exp(-0.5 * (t[:, None] ** 2 + t[None, :] ** 2) / sig[..., None, None] ** 2)
    bank = synthetic_bank(K=K, G=G, pitch_px=1.0, width_px=S)
    bank.psf = (g / g.sum((-1, -2), keepdim=True)).expand(2, G, G, K, K).clone()
    bank.validate()
    rb = bank.resample_to(S, S, dtype=D64, radiometry="energy")
    assert _flat_field_d2(rb) < 3e-3
    rb.field_weight = (rb.field_weight == rb.field_weight.max(0, keepdim=True).values).double()
    rb._zones.clear()
    assert _flat_field_d2(rb) > 0.05


# ----------------------------------------------------------------------------- refusals
def test_operators_refuse_primaries_that_do_not_fit_the_bank():
    """Integer primaries are refused by the dtype check (naming the allowed dtypes), float64 primaries on a
    float32 bank and a channel count other than the bank's by name, for every operator."""
    rb, rb64 = _rb8(), random_bank().resample_to(8, 8, dtype=D64)
    for op in (psf_exact, psf_distortion, psf_reference, psf_fast):
        with pytest.raises(InputValueError, match="primaries.*float32.*bank.*float64"):
            op(torch.zeros(3, 8, 8), rb64)
        with pytest.raises(InputValueError, match=r"primaries.*\['torch.float32', 'torch.float64'\].*int64"):
            op(torch.zeros(3, 8, 8, dtype=torch.int64), rb)
        with pytest.raises(InputValueError, match="primaries.*float64.*bank.*float32"):
            op(torch.zeros(3, 8, 8, dtype=D64), rb)
        with pytest.raises(ShapeError, match="primaries must have size 3 in dim -3"):
            op(torch.zeros(2, 8, 8), rb)                                          # 2 channels, bank has 3


@pytest.mark.parametrize("kw, match", [
    *[(dict(tol=t), r"tol must be in \[0, 1\)") for t in (-0.01, 1.0, float("nan"), "0.1")],
    *[(dict(zone=z), "zone must be an int >= 1") for z in (0, -2, 2.0)],
])
def test_psf_fast_refuses_bad_knobs(kw, match):
    with pytest.raises(InputValueError, match=match):
        psf_fast(torch.zeros(3, 8, 8), _rb8(), **kw)
