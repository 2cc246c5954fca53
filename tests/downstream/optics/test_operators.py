"""Tests of ``controlgs_adapter.downstream.optics.operators``."""

from __future__ import annotations

import functools

import pytest
import torch
import torch.nn.functional as F
from helpers.banks import D64, synthetic_bank, tiny_bank
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.optics import operators
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast, psf_reference
from controlgs_adapter.errors import InputValueError, ShapeError


def test_resample_to_names_the_device_as_tensors_report_it():
    """A device given with an index ("cpu:0"; on a GPU "cuda" vs "cuda:0") is the tensors' device: the
    bank is the cached one and applies to images on it (it was refused as another device)."""
    from controlgs_adapter.downstream.optics.operators import psf_exact

    bank = tiny_bank()
    rb = bank.resample_to(12, 12, device="cpu:0", dtype=torch.float64)
    assert rb is bank.resample_to(12, 12, device="cpu", dtype=torch.float64)
    x = torch.rand(bank.num_wavelengths, 12, 12, dtype=torch.float64)
    torch.testing.assert_close(psf_exact(x, rb), psf_exact(x, bank.resample_to(12, 12, dtype=torch.float64)))


D64_2 = torch.float64


OPS = {"distortion": psf_distortion, "exact": psf_exact, "fast": lambda x, rb: psf_fast(x, rb, tol=0.05, zone=5)}


def _bank(G=5, K=9, L=2, S=32, magnification=None, pincushion=0.0, transmission=None, seed=0):
    """Synthetic bank on a 24 mm display: Gaussian PSFs widening and shifting off-centre across the
    field (so they differ field to field), chief rays ``d * (s + k |d|^2)``."""
    f = -1 + (2 * torch.arange(G, dtype=D64_2) + 1) / G
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    t = torch.arange(K, dtype=D64_2) - K // 2
    sig = 0.5 + 0.8 * (fx ** 2 + fy ** 2)
    off = 0.6 * fx                                                            # coma-like shift (px)
    g = torch.exp(-0.5 * (((t[None, :] - off[..., None, None]) ** 2 + t[:, None] ** 2) / sig[..., None, None] ** 2))
    psf = (g / g.sum((-1, -2), keepdim=True)).expand(L, G, G, K, K).clone()
    c = torch.linspace(-1, 1, 17, dtype=D64_2)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    s = (magnification or 1.0) + pincushion * (cx ** 2 + cy ** 2)
    chief = torch.stack([cx * s, cy * s], -1).expand(L, 17, 17, 2).clone()
    meta = {} if transmission is None else {"transmission": transmission.expand(L, G, G).tolist()}
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), 24 / S, dtype=D64_2), field_x=f, field_y=f, chief=chief,
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


def test_pure_magnification_gives_a_uniform_flat_field_analytically():
    """Chief rays ``1.1 d``: every display pixel's image is 1.21 output pixels. Radiance: the
    covered frame is exactly 1; energy: exactly 1 / 1.21 (both where the footprints cover whole
    output pixels, i.e. away from the border; to the float32 storage of the bank)."""
    S = 40
    bank = _bank(S=S, magnification=1.1)
    x = torch.ones(2, S, S, dtype=D64_2)
    for radiometry, want in (("radiance", 1.0), ("energy", 1 / 1.21)):
        rb = bank.resample_to(S, S, dtype=D64_2, radiometry=radiometry)
        assert torch.allclose(rb.area, torch.full_like(rb.area, 1.21), atol=1e-6)
        assert (_inner(psf_distortion(x, rb), 0.8) - want).abs().max() < 1e-6
        if radiometry == "radiance":                                          # PSFs stored as float32 sums
            for mode in ("exact", "fast"):
                assert (_inner(OPS[mode](x, rb), 0.5) - want).abs().max() < 1e-7


def test_vignetting_is_the_traced_transmission_blended_where_the_light_arrives():
    """A distortion-free bank with transmission falling towards the edge: a flat field equals the
    bilinear interpolation of the transmission at the output pixel centres (computed here by hand)."""
    G, S = 5, 30
    f = -1 + (2 * torch.arange(G, dtype=D64_2) + 1) / G
    T = 1 - 0.2 * (f[:, None] ** 2 + f[None, :] ** 2)
    bank = _bank(G=G, S=S, transmission=T)
    u = (2 * torch.arange(S, dtype=D64_2) + 1) / S - 1
    pos = ((u + 1) / 2 * G - 0.5).clamp(0, G - 1)                             # field-grid coordinate
    i0 = pos.floor().clamp(max=G - 2).long()
    a = pos - i0
    Ty = T[i0] * (1 - a)[:, None] + T[i0 + 1] * a[:, None]                    # rows interpolated
    want = Ty[:, i0] * (1 - a) + Ty[:, i0 + 1] * a
    rb = bank.resample_to(S, S, dtype=D64_2)
    x = torch.ones(2, S, S, dtype=D64_2)
    assert torch.allclose(psf_distortion(x, rb), want.expand(2, S, S), atol=1e-12)
    for mode in ("exact", "fast"):
        assert (_inner(OPS[mode](x, rb), 0.6) - want[6:-6, 6:-6]).abs().max() < 1e-7
    assert torch.allclose(psf_distortion(x, bank.resample_to(S, S, dtype=D64_2, radiometry="energy")), x)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_distortion_free_bank_is_a_blend_of_convolutions(radiometry):
    """Identity chief rays and PSFs varying across the field: radiance is each field PSF's
    convolution (conv2d) blended with the bilinear weights of the output pixel; energy is the
    convolution of each field's weighted image (the weights of the source pixel)."""
    G, K, S = 4, 7, 24
    bank = _bank(G=G, K=K, S=S)
    rb = bank.resample_to(S, S, dtype=D64_2, radiometry=radiometry)
    x = torch.rand(2, S, S, dtype=D64_2, generator=torch.Generator().manual_seed(3))
    u = (2 * torch.arange(S, dtype=D64_2) + 1) / S - 1
    pos = ((u + 1) / 2 * G - 0.5).clamp(0, G - 1)
    i0 = pos.floor().clamp(max=G - 2).long()
    a = pos - i0
    w1 = torch.zeros(G, S, dtype=D64_2)                                          # 1-D hat weights [field, pixel]
    w1[i0, torch.arange(S)] += 1 - a
    w1[i0 + 1, torch.arange(S)] += a
    want = torch.zeros(2, S, S, dtype=D64_2)
    for fy in range(G):
        for fx in range(G):
            w = w1[fy][:, None] * w1[fx][None, :]
            k = bank.psf[:, fy, fx].double().flip(-1, -2)[:, None]             # conv2d correlates
            src = x * w if radiometry == "energy" else x
            conv = F.conv2d(F.pad(src[None], (K // 2,) * 4), k, groups=2)[0]
            want += conv if radiometry == "energy" else conv * w
    for op in (psf_exact, psf_reference, lambda v, r: psf_fast(v, r, tol=0.0, zone=2)):
        assert torch.allclose(op(x, rb), want, atol=1e-12)


def test_a_ramp_through_field_varying_psfs_has_no_seams():
    """No distortion (so no box-pixel resampling), PSFs widening from 0.5 to 2 px and shifting by up
    to 1.5 px quadratically across a 6 x 6 field grid, a horizontal ramp: the radiance form's
    output has no step beyond the trend above 1e-4 (its blend is continuous, with kinks only);
    the energy form's scatter steps by ~4e-3 on the sample lines."""
    G, K, S = 6, 15, 96
    bank = _bank(G=G, K=K, S=S)
    f = -1 + (2 * torch.arange(G, dtype=D64_2) + 1) / G
    fy, fx = torch.meshgrid(f, f, indexing="ij")
    t = torch.arange(K, dtype=D64_2) - K // 2
    sig, off = 0.5 + 1.5 * (fx ** 2 + fy ** 2), 1.5 * fx ** 2 * torch.sign(fx)
    g = torch.exp(-0.5 * (((t[None, :] - off[..., None, None]) ** 2 + t[:, None] ** 2) / sig[..., None, None] ** 2))
    bank.psf = (g / g.sum((-1, -2), keepdim=True)).expand(2, G, G, K, K).clone()
    bank.validate()
    x = torch.linspace(0.1, 0.9, S, dtype=D64_2).expand(2, S, S).clone()
    rb = bank.resample_to(S, S, dtype=D64_2)
    assert _steps(_inner(psf_exact(x, rb), 0.7)) < 1e-4
    assert _steps(_inner(psf_fast(x, rb, tol=0.02, zone=3), 0.7)) < 1e-4
    assert _steps(_inner(psf_exact(x, bank.resample_to(S, S, dtype=D64_2, radiometry="energy")), 0.7)) > 1e-3


def test_fast_mode_converges_to_the_radiance_exact_operator_and_keeps_flat_fields():
    bank = PSFBank.default()
    rb = bank.resample_to(48, 48, dtype=D64_2)
    g = torch.Generator().manual_seed(0)
    x = F.avg_pool2d(torch.rand(3, 96, 96, generator=g, dtype=D64_2)[None], 2)[0]
    ref = psf_exact(x, rb)
    errs = [((psf_fast(x, rb, tol=t, zone=5) - ref).norm() / ref.norm()).item() for t in (0.3, 0.1, 0.03, 0.0)]
    assert errs[0] > errs[1] > errs[2] and errs[3] < 1e-9
    flat = psf_fast(torch.ones(3, 48, 48, dtype=D64_2), rb, tol=0.3, zone=6)
    assert (flat - rb.vignetting.reshape(3, 48, 48))[:, 4:-4, 4:-4].abs().max() < 1e-6   # kernel sums kept


D64_3 = torch.float64


def _padded_means(buckets):
    return [sum((bh + 2 * mz) * (bw + 2 * mz) for _, _, bh, bw, mz in bk.boxes) / len(bk.boxes)
            for bks in buckets for bk in bks]


@pytest.fixture(scope="module")
def rb():
    return PSFBank.default().resample_to(24, 24, dtype=D64_3, radiometry="radiance")


@pytest.mark.parametrize("rule", ["slices", "mixed", "tables"])
@pytest.mark.parametrize("op", ["exact", "fast"])
def test_tables_and_slices_match_the_reference(rb, monkeypatch, rule, op):
    buckets = rb.zones(1, 0.0) if op == "exact" else rb.zones(2, 0.0)   # fast at tol 0: exact, ranks 1..4
    means = sorted(_padded_means(buckets))
    assert means[0] < means[-1]                                  # a threshold between them splits the buckets
    thr = {"slices": 0, "mixed": means[len(means) // 2], "tables": means[-1]}[rule]
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", thr)
    used = {operators._use_tables(bk) for bks in buckets for bk in bks}
    assert used == {"slices": {False}, "mixed": {False, True}, "tables": {True}}[rule]

    run = (lambda a: psf_exact(a, rb)) if op == "exact" else (lambda a: psf_fast(a, rb, tol=0.0, zone=2))
    x = torch.rand(2, 3, 24, 24, dtype=D64_3, requires_grad=True)
    w = torch.rand(2, 3, 24, 24, dtype=D64_3)
    out = run(x)
    (g,) = torch.autograd.grad((out * w).sum(), x)
    ref = psf_reference(x, rb)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    tol = 1e-12 if op == "exact" else 1e-9     # fast: its eigen-split drops singular values at rounding level (4e-10 here)
    assert torch.allclose(out, ref, atol=tol, rtol=0)
    assert torch.allclose(g, g_ref, atol=tol, rtol=0)


@pytest.mark.parametrize("rule", [0, 10 ** 9])
def test_gradcheck_both_branches(monkeypatch, rule):
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", rule)
    rb = PSFBank.default().resample_to(6, 6, dtype=D64_3, radiometry="radiance")
    x = torch.rand(1, 3, 6, 6, dtype=D64_3, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: psf_exact(a, rb), (x,))
    assert torch.autograd.gradcheck(lambda a: psf_fast(a, rb, tol=0.0, zone=3), (x,))   # ranks > 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: the CUDA table rule not run")
def test_cuda_uses_tables_for_every_bucket_and_matches_the_cpu_reference(monkeypatch):
    """On CUDA every bucket moves its boxes through index tables (a Python step per box is ~10 kernel
    launches there), even where the CPU rule picks slices; outputs and gradients equal the float64
    per-pixel reference computed on the CPU."""
    monkeypatch.setattr(operators, "_TABLE_MAX_AREA", 0)            # the CPU rule: slices for every bucket
    bank = PSFBank.default()
    cpu = bank.resample_to(24, 24, dtype=D64_3, radiometry="radiance")
    x = torch.rand(2, 3, 24, 24, dtype=D64_3, requires_grad=True)
    xg = x.detach().cuda().requires_grad_(True)
    gpu = bank.resample_to(24, 24, device=xg.device, dtype=D64_3, radiometry="radiance")   # cuda:0, as the stage does
    assert {operators._use_tables(bk) for bks in cpu.zones(1, 0.0) for bk in bks} == {False}
    assert {operators._use_tables(bk) for bks in gpu.zones(1, 0.0) for bk in bks} == {True}
    w = torch.rand(2, 3, 24, 24, dtype=D64_3)
    out = psf_exact(xg, gpu)
    (g,) = torch.autograd.grad((out * w.cuda()).sum(), xg)
    ref = psf_reference(x, cpu)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), x)
    assert torch.allclose(out.cpu(), ref, atol=1e-12, rtol=0)
    assert torch.allclose(g.cpu(), g_ref, atol=1e-12, rtol=0)


@pytest.fixture(scope="module")
def cardboard():
    return PSFBank.default()


RADIOMETRIES = ("radiance", "energy")


def _flat_field_d2(rb):  # energy form: the paper's scatter of bilinearly blended PSFs
    o = psf_exact(torch.ones(2, rb.H, rb.W, dtype=D64), rb)[:, 8:-8, 8:-8]
    return max((o[:, :, 2:] - 2 * o[:, :, 1:-1] + o[:, :, :-2]).abs().max().item(),
               (o[:, 2:] - 2 * o[:, 1:-1] + o[:, :-2]).abs().max().item())


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_uniform_psf_field_is_a_single_convolution(radiometry):
    bank = synthetic_bank()
    rb = bank.resample_to(16, 16, dtype=D64, radiometry=radiometry)
    x = torch.rand(3, 2, 16, 16, dtype=D64)
    k = bank.psf[0, 0, 0].double()
    ref = F.conv2d(F.pad(x.reshape(-1, 1, 16, 16), (3, 3, 3, 3)), k.flip(0, 1)[None, None]).reshape(3, 2, 16, 16)
    for op in (psf_exact, psf_reference, lambda a, r: psf_fast(a, r, tol=0.5, zone=4)):
        assert (op(x, rb) - ref).abs().max() < 1e-6


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_exact_equals_brute_force_splat_on_the_cardboard_bank(cardboard, radiometry):
    rb = cardboard.resample_to(24, 24, dtype=D64, radiometry=radiometry)
    x = torch.rand(3, 24, 24, dtype=D64)
    assert torch.allclose(psf_exact(x, rb), psf_reference(x, rb), atol=1e-12, rtol=0)


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
    small = torch.rand(1, 2, 8, 8, dtype=D64, requires_grad=True)
    for op in (psf_reference, psf_exact, psf_distortion, lambda a, r: psf_fast(a, r, tol=0.05, zone=2)):
        assert torch.autograd.gradcheck(lambda a: op(a, rb), (small,))


@settings(max_examples=10, deadline=None)
@given(a=st.floats(-3, 3), b=st.floats(-3, 3), seed=st.integers(0, 100), radiometry=st.sampled_from(RADIOMETRIES))
def test_linearity(a, b, seed, radiometry):
    bank = synthetic_bank(uniform=False, identity=False, seed=seed % 3)
    rb = bank.resample_to(12, 12, dtype=D64, radiometry=radiometry)
    g = torch.Generator().manual_seed(seed)
    x, y = torch.rand(2, 12, 12, generator=g, dtype=D64), torch.rand(2, 12, 12, generator=g, dtype=D64)
    for op in (psf_exact, psf_distortion, lambda v, r: psf_fast(v, r, tol=0.1, zone=2)):
        assert torch.allclose(op(a * x + b * y, rb), a * op(x, rb) + b * op(y, rb), atol=1e-12)


def test_light_is_conserved_where_none_leaves(cardboard):
    """Energy form: every display pixel's light is kept. Radiance form: each pixel's light is
    multiplied by its area magnification (its image is that much larger at the same radiance)."""
    x = torch.zeros(3, 64, 64, dtype=D64)
    x[:, 20:44, 20:44] = torch.rand(3, 24, 24, dtype=D64)
    rb = cardboard.resample_to(64, 64, dtype=D64, radiometry="energy")
    for op in (psf_exact, psf_distortion):
        out = op(x, rb)
        assert ((out.sum((-1, -2)) - x.sum((-1, -2))).abs() / x.sum((-1, -2))).max() < 1e-5
    rb = cardboard.resample_to(64, 64, dtype=D64)
    want = (x.reshape(3, -1) * rb.area).sum(-1)
    assert torch.allclose(psf_distortion(x, rb).sum((-1, -2)), want, rtol=1e-12, atol=0)


def test_no_seams_in_a_flat_field():
    """Energy form (the paper's scatter). Gaussian PSFs widening from 0.6 to 2 px across a 6 x 6
    field grid, on a flat field: no step at field-cell borders. The remaining smooth curvature (1/2 laplacian of the PSF variance, a
    property of any shift-variant scatter) stays < 3e-3, while blending with the nearest field
    instead (patch-wise PSFs, DeepLens-style) makes steps of ~0.17."""
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


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_fast_operator_converges_to_exact(cardboard, radiometry):
    rb = cardboard.resample_to(48, 48, dtype=D64, radiometry=radiometry)
    g = torch.Generator().manual_seed(1)
    x = F.avg_pool2d(torch.rand(3, 96, 96, generator=g, dtype=D64)[None], 2)[0]
    ref = psf_exact(x, rb)
    errs = [((psf_fast(x, rb, tol=t, zone=6) - ref).norm() / ref.norm()).item() for t in (0.3, 0.1, 0.03, 0.0)]
    assert errs[0] > errs[1] > errs[2] and errs[2] < 0.01 and errs[3] < 1e-8
    assert ((psf_distortion(x, rb) - ref).norm() / ref.norm()).item() > errs[2]


@pytest.mark.parametrize("radiometry", RADIOMETRIES)
def test_empty_regions_are_skipped_without_changing_the_result(cardboard, radiometry):
    rb = cardboard.resample_to(32, 32, dtype=D64, radiometry=radiometry)
    x = torch.zeros(1, 3, 32, 32, dtype=D64)
    x[..., 10:14, 5:9] = 1.0
    with torch.no_grad():
        skipped = psf_fast(x, rb, tol=0.05)
    dense = psf_fast(x.clone().requires_grad_(True), rb, tol=0.05).detach()
    assert torch.allclose(skipped, dense, atol=1e-12)


D64_4 = torch.float64


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_exact_and_fast_on_a_wide_image_equal_the_reference(cardboard, radiometry):
    rb = cardboard.resample_to(18, 32, dtype=D64_4, radiometry=radiometry)
    x = torch.rand(2, 3, 18, 32, dtype=D64_4, generator=torch.Generator().manual_seed(1))
    ref = psf_reference(x, rb)
    assert torch.allclose(psf_exact(x, rb), ref, atol=1e-12, rtol=0)
    # one field per group: exact at any tol (the one-field eigen-PSF is the field's kernel itself)
    assert torch.allclose(psf_fast(x, rb, tol=0.3, zone=1), ref, atol=1e-12, rtol=0)
    # several fields per group at tol 0: the full eigen-expansion (eigh of K K^T: to 1e-9, as in
    # test_fast_operator_converges_to_exact)
    assert ((psf_fast(x, rb, tol=0.0, zone=3) - ref).norm() / ref.norm()) < 1e-9


D64_5 = torch.float64


def _uniform_identity_bank(S: int, K: int = 7, G: int = 4) -> PSFBank:
    """One random PSF everywhere, identity chief rays, one PSF sample per display pixel."""
    g = torch.Generator().manual_seed(3)
    psf = (torch.rand(1, 1, 1, K, K, generator=g, dtype=D64_5) ** 3).expand(1, G, G, K, K).clone()
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64_5)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64_5) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((1, G, G), 24.0 / S, dtype=D64_5), field_x=f, field_y=f,
                   chief=torch.stack([cx, cy], -1)[None].clone(), chief_x=c, chief_y=c, wavelengths_nm=(550.0,),
                   display_mm=(24.0, 24.0))


@pytest.mark.parametrize("iy, ix", [(3, 3), (3, 12), (16, 16)])
def test_a_lone_lit_pixel_images_to_the_bank_psf_in_the_energy_form(iy, ix):
    # a point source on black (the case the zero-pixel skip is for): under identity chief rays and one
    # PSF everywhere, its image is that PSF centred on the pixel. (3, 3) lies before the first field
    # sample (its blend has one field and its footprint one tap); the others blend 2 and 4 fields.
    S, K = 32, 7
    bank = _uniform_identity_bank(S, K)
    rb = bank.resample_to(S, S, dtype=D64_5, radiometry="energy")
    x = torch.zeros(1, S, S, dtype=D64_5)
    x[0, iy, ix] = 2.5
    want = torch.zeros(S, S, dtype=D64_5)
    want[iy - K // 2:iy + K // 2 + 1, ix - K // 2:ix + K // 2 + 1] = 2.5 * bank.psf[0, 0, 0].double()
    for out in (psf_exact(x, rb), psf_fast(x, rb, tol=0.0, zone=2)):
        assert out[0].sum().item() == pytest.approx(2.5, abs=1e-6)   # the energy form keeps the light (float32 PSF)
        assert torch.allclose(out[0], want, atol=1e-13, rtol=0)


D64_6 = torch.float64


def _bank_2(L=3, G=4, K=5, pitch_mm=2.0, seed=0, pincushion=0.1):
    """Random PSFs on a ``G x G`` field grid, a mild pincushion chief-ray map, a 24 mm display."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64_6, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64_6)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    s = 1 + pincushion * (cx ** 2 + cy ** 2)
    ch = torch.stack([cx * s, cy * s], -1).expand(L, 9, 9, 2).clone()
    f = -1 + (2 * torch.arange(G, dtype=D64_6) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64_6), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


def _sparse_images(S=12):
    """Images that black-pixel skipping must treat exactly like dense ones.

    ``a``: batch of 2; a block of exactly 1.0 in every channel of both items (40 % of the pixels),
    item 1 adds random pixels lit in channel 0 only and a lone pixel lit in channel 2 only.
    ``b``: channel 1 black everywhere, a few pixels in channels 0 and 2.
    ``c``: one lone pixel of value 1 in one channel."""
    g = torch.Generator().manual_seed(11)
    a = torch.zeros(2, 3, S, S, dtype=D64_6)
    a[:, :, 2:8, 1:9] = 1.0                                                     # 48 of 144 pixels, = 1 exactly
    a[1, 0, 9:11, 2:10] = torch.rand(2, 8, dtype=D64_6, generator=g) + 0.5          # channel 0 of item 1 only
    a[1, 2, 10, 11] = 0.7                                                         # a lone pixel, channel 2 of item 1
    b = torch.zeros(1, 3, S, S, dtype=D64_6)
    b[0, 0, 3:6, 3:6] = torch.rand(3, 3, dtype=D64_6, generator=g) + 0.5
    b[0, 2, 8, 9] = 1.0
    c = torch.zeros(1, 3, S, S, dtype=D64_6)
    c[0, 1, 9, 3] = 1.0
    return a, b, c


_OPS = {"distortion": psf_distortion, "exact": psf_exact, "reference": psf_reference,
        "fast": lambda x, rb: psf_fast(x, rb, 0.05, 2)}


@pytest.mark.parametrize(("radiometry", "table_area"), [("radiance", None), ("radiance", 0), ("energy", None)])
def test_black_pixel_skipping_is_exact_for_awkward_sparse_images(monkeypatch, radiometry, table_area):
    """Module docstring: pixels black in every channel are skipped when no gradient is needed. The
    result must equal the dense path (an input that requires a gradient: nothing is skipped) for
    every operator, with lit values of exactly 1, pixels lit in one channel or one batch item only,
    a black channel, and a lone lit pixel; radiance both with index tables and with box slices."""
    if table_area is not None:  # the table / slice rule is the radiance operator's
        monkeypatch.setattr(operators, "_TABLE_MAX_AREA", table_area)  # every bucket by slices
    rb = _bank_2().resample_to(12, 12, dtype=D64_6, radiometry=radiometry)
    for x in _sparse_images():
        for name, op in _OPS.items():
            with torch.no_grad():
                skipped = op(x, rb)
            dense = op(x.clone().requires_grad_(True), rb).detach()
            assert dense.abs().sum() > 0.1, name
            assert torch.allclose(skipped, dense, atol=1e-12, rtol=0), (name, (skipped - dense).abs().max())


def test_a_lone_pixel_is_not_skipped_where_it_is_a_groups_only_tap():
    """Distortion-free lens, one lit pixel between field samples: in the energy operator's per-field
    groups it is the one active tap of several groups. Skipping black pixels (no gradient) must keep
    those groups: the result equals the dense path and carries the pixel's light (energy form: the
    PSFs sum to 1, held as float32, and nothing leaves the 12 x 12 image from its centre)."""
    rb = _bank_2(pincushion=0.0).resample_to(12, 12, dtype=D64_6, radiometry="energy")
    x = torch.zeros(1, 3, 12, 12, dtype=D64_6)
    x[0, 1, 5, 6] = 1.0
    with torch.no_grad():
        skipped = psf_exact(x, rb)
    dense = psf_exact(x.clone().requires_grad_(True), rb).detach()
    assert dense[0, 1].sum().item() == pytest.approx(1.0, abs=1e-6)          # PSFs held as float32
    assert torch.allclose(skipped, dense, atol=1e-12, rtol=0)


@pytest.mark.parametrize("chunk", [1, 300])
def test_energy_reference_is_independent_of_its_tap_chunks(monkeypatch, chunk):
    """The energy reference walks the kernel taps in chunks of at most ``_CHUNK_ELEMS`` elements (a
    memory bound); whatever the chunk, it equals the per-field FFT operator (and its gradient the
    FFT operator's exact adjoint)."""
    rb = _bank_2(K=5).resample_to(10, 10, dtype=D64_6, radiometry="energy")
    assert rb.k > 2
    x = torch.rand(2, 3, 10, 10, dtype=D64_6, generator=torch.Generator().manual_seed(4), requires_grad=True)
    w = torch.rand(2, 3, 10, 10, dtype=D64_6, generator=torch.Generator().manual_seed(5))
    want = psf_exact(x, rb)
    (g_want,) = torch.autograd.grad((want * w).sum(), x)
    monkeypatch.setattr(operators, "_CHUNK_ELEMS", chunk)
    got = psf_reference(x, rb)
    (g_got,) = torch.autograd.grad((got * w).sum(), x)
    assert torch.allclose(got, want, atol=1e-12, rtol=0) and torch.allclose(g_got, g_want, atol=1e-12, rtol=0)


def test_energy_operators_on_a_batch_with_several_eigen_psfs():
    """Energy form, a batch of 2 and field groups of several eigen-PSFs (``psf_fast`` at tol 0,
    zone 2: exact): outputs and gradients equal the brute-force reference item by item."""
    rb = _bank_2(G=4).resample_to(12, 12, dtype=D64_6, radiometry="energy")
    assert max(b.kernel_fft.shape[0] for bks in rb.zones(2, 0.0) for b in bks) > 1
    x = torch.rand(2, 3, 12, 12, dtype=D64_6, generator=torch.Generator().manual_seed(8), requires_grad=True)
    w = torch.rand(2, 3, 12, 12, dtype=D64_6, generator=torch.Generator().manual_seed(9))
    for op in (lambda a: psf_fast(a, rb, 0.0, 2), lambda a: psf_exact(a, rb)):
        out = op(x)
        (g,) = torch.autograd.grad((out * w).sum(), x)
        for i in range(2):
            xi = x[i].detach().clone().requires_grad_(True)
            ref = psf_reference(xi, rb)
            (gi,) = torch.autograd.grad((ref * w[i]).sum(), xi)
            assert torch.allclose(out[i], ref, atol=1e-10, rtol=0) and torch.allclose(g[i], gi, atol=1e-10, rtol=0)


def test_integer_primaries_are_refused_by_the_dtype_check():
    """The operators take float32 / float64 primaries: an integer image is refused by the dtype check
    (naming the allowed dtypes), not only by the later bank-dtype comparison."""
    rb = _bank_2().resample_to(8, 8)                                               # float32
    for op in (psf_exact, psf_distortion, psf_reference, psf_fast):
        with pytest.raises(InputValueError, match=r"primaries must have dtype in \['torch.float32', 'torch.float64'\], "
                                                  "got torch.int64"):
            op(torch.zeros(3, 8, 8, dtype=torch.int64), rb)


D64_7 = torch.float64


def _bank_3(L=3, G=3, K=5, pitch_mm=1.0, chief=lambda d: d, C=9, seed=0, flip_x=False):
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64_7, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64_7)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64_7) + 1) / G
    ch = torch.stack([-chief(cx) if flip_x else chief(cx), chief(cy)], -1).expand(L, C, C, 2).clone()
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64_7), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


@functools.lru_cache(maxsize=1)
def _rb8():
    return _bank_3().resample_to(8, 8)


# ----------------------------------------------------------------------------- operators
def test_operators_refuse_mismatched_primaries():
    rb = _rb8()                                                                  # float32
    for op in (psf_exact, psf_distortion, psf_reference, psf_fast):
        with pytest.raises(InputValueError, match="primaries is torch.float64 on cpu but the resampled bank is torch.float32"):
            op(torch.zeros(3, 8, 8, dtype=D64_7), rb)
        with pytest.raises(ShapeError, match="primaries must have size 3 in dim -3"):
            op(torch.zeros(2, 8, 8), rb)                                          # 2 channels, bank has 3
        with pytest.raises(InputValueError, match="primaries"):
            op(torch.zeros(3, 8, 8, dtype=torch.int64), rb)


@pytest.mark.parametrize("kw, match", [(dict(tol=-0.01), "tol must be in"), (dict(tol=1.0), r"tol must be in \[0, 1\)"),
                                       (dict(tol="0.1"), "tol"), (dict(zone=0), "zone must be an int >= 1"),
                                       (dict(zone=2.0), "zone must be an int >= 1")])
def test_psf_fast_refuses_bad_knobs(kw, match):
    rb = _rb8()
    with pytest.raises(InputValueError, match=match):
        psf_fast(torch.zeros(3, 8, 8), rb, **kw)


def test_fast_defaults_and_an_integer_zero_tolerance():
    rb = _bank_3(G=8).resample_to(16, 16, dtype=D64_7)
    x = torch.rand(3, 16, 16, dtype=D64_7, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(psf_fast(x, rb, tol=0, zone=1), psf_exact(x, rb), atol=1e-12)   # tol 0 as an int
    assert torch.equal(psf_fast(x, rb), psf_fast(x, rb, 0.02, 6))             # operator defaults: tol 0.02, zone 6
    assert not torch.allclose(psf_fast(x, rb, 0.02, 6), psf_fast(x, rb, 0.04, 6), atol=1e-9)
    assert not torch.allclose(psf_fast(x, rb, 0.02, 6), psf_fast(x, rb, 0.02, 7), atol=1e-9)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_gradient_at_a_sparse_image_is_the_dense_one(radiometry):
    """Every operator is linear: d<A x, w>/dx = A^T w whatever x. Pixels that are zero may be skipped
    only without a gradient; with one, the gradient at a mostly black image equals the one at a
    dense image (where nothing is skipped)."""
    rb = _bank_3(G=4, pitch_mm=2.0, chief=lambda d: d * (1 + 0.1 * d * d)).resample_to(12, 12, dtype=D64_7,
                                                                                       radiometry=radiometry)
    w = torch.rand(3, 12, 12, dtype=D64_7, generator=torch.Generator().manual_seed(5))
    sparse = torch.zeros(3, 12, 12, dtype=D64_7)
    sparse[:, 3:5, 6:8] = 1.0
    dense = torch.rand(3, 12, 12, dtype=D64_7, generator=torch.Generator().manual_seed(6)) + 0.5
    for op in (psf_distortion, psf_exact, psf_reference, lambda a, r: psf_fast(a, r, 0.05, 2)):
        grads = []
        for x in (sparse, dense):
            xr = x.clone().requires_grad_(True)
            (g,) = torch.autograd.grad((op(xr, rb) * w).sum(), xr)
            grads.append(g)
        assert grads[0].abs().sum() > 1 and torch.allclose(grads[0], grads[1], atol=1e-12)
        with torch.no_grad():                                                    # and the skipping forward is exact
            assert torch.allclose(op(sparse, rb), op(sparse.clone().requires_grad_(True), rb), atol=1e-12)


def test_fast_mode_rank_cap():
    """``max_rank`` caps the eigen-PSFs per field group; without it, tol 0 keeps the full rank."""
    rb = _bank_3(G=4).resample_to(12, 12, dtype=D64_7)
    ranks = {b.kernel_fft.shape[0] for bk in rb.zones(2, 0.0, 1) for b in bk}
    assert ranks == {1}
    assert max(b.kernel_fft.shape[0] for bk in rb.zones(2, 0.0) for b in bk) == 4    # 2 x 2 random fields
    x = torch.rand(3, 12, 12, dtype=D64_7, generator=torch.Generator().manual_seed(7))
    assert (psf_fast(x, rb, 0.0, 2, max_rank=1) - psf_exact(x, rb)).abs().max() > 1e-4
    assert torch.allclose(psf_fast(x, rb, 0.0, 2, max_rank=4), psf_exact(x, rb), atol=1e-12)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_psf_fast_is_exact_for_any_zone_size_at_tol_zero_and_for_one_field_zones(radiometry):
    """A 4 x 4 field grid of different PSFs: zones of 1 (any tol), 3 (not dividing 4) and 10 (larger
    than the grid) at tol=0 all equal the brute-force splat."""
    bank = synthetic_bank(K=5, G=4, L=2, uniform=False, identity=False, seed=2)
    rb = bank.resample_to(12, 10, dtype=torch.float64, radiometry=radiometry)
    x = torch.rand(2, 12, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    ref = psf_reference(x, rb)
    for zone, tol in ((1, 0.9), (3, 0.0), (10, 0.0), (4, 0.0)):
        assert torch.allclose(psf_fast(x, rb, tol=tol, zone=zone), ref, atol=1e-10, rtol=0), (zone, tol)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_psf_fast_extreme_tol_is_rank_one(radiometry):
    """tol near 1 keeps one eigen-PSF per group: the same operator as max_rank=1, and not exact."""
    bank = synthetic_bank(K=5, G=4, L=2, uniform=False, identity=False, seed=2)
    rb = bank.resample_to(12, 10, dtype=torch.float64, radiometry=radiometry)
    x = torch.rand(2, 12, 10, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    rank_one = psf_fast(x, rb, tol=0.999, zone=4)
    assert torch.allclose(rank_one, psf_fast(x, rb, tol=0.0, zone=4, max_rank=1), atol=1e-12, rtol=0)
    ref = psf_reference(x, rb)
    assert float((rank_one - ref).norm() / ref.norm()) > 1e-3


def test_psf_fast_refuses_bad_knobs_2():
    rb = synthetic_bank(K=3, G=2, L=1).resample_to(6, 6, dtype=torch.float64)
    x = torch.rand(1, 6, 6, dtype=torch.float64)
    for tol in (1.0, -0.01, float("nan"), "0.1"):
        with pytest.raises(InputValueError, match=r"tol must be in \[0, 1\)"):
            psf_fast(x, rb, tol=tol)  # type: ignore[arg-type]
    for zone in (0, -2, 2.0):
        with pytest.raises(InputValueError, match="zone must be an int >= 1"):
            psf_fast(x, rb, zone=zone)  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match="primaries"):
        psf_fast(x.float(), rb)
    assert psf_fast(x, rb, tol=0.0, zone=1).shape == (1, 6, 6)
