"""Tests of ``controlgs_adapter.metrics``: PSNR, SSIM and its Gaussian window against their definitions and
scikit-image, NVIDIA's FLIP and ColorVideoVDP through their packages, and the optional-metric table."""

from __future__ import annotations

import json
import math
import re
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.cvvdp_reference import direct_cvvdp, needs_cvvdp
from helpers.oracles import ssim_brute_force
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.metrics import (FLIP_PPD, ColorVideoVDP, check_image_pair, cvvdp_missing, flip, gaussian_window,
                                       optional_metrics, psnr, ssim)

D64 = torch.float64


def _pair(seed: int, shape=(3, 13, 16), noise: float = 0.2) -> tuple[torch.Tensor, torch.Tensor]:
    """A float64 image in [0, 1] and a noisy copy of it, clamped to [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=D64)
    return x, (x + noise * torch.randn(shape, generator=g, dtype=D64)).clamp(0, 1)


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.permute(1, 2, 0).contiguous().numpy()


# ------------------------------------------------------------------------------ SSIM
@pytest.mark.parametrize("data_range, size, sigma", [(1.0, 11, 1.5), (1.0, 7, 1.0), (1.0, 5, 2.5), (255.0, 7, 2.0),
                                                     (2.0, 5, 0.8), (0.5, 11, 1.5)])
def test_ssim_matches_the_brute_force_definition(data_range, size, sigma):
    x, y = _pair(0)
    x, y = x * data_range, y * data_range
    want = ssim_brute_force(x, y, data_range=data_range, size=size, sigma=sigma)
    assert float(ssim(x, y, data_range=data_range, window_size=size, sigma=sigma)) == pytest.approx(want, abs=1e-12)
    if (data_range, size, sigma) == (1.0, 11, 1.5):  # the defaults
        assert float(ssim(x, y)) == pytest.approx(want, abs=1e-12)


def test_ssim_scales_its_constants_with_the_data_range():
    """c1 and c2 scale with L: 8-bit values with ``data_range=255`` score as the [0, 1] images; without it they do not."""
    x, y = _pair(0)
    assert float(ssim(255 * x, 255 * y, data_range=255.0)) == pytest.approx(float(ssim(x, y)), abs=1e-12)
    assert float(ssim(255 * x, 255 * y)) != pytest.approx(float(ssim(x, y)), abs=1e-3)


def test_ssim_and_psnr_match_scikit_image():
    metrics = pytest.importorskip("skimage.metrics")
    x, y = _pair(1, (3, 32, 40), noise=0.1)
    a, b = _hwc(x), _hwc(y)
    ref = metrics.structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False)
    assert float(ssim(x, y)) == pytest.approx(ref, abs=1e-6)
    assert float(psnr(x, y)) == pytest.approx(metrics.peak_signal_noise_ratio(a, b, data_range=1.0), abs=1e-9)


def test_ssim_and_psnr_keep_batch_dimensions():
    """[2, 2, 3, H, W] in, [2, 2] out, each entry the pair's own value; float32 agrees to float32 precision."""
    xs, ys = zip(*(_pair(s, (3, 12, 11)) for s in range(4)))
    x, y = torch.stack(xs).view(2, 2, 3, 12, 11), torch.stack(ys).view(2, 2, 3, 12, 11)
    s, p = ssim(x, y), psnr(x, y)
    assert s.shape == (2, 2) and p.shape == (2, 2)
    for k in range(4):
        a, b = xs[k].numpy(), ys[k].numpy()
        assert float(s.view(-1)[k]) == pytest.approx(ssim_brute_force(a, b), abs=1e-12)
        assert float(p.view(-1)[k]) == pytest.approx(10 * math.log10(1.0 / np.mean((a - b) ** 2)), abs=1e-10)
    s32 = ssim(x.float(), y.float())
    assert s32.dtype == torch.float32 and float((s32.double() - s).abs().max()) < 1e-5


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.0, 0.5))
def test_ssim_and_psnr_properties(seed, scale):
    """SSIM is 1 for identical images, symmetric, at most 1, low against a black image; PSNR is symmetric."""
    x, y = _pair(seed, (3, 13, 15), noise=scale)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-12)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(y, x)), abs=1e-12)
    assert float(ssim(x, y)) <= 1.0 + 1e-12
    assert float(ssim(x, torch.zeros_like(x))) < 0.5
    assert float(psnr(x, y)) == pytest.approx(float(psnr(y, x)), abs=1e-9)


def test_ssim_gradients():
    x, y = _pair(2, (3, 12, 13), noise=0.1)
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ssim(t, y), (x,), fast_mode=True)


def test_ssim_needs_both_sides_at_least_the_window():
    ssim(torch.rand(3, 11, 11), torch.rand(3, 11, 11))  # exactly the window: one position
    for h, w in ((10, 11), (11, 10), (20, 6), (8, 8)):
        with pytest.raises(ShapeError, match=rf"11x11.*got {h}x{w}"):
            ssim(torch.rand(3, h, w), torch.rand(3, h, w))
    with pytest.raises(ShapeError, match=r"7x7.*got 6x9"):
        ssim(torch.rand(3, 6, 9), torch.rand(3, 6, 9), window_size=7)


def test_gaussian_window_values():
    # exp(-r^2 / 4.5) for r = -5..5, normalised (computed with math.exp)
    want = [0.00102838008447911, 0.007598758135239185, 0.03600077212843083, 0.10936068950970002, 0.2130055377112537,
            0.26601172486179436, 0.2130055377112537, 0.10936068950970002, 0.03600077212843083, 0.007598758135239185,
            0.00102838008447911]
    g = gaussian_window(dtype=D64)
    assert g.dtype == D64 and g.shape == (11,)
    assert torch.allclose(g, torch.tensor(want, dtype=D64), rtol=0, atol=1e-15)
    assert gaussian_window().dtype == torch.float32
    assert gaussian_window(1).tolist() == [1.0]
    # size 3, sigma 1: (e^-0.5, 1, e^-0.5) / (1 + 2 e^-0.5)
    e = math.exp(-0.5)
    assert torch.allclose(gaussian_window(3, 1.0, dtype=D64), torch.tensor([e, 1.0, e], dtype=D64) / (1 + 2 * e),
                          rtol=0, atol=1e-15)
    five = torch.tensor([math.exp(-(i - 2) ** 2 / (2 * 0.49)) for i in range(5)], dtype=D64)
    torch.testing.assert_close(gaussian_window(5, 0.7, dtype=D64), five / five.sum(), rtol=1e-14, atol=0)
    for bad in (0, -1, 4, 10):
        with pytest.raises(InputValueError, match=rf"window size.*got {bad}"):
            gaussian_window(bad)


# ------------------------------------------------------------------------------ PSNR
def test_psnr_known_values():
    x = torch.zeros(3, 4, 4)
    assert float(psnr(x, x + 0.1)) == pytest.approx(20.0, abs=1e-4)
    assert float(psnr(x, x)) == float("inf")
    # 8-bit values: an error of 5 levels everywhere is 10 log10(255^2 / 25) = 34.1514 dB, in either scale
    v = torch.full((3, 4, 5), 100.0, dtype=D64)
    assert float(psnr(v, v + 5.0, data_range=255.0)) == pytest.approx(10 * math.log10(255.0**2 / 25.0), abs=1e-9)
    assert float(psnr(v / 255.0, (v + 5.0) / 255.0)) == pytest.approx(34.15140352195873, abs=1e-9)
    # a batch of two pairs with data_range 4
    a, b = _pair(2, (3, 5, 6))
    xb, yb = torch.stack([a, b]) * 4.0, torch.stack([b, b * 0.5]) * 4.0
    want = [10 * math.log10(16.0 / float(((p - q) ** 2).mean())) for p, q in zip(xb, yb)]
    torch.testing.assert_close(psnr(xb, yb, data_range=4.0), torch.tensor(want, dtype=D64), rtol=1e-12, atol=0)


def test_image_pair_checks_name_the_argument():
    with pytest.raises(ShapeError, match=r"^x and y .*\[3, 4, 4\] and \[3, 4, 5\]"):
        check_image_pair(torch.rand(3, 4, 4), torch.rand(3, 4, 5))
    with pytest.raises(ShapeError, match=r"\[3, 8, 8\] and \[3, 8, 9\]"):
        psnr(torch.rand(3, 8, 8), torch.rand(3, 8, 9))
    with pytest.raises(Exception, match="^y"):
        psnr(torch.rand(3, 4, 4), torch.rand(2, 4, 4))
    with pytest.raises(Exception, match="^x"):
        ssim(torch.rand(4, 12, 12), torch.rand(3, 12, 12))


# ------------------------------------------------------------------------------ FLIP
def test_flip_is_the_packages_value_at_any_observer():
    """FLIP at the default observer (a 0.7 m wide 4K display seen from 0.7 m: 3840 px over 1 rad) and at
    other pixels per degree, below one included, is the package's own value; float32 and images that
    require grad (a render being trained) score the same, without torch's grad-to-number warning."""
    import flip_evaluator

    assert FLIP_PPD == pytest.approx(3840 * math.pi / 180, rel=1e-12) and FLIP_PPD == pytest.approx(67.0206, abs=1e-4)
    a, b = _pair(3, (3, 20, 24))
    for ppd in (FLIP_PPD, 10.0, 30, 0.5, 1.0):
        want = flip_evaluator.evaluate(_hwc(b), _hwc(a), "LDR", applyMagma=False, parameters={"ppd": float(ppd)})[1]
        assert flip(a, b, ppd=ppd) == pytest.approx(float(want), abs=1e-7)
    assert flip(a, b) == flip(a, b, ppd=FLIP_PPD) and flip(a, b) != flip(a, b, ppd=10.0)
    assert flip(a.float(), b.float()) == pytest.approx(flip(a, b), abs=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert flip(a.clone().requires_grad_(True), b.clone().requires_grad_(True)) == flip(a, b)
    assert flip(a, a) == 0.0 and flip(a, torch.rand(3, 20, 24, generator=torch.Generator().manual_seed(1))) > 0.1
    edge = torch.zeros(3, 20, 24, dtype=D64)
    assert flip(edge, edge + 1.0) > 0.5 and flip(edge, edge) == 0.0  # 0 and 1 themselves are accepted


def test_flip_matches_the_package_cli_and_png_loader(tmp_path):
    """Our wrapper takes [3, H, W] sRGB tensors; the package's own PNG loader and command line read
    the same 8-bit sRGB images: the same value (an H/W or channel mix-up or a linearisation would
    not agree on this non-square, colourful pair)."""
    import flip_evaluator

    rng = np.random.default_rng(0)
    a = (rng.random((20, 30, 3)) * 255).astype(np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-40, 40, a.shape), 0, 255).astype(np.uint8)
    Image.fromarray(a).save(tmp_path / "ref.png")
    Image.fromarray(b).save(tmp_path / "test.png")
    ref_t = torch.from_numpy(a).permute(2, 0, 1).double() / 255
    test_t = torch.from_numpy(b).permute(2, 0, 1).double() / 255
    ours = flip(test_t, ref_t)
    from_files = flip_evaluator.evaluate(str(tmp_path / "ref.png"), str(tmp_path / "test.png"), "LDR", applyMagma=False)[1]
    assert ours == pytest.approx(from_files, abs=1e-7)
    cli = Path(sys.executable).parent / "flip"
    out = subprocess.run([str(cli), "-r", str(tmp_path / "ref.png"), "-t", str(tmp_path / "test.png"), "-v", "1", "-nerm",
                          "-d", str(tmp_path)], capture_output=True, text=True, check=True).stdout
    assert ours == pytest.approx(float(re.search(r"Mean:\s*([0-9.]+)", out).group(1)), abs=1e-6)
    assert ours != pytest.approx(flip(test_t.flip(0), ref_t.flip(0)), abs=1e-4)  # channel order matters


def test_flip_refusals_name_the_argument_and_value():
    """Refusals name ``test`` before ``reference`` (FLIP's own argument names), the values found, and a
    ``ppd`` that is not a finite number > 0 (the package itself would sys.exit())."""
    a, b = _pair(3, (3, 20, 24))
    s, t = torch.rand(3, 12, 12), torch.rand(3, 12, 13)
    with pytest.raises(ShapeError, match=r"^test and reference .*\[3, 12, 12\] and \[3, 12, 13\]"):
        flip(s, t)
    with pytest.raises(ShapeError, match=r"^test and reference .*\[3, 12, 13\] and \[3, 12, 12\]"):
        flip(t, s)
    with pytest.raises(Exception, match="^reference"):
        flip(s, torch.rand(2, 12, 12))
    with pytest.raises(Exception, match="^test"):
        flip(torch.rand(2, 12, 12), s)
    with pytest.raises(ShapeError, match=r"\[3, H, W\].*\[1, 3, 20, 24\]"):
        flip(a[None], b[None])
    for bad in (0, 0.0, -1.0, math.inf, math.nan, True, "67", None):
        with pytest.raises(InputValueError, match=rf"ppd.*got {re.escape(repr(bad))}"):
            flip(a, b, ppd=bad)  # type: ignore[arg-type]
    out = a.clone()
    out[0, 0, 0], out[0, 0, 1] = -0.25, 1.0
    with pytest.raises(InputValueError, match=r"^flip: test .*got \[-0\.25, 1\]"):
        flip(out, b)
    with pytest.raises(InputValueError, match=r"^flip: reference .*got \[0, 1\.5\]"):
        flip(a, torch.cat([b[:, :1] * 0, b[:, 1:] * 0 + 1.5], dim=1))
    with pytest.raises(InputValueError, match="^flip: test "):
        flip(a.clamp(0, 1) + 0.5 * (a > 0.99), b)


def test_flip_without_its_package_says_how_to_install_it(monkeypatch):
    """Without ``flip-evaluator`` importable, FLIP is refused with the install line (not a NameError)."""
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # what Python does for a package that is absent
    x = torch.rand(3, 8, 8)
    with pytest.raises(InputValueError, match=r"^FLIP .*pip install flip-evaluator$"):
        flip(x, x)


# ------------------------------------------------------------------------------ ColorVideoVDP
@needs_cvvdp
def test_cvvdp_is_the_package_called_directly():
    """The library's JOD equals the package's on the same images and geometry; the ppd is the one given, per size
    ``(H, W)``, and it matters; identical images score 10."""
    asked = []

    def ppd_of(h: int, w: int) -> float:
        asked.append((h, w))
        return 2.0 + w / 4

    metric = ColorVideoVDP(ppd_of)
    for seed, shape in ((0, (3, 64, 64)), (1, (3, 48, 64))):
        ref, test = _pair(seed, shape, noise=0.05)
        score = metric(test, ref)
        assert score == pytest.approx(direct_cvvdp(test, ref, 18.0), abs=1e-6)
        assert score != pytest.approx(direct_cvvdp(test, ref, 40.0), abs=1e-3)
        assert 5.0 < score < 10.0 and isinstance(score, float)
        assert metric(ref, ref) == pytest.approx(10.0, abs=1e-6)
    assert asked == [(64, 64), (48, 64)] and metric.ppd_used == {"64x64": 18.0, "64x48": 18.0}
    fixed = ColorVideoVDP(25.0)
    ref, test = _pair(2, (3, 64, 64), noise=0.05)
    assert fixed(test, ref) == pytest.approx(direct_cvvdp(test, ref, 25.0), abs=1e-6)
    # sRGB values outside [0, 1] are clamped, as a display holds them
    assert fixed(test * 1.5 - 0.2, ref) == pytest.approx(direct_cvvdp((test * 1.5 - 0.2).clamp(0, 1), ref, 25.0), abs=1e-6)


@needs_cvvdp
def test_cvvdp_refusals_name_the_argument():
    x = torch.rand(3, 64, 64)
    for bad in (0.0, -3.0, float("nan"), float("inf"), True, "60"):
        with pytest.raises(InputValueError, match=r"^cvvdp: ppd must be .*for 64x64$"):
            ColorVideoVDP(bad)(x, x)
    with pytest.raises(InputValueError, match=r"^cvvdp: ppd .*got nan for 64x64$"):
        ColorVideoVDP(lambda h, w: float("nan"))(x, x)
    with pytest.raises(ShapeError, match=r"^cvvdp takes one image pair \[3, H, W\], got \[2, 3, 64, 64\]$"):
        ColorVideoVDP(30.0)(x.expand(2, 3, 64, 64), x.expand(2, 3, 64, 64))
    with pytest.raises(ShapeError, match="^test and reference must have the same shape"):
        ColorVideoVDP(30.0)(x, x[:, :32])


@needs_cvvdp
def test_cvvdp_makes_no_network_connection():
    """In a fresh interpreter whose sockets refuse to connect (and record every try), importing ColorVideoVDP and
    scoring with its base metric try none."""
    code = textwrap.dedent("""
        import json, socket
        tries = []
        def refuse(*args, **kwargs):
            tries.append(repr(args[1:] or args))
            raise OSError("network disabled")
        socket.socket.connect = socket.socket.connect_ex = refuse
        socket.create_connection = socket.getaddrinfo = refuse
        import torch
        from controlgs_adapter.metrics import ColorVideoVDP
        x = torch.rand(3, 64, 64, generator=torch.Generator().manual_seed(0))
        jod = ColorVideoVDP(20.0)((x + 0.05).clamp(0, 1), x)
        print(json.dumps({"jod": jod, "tries": tries}))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["tries"] == [] and 5.0 < result["jod"] < 10.0


# ------------------------------------------------------------------------------ optional metrics
def test_optional_metrics(monkeypatch):
    found = optional_metrics()
    assert list(found) == ["flip"] and found["flip"] is flip  # ColorVideoVDP needs the pixels per degree
    calls = []

    def fake_lpips(e: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        calls.append((e, g))
        return torch.tensor(0.375)

    found = optional_metrics(fake_lpips)
    assert list(found) == ["flip", "lpips"]
    x = torch.zeros(3, 4, 4)
    value = found["lpips"](x, x + 1)
    assert value == 0.375 and isinstance(value, float) and calls[0][0] is x
    monkeypatch.setitem(sys.modules, "pycvvdp", None)  # ColorVideoVDP not installed: left out, and said why
    assert list(optional_metrics(ppd=30.0)) == ["flip"]
    assert re.fullmatch(r"ColorVideoVDP does not import \(.*\); pip install .*--no-deps cvvdp==0\.5\.7", cvvdp_missing() or "")


@needs_cvvdp
def test_optional_metrics_with_cvvdp():
    found = optional_metrics(ppd=30.0)
    assert list(found) == ["flip", "cvvdp"] and isinstance(found["cvvdp"], ColorVideoVDP) and cvvdp_missing() is None
    ref, test = _pair(3, (3, 64, 64), noise=0.05)
    assert found["cvvdp"](test, ref) == pytest.approx(direct_cvvdp(test, ref, 30.0), abs=1e-6)
