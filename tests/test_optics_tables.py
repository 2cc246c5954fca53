"""The per-resolution tables of the PSF operators (issue 13: built fast at 1024 px) equal their
literal definitions: chunked quad footprints vs one ``quad_overlap`` per pixel offset, cropped
per-field kernels vs the full ``kernels`` table, the slice-based radiance operator vs the
brute-force reference on a 16:9 image, and the one-field eigen-PSF shortcut."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream.optics import resampled
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_exact, psf_fast, psf_reference
from controlgs_adapter.downstream.optics.resampled import quad_overlap, quad_overlaps

D64 = torch.float64


@pytest.fixture(scope="module")
def cardboard():
    return PSFBank.default()


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


def _pincushion_bank(strength: float) -> PSFBank:
    """Small PSFs (reach 1 px at 24 px) and a strong pincushion: corner quads leave the canvas."""
    K, G = 5, 3
    psf = torch.rand(2, G, G, K, K, generator=torch.Generator().manual_seed(0), dtype=D64)
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    scale = 1 + strength * (cx ** 2 + cy ** 2)
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((2, G, G), 0.3 * 24 / 24, dtype=D64), field_x=f, field_y=f,
                   chief=torch.stack([cx * scale, cy * scale], -1).expand(2, 9, 9, 2).clone(), chief_x=c, chief_y=c,
                   wavelengths_nm=(600.0, 500.0), display_mm=(24.0, 24.0))


def _copy(bank: PSFBank) -> PSFBank:        # a bank without cached tables
    return PSFBank(**{f: getattr(bank, f) for f in ("psf", "psf_pitch_mm", "field_x", "field_y", "chief", "chief_x",
                                                    "chief_y", "wavelengths_nm", "display_mm", "meta")})


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
@pytest.mark.parametrize("h, w, which", [(40, 40, "cardboard"), (27, 48, "cardboard"), (24, 24, "pincushion"),
                                         (18, 30, "pincushion")])
def test_chunked_footprints_equal_the_literal_ones(cardboard, radiometry, h, w, which, monkeypatch):
    monkeypatch.setattr(resampled, "_FOOTPRINT_CHUNK", 37)          # many chunks of differing extents
    bank = _copy(cardboard) if which == "cardboard" else _pincushion_bank(0.25)
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


def test_field_kernels_are_the_crop_of_the_full_table(cardboard):
    rb = cardboard.resample_to(64, 64, dtype=D64)
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


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_exact_and_fast_on_a_wide_image_equal_the_reference(cardboard, radiometry):
    rb = cardboard.resample_to(18, 32, dtype=D64, radiometry=radiometry)
    x = torch.rand(2, 3, 18, 32, dtype=D64, generator=torch.Generator().manual_seed(1))
    ref = psf_reference(x, rb)
    assert torch.allclose(psf_exact(x, rb), ref, atol=1e-12, rtol=0)
    # one field per group: exact at any tol (the one-field eigen-PSF is the field's kernel itself)
    assert torch.allclose(psf_fast(x, rb, tol=0.3, zone=1), ref, atol=1e-12, rtol=0)
    # several fields per group at tol 0: the full eigen-expansion (eigh of K K^T: to 1e-9, as in
    # test_fast_operator_converges_to_exact)
    assert ((psf_fast(x, rb, tol=0.0, zone=3) - ref).norm() / ref.norm()) < 1e-9


def test_bench_sizes_and_a_tiny_run(tmp_path):
    pytest.importorskip("skimage")
    from controlgs_adapter.downstream.optics.bench import parse_size, run

    assert parse_size("24") == (24, 24) and parse_size("18x32") == (18, 32) and parse_size(20) == (20, 20)
    for bad in ("0", "12x", "x12", "1x2x3", "a"):
        with pytest.raises(ValueError):
            parse_size(bad)
    n = torch.get_num_threads()
    try:
        rows = run(sizes=["16", "12x20"], threads=1, out=tmp_path, repeat=1, scaling=False, command="test")
    finally:
        torch.set_num_threads(n)                                     # the bench sets the process's threads
    tables = [r for r in rows if r["op"] == "tables"]
    assert [(r["size"], r["radiometry"]) for r in tables] == [("16x16", "radiance"), ("16x16", "energy"),
                                                              ("12x20", "radiance"), ("12x20", "energy")]
    exact = [r for r in rows if r["op"] == "exact"]
    assert len(exact) == 4 and all(r["rel_l2"] == 0 for r in exact)
    text = (tmp_path / "optics_bench.md").read_text()
    assert "| 12x20 | exact fwd+bwd |" in text and "Command: `test`" in text
