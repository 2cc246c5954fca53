"""Resampling helpers, operator and stage refusals, the stage's documented defaults (compared with
their numbers through the public API), and the bench's table helpers; hand-computed values."""

import functools
import math
import warnings

import pytest
import torch

from controlgs_adapter.downstream.optics import resampled as R
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast, psf_reference
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics, set_optics_mode
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import RuntimeState

D64 = torch.float64


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


@functools.lru_cache(maxsize=1)
def _rb8():
    return _bank().resample_to(8, 8)


# ----------------------------------------------------------------------------- resampling helpers
def test_fast_fft_lengths_by_hand():
    # 11 -> 12 = 2^2 3; 13 -> 14 = 2 7; 97 (prime) -> 98 = 2 7^2; 121 = 11^2 -> 125 = 5^3 (122 = 2 61,
    # 123 = 3 41, 124 = 4 31); smooth numbers stay
    assert [R.fast_len(n) for n in (1, 8, 11, 13, 97, 121, 210)] == [1, 8, 12, 14, 98, 125, 210]
    # ladder: 8 * 1.12^i rounded up to 7-smooth sizes: 8, 8.96 -> 9, 10.04 -> 11 -> 12, 11.24 -> 12 (kept once),
    # 12.59 -> 13 -> 14, 14.10 -> 15, 15.79 -> 16, 17.69 -> 18, 19.81 -> 20
    assert [R.ladder_len(n) for n in (1, 8, 9, 10, 12, 13, 15, 16, 17, 19)] == [8, 8, 9, 12, 12, 14, 15, 16, 18, 20]
    assert R.ladder_len(200_001) == R.fast_len(200_001) > 200_001              # beyond the ladder (2^16)


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


# ----------------------------------------------------------------------------- operators
def test_operators_refuse_mismatched_primaries():
    rb = _rb8()                                                                  # float32
    for op in (psf_exact, psf_distortion, psf_reference, psf_fast):
        with pytest.raises(InputValueError, match="primaries is torch.float64 on cpu but the resampled bank is torch.float32"):
            op(torch.zeros(3, 8, 8, dtype=D64), rb)
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
    rb = _bank(G=8).resample_to(16, 16, dtype=D64)
    x = torch.rand(3, 16, 16, dtype=D64, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(psf_fast(x, rb, tol=0, zone=1), psf_exact(x, rb), atol=1e-12)   # tol 0 as an int
    assert torch.equal(psf_fast(x, rb), psf_fast(x, rb, 0.02, 6))             # operator defaults: tol 0.02, zone 6
    assert not torch.allclose(psf_fast(x, rb, 0.02, 6), psf_fast(x, rb, 0.04, 6), atol=1e-9)
    assert not torch.allclose(psf_fast(x, rb, 0.02, 6), psf_fast(x, rb, 0.02, 7), atol=1e-9)


# ----------------------------------------------------------------------------- stage
def test_stage_defaults_by_number():
    """Documented defaults: mode "exact", tol 0.02, zone 5, placement "fit", radiometry "radiance"."""
    from controlgs_adapter.downstream.optics import stage

    st = PSFOptics()
    assert (st.mode, st.tol, st.zone, st.placement, st.radiometry) == ("exact", 0.02, 5, "fit", "radiance")
    assert st.bank is PSFBank.default() and (stage.DEFAULT_TOL, stage.DEFAULT_ZONE) == (0.02, 5)
    assert repr(st).endswith("(mode='exact', placement='fit', radiometry='radiance', tol=0.02, zone=5, "
                             "wavelengths=(656.0, 550.0, 486.0))")
    assert stage.MODES == ("distortion", "fast", "exact")
    assert (PSFOptics.name, PSFOptics.domain) == ("optics", "linear")


def test_psf_optics_defaults_equal_their_explicit_values():
    bank = PSFBank.default()
    img = torch.rand(3, 16, 24, dtype=D64, generator=torch.Generator().manual_seed(2))
    out = psf_optics(img, bank)
    assert torch.equal(out, psf_optics(img, bank, "exact", 0.02, 5, "fit", "radiance"))
    assert torch.equal(psf_optics(img), out)                                       # bank None: the shipped one
    for other in (psf_optics(img, bank, "distortion"), psf_optics(img, bank, placement="stretch"),
                  psf_optics(img, bank, radiometry="energy")):
        assert (out - other).abs().max() > 1e-3
    b8 = _bank(G=8)                                                              # random PSFs: every knob shows
    img = img[..., :16, :16]
    fast = psf_optics(img, b8, "fast")
    assert torch.equal(fast, psf_optics(img, b8, "fast", 0.02, 5))
    assert (fast - psf_optics(img, b8, "fast", 0.04, 5)).abs().max() > 1e-6
    assert (fast - psf_optics(img, b8, "fast", 0.02, 6)).abs().max() > 1e-6


def test_stage_passes_every_setting_through():
    bank = PSFBank.default()
    img = torch.rand(3, 18, 32, dtype=D64, generator=torch.Generator().manual_seed(3))
    state = RuntimeState(downsample=1.0, power_saving=0.0)
    st = PSFOptics(bank, mode="fast", tol=0.1, zone=3, placement="stretch", radiometry="energy")
    want = psf_optics(img, bank, "fast", 0.1, 3, "stretch", "energy")
    assert torch.equal(st(img, state, None), want)
    assert not torch.allclose(want, psf_optics(img, bank, "fast", 0.1, 3, "fit", "energy"), atol=1e-6)
    st.mode = "distortion"
    assert torch.equal(st(img, state, None), psf_optics(img, bank, "distortion", placement="stretch", radiometry="energy"))


def test_stage_loads_a_bank_file(tmp_path):
    bank = _bank()
    bank.save(tmp_path / "b.safetensors")
    st = PSFOptics(str(tmp_path / "b.safetensors"), mode="distortion")
    assert torch.allclose(st.bank.chief, bank.chief) and st.bank.psf.shape == bank.psf.shape
    st2 = PSFOptics(tmp_path / "b.safetensors")
    assert st2.bank.display_mm == (24.0, 24.0)


@pytest.mark.parametrize("kw, match", [
    (dict(tol=-0.1), r"tol must be in \[0, 1\)"), (dict(tol=1), "tol must be in"), (dict(tol="0"), "tol"),
    (dict(zone=0), "zone must be an int >= 1"), (dict(zone=1.5), "zone"),
    (dict(placement="crop"), "placement must be one of.*'crop'"), (dict(radiometry="flux"), "radiometry must be one of"),
    (dict(mode="blur"), r"mode must be one of \('distortion', 'fast', 'exact'\), got 'blur'"),
])
def test_stage_refuses_bad_settings(kw, match):
    with pytest.raises(InputValueError, match=match):
        PSFOptics(**kw)


def test_stage_mode_setter_and_deprecated_stretch():
    st = PSFOptics(mode="fast", tol=0, zone=1)
    assert st.tol == 0.0 and isinstance(st.tol, float)
    with pytest.raises(InputValueError, match="mode must be one of.*'sharp'"):
        st.mode = "sharp"
    assert st.mode == "fast"
    with pytest.warns(DeprecationWarning, match="stretch"):
        assert PSFOptics(stretch=True).placement == "stretch"
    with pytest.warns(DeprecationWarning, match="stretch"):
        assert PSFOptics(placement="stretch", stretch=False).placement == "fit"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert PSFOptics(placement="stretch").placement == "stretch"


def test_psf_optics_refusals():
    img = torch.rand(3, 8, 8)
    with pytest.raises(InputValueError, match=r"mode must be one of \('distortion', 'fast', 'exact'\), got 'blur'"):
        psf_optics(img, mode="blur")  # type: ignore[arg-type]
    with pytest.raises(InputValueError, match=r"needs a bank with 3 wavelengths.*\(656.0, 550.0\)"):
        psf_optics(img, _bank(L=2))
    with pytest.raises(ShapeError, match="image must have size 3"):
        psf_optics(torch.rand(2, 8, 8))


def test_set_optics_mode_reaches_the_stage_and_checks_the_mode():
    from controlgs_adapter.downstream.pipeline import Pipeline

    p = Pipeline([PSFOptics(mode="exact")])
    set_optics_mode(p, "distortion")
    assert p["optics"].mode == "distortion"
    with pytest.raises(InputValueError, match="mode must be one of"):
        set_optics_mode(p, "blurry")


def test_optics_runs_last_after_a_stage_ordered_between():
    """Stage order 50: a third-party stage at order 45 runs before it, one at 55 after it."""
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.downstream.stage import Stage

    class S(Stage):
        def process(self, image, state, ctx):
            return image

    a, b = S(), S()
    a.name, a.order, b.name, b.order = "a45", 45.0, "b55", 55.0
    assert Pipeline([b, PSFOptics(mode="distortion"), a]).names == ["a45", "optics", "b55"]


# ----------------------------------------------------------------------------- bench helpers
def test_bench_parse_size_and_ratio_tables():
    from controlgs_adapter.downstream.optics import bench

    assert bench.parse_size("576X1024") == (576, 1024) and bench.parse_size("2") == (2, 2)
    for bad in ("1", "2x1", "", "-4"):
        with pytest.raises(ValueError, match="size must be N or HxW"):
            bench.parse_size(bad)
    assert bench.SIZES == ("256", "512", "1024", "576x1024") and bench.TOLS == (0.02,)
    rows = [dict(size="8x8", radiometry="radiance", op="tables", knob="-", resample_s=1.0, resample_cpu=2.0,
                 exact_s=3.0, exact_cpu=4.0),
            dict(size="8x8", radiometry="energy", op="tables", knob="-", resample_s=0.5, resample_cpu=1.0,
                 exact_s=1.5, exact_cpu=2.0),
            dict(size="8x8", radiometry="radiance", op="fast", knob="tol=0.02, zone=5", fwd_bwd_s=6.0, fwd_bwd_cpu=9.0),
            dict(size="8x8", radiometry="energy", op="fast", knob="tol=0.02, zone=5", fwd_bwd_s=2.0, fwd_bwd_cpu=3.0),
            dict(size="8x8", radiometry="radiance", op="exact", knob="-", fwd_bwd_s=1.0, fwd_bwd_cpu=1.0)]
    ratios = bench._ratios(rows)                     # the radiance exact row has no energy partner: no ratio
    assert ratios == [dict(size="8x8", op="tables (resample_to + exact)", wall=2.0, cpu=2.0, rad_s=4.0, en_s=2.0),
                      dict(size="8x8", op="fast fwd+bwd (tol=0.02, zone=5)", wall=3.0, cpu=3.0, rad_s=6.0, en_s=2.0)]
    lines = bench._ratio_lines(ratios)
    assert lines[2] == "| 8x8 | tables (resample_to + exact) | 4.000 | 2.000 | 2.00 | 2.00 |"
    assert lines[3] == "| 8x8 | fast fwd+bwd (tol=0.02, zone=5) | 6.000 | 2.000 | 3.00 | 3.00 |" and len(lines) == 4
    assert bench._ratio_lines([]) == []


def test_bench_timer_keeps_the_best_of_its_repeats():
    from controlgs_adapter.downstream.optics import bench

    calls = []
    wall, cpu = bench._time(lambda: calls.append(1), repeat=4)
    assert len(calls) == 4 and 0 <= wall < 0.5 and 0 <= cpu < 0.5
    r, w, c = bench._clock(lambda: math.sqrt(16.0))
    assert r == 4.0 and w >= 0 and c >= 0


def test_bench_report_tables_by_hand(tmp_path):
    from controlgs_adapter.downstream.optics import bench

    rows = [dict(size="8x8", radiometry="radiance", op="tables", knob="-", resample_s=1.0, resample_cpu=2.0,
                 exact_s=3.0, exact_cpu=4.0, fast_s={0.02: 0.5}, fast_cpu={0.02: 0.25}),
            dict(size="8x8", radiometry="radiance", op="fast", knob="tol=0.02, zone=5", fwd_s=0.125, fwd_cpu=0.25,
                 fwd_bwd_s=0.5, fwd_bwd_cpu=1.0, rel_l2=0.0123, max_rel=0.0456),
            dict(size="8x8", radiometry="radiance", op="exact", knob="-", fwd_s=0.1, fwd_cpu=0.2,
                 fwd_bwd_s=0.3, fwd_bwd_cpu=0.4, rel_l2=0.0, max_rel=0.0)]
    bench._write(rows, [], [(33, 0.5), (129, 1.5)], threads=2, repeat=3, out=tmp_path / "o", command="cmd")
    lines = (tmp_path / "o" / "optics_bench.md").read_text().splitlines()
    assert lines[0].startswith("Operators of the shipped Cardboard bank") and "2 CPU threads, best of 3" in lines[0]
    assert "Command: `cmd; " in lines[0]
    assert "| 8x8 | radiance | 1.00 (2.00) | 3.00 (4.00) | tol 0.02: 0.50 (0.25) |" in lines
    assert "| 8x8 | radiance | fast | tol=0.02, zone=5 | 0.125 | 0.250 | 0.500 | 1.000 | 1.23e-02 | 4.56e-02 |" in lines
    assert "| 8x8 | radiance | exact | - | 0.100 | 0.200 | 0.300 | 0.400 | 0.00e+00 | 0.00e+00 |" in lines
    assert lines[-1] == ("Kernel-size scaling of the fast mode (Gaussian PSF banks, fwd+bwd CPU time): k = 33: 0.500 s, "
                         "k = 129: 1.500 s (ratio 3.00)")
    assert not any("Radiance (default) vs energy" in ln for ln in lines)
    if (tmp_path / "o" / "optics_bench.png").exists():
        assert (tmp_path / "o" / "optics_bench.png").stat().st_size > 1000


def test_bench_kernel_scaling_banks_span_33_and_129_px():
    """Gaussian banks whose stored window spans k = 33 and 129 output px (24 / size mm per px, K = 33
    cells): the resampled kernels are 33 and 129 (+2: the float32 pitch rounds the margin up) px wide."""
    pytest.importorskip("skimage")
    from controlgs_adapter.downstream.optics import bench

    out = bench._kernel_scaling(16, zone=6)
    assert [k for k, _ in out][0] == 33 and [k for k, _ in out][1] in (129, 131)
    assert all(t > 0 for _, t in out)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_gradient_at_a_sparse_image_is_the_dense_one(radiometry):
    """Every operator is linear: d<A x, w>/dx = A^T w whatever x. Pixels that are zero may be skipped
    only without a gradient; with one, the gradient at a mostly black image equals the one at a
    dense image (where nothing is skipped)."""
    rb = _bank(G=4, pitch_mm=2.0, chief=lambda d: d * (1 + 0.1 * d * d)).resample_to(12, 12, dtype=D64,
                                                                                       radiometry=radiometry)
    w = torch.rand(3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(5))
    sparse = torch.zeros(3, 12, 12, dtype=D64)
    sparse[:, 3:5, 6:8] = 1.0
    dense = torch.rand(3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(6)) + 0.5
    for op in (psf_distortion, psf_exact, psf_reference, lambda a, r: psf_fast(a, r, 0.05, 2)):
        grads = []
        for x in (sparse, dense):
            xr = x.clone().requires_grad_(True)
            (g,) = torch.autograd.grad((op(xr, rb) * w).sum(), xr)
            grads.append(g)
        assert grads[0].abs().sum() > 1 and torch.allclose(grads[0], grads[1], atol=1e-12)
        with torch.no_grad():                                                    # and the skipping forward is exact
            assert torch.allclose(op(sparse, rb), op(sparse.clone().requires_grad_(True), rb), atol=1e-12)


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


def test_fast_mode_rank_cap():
    """``max_rank`` caps the eigen-PSFs per field group; without it, tol 0 keeps the full rank."""
    rb = _bank(G=4).resample_to(12, 12, dtype=D64)
    ranks = {b.kernel_fft.shape[0] for bk in rb.zones(2, 0.0, 1) for b in bk}
    assert ranks == {1}
    assert max(b.kernel_fft.shape[0] for bk in rb.zones(2, 0.0) for b in bk) == 4    # 2 x 2 random fields
    x = torch.rand(3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(7))
    assert (psf_fast(x, rb, 0.0, 2, max_rank=1) - psf_exact(x, rb)).abs().max() > 1e-4
    assert torch.allclose(psf_fast(x, rb, 0.0, 2, max_rank=4), psf_exact(x, rb), atol=1e-12)


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_fast_mode_rank_is_the_smallest_within_the_relative_residual(radiometry):
    """Per field group, the number of eigen-PSFs is the smallest R whose truncated SVD leaves a
    relative Frobenius residual sqrt(sum_{i > R} s_i^2 / sum s_i^2) <= tol (reference: torch's SVD
    of the group's 4 kernels, float64)."""
    rb = _bank(G=2, K=5, seed=3).resample_to(10, 10, dtype=D64, radiometry=radiometry)
    K, _ = rb.field_kernels(1, torch.arange(4))
    s = torch.linalg.svdvals(K.reshape(4, -1))
    rel = [(s[r:] ** 2).sum().sqrt().item() / (s ** 2).sum().sqrt().item() for r in range(5)]   # residual of rank r
    seen = set()
    for tol in (0.9, 0.5, 0.3, 0.1, 0.03, 0.01, 0.0):
        want = min(r for r in range(1, 5) if rel[r] <= tol or r == 4)
        (bk,) = rb.zones(2, tol)[1]
        assert bk.kernel_fft.shape[0] == want, (tol, rel)
        seen.add(want)
    assert len(seen) >= 3                                                       # the tolerances reach several ranks


def test_bench_figure_lines_labels_and_exact_marker():
    plt = pytest.importorskip("matplotlib.pyplot")
    from controlgs_adapter.downstream.optics import bench

    def row(rad, op, knob, cpu, rel):
        return dict(size="8x8", radiometry=rad, op=op, knob=knob, fwd_bwd_cpu=cpu, rel_l2=rel)

    ops = [row("radiance", "distortion", "-", 0.5, 0.2), row("radiance", "fast", "tol=0.02, zone=5", 2.0, 0.0),
           row("radiance", "exact", "-", 4.0, 0.0), row("energy", "distortion", "-", 0.25, 0.3),
           row("energy", "fast", "tol=0.05, zone=5", 1.0, 0.01)]
    fig = bench._figure(plt, ops)
    try:
        ax = fig.axes[0]
        rad, exact, en = ax.lines                                                   # the energy key has no exact row
        assert list(rad.get_xdata()) == [0.5, 2.0] and list(rad.get_ydata()) == [0.2, 1e-7]   # 0 floored at 1e-7
        assert (rad.get_marker(), rad.get_linestyle()) == ("o", "-") and rad.get_label() == "8x8 radiance"
        assert list(en.get_xdata()) == [0.25, 1.0] and list(en.get_ydata()) == [0.3, 0.01]
        assert (en.get_marker(), en.get_linestyle()) == ("s", "--") and en.get_label() == "8x8 energy"
        assert list(exact.get_xdata()) == [4.0, 4.0] and exact.get_linestyle() == ":"
        assert exact.get_color() == rad.get_color()
        notes = [(t.get_text(), tuple(t.xy)) for t in ax.texts]
        assert notes == [("distortion", (0.5, 0.2)), ("tol=0.02", (2.0, 1e-7)), ("distortion", (0.25, 0.3)),
                         ("tol=0.05", (1.0, 0.01))]
        assert {t.get_fontsize() for t in ax.texts} == {6}
        assert (ax.get_xscale(), ax.get_yscale()) == ("log", "log")
    finally:
        plt.close(fig)
