"""Tests of ``controlgs_adapter.downstream.optics.resampled``: a bank resampled to an image's pixel grid
(footprints of the chief-ray map, area magnification, field blends, per-pixel kernels), and its
geometric helpers, checked against brute force and closed forms."""

from __future__ import annotations

import pytest
import torch
from helpers.banks import random_bank

from controlgs_adapter.downstream.optics import resampled as R
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.resampled import quad_overlap, quad_overlaps
from controlgs_adapter.downstream.optics.stage import psf_optics
from controlgs_adapter.downstream.placement import image_region
from controlgs_adapter.errors import InputValueError

D64 = torch.float64


# ----------------------------------------------------------------------------- geometric helpers
def test_box_matrix_splits_cells_between_taps():
    """Cells of half an output pixel, K = 5 (centres -1 .. 1 px), taps -1 .. 1: a cell centred on a
    tap edge splits in half between its two taps."""
    got = R._box_matrix(torch.tensor([0.5], dtype=D64), 5, 1)[0]
    want = torch.tensor([[1, 0.5, 0, 0, 0], [0, 0.5, 1, 0.5, 0], [0, 0, 0, 0.5, 1]], dtype=D64)
    assert torch.allclose(got, want, atol=1e-15)
    assert torch.allclose(R._box_matrix(torch.tensor([1.0], dtype=D64), 3, 1)[0], torch.eye(3, dtype=D64))


def test_mean_relu_and_pixel_overlaps():
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


# ----------------------------------------------------------------------------- footprints and areas
def test_fit_samples_the_bank_at_the_pixels_display_positions():
    """16:9 under "fit": a 27 x 48 image's pixel corners sit at display-normalised
    ``(x, 9/16 y)``; each pixel's footprint is the quad of its corners' chief-ray images, computed
    here from the bank's chief rays (the 48 x 48 image's map, landing points divided by the
    half-extents): its overlap areas add up to the quad's area and sit on the quad; the PSFs use the
    square pixel pitch."""
    bank = PSFBank.default()
    wide, square = bank.resample_to(27, 48, dtype=D64), bank.resample_to(48, 48, dtype=D64)
    ue = torch.linspace(-1, 1, 49, dtype=D64)
    ve = torch.linspace(-1, 1, 28, dtype=D64)
    V, U = torch.meshgrid(ve, ue, indexing="ij")
    ch = square._chief_at(U, V * 27 / 48)                                    # [L, 28, 49, 2]
    X = (ch[..., 0] + 1) * 24 + wide.m
    Y = (ch[..., 1] * 48 / 27 + 1) * 13.5 + wide.m
    qx = torch.stack([X[:, :-1, :-1], X[:, :-1, 1:], X[:, 1:, 1:], X[:, 1:, :-1]]).reshape(4, 3, -1)
    qy = torch.stack([Y[:, :-1, :-1], Y[:, :-1, 1:], Y[:, 1:, 1:], Y[:, 1:, :-1]]).reshape(4, 3, -1)
    cross = [qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4)]
    area = 0.5 * sum(cross)
    cx = sum((qx[e] + qx[(e + 1) % 4]) * cross[e] for e in range(4)) / (6 * area)
    cy = sum((qy[e] + qy[(e + 1) % 4]) * cross[e] for e in range(4)) / (6 * area)
    idx, w = wide.splat_index, wide.splat_weight                             # [L, J, N] (radiance: areas)
    col, row = (idx % wide.Wc).double() + 0.5, (idx // wide.Wc).double() + 0.5
    assert torch.allclose(w.sum(1), area, atol=1e-12)
    assert torch.allclose(wide.area, area, atol=1e-12)
    # first moments by pixel-centre quadrature of the overlaps: within a tenth of a pixel
    assert ((w * col).sum(1) / area - cx).abs().max() < 0.1
    assert ((w * row).sum(1) / area - cy).abs().max() < 0.1
    assert torch.equal(wide.kernels, square.kernels)       # pitch 0.5 mm in both


def _pincushion_bank(strength: float) -> PSFBank:
    """Small PSFs (reach 1 px at 24 px) and a strong pincushion: corner quads leave the canvas."""
    K, G = 5, 3
    psf = torch.rand(2, G, G, K, K, generator=torch.Generator().manual_seed(0), dtype=D64)
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    scale = 1 + strength * (cx ** 2 + cy ** 2)
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((2, G, G), 0.3, dtype=D64), field_x=f, field_y=f,
                   chief=torch.stack([cx * scale, cy * scale], -1).expand(2, 9, 9, 2).clone(), chief_x=c, chief_y=c,
                   wavelengths_nm=(600.0, 500.0), display_mm=(24.0, 24.0))


def _uncached(bank: PSFBank) -> PSFBank:
    """A copy of ``bank`` without its cached tables."""
    return PSFBank(**{f: getattr(bank, f) for f in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x",
                                                    "chief_y", "wavelengths_nm", "display_mm", "meta")})


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
@pytest.mark.parametrize("h, w, which", [(40, 40, "cardboard"), (27, 48, "cardboard"), (24, 24, "pincushion"),
                                         (18, 30, "pincushion")])
def test_chunked_footprints_equal_the_literal_ones(radiometry, h, w, which, monkeypatch):
    """Footprints computed in many chunks of differing extents equal every quad's overlap with every
    pixel of its bounding box (area-normalised in the energy form), taps off the canvas included."""
    monkeypatch.setattr(R, "_FOOTPRINT_CHUNK", 37)
    bank = _uncached(PSFBank.default()) if which == "cardboard" else _pincushion_bank(0.25)
    rb = bank.resample_to(h, w, dtype=D64, radiometry=radiometry)
    if which == "pincushion":                                        # some footprint taps fall off the canvas
        assert (rb.splat_index == rb.Hc * rb.Wc).any()
    X, Y = rb.corners()
    qx = torch.stack([X[:, :-1, :-1], X[:, :-1, 1:], X[:, 1:, 1:], X[:, 1:, :-1]]).reshape(4, rb.L, -1)
    qy = torch.stack([Y[:, :-1, :-1], Y[:, :-1, 1:], Y[:, 1:, 1:], Y[:, 1:, :-1]]).reshape(4, rb.L, -1)
    area = 0.5 * sum(qx[e] * qy[(e + 1) % 4] - qx[(e + 1) % 4] * qy[e] for e in range(4))
    x0, y0 = torch.floor(qx.min(0).values), torch.floor(qy.min(0).values)
    J = rb.splat_index.shape[1]
    jx = int((torch.ceil(qx.max(0).values) - x0).max())
    for j in range(J):
        oy, ox = divmod(j, jx)
        px, py = x0 + ox, y0 + oy
        want = quad_overlap(qx, qy, px, py).clamp_min(0)
        if radiometry == "energy":
            want = want / area
        inside = (px >= 0) & (px < rb.Wc) & (py >= 0) & (py < rb.Hc)
        idx = torch.where(inside, py * rb.Wc + px, torch.full_like(px, rb.Hc * rb.Wc)).long()
        assert torch.equal(rb.splat_index[:, j], idx)
        assert (rb.splat_weight[:, j] - torch.where(inside, want, 0)).abs().max() < 1e-13


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


@pytest.mark.parametrize("n", [27, 32])
def test_square_images_are_placed_the_same_by_fit_and_stretch(n):
    """A square image spans the square display under both placements: the tables are bit-identical (but
    cached apart), and so is the optics in every mode."""
    bank = PSFBank.default()
    fit = bank.resample_to(n, n, dtype=D64)
    stretch = bank.resample_to(n, n, dtype=D64, placement="stretch")
    assert fit is not stretch
    for name in ("field_index", "field_weight", "splat_index", "splat_weight", "kernels"):
        assert torch.equal(getattr(fit, name), getattr(stretch, name)), name
    x = torch.rand(3, n, n, dtype=D64, generator=torch.Generator().manual_seed(n))
    for mode in ("distortion", "exact"):
        assert torch.equal(psf_optics(x, bank, mode), psf_optics(x, bank, mode, placement="stretch"))


@pytest.mark.parametrize("h, w, axis", [(54, 96, -2), (96, 54, -1)])
@pytest.mark.parametrize("mode", ["distortion", "exact"])
def test_fit_simulates_the_image_region_of_a_black_display(h, w, axis, mode):
    """Only the image's region is simulated and the rest of the display is black: the optics of a
    16:9 (9:16) image equals, inside its band, the optics of the square image that holds it in the
    display's central band and black elsewhere (same pixel pitch)."""
    n = max(h, w)
    x = torch.rand(3, h, w, dtype=D64, generator=torch.Generator().manual_seed(1))
    big = torch.zeros(3, n, n, dtype=D64)
    band = [slice(None)] * 3
    band[axis] = slice((n - min(h, w)) // 2, (n + min(h, w)) // 2)
    big[tuple(band)] = x
    bank = PSFBank.default()
    got = psf_optics(x, bank, mode)
    want = psf_optics(big, bank, mode)[tuple(band)]
    assert torch.allclose(got, want, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- field blends
def test_output_field_weights_invert_the_chief_ray_map():
    """Radiance blends the fields at the display point whose chief ray lands on the output pixel:
    for chief rays 1.2 d (no field beyond), output pixel centre u comes from display point u / 1.2;
    energy blends them at the display pixel itself, and has no vignetting."""
    G, S = 3, 12
    bank = random_bank(G=G, chief=lambda d: 1.2 * d)
    u = (2 * torch.arange(S, dtype=D64) + 1) / S - 1
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G

    def hats(d: torch.Tensor) -> torch.Tensor:                                  # [S * S, G * G] bilinear weights
        lo, hi, a = R._bilinear_axis(f, d)
        w = torch.zeros(S, G, dtype=D64)
        w[torch.arange(S), lo] += 1 - a
        w[torch.arange(S), hi] += a
        return torch.einsum("yf,xg->yxfg", w, w).reshape(S * S, G * G)

    rb = bank.resample_to(S, S, dtype=D64)
    got = torch.zeros(S * S, G * G, dtype=D64)
    got.scatter_add_(1, rb.out_field_index[1].T, rb.out_field_weight[1].T)
    assert torch.allclose(got, hats(u / 1.2), atol=1e-9)
    re = bank.resample_to(S, S, dtype=D64, radiometry="energy")
    got = torch.zeros(S * S, G * G, dtype=D64)
    got.scatter_add_(1, re.field_index.T, re.field_weight.T)
    assert torch.allclose(got, hats(u), atol=1e-12)
    assert torch.equal(re.vignetting, torch.ones(3, S * S, dtype=D64))


# ----------------------------------------------------------------------------- kernels
def test_kernel_margin_from_the_widest_psf():
    """m = ceil(max pitch (K // 2 + 1/2) / pixel - 1/2): 24 px on 24 mm is 1 mm per pixel."""
    for pitch, K, m in ((1.0, 5, 2), (1.5, 5, 4), (0.1, 5, 0), (0.5, 9, 2), (0.6, 9, 3)):
        rb = random_bank(K=K, pitch_mm=pitch).resample_to(24, 24, dtype=D64, radiometry="energy")
        assert (rb.m, rb.k, rb.Hc, rb.Wc) == (m, 2 * m + 1, 24 + 2 * m, 24 + 2 * m)
        assert rb.kernels.shape == (3, 9, 2 * m + 1, 2 * m + 1)
    assert R.INVERSE_GRID == 129


def test_field_kernels_are_the_crop_of_the_full_table():
    rb = PSFBank.default().resample_to(64, 64, dtype=D64)
    full = rb.kernels                                                            # [L, G, k, k]
    for li in range(rb.L):
        boxes = rb.box_matrices(li)
        for fields in (torch.tensor([0]), torch.tensor([434, 435, 464]), torch.arange(900)):
            K, r = rb.field_kernels(li, fields)
            assert torch.equal(rb.field_kernels(li, fields, boxes)[0], K)
            m = rb.m
            assert K.shape == (len(fields), 2 * r + 1, 2 * r + 1) and r <= m
            assert (K - full[li, fields, m - r:m + r + 1, m - r:m + r + 1]).abs().max() < 1e-15
            outside = full[li, fields].clone()
            outside[:, m - r:m + r + 1, m - r:m + r + 1] = 0
            assert outside.abs().max() == 0


def test_anisotropic_pixels_resample_each_axis_with_its_own_pitch():
    """Stretch placement of a 12 x 24 image on the 24 mm display: pixels 1 mm wide, 2 mm tall. A
    horizontal line PSF (5 cells of 1 mm in the centre row) is 5 taps of 1/5 along x and one tap
    along y; the margin follows the finer axis (m = ceil(1 * 2.5 / 1 - 1/2) = 2)."""
    psf = torch.zeros(3, 1, 1, 5, 5, dtype=D64)
    psf[..., 2, :] = 0.2
    c = torch.linspace(-1, 1, 5, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    bank = PSFBank(psf=psf, psf_pitch_mm=torch.ones(3, 1, 1, dtype=D64), field_x=torch.zeros(1, dtype=D64),
                   field_y=torch.zeros(1, dtype=D64), chief=torch.stack([cx, cy], -1).expand(3, 5, 5, 2).clone(),
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
    rb = bank.resample_to(12, 24, dtype=D64, placement="stretch", radiometry="energy")
    assert rb.region.pitch_mm == (1.0, 2.0) and (rb.m, rb.k) == (2, 5)
    want = torch.zeros(5, 5, dtype=D64)
    want[2] = 0.2
    assert torch.allclose(rb.kernels[1, 0], want, atol=1e-7)
    k, r = rb.field_kernels(1, torch.tensor([0]))
    assert r == 2 and torch.allclose(k[0], want, atol=1e-7)
    k, r = rb.field_kernels(1, torch.tensor([0]), rb.box_matrices(1))
    assert torch.allclose(k[0], want, atol=1e-7)
    # the transposed image (24 x 12): 2 mm wide pixels; the line [-2.5, 2.5] mm covers 1.5 mm of the
    # taps at +-2 mm and all 2 mm of the centre tap: 0.3, 0.4, 0.3 (the PSF is stored as float32)
    rt = bank.resample_to(24, 12, dtype=D64, placement="stretch", radiometry="energy")
    assert rt.region.pitch_mm == (2.0, 1.0) and rt.m == 2
    assert rt.kernels[1, 0, 2].tolist() == pytest.approx([0.0, 0.3, 0.4, 0.3, 0.0], abs=1e-7)
    assert rt.kernels[1, 0].sum().item() == pytest.approx(1.0, abs=1e-7)


# ----------------------------------------------------------------------------- refusals
def test_resampled_bank_refusals():
    """An unknown radiometry, a chief-ray map that folds over (a mirror: negative areas), and one that
    cannot be inverted for the radiance form (``d - 0.3 d^3`` is monotonic on the display but reaches
    only |x| <= 0.7: landing points near the edge of [-1, 1] have no display point; the energy form's
    footprints are fine) are refused."""
    with pytest.raises(InputValueError, match="radiometry must be one of .*'flux'"):
        R.ResampledBank(random_bank(), 8, 8, image_region(8, 8), device=torch.device("cpu"), dtype=D64, radiometry="flux")
    with pytest.raises(InputValueError, match="chief-ray map folds over"):
        random_bank(flip_x=True).resample_to(8, 8)
    shrink = random_bank(chief=lambda d: d - 0.3 * d ** 3)
    assert shrink.resample_to(8, 8, radiometry="energy").area.min() > 0
    with pytest.raises(InputValueError, match="chief-ray map cannot be inverted"):
        shrink.resample_to(8, 8)
