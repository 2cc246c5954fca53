"""Sweep-4 audit of the optics package (operators, bench, generate, bank, stage, prescription): the
skipping of black pixels checked against the dense path with images that defeat the easy cases
(values exactly 1, a channel or a batch item lit alone, a lone pixel), the tap chunking of the
energy reference, batched energy gradients, refusal messages, the bench's reported errors and
documented defaults, and a few prescription details."""

import dataclasses
import inspect
import math

import pytest
import torch

from controlgs_adapter.downstream.optics import operators
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast, psf_reference
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription
from controlgs_adapter.errors import InputValueError

D64 = torch.float64


def _bank(L=3, G=4, K=5, pitch_mm=2.0, seed=0, pincushion=0.1):
    """Random PSFs on a ``G x G`` field grid, a mild pincushion chief-ray map, a 24 mm display."""
    g = torch.Generator().manual_seed(seed)
    psf = torch.rand(L, G, G, K, K, dtype=D64, generator=g) ** 2
    psf /= psf.sum((-1, -2), keepdim=True)
    c = torch.linspace(-1, 1, 9, dtype=D64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    s = 1 + pincushion * (cx ** 2 + cy ** 2)
    ch = torch.stack([cx * s, cy * s], -1).expand(L, 9, 9, 2).clone()
    f = -1 + (2 * torch.arange(G, dtype=D64) + 1) / G
    return PSFBank(psf=psf, psf_pitch_mm=torch.full((L, G, G), pitch_mm, dtype=D64), field_x=f, field_y=f, chief=ch,
                   chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0)[:L], display_mm=(24.0, 24.0))


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
    rb = _bank().resample_to(12, 12, dtype=D64, radiometry=radiometry)
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
    rb = _bank(pincushion=0.0).resample_to(12, 12, dtype=D64, radiometry="energy")
    x = torch.zeros(1, 3, 12, 12, dtype=D64)
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
    rb = _bank(K=5).resample_to(10, 10, dtype=D64, radiometry="energy")
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
    rb = _bank(G=4).resample_to(12, 12, dtype=D64, radiometry="energy")
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


def test_integer_primaries_are_refused_by_the_dtype_check():
    """The operators take float32 / float64 primaries: an integer image is refused by the dtype check
    (naming the allowed dtypes), not only by the later bank-dtype comparison."""
    rb = _bank().resample_to(8, 8)                                               # float32
    for op in (psf_exact, psf_distortion, psf_reference, psf_fast):
        with pytest.raises(InputValueError, match=r"primaries must have dtype in \['torch.float32', 'torch.float64'\], "
                                                  "got torch.int64"):
            op(torch.zeros(3, 8, 8, dtype=torch.int64), rb)


# ----------------------------------------------------------------------------- prescription
def test_prescription_surfaces_are_immutable_values():
    """A checked prescription's surfaces are frozen dataclasses: not editable after the checks, and
    equal by value."""
    rx, rx2 = Prescription.cardboard(), Prescription(CARDBOARD)
    s = rx.surfaces[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.thickness = 1.0                                                       # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        rx.surfaces[1].radius = math.inf                                        # type: ignore[misc]
    assert (s.thickness, rx.surfaces[1].radius) == (8.795, -25.498) and s == rx2.surfaces[0]


@pytest.mark.parametrize("key, value", [("object_distance_mm", 0), ("pupil_diameter_mm", -4.0),
                                        ("virtual_image_distance_mm", "667")])
def test_a_bad_number_is_refused_with_its_own_message(key, value):
    """A present but non-positive (or non-numeric) field is named by its own message, not reported as
    a missing or malformed field (that message is for absent keys and wrong shapes)."""
    spec = dict(CARDBOARD)
    spec[key] = value
    with pytest.raises(InputValueError) as e:
        Prescription(spec)
    assert str(e.value) == f"prescription[{key!r}] must be a positive number, got {value!r}"


# ----------------------------------------------------------------------------- bench
def test_bench_run_defaults_are_the_documented_command_defaults():
    """docs/optics.md, "Benchmark": ``controlgs optics bench [--sizes 256 512 1024 576x1024]
    [--radiometry radiance energy] [--tols 0.02] [--zone 5] [--threads 2] [--repeat 3]
    [--no-scaling]``, and ``--exact-max`` (default 1024, the command's help): ``bench.run`` has the
    same defaults (scaling on unless ``--no-scaling``)."""
    from controlgs_adapter.downstream.optics import bench

    p = {k: v.default for k, v in inspect.signature(bench.run).parameters.items()}
    assert tuple(p["sizes"]) == ("256", "512", "1024", "576x1024") and tuple(p["tols"]) == (0.02,)
    assert tuple(p["radiometries"]) == ("radiance", "energy")
    assert (p["zone"], p["threads"], p["repeat"], p["exact_max"], p["scaling"]) == (5, 2, 3, 1024, True)
    assert p["out"] is None and p["command"] == "controlgs optics bench --doc"


def test_bench_rows_report_each_operators_error_against_exact(tmp_path):
    """A tiny run (12 x 12, energy, tol 0.3, ``exact_max`` = 12: the size is at the limit, so exact is
    timed too): each row's ``rel_l2`` = ||y - exact|| / ||exact|| and ``max_rel`` = max|y - exact| /
    max|exact|, recomputed here in float64 from the public operators on the bench's own image."""
    pytest.importorskip("skimage")
    from controlgs_adapter.downstream.optics import bench

    n = torch.get_num_threads()
    try:
        rows = bench.run(sizes=["12"], exact_max=12, threads=1, tols=(0.3,), radiometries=("energy",), repeat=1,
                         scaling=False)
    finally:
        torch.set_num_threads(n)
    by = {r["op"]: r for r in rows}
    assert sorted(by) == ["distortion", "exact", "fast", "tables"]
    assert list(by["tables"]["fast_s"]) == [0.3] and by["fast"]["knob"] == "tol=0.3, zone=5"
    rb = PSFBank.default().resample_to(12, 12, radiometry="energy")
    x = bench._image(12)
    with torch.no_grad():
        ref = psf_exact(x, rb).double()
        outs = {"distortion": psf_distortion(x, rb), "fast": psf_fast(x, rb, 0.3, 5), "exact": psf_exact(x, rb)}
    for op, y in outs.items():
        d = y.double() - ref
        assert by[op]["rel_l2"] == pytest.approx((d.norm() / ref.norm()).item(), rel=1e-4, abs=1e-9), op
        assert by[op]["max_rel"] == pytest.approx((d.abs().max() / ref.abs().max()).item(), rel=1e-4, abs=1e-9), op
    assert by["distortion"]["rel_l2"] > 1e-4 and by["fast"]["rel_l2"] > 1e-6 and by["exact"]["rel_l2"] == 0
    assert math.isfinite(by["fast"]["fwd_bwd_s"]) and by["fast"]["fwd_bwd_s"] > 0


# ----------------------------------------------------------------------------- generate
@pytest.mark.parametrize("r", [0.0, 8.0, 16.0])
def test_spot_weights_cover_the_whole_pupil_disc(r):
    """Generator step 2 (module docstring): each kept ray stands for its pupil area, rim cells by the
    fraction inside the disc, so on the unvignetted Cardboard lens the weights add up to the pupil's
    area pi (2 mm)^2 (transmission and coverage 1) to the grid's sampling error, here < 2e-3 with
    ~40 rays across the pupil; the offsets are finite and the weights positive."""
    import numpy as np

    from controlgs_adapter.downstream.optics import generate
    from controlgs_adapter.downstream.optics.raytrace import chief_ray

    rx = Prescription.cardboard()
    v0, Y0, ok = chief_ray(rx, 550.0, np.array([r]))
    assert ok.all()
    sx, sy, w, tr, cov = generate._spot(rx, 550.0, r, v0[0], Y0[0], 40)
    assert w.sum() == pytest.approx(math.pi * 2.0 ** 2, rel=2e-3)
    assert tr == pytest.approx(1.0, abs=2e-3) and cov == pytest.approx(1.0, abs=2e-3) and tr <= 1.0
    assert (w > 0).all() and np.isfinite(sx).all() and np.isfinite(sy).all() and len(w) > 1000
