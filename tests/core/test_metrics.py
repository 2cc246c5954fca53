"""Tests of ``controlgs_adapter.metrics``."""

from __future__ import annotations

import math
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.losses import LossWeights, image_loss
from controlgs_adapter.metrics import FLIP_PPD, check_image_pair, flip, gaussian_window, optional_metrics, psnr, ssim


def _pair(seed, shape=(3, 17, 21), dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=dtype)
    y = (x + 0.1 * torch.randn(shape, generator=g, dtype=dtype)).clamp(0, 1)
    return x, y


def _ssim_bruteforce(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. with an explicit 11x11 Gaussian (sigma 1.5) at every valid window position."""
    r = np.arange(11) - 5.0
    g1 = np.exp(-r**2 / (2 * 1.5**2))
    w = np.outer(g1, g1) / np.outer(g1, g1).sum()
    c1, c2 = 0.01**2, 0.03**2
    vals = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - 10):
            for j in range(x.shape[2] - 10):
                a, b = x[c, i:i + 11, j:j + 11], y[c, i:i + 11, j:j + 11]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
                cov = (w * (a - ma) * (b - mb)).sum()
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


def test_ssim_matches_bruteforce():
    x, y = _pair(0)
    assert float(ssim(x, y)) == pytest.approx(_ssim_bruteforce(x.numpy(), y.numpy()), abs=1e-12)
    # float32 path agrees to float32 precision, batch dims are kept
    xb, yb = torch.stack([x, y]).float(), torch.stack([y, x]).float()
    out = ssim(xb, yb)
    assert out.shape == (2,) and float((out - float(ssim(x, y))).abs().max()) < 1e-5


def test_against_scikit_image():
    metrics = pytest.importorskip("skimage.metrics")
    x, y = _pair(1, (3, 32, 40))
    a, b = x.permute(1, 2, 0).numpy(), y.permute(1, 2, 0).numpy()
    ref = metrics.structural_similarity(a, b, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                        use_sample_covariance=False)
    assert float(ssim(x, y)) == pytest.approx(ref, abs=1e-6)
    assert float(psnr(x, y)) == pytest.approx(metrics.peak_signal_noise_ratio(a, b, data_range=1.0), abs=1e-9)


def test_psnr_known_value_and_identity():
    x = torch.zeros(3, 4, 4)
    assert float(psnr(x, x + 0.1)) == pytest.approx(20.0, abs=1e-4)
    assert float(psnr(x, x)) == float("inf")
    assert float(ssim(torch.rand(3, 12, 12), torch.rand(3, 12, 12) * 0)) < 0.5


def test_psnr_data_range_by_hand():
    # 8-bit values: an error of 5 levels everywhere is 10 log10(255^2 / 25) = 34.1514 dB
    x = torch.full((3, 4, 5), 100.0, dtype=torch.float64)
    assert float(psnr(x, x + 5.0, data_range=255.0)) == pytest.approx(10 * math.log10(255.0**2 / 25.0), abs=1e-9)
    assert float(psnr(x / 255.0, (x + 5.0) / 255.0)) == pytest.approx(34.15140352195873, abs=1e-9)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.floats(0.0, 0.5))
def test_ssim_properties(seed, scale):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(3, 13, 15, generator=g, dtype=torch.float64)
    y = (x + scale * torch.randn(3, 13, 15, generator=g, dtype=torch.float64)).clamp(0, 1)
    assert float(ssim(x, x)) == pytest.approx(1.0, abs=1e-12)
    assert float(ssim(x, y)) == pytest.approx(float(ssim(y, x)), abs=1e-12)
    assert float(ssim(x, y)) <= 1.0 + 1e-12
    assert float(psnr(x, y)) == pytest.approx(float(psnr(y, x)), abs=1e-9)


def test_gradients():
    x, y = _pair(2, (3, 12, 13))
    x.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: ssim(t, y), (x,), fast_mode=True)
    assert torch.autograd.gradcheck(lambda t: image_loss(t, y), (x,), fast_mode=True)


def test_errors_are_clear():
    with pytest.raises(InputValueError, match="LPIPS"):
        LossWeights(lpips=0.1)
    with pytest.raises(InputValueError, match="l1"):
        LossWeights(l1=-1.0)
    with pytest.raises(ShapeError, match="at least 11x11"):
        ssim(torch.rand(3, 8, 8), torch.rand(3, 8, 8))
    with pytest.raises(ShapeError, match="same shape"):
        psnr(torch.rand(3, 8, 8), torch.rand(3, 8, 9))


D = torch.float64


def _images(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(3, h, w, generator=g, dtype=D)
    y = (x + 0.2 * torch.randn(3, h, w, generator=g, dtype=D)).clamp(0, 1)
    return x, y


def _ssim_by_hand(x: torch.Tensor, y: torch.Tensor, data_range: float, size: int, sigma: float) -> float:
    """Brute-force SSIM: every valid window position, Gaussian weights g(u) g(v), exp(-r^2 / 2 sigma^2)
    normalised, c1 = (0.01 L)^2, c2 = (0.03 L)^2, mean over channels and positions."""
    r = [i - (size - 1) / 2 for i in range(size)]
    g = [math.exp(-t * t / (2 * sigma * sigma)) for t in r]
    g = [v / sum(g) for v in g]
    w = torch.tensor([[a * b for b in g] for a in g], dtype=D)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    vals = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - size + 1):
            for j in range(x.shape[2] - size + 1):
                px, py = x[c, i:i + size, j:j + size], y[c, i:i + size, j:j + size]
                mx, my = (w * px).sum(), (w * py).sum()
                vx, vy = (w * px * px).sum() - mx * mx, (w * py * py).sum() - my * my
                cxy = (w * px * py).sum() - mx * my
                vals.append(float((2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2))))
    return sum(vals) / len(vals)


@pytest.mark.parametrize("data_range,size,sigma", [(1.0, 11, 1.5), (255.0, 7, 2.0), (2.0, 5, 0.8)])
def test_ssim_options_by_hand(data_range, size, sigma):
    x, y = _images(12, 14, 1)
    x, y = x * data_range, y * data_range
    got = float(ssim(x, y, data_range=data_range, window_size=size, sigma=sigma))
    assert got == pytest.approx(_ssim_by_hand(x, y, data_range, size, sigma), rel=1e-10, abs=1e-12)


def test_gaussian_window_options_by_hand():
    got = gaussian_window(5, 0.7, dtype=D)
    want = torch.tensor([math.exp(-(i - 2) ** 2 / (2 * 0.49)) for i in range(5)], dtype=D)
    torch.testing.assert_close(got, want / want.sum(), rtol=1e-14, atol=0)


def test_psnr_batch_and_data_range_by_hand():
    x, y = _images(5, 6, 2)
    xb, yb = torch.stack([x, y]) * 4.0, torch.stack([y, y * 0.5]) * 4.0
    got = psnr(xb, yb, data_range=4.0)
    want = [10 * math.log10(16.0 / float(((a - b) ** 2).mean())) for a, b in zip(xb, yb)]
    torch.testing.assert_close(got, torch.tensor(want, dtype=D), rtol=1e-12, atol=0)


def _image(seed: int, h: int = 20, w: int = 28) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(3, h, w, generator=g, dtype=torch.float64)


def test_flip_of_identical_images_is_zero_and_checks_its_arguments():
    x = _image(0)
    assert flip(x, x) == 0.0
    assert flip(x, _image(1)) > 0.1
    with pytest.raises(InputValueError, match="ppd"):
        flip(x, x, ppd=0.0)  # the package itself would sys.exit()
    with pytest.raises(InputValueError, match=r"\[0, 1\]"):
        flip(x * 1.5, x)
    with pytest.raises(ShapeError):
        flip(torch.stack([x, x]), torch.stack([x, x]))


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


# ------------------------------------------------------------------------------ metrics
def test_flip_refusals_name_test_and_reference():
    """FLIP's shape refusals name its own arguments, ``test`` first (its other refusals already do)."""
    a, b = torch.rand(3, 12, 12), torch.rand(3, 12, 13)
    with pytest.raises(ShapeError, match=r"^test and reference must have the same shape, got \[3, 12, 12\] and \[3, 12, 13\]"):
        flip(a, b)
    with pytest.raises(ShapeError, match=r"^test and reference must have the same shape, got \[3, 12, 13\] and \[3, 12, 12\]"):
        flip(b, a)
    with pytest.raises(Exception, match="^reference"):
        flip(a, torch.rand(2, 12, 12))
    with pytest.raises(Exception, match="^test"):
        flip(torch.rand(2, 12, 12), a)


def test_flip_without_its_package_says_how_to_install_it(monkeypatch):
    """Without ``flip-evaluator`` importable, FLIP is refused with the install line (not a NameError)."""
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # what Python does for a package that is absent
    x = torch.rand(3, 8, 8)
    with pytest.raises(InputValueError, match=r"^FLIP needs the flip-evaluator package .*: pip install flip-evaluator$"):
        flip(x, x)


def test_flip_takes_any_positive_pixels_per_degree():
    """``ppd`` must be > 0 (documented refusal); an observer below one pixel per degree is still one: FLIP
    at ppd 0.5 and 1 is the package's own value there."""
    import flip_evaluator

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 12, 12, generator=g, dtype=torch.float64), torch.rand(3, 12, 12, generator=g, dtype=torch.float64)
    hwc = lambda t: t.permute(1, 2, 0).contiguous().numpy()  # noqa: E731
    for ppd in (0.5, 1.0):
        want = float(flip_evaluator.evaluate(hwc(b), hwc(a), "LDR", applyMagma=False, parameters={"ppd": ppd})[1])
        assert flip(a, b, ppd=ppd) == pytest.approx(want, abs=1e-9)


def _pair_2(seed: int, shape=(3, 13, 16)) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(shape, generator=g, dtype=torch.float64)
    return x, (x + 0.2 * torch.randn(shape, generator=g, dtype=torch.float64)).clamp(0, 1)


def _ssim_brute(x: np.ndarray, y: np.ndarray, size: int, sigma: float, L: float) -> float:
    """Wang et al. at every valid window position, an explicit size x size Gaussian window."""
    r = np.arange(size) - (size - 1) / 2
    g1 = np.exp(-r**2 / (2 * sigma**2))
    w = np.outer(g1, g1) / np.outer(g1, g1).sum()
    c1, c2 = (0.01 * L) ** 2, (0.03 * L) ** 2
    vals = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - size + 1):
            for j in range(x.shape[2] - size + 1):
                a, b = x[c, i:i + size, j:j + size], y[c, i:i + size, j:j + size]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * (a - ma) ** 2).sum(), (w * (b - mb) ** 2).sum()
                cov = (w * (a - ma) * (b - mb)).sum()
                vals.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return float(np.mean(vals))


# ------------------------------------------------------------------------------ PSNR / SSIM
def test_gaussian_window_numbers():
    # exp(-r^2 / 4.5) for r = -5..5, normalised (computed with math.exp)
    want = [0.00102838008447911, 0.007598758135239185, 0.03600077212843083, 0.10936068950970002, 0.2130055377112537,
            0.26601172486179436, 0.2130055377112537, 0.10936068950970002, 0.03600077212843083, 0.007598758135239185,
            0.00102838008447911]
    g = gaussian_window(dtype=torch.float64)
    assert g.dtype == torch.float64 and g.shape == (11,)
    assert torch.allclose(g, torch.tensor(want, dtype=torch.float64), rtol=0, atol=1e-15)
    assert gaussian_window().dtype == torch.float32
    assert gaussian_window(1).tolist() == [1.0]
    # size 3, sigma 1: (e^-0.5, 1, e^-0.5) / (1 + 2 e^-0.5)
    e = math.exp(-0.5)
    assert torch.allclose(gaussian_window(3, 1.0, dtype=torch.float64),
                          torch.tensor([e, 1.0, e], dtype=torch.float64) / (1 + 2 * e), rtol=0, atol=1e-15)
    for bad in (0, -1, 4, 10):
        with pytest.raises(InputValueError, match=f"window size must be odd and >= 1, got {bad}"):
            gaussian_window(bad)


def test_ssim_other_windows_and_ranges_against_brute_force():
    x, y = _pair_2(0)
    assert float(ssim(x, y, window_size=7, sigma=1.0)) == pytest.approx(
        _ssim_brute(x.numpy(), y.numpy(), 7, 1.0, 1.0), abs=1e-12)
    assert float(ssim(x, y, window_size=5, sigma=2.5)) == pytest.approx(
        _ssim_brute(x.numpy(), y.numpy(), 5, 2.5, 1.0), abs=1e-12)
    # the default window is 11 taps of sigma 1.5
    assert float(ssim(x, y)) == pytest.approx(_ssim_brute(x.numpy(), y.numpy(), 11, 1.5, 1.0), abs=1e-12)
    # 8-bit values with data_range 255: C1, C2 scale with L, so SSIM is that of the [0, 1] images
    assert float(ssim(255 * x, 255 * y, data_range=255.0)) == pytest.approx(float(ssim(x, y)), abs=1e-12)
    assert float(ssim(255 * x, 255 * y)) != pytest.approx(float(ssim(x, y)), abs=1e-3)
    assert float(ssim(0.5 * x, 0.5 * y, data_range=0.5)) == pytest.approx(
        _ssim_brute(0.5 * x.numpy(), 0.5 * y.numpy(), 11, 1.5, 0.5), abs=1e-12)


def test_ssim_and_psnr_keep_batch_dimensions():
    xs, ys = zip(*(_pair_2(s, (3, 12, 11)) for s in range(4)))
    x, y = torch.stack(xs).view(2, 2, 3, 12, 11), torch.stack(ys).view(2, 2, 3, 12, 11)
    s, p = ssim(x, y), psnr(x, y)
    assert s.shape == (2, 2) and p.shape == (2, 2)
    for k in range(4):
        a, b = xs[k].numpy(), ys[k].numpy()
        assert float(s.view(-1)[k]) == pytest.approx(_ssim_brute(a, b, 11, 1.5, 1.0), abs=1e-12)
        assert float(p.view(-1)[k]) == pytest.approx(10 * math.log10(1.0 / np.mean((a - b) ** 2)), abs=1e-10)


def test_ssim_needs_both_sides_at_least_the_window():
    ssim(torch.rand(3, 11, 11), torch.rand(3, 11, 11))  # exactly the window: one position
    for h, w in ((10, 11), (11, 10), (20, 6)):
        with pytest.raises(ShapeError, match=f"at least 11x11 pixels \\(window size\\), got {h}x{w}"):
            ssim(torch.rand(3, h, w), torch.rand(3, h, w))
    with pytest.raises(ShapeError, match="at least 7x7"):
        ssim(torch.rand(3, 6, 9), torch.rand(3, 6, 9), window_size=7)


def test_image_pair_checks_name_the_argument():
    with pytest.raises(ShapeError, match=r"x and y must have the same shape, got \[3, 4, 4\] and \[3, 4, 5\]"):
        check_image_pair(torch.rand(3, 4, 4), torch.rand(3, 4, 5))
    with pytest.raises(Exception, match="^y"):
        psnr(torch.rand(3, 4, 4), torch.rand(2, 4, 4))
    with pytest.raises(Exception, match="^x"):
        ssim(torch.rand(4, 12, 12), torch.rand(3, 12, 12))


# ------------------------------------------------------------------------------ FLIP
def test_flip_observer_and_refusals():
    # the default observer: a 0.7 m wide 4K display seen from 0.7 m, 3840 px over 1 rad ~ 3840 pi / 180 px per degree
    assert FLIP_PPD == pytest.approx(3840 * math.pi / 180, rel=1e-12) and FLIP_PPD == pytest.approx(67.0206, abs=1e-4)
    import flip_evaluator

    a, b = _pair_2(3, (3, 20, 24))
    hwc = lambda t: t.permute(1, 2, 0).contiguous().numpy()  # noqa: E731
    for ppd in (FLIP_PPD, 10.0, 30):
        want = flip_evaluator.evaluate(hwc(b), hwc(a), "LDR", applyMagma=False, parameters={"ppd": float(ppd)})[1]
        assert flip(a, b, ppd=ppd) == pytest.approx(float(want), abs=1e-7)
    assert flip(a, b) == pytest.approx(flip(a, b, ppd=FLIP_PPD), abs=0) and flip(a, b) != flip(a, b, ppd=10.0)
    assert flip(a.float(), b.float()) == pytest.approx(flip(a, b), abs=1e-6)
    # an image that requires grad (a render being trained) is scored as its value
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # and without torch's warning on converting a grad tensor to a number
        assert flip(a.clone().requires_grad_(True), b.clone().requires_grad_(True)) == flip(a, b)
    with pytest.raises(ShapeError, match=r"one image pair \[3, H, W\], got \[1, 3, 20, 24\]"):
        flip(a[None], b[None])
    for bad in (0, 0.0, -1.0, math.inf, math.nan, True, "67", None):
        with pytest.raises(InputValueError, match="ppd must be a finite number > 0"):
            flip(a, b, ppd=bad)  # type: ignore[arg-type]
    t = a.clone()
    t[0, 0, 0], t[0, 0, 1] = -0.25, 1.0
    with pytest.raises(InputValueError, match=r"flip: test must hold sRGB values in \[0, 1\] \(LDR-FLIP\), got \[-0\.25, 1\]"):
        flip(t, b)
    with pytest.raises(InputValueError, match=r"flip: reference must hold .* got \[0, 1\.5\]"):
        flip(a, torch.cat([b[:, :1] * 0, b[:, 1:] * 0 + 1.5], dim=1))
    with pytest.raises(InputValueError, match="test must hold"):
        flip(a.clamp(0, 1) + 0.5 * (a > 0.99), b)
    edge = torch.zeros(3, 20, 24, dtype=torch.float64)
    assert flip(edge, edge + 1.0) > 0.5 and flip(edge, edge) == 0.0  # 0 and 1 themselves are accepted


def test_optional_metrics():
    found = optional_metrics()
    assert list(found) == ["flip"] and found["flip"] is flip  # pycvvdp is not installed here
    calls = []

    def fake_lpips(e: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        calls.append((e, g))
        return torch.tensor(0.375)

    found = optional_metrics(fake_lpips)
    assert list(found) == ["flip", "lpips"]
    x = torch.zeros(3, 4, 4)
    value = found["lpips"](x, x + 1)
    assert value == 0.375 and isinstance(value, float) and calls[0][0] is x
