"""controlgs_adapter.metrics and .perceptual by hand: the Gaussian window's numbers, SSIM with other
windows and ranges against a float64 brute force, PSNR per image of a batch, FLIP's argument checks
and its observer, the LPIPS key names, file refusals and network against a float64 AlexNet written
out here with the published LPIPS constants."""

from __future__ import annotations

import math
import pickle
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.metrics import FLIP_PPD, check_image_pair, flip, gaussian_window, optional_metrics, psnr, ssim
from controlgs_adapter.perceptual import LPIPS, LPIPS_MIN_SIZE, _canonical, _expected, _read, load_lpips


def _pair(seed: int, shape=(3, 13, 16)) -> tuple[torch.Tensor, torch.Tensor]:
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
    x, y = _pair(0)
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
    xs, ys = zip(*(_pair(s, (3, 12, 11)) for s in range(4)))
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

    a, b = _pair(3, (3, 20, 24))
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


# ------------------------------------------------------------------------------ LPIPS
def test_canonical_key_names():
    cases = {"features.0.weight": "conv0.weight", "features.3.bias": "conv1.bias", "features.6.weight": "conv2.weight",
             "features.8.bias": "conv3.bias", "features.10.weight": "conv4.weight", "features.1.weight": None,
             "features.12.weight": None, "features.0.running_mean": None, "features.x.weight": None,
             "net.slice1.0.weight": "conv0.weight", "net.slice5.10.bias": "conv4.bias", "net.slice2.4.weight": None,
             "net.slice1.0.other": None, "lin0.model.1.weight": "lin0", "lin4.model.0.weight": "lin4",
             "lin5.model.1.weight": None, "lin1.model.2.weight": None, "lin1.model.1.bias": None,
             "lin1.model.1": None, "classifier.1.weight": None, "conv0.weight": None, "features.0": None}
    for key, want in cases.items():
        assert _canonical(key) == want, key


def test_expected_shapes_of_alexnet_and_head():
    e = _expected()
    assert len(e) == 15
    assert e["conv0.weight"] == (64, 3, 11, 11) and e["conv1.weight"] == (192, 64, 5, 5)
    assert e["conv2.weight"] == (384, 192, 3, 3) and e["conv3.weight"] == (256, 384, 3, 3)
    assert e["conv4.weight"] == (256, 256, 3, 3) and e["conv4.bias"] == (256,) and e["conv2.bias"] == (384,)
    assert [e[f"lin{i}"] for i in range(5)] == [(1, 64, 1, 1), (1, 192, 1, 1), (1, 384, 1, 1), (1, 256, 1, 1),
                                                (1, 256, 1, 1)]


def _weights(seed: int = 0, scale: float = 0.1) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    w = {k: (torch.rand(s, generator=g) - 0.3) * scale for k, s in _expected().items()}
    for i in range(5):
        w[f"lin{i}"] = w[f"lin{i}"].abs()
    return w


def _lpips_brute(w: dict[str, torch.Tensor], x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """LPIPS v0.1 (alex) in float64 from its definition: AlexNet conv1 (11x11, stride 4, pad 2) - ReLU -
    maxpool 3/2 - conv2 (5x5, pad 2) - ReLU - maxpool 3/2 - conv3..5 (3x3, pad 1) - ReLU; inputs
    2x - 1, then (v - shift) / scale with shift (-.030, -.088, -.188), scale (.458, .448, .450);
    channel-unit-normalised taps (eps 1e-10), squared difference, 1x1 head, spatial mean, sum."""
    shift = torch.tensor([-0.030, -0.088, -0.188], dtype=torch.float64).view(3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450], dtype=torch.float64).view(3, 1, 1)
    d = {k: v.double() for k, v in w.items()}

    def taps(v: torch.Tensor) -> list[torch.Tensor]:
        v = ((2 * v - 1) - shift) / scale
        out = []
        v = F.relu(F.conv2d(v, d["conv0.weight"], d["conv0.bias"], stride=4, padding=2))
        out.append(v)
        v = F.relu(F.conv2d(F.max_pool2d(v, 3, 2), d["conv1.weight"], d["conv1.bias"], padding=2))
        out.append(v)
        v = F.relu(F.conv2d(F.max_pool2d(v, 3, 2), d["conv2.weight"], d["conv2.bias"], padding=1))
        out.append(v)
        v = F.relu(F.conv2d(v, d["conv3.weight"], d["conv3.bias"], padding=1))
        out.append(v)
        out.append(F.relu(F.conv2d(v, d["conv4.weight"], d["conv4.bias"], padding=1)))
        return out

    total = torch.zeros(x.shape[0], dtype=torch.float64)
    for i, (a, b) in enumerate(zip(taps(x.double()), taps(y.double()))):
        a = a / (a.square().sum(1, keepdim=True).sqrt() + 1e-10)
        b = b / (b.square().sum(1, keepdim=True).sqrt() + 1e-10)
        total += ((a - b).square() * d[f"lin{i}"].view(1, -1, 1, 1)).sum(1).mean(dim=(-2, -1))
    return total


def test_lpips_against_a_float64_network_written_out():
    w = _weights()
    net = LPIPS(w, "mine")
    assert net.source == "mine" and not net.training
    g = torch.Generator().manual_seed(5)
    x, y = torch.rand(2, 3, 37, 45, generator=g), torch.rand(2, 3, 37, 45, generator=g)
    with torch.no_grad():
        got = net(x, y)
    assert got.shape == (2,) and got.dtype == torch.float32
    assert torch.allclose(got.double(), _lpips_brute(w, x, y), rtol=2e-5, atol=1e-8)
    # negative biases leave channels dead (all-zero taps): the eps keeps them at 0, not NaN
    dead = dict(w)
    dead["conv0.bias"] = torch.full((64,), -50.0)
    with torch.no_grad():
        out = LPIPS(dead)(x, y)
    assert bool(torch.isfinite(out).all()) and torch.allclose(out.double(), _lpips_brute(dead, x, y), rtol=2e-5, atol=1e-8)
    # leading dimensions are kept, float64 inputs run in the buffers' float32
    with torch.no_grad():
        assert net(x.view(1, 2, 3, 37, 45).double(), y.view(1, 2, 3, 37, 45).double()).shape == (1, 2)


def test_lpips_size_and_weight_refusals():
    net = LPIPS(_weights())
    # the pair's checks name the argument at fault, x before y
    with pytest.raises(ShapeError, match=r"x and y must have the same shape, got \[3, 31, 31\] and \[3, 31, 32\]"):
        net(torch.rand(3, 31, 31), torch.rand(3, 31, 32))
    with pytest.raises(Exception, match="^y"):
        net(torch.rand(3, 31, 31), torch.rand(3, 31, 31, dtype=torch.float64).to(torch.int64))
    with pytest.raises(Exception, match="^x"):
        net(torch.rand(2, 31, 31), torch.rand(3, 31, 31))
    with torch.no_grad():
        net(torch.rand(3, LPIPS_MIN_SIZE, LPIPS_MIN_SIZE), torch.rand(3, LPIPS_MIN_SIZE, LPIPS_MIN_SIZE))
    assert LPIPS_MIN_SIZE == 31
    for h, w in ((30, 40), (40, 30)):
        with pytest.raises(ShapeError, match=f"at least 31x31 pixels, got {h}x{w}"):
            net(torch.rand(3, h, w), torch.rand(3, h, w))
    backbone = {k: v for k, v in _weights().items() if k.startswith("conv")}
    with pytest.raises(InputValueError, match=r"LPIPS weights src: missing \['lin0', .*'lin4'\] \(the LPIPS head") as e:
        LPIPS(backbone, "src")
    assert "alexnet-owt" not in str(e.value)
    head = {k: v for k, v in _weights().items() if k.startswith("lin")}
    with pytest.raises(InputValueError, match=r"missing \['conv0.bias'.*\(the AlexNet backbone: torchvision's alexnet") as e:
        LPIPS(head)
    assert "LPIPS head" not in str(e.value)
    bad = _weights()
    bad["conv1.weight"] = bad["conv1.weight"][:, :, :3, :3]
    with pytest.raises(InputValueError, match=r"conv1.weight must be a float tensor of shape \[192, 64, 5, 5\]"):
        LPIPS(bad)
    ints = _weights()
    ints["lin2"] = ints["lin2"].to(torch.int32)
    with pytest.raises(InputValueError, match=r"lin2 must be a float tensor .* got torch.int32"):
        LPIPS(ints)
    # float64 weights are kept as float32 copies (the caller's tensors untouched)
    w64 = {k: v.double() for k, v in _weights().items()}
    net64 = LPIPS(w64)
    assert net64.conv0_weight.dtype == torch.float32 and w64["conv0.weight"].dtype == torch.float64
    assert net64.shift.view(-1).tolist() == pytest.approx([-0.030, -0.088, -0.188])
    assert net64.scale.view(-1).tolist() == pytest.approx([0.458, 0.448, 0.450])


class _NotATensor:
    pass


def test_weight_files_refused_by_name(tmp_path: Path):
    with pytest.raises(InputValueError, match="LPIPS: no weight files given"):
        load_lpips([])
    missing = tmp_path / "nope.pth"
    with pytest.raises(InputValueError, match=f"LPIPS weights {missing}: no such file"):
        load_lpips(missing)
    obj = tmp_path / "obj.pth"
    torch.save({"a": _NotATensor()}, obj)
    with pytest.raises(InputValueError, match="refused, not a tensor-only checkpoint"):
        _read(obj)
    text = tmp_path / "text.pth"
    text.write_text("hello")
    with pytest.raises(InputValueError, match=f"LPIPS weights {text}: not a torch checkpoint or safetensors file"):
        _read(text)
    bad_st = tmp_path / "bad.safetensors"
    bad_st.write_bytes(b"\x00" * 4)
    with pytest.raises(InputValueError, match="not a torch checkpoint or safetensors file"):
        _read(bad_st)
    lst = tmp_path / "list.pth"
    torch.save([torch.zeros(1)], lst)
    with pytest.raises(InputValueError, match=r"expected a flat \{name: tensor\} state dict, got list"):
        _read(lst)
    nested = tmp_path / "nested.pth"
    torch.save({"a": {"b": torch.zeros(1)}}, nested)
    with pytest.raises(InputValueError, match="got dict"):
        _read(nested)
    other = tmp_path / "other.pth"
    torch.save({f"k{i}": torch.zeros(1) for i in range(9)}, other)
    with pytest.raises(InputValueError, match=r"none of its keys .* it holds \['k0', .*'k7'\] \.\.\.$"):
        load_lpips(other)
    few = tmp_path / "few.pth"
    torch.save({"k0": torch.zeros(1)}, few)
    with pytest.raises(InputValueError, match=r"it holds \['k0'\]$"):
        load_lpips(str(few))
    assert pickle is not None


def test_load_lpips_merges_files_and_finds_the_package_head(tmp_path: Path):
    from safetensors.torch import save_file

    w = _weights(2)
    tv = {}
    for i, (idx, *_rest) in enumerate(((0,), (3,), (6,), (8,), (10,))):
        tv[f"features.{idx}.weight"] = w[f"conv{i}.weight"]
        tv[f"features.{idx}.bias"] = w[f"conv{i}.bias"]
    tv["classifier.1.weight"] = torch.zeros(2, 2)  # ignored
    head = {f"lin{i}.model.1.weight": w[f"lin{i}"] for i in range(5)}
    torch.save(tv, tmp_path / "alex.pth")
    save_file(head, str(tmp_path / "head.safetensors"))
    net = load_lpips([tmp_path / "alex.pth", str(tmp_path / "head.safetensors")])
    assert net.source == f"{tmp_path / 'alex.pth'}, {tmp_path / 'head.safetensors'}"
    x, y = torch.rand(1, 3, 33, 33), torch.rand(1, 3, 33, 33)
    with torch.no_grad():
        assert torch.allclose(net(x, y).double(), _lpips_brute(w, x, y), rtol=2e-5, atol=1e-8)
    # the backbone alone: the installed lpips package's head file is added, and named
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        pytest.skip("lpips not installed")
    alone = load_lpips(tmp_path / "alex.pth")
    assert alone.source.startswith(f"{tmp_path / 'alex.pth'} + ") and alone.source.endswith("alex.pth")
    assert not torch.equal(alone.lin0, net.lin0)
    # a file with a head keeps its own head
    assert torch.equal(load_lpips([tmp_path / "head.safetensors", tmp_path / "alex.pth"]).lin3, w["lin3"])


def test_image_loss_checks_name_pred_and_target_in_order():
    from controlgs_adapter.errors import ShapeError as _ShapeError
    from controlgs_adapter.losses import image_loss

    with pytest.raises(_ShapeError, match=r"pred and target must have the same shape, got \[3, 4, 4\] and \[3, 4, 5\]"):
        image_loss(torch.rand(3, 4, 4), torch.rand(3, 4, 5))
    with pytest.raises(_ShapeError, match="target"):
        image_loss(torch.rand(3, 4, 4), torch.rand(2, 4, 4))
