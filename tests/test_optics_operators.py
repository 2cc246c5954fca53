"""PSF operators: exactness vs a brute-force splat and vs convolution, adjointness, gradients,
linearity, energy, seams, point sources, convergence of the fast mode; the optics stage. Both
radiometries where a property holds for both; the paper's energy-conserving form where the test
is about energy (the radiance default's own targets: tests/test_optics_fidelity.py)."""

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast, psf_reference

D64 = torch.float64


def synthetic_bank(K=7, G=4, L=2, pitch_px=1.0, width_px=16, uniform=True, identity=True, seed=0):
    """A small bank: random PSFs (the same everywhere if ``uniform``), identity or pincushion chief rays."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, generator=g, dtype=D64) ** 3
    if uniform:
        psf = psf[:1, :1, :1].expand(L, G, G, K, K).clone()
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    scale = 1.0 if identity else 1 + 0.08 * (cx ** 2 + cy ** 2)
    chief = torch.stack([cx * scale, cy * scale], -1).expand(L, 9, 9, 2).clone()
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_px * 24 / width_px, dtype=D64), field_x=f,
                   field_y=f, chief=chief, chief_x=c, chief_y=c, wavelengths_nm=(600.0, 500.0)[:L],
                   display_mm=(24.0, 24.0))


@pytest.fixture(scope="module")
def cardboard():
    return PSFBank.default()


RADIOMETRIES = ("radiance", "energy")


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


def _flat_field_d2(rb):  # energy form: the paper's scatter of bilinearly blended PSFs
    o = psf_exact(torch.ones(2, rb.H, rb.W, dtype=D64), rb)[:, 8:-8, 8:-8]
    return max((o[:, :, 2:] - 2 * o[:, :, 1:-1] + o[:, :, :-2]).abs().max().item(),
               (o[:, 2:] - 2 * o[:, 1:-1] + o[:, :-2]).abs().max().item())


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


def test_point_source_lands_at_its_chief_ray_with_the_bank_psf(cardboard):
    """Energy form: unit energy, centroid at the chief ray plus the blended bank PSF's centroid
    (the radiance form: tests/test_optics_fidelity.py)."""
    S = 48
    rb = cardboard.resample_to(S, S, dtype=D64, radiometry="energy")
    iy, ix = 30, 17                                   # off-axis pixel
    x = torch.zeros(3, S, S, dtype=D64)
    x[:, iy, ix] = 1
    out = psf_exact(x, rb)
    yy, xx = torch.meshgrid(torch.arange(S, dtype=D64) + 0.5, torch.arange(S, dtype=D64) + 0.5, indexing="ij")
    u, v = (2 * ix + 1) / S - 1, (2 * iy + 1) / S - 1
    chief = rb._chief_at(torch.tensor([u], dtype=D64), torch.tensor([v], dtype=D64))[:, 0]   # [L, 2]
    for li in range(3):
        o = out[li]
        assert o.sum().item() == pytest.approx(1.0, abs=1e-6)
        cx, cy = (o * xx).sum().item(), (o * yy).sum().item()
        # the bank PSF's own centroid (continuous, from the stored samples) at the blended fields
        w, idx = rb.field_weight[:, iy * S + ix], rb.field_index[:, iy * S + ix]
        K = cardboard.psf.shape[-1]
        t = torch.arange(K, dtype=D64) - K // 2
        ps = cardboard.psf[li].reshape(-1, K, K).double()[idx]
        pitch = cardboard.psf_pitch_mm[li].reshape(-1).double()[idx] / (24 / S)
        ox = (w * (ps.sum(1) * t).sum(-1) * pitch).sum().item()
        oy = (w * (ps.sum(2) * t).sum(-1) * pitch).sum().item()
        assert cx == pytest.approx((chief[li, 0].item() + 1) * S / 2 + ox, abs=0.02)
        assert cy == pytest.approx((chief[li, 1].item() + 1) * S / 2 + oy, abs=0.02)
    # lateral colour: blue (486) lands further out than red (656)
    assert abs(chief[2, 0]) > abs(chief[0, 0])


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


def test_optics_stage_in_the_pipeline(cardboard):
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.state import RuntimeState

    pipe = Pipeline.from_config({"optics": {"mode": "distortion"}})
    assert "optics" in pipe.names
    img = torch.rand(1, 3, 32, 32)
    out = pipe(img, RuntimeState(downsample=1.0, power_saving=0.0))
    assert out.shape == img.shape and torch.isfinite(out).all()
    stage = PSFOptics(mode="exact")
    gray = torch.full((3, 32, 32), 0.5, dtype=D64)
    res = stage(gray, RuntimeState(downsample=1.0, power_saving=0.0), None)
    assert res[:, 14:18, 14:18].sub(0.5).abs().max() < 0.02            # grey stays grey near the centre
    with pytest.raises(ValueError, match="mode"):
        stage.mode = "blurry"
