"""Tests of ``controlgs_adapter.downstream.optics.resampled``."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream.optics import resampled as R
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.resampled import quad_overlap, quad_overlaps
from controlgs_adapter.errors import InputValueError

D64 = torch.float64


def test_quad_overlaps_equal_one_quad_overlap_per_pixel():
    g = torch.Generator().manual_seed(3)
    n = 500
    cx, cy = torch.rand(n, generator=g, dtype=D64) * 50, torch.rand(n, generator=g, dtype=D64) * 50
    sx, sy = 0.2 + 2.5 * torch.rand(n, generator=g, dtype=D64), 0.2 + 2.5 * torch.rand(n, generator=g, dtype=D64)
    shear = 0.4 * (torch.rand(n, generator=g, dtype=D64) - 0.5)
    jit = 0.15 * (torch.rand(2, 4, n, generator=g, dtype=D64) - 0.5)
    ux, uy = torch.tensor([0.0, 1, 1, 0], dtype=D64)[:, None], torch.tensor([0.0, 0, 1, 1], dtype=D64)[:, None]
    qx = cx + sx * (ux + shear * uy) + jit[0]
    qy = cy + sy * uy + jit[1]
    x0, y0 = torch.floor(qx.min(0).values), torch.floor(qy.min(0).values)
    jx = int((torch.ceil(qx.max(0).values) - x0).max())
    jy = int((torch.ceil(qy.max(0).values) - y0).max())
    got = quad_overlaps(qx, qy, x0, y0, jx, jy)                                  # [jy, jx, n]
    want = torch.stack([torch.stack([quad_overlap(qx, qy, x0 + i, y0 + j) for i in range(jx)]) for j in range(jy)])
    assert (got - want).abs().max() < 1e-13
    area = 0.5 * sum(qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4))
    assert torch.allclose(got.sum((0, 1)), area, atol=1e-12, rtol=0)


def _bank(L=3, G=3, K=5, pitch_mm=1.0, chief=lambda d: d, C=9, seed=0, flip_x=False):
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, C, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    ch = torch.stack([-chief(cx) if flip_x else chief(cx), chief(cy)], -1).expand(L, C, C, 2).clone()
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


def test_box_matrix_by_hand():
    """Cells of half an output pixel, K = 5 (centres -1 .. 1 px), taps -1 .. 1: a cell centred on a
    tap edge splits in half between its two taps."""
    got = R._box_matrix(torch.tensor([0.5], dtype=D64), 5, 1)[0]
    want = torch.tensor([[1, 0.5, 0, 0, 0], [0, 0.5, 1, 0.5, 0], [0, 0, 0, 0.5, 1]], dtype=D64)
    assert torch.allclose(got, want, atol=1e-15)
    assert torch.allclose(R._box_matrix(torch.tensor([1.0], dtype=D64), 3, 1)[0], torch.eye(3, dtype=D64))


def test_mean_relu_and_pixel_overlaps_by_hand():
    g0 = torch.tensor([-1.0, 1.0, -3.0, 2.0, -1.0, 3.0], dtype=D64)
    g1 = torch.tensor([1.0, 3.0, -1.0, 2.0, 3.0, -1.0], dtype=D64)
    # mean of max(g, 0) over a line: 1/4; 2; 0; 2; triangle 3 * 3 / 2 over 4 = 9/8; the same reversed
    assert R._mean_relu(g0, g1).tolist() == pytest.approx([0.25, 2.0, 0.0, 2.0, 1.125, 1.125], abs=1e-15)
    # box [0.25, 1.25] x [0, 1] in pixel [0, 1]^2: 0.75; box [0.5, 2.5] x [0.5, 1.5] in pixel [1, 2]^2: 0.5;
    # the diamond with vertices at the pixel's edge midpoints: 0.5
    qx = torch.tensor([[0.25, 0.5, 0.5], [1.25, 2.5, 1.0], [1.25, 2.5, 0.5], [0.25, 0.5, 0.0]], dtype=D64)
    qy = torch.tensor([[0.0, 0.5, 0.0], [0.0, 0.5, 0.5], [1.0, 1.5, 1.0], [1.0, 1.5, 0.5]], dtype=D64)
    a = torch.tensor([0.0, 1.0, 0.0], dtype=D64)
    assert R.quad_overlap(qx, qy, a, a).tolist() == pytest.approx([0.75, 0.5, 0.5], abs=1e-14)
    many = R.quad_overlaps(qx, qy, a - 1, a - 1, 3, 3)                         # pixels from (a-1, a-1), 3 x 3
    assert many[1, 1].tolist() == pytest.approx([0.75, 0.5, 0.5], abs=1e-14)
    assert many.sum((0, 1)).tolist() == pytest.approx([1.0, 2.0, 0.5], abs=1e-14)   # the whole areas


def test_bilinear_axis_clamps_and_single_sample():
    f = torch.tensor([-0.5, 0.5], dtype=D64)
    lo, hi, a = R._bilinear_axis(f, torch.tensor([-1.0, -0.5, 0.25, 0.5, 2.0], dtype=D64))
    assert lo.tolist() == [0] * 5 and hi.tolist() == [1] * 5 and a.tolist() == [0.0, 0.0, 0.75, 1.0, 1.0]
    f3 = torch.tensor([-2 / 3, 0.0, 2 / 3], dtype=D64)
    lo, hi, a = R._bilinear_axis(f3, torch.tensor([0.5], dtype=D64))
    assert (lo.item(), hi.item()) == (1, 2) and a.item() == pytest.approx(0.75)
    lo, hi, a = R._bilinear_axis(torch.zeros(1, dtype=D64), torch.tensor([-0.3, 0.9], dtype=D64))
    assert lo.tolist() == hi.tolist() == [0, 0] and a.tolist() == [0.0, 0.0]


def test_keys_cubic_weights_and_quadratic_padding():
    w = R._keys(torch.tensor([0.0, 0.5], dtype=D64))
    assert w[0].tolist() == [0.0, 1.0, 0.0, 0.0]
    assert w[1].tolist() == pytest.approx([-1 / 16, 9 / 16, 9 / 16, -1 / 16], abs=1e-15)   # Keys, a = -1/2
    g = torch.arange(4, dtype=D64) ** 2                                            # i^2, i = 0..3
    pad = R._pad_quadratic(g[None, :, None, None].expand(1, 4, 3, 1))
    assert pad[0, :, 1, 0].tolist() == [1.0, 0.0, 1.0, 4.0, 9.0, 16.0]            # (-1)^2 and 4^2
    assert pad.shape == (1, 6, 5, 1) and pad[0, 0, :, 0].tolist() == [1.0] * 5
    # Keys reproduces quadratics: t^2 sampled on linspace(-1, 1, 7), interpolated anywhere in [-1, 1]
    n, t = 7, torch.tensor([-1.0, -0.93, -0.2, 0.0, 0.41, 0.999, 1.0], dtype=D64)
    s = torch.linspace(-1, 1, n, dtype=D64)
    vals = torch.cat([3 * s[:1] ** 2 - 3 * s[1:2] ** 2 + s[2:3] ** 2, s ** 2, 3 * s[-1:] ** 2 - 3 * s[-2:-1] ** 2 + s[-3:-2] ** 2])
    assert (R._keys_matrix(t, n) @ vals).tolist() == pytest.approx((t ** 2).tolist(), abs=1e-13)


def test_kernel_margin_from_the_widest_psf():
    """m = ceil(max pitch (K // 2 + 1/2) / pixel - 1/2): 24 px on 24 mm is 1 mm per pixel."""
    for pitch, K, m in ((1.0, 5, 2), (1.5, 5, 4), (0.1, 5, 0), (0.5, 9, 2), (0.6, 9, 3)):
        rb = _bank(K=K, pitch_mm=pitch).resample_to(24, 24, dtype=D64, radiometry="energy")
        assert (rb.m, rb.k, rb.Hc, rb.Wc) == (m, 2 * m + 1, 24 + 2 * m, 24 + 2 * m)
        assert rb.kernels.shape == (3, 9, 2 * m + 1, 2 * m + 1)
    assert R.INVERSE_GRID == 129


def test_resampled_bank_refusals():
    bank = _bank()
    from controlgs_adapter.downstream.placement import image_region

    with pytest.raises(InputValueError, match="radiometry must be one of"):
        R.ResampledBank(bank, 8, 8, image_region(8, 8), device=torch.device("cpu"), dtype=D64, radiometry="flux")
    with pytest.raises(InputValueError, match="chief-ray map folds over"):
        _bank(flip_x=True).resample_to(8, 8)                                   # a mirror: negative areas
    # d - 0.3 d^3 is monotonic on the display but reaches only |x| <= 0.7: the landing points near the
    # edge of [-1, 1] have no display point, in either radiometry's footprints fine; radiance needs the inverse
    shrink = _bank(chief=lambda d: d - 0.3 * d ** 3)
    assert shrink.resample_to(8, 8, radiometry="energy").area.min() > 0
    with pytest.raises(InputValueError, match="chief-ray map cannot be inverted"):
        shrink.resample_to(8, 8)


def test_output_field_weights_invert_the_chief_ray_map():
    """Radiance blends the fields at the display point whose chief ray lands on the output pixel:
    for chief rays 1.2 d (no field beyond), output pixel centre u comes from display point u / 1.2."""
    G, S = 3, 12
    rb = _bank(G=G, chief=lambda d: 1.2 * d).resample_to(S, S, dtype=D64)
    u = (2 * torch.arange(S, dtype=D64) + 1) / S - 1
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    d = u / 1.2
    lo, hi, a = R._bilinear_axis(f, d)
    w = torch.zeros(S, G, dtype=D64)                                           # hat weights per axis
    w[torch.arange(S), lo] += 1 - a
    w[torch.arange(S), hi] += a
    want = torch.einsum("yf,xg->yxfg", w, w).reshape(S * S, G * G)
    got = torch.zeros(S * S, G * G, dtype=D64)
    got.scatter_add_(1, rb.out_field_index[1].T, rb.out_field_weight[1].T)
    assert torch.allclose(got, want, atol=1e-9)
    # energy: at the display pixel itself
    re = _bank(G=G, chief=lambda d: 1.2 * d).resample_to(S, S, dtype=D64, radiometry="energy")
    lo, hi, a = R._bilinear_axis(f, u)
    w = torch.zeros(S, G, dtype=D64)
    w[torch.arange(S), lo] += 1 - a
    w[torch.arange(S), hi] += a
    got = torch.zeros(S * S, G * G, dtype=D64)
    got.scatter_add_(1, re.field_index.T, re.field_weight.T)
    assert torch.allclose(got, torch.einsum("yf,xg->yxfg", w, w).reshape(S * S, G * G), atol=1e-12)
    assert torch.equal(re.vignetting, torch.ones(3, S * S, dtype=D64))
