"""Tests of ``controlgs_adapter.perceptual``: LPIPS (AlexNet, v0.1) against the lpips package and a float64
network written out, its invariants and refusals, and the weight files it reads (torchvision, lpips,
safetensors; tensors only, saved on any device)."""

from __future__ import annotations

import argparse
import io
import sys
import types
import zipfile
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from helpers.lpips_weights import random_lpips_weights

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.perceptual import LPIPS, LPIPS_MIN_SIZE, _canonical, _expected, _read, load_lpips

#: the files the missing-weight hints point at
BACKBONE_FILE = "alexnet-owt-7be5be79.pth"
HEAD_FILE = "weights/v0.1/alex.pth"


def _alexnet_features() -> torch.nn.Sequential:
    """torchvision's AlexNet ``features`` layout (the stand-in's backbone), random weights."""
    nn = torch.nn
    return nn.Sequential(nn.Conv2d(3, 64, 11, 4, 2), nn.ReLU(), nn.MaxPool2d(3, 2), nn.Conv2d(64, 192, 5, padding=2),
                         nn.ReLU(), nn.MaxPool2d(3, 2), nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
                         nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(), nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
                         nn.MaxPool2d(3, 2))


@pytest.fixture(scope="module")
def backbone_file(tmp_path_factory):
    """A torchvision-format AlexNet file (random weights, ``features.*`` + a ``classifier.*`` key)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        sd = {f"features.{k}": v for k, v in _alexnet_features().state_dict().items()}
    sd["classifier.1.weight"] = torch.zeros(4, 9216)
    path = tmp_path_factory.mktemp("lpips") / "alexnet.pth"
    torch.save(sd, path)
    return path


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


def _as_if_saved_on_cuda(src: bytes) -> bytes:
    """A torch checkpoint whose storages say ``cuda:0`` (what ``torch.save`` writes for GPU tensors):
    the pickled location string ``cpu`` rewritten, every other record copied."""
    zin = zipfile.ZipFile(io.BytesIO(src))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zout:
        for name in zin.namelist():
            data = zin.read(name)
            if name.endswith("/data.pkl"):
                # protocol-2 BINUNICODE: 'X' + 4-byte little-endian length + UTF-8
                assert b"X\x03\x00\x00\x00cpu" in data
                data = data.replace(b"X\x03\x00\x00\x00cpu", b"X\x06\x00\x00\x00cuda:0")
            zout.writestr(name, data)
    return out.getvalue()


class _NotATensor:
    pass


# ------------------------------------------------------------------------------ the network
def test_lpips_matches_the_lpips_package(backbone_file, monkeypatch):
    """The lpips package's own LPIPS(alex, v0.1) with its shipped head and the same backbone: its
    scaling, layer taps, normalisation, head and averaging against ours."""
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        pytest.skip("lpips not installed (scripts/setup.sh installs it with --no-deps)")
    sd = torch.load(backbone_file, weights_only=True)
    features = _alexnet_features()
    features.load_state_dict({k[9:]: v for k, v in sd.items() if k.startswith("features.")})
    tv = types.ModuleType("torchvision")
    tv.models = types.SimpleNamespace(alexnet=lambda pretrained=False, **_: types.SimpleNamespace(features=features))
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.models", tv.models)

    def forget_lpips() -> None:  # import it afresh over the stand-in, and leave no module bound to it
        for name in [m for m in sys.modules if m == "lpips" or m.startswith("lpips.")]:
            del sys.modules[name]

    forget_lpips()
    try:
        import lpips

        reference = lpips.LPIPS(net="alex", verbose=False)
    finally:
        forget_lpips()
    ours = load_lpips(backbone_file)  # the head comes from the installed lpips package
    assert "alex.pth" in ours.source
    x, y = torch.rand(2, 3, 40, 52), torch.rand(2, 3, 40, 52)
    with torch.no_grad():
        want = reference(x, y, normalize=True).flatten()
        assert torch.allclose(ours(x, y), want, rtol=1e-5, atol=1e-7)
        # one file holding the whole lpips model (net.sliceK.* + lin*) loads the same network
        whole = backbone_file.parent / "lpips_full.pth"
        torch.save(reference.state_dict(), whole)
        assert torch.allclose(load_lpips(whole)(x, y), want, rtol=1e-5, atol=1e-7)


def test_lpips_against_a_float64_network_written_out():
    w = random_lpips_weights()
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


def test_lpips_invariants():
    """0 for identical images, symmetric, > 0 for different ones; one pair gives a scalar."""
    net = LPIPS(random_lpips_weights(), "random")
    x, y = torch.rand(3, 3, 35, 40), torch.rand(3, 3, 35, 40)
    with torch.no_grad():
        assert torch.equal(net(x, x), torch.zeros(3))
        assert torch.allclose(net(x, y), net(y, x), rtol=0, atol=1e-7)
        assert bool((net(x, y) > 0).all()) and net(x[0], y[0]).shape == ()


def test_lpips_is_frozen_even_from_weights_that_require_grad():
    """LPIPS is documented as frozen: weights taken from a trainable module (parameters that require
    grad) become plain buffers, so the distance of two constant images carries no graph."""
    w = {k: torch.nn.Parameter(v) for k, v in random_lpips_weights(1).items()}
    net = LPIPS(w)
    assert not any(b.requires_grad for b in net.buffers())
    assert [p for p in net.parameters()] == []
    x, y = torch.rand(1, 3, 31, 31), torch.rand(1, 3, 31, 31)
    out = net(x, y)
    assert not out.requires_grad and out.grad_fn is None
    # the image being scored still gets its gradient
    xr = x.clone().requires_grad_(True)
    net(xr, y).sum().backward()
    assert xr.grad is not None and all(p.grad is None for p in w.values())


def test_lpips_size_and_weight_refusals():
    net = LPIPS(random_lpips_weights())
    # the pair's checks name the argument at fault, x before y
    with pytest.raises(ShapeError, match=r"^x and y .*\[3, 31, 31\] and \[3, 31, 32\]"):
        net(torch.rand(3, 31, 31), torch.rand(3, 31, 32))
    with pytest.raises(Exception, match="^y"):
        net(torch.rand(3, 31, 31), torch.rand(3, 31, 31, dtype=torch.float64).to(torch.int64))
    with pytest.raises(Exception, match="^x"):
        net(torch.rand(2, 31, 31), torch.rand(3, 31, 31))
    with torch.no_grad():
        net(torch.rand(3, LPIPS_MIN_SIZE, LPIPS_MIN_SIZE), torch.rand(3, LPIPS_MIN_SIZE, LPIPS_MIN_SIZE))
    assert LPIPS_MIN_SIZE == 31
    for h, w in ((30, 40), (40, 30), (20, 40)):
        with pytest.raises(ShapeError, match=f"31x31.*got {h}x{w}"):
            net(torch.rand(3, h, w), torch.rand(3, h, w))
    bad = random_lpips_weights()
    bad["conv1.weight"] = bad["conv1.weight"][:, :, :3, :3]
    with pytest.raises(InputValueError, match=r"conv1.weight .*\[192, 64, 5, 5\].*\[192, 64, 3, 3\]"):
        LPIPS(bad)
    ints = random_lpips_weights()
    ints["lin2"] = ints["lin2"].to(torch.int32)
    with pytest.raises(InputValueError, match=r"lin2 .*got torch.int32"):
        LPIPS(ints)
    # float64 weights are kept as float32 copies (the caller's tensors untouched)
    w64 = {k: v.double() for k, v in random_lpips_weights().items()}
    net64 = LPIPS(w64)
    assert net64.conv0_weight.dtype == torch.float32 and w64["conv0.weight"].dtype == torch.float64
    assert net64.shift.view(-1).tolist() == pytest.approx([-0.030, -0.088, -0.188])
    assert net64.scale.view(-1).tolist() == pytest.approx([0.458, 0.448, 0.450])


def test_lpips_missing_weights_name_them_and_the_file_of_each_part():
    """Missing tensors are listed, sorted, after the source; each missing part (the AlexNet backbone, the
    LPIPS head) adds the file it comes from, and only the missing parts do."""
    full = random_lpips_weights()
    with pytest.raises(InputValueError, match=r"^LPIPS weights w\.pth: missing \[") as e:
        LPIPS({}, "w.pth")
    assert BACKBONE_FILE in str(e.value) and HEAD_FILE in str(e.value)
    with pytest.raises(InputValueError, match=r"^LPIPS weights src: missing \['lin0', .*'lin4'\]") as e:
        LPIPS({k: v for k, v in full.items() if not k.startswith("lin")}, "src")
    assert HEAD_FILE in str(e.value) and BACKBONE_FILE not in str(e.value)
    with pytest.raises(InputValueError, match=r"missing \['conv0.bias'") as e:
        LPIPS({k: v for k, v in full.items() if k.startswith("lin")})
    assert BACKBONE_FILE in str(e.value) and HEAD_FILE not in str(e.value)
    for gone in (("conv0.bias", "lin4"), ("conv0.weight", "lin3")):
        with pytest.raises(InputValueError, match=rf"^LPIPS weights mix\.pth: missing \['{gone[0]}', '{gone[1]}'\]") as e:
            LPIPS({k: v for k, v in full.items() if k not in gone}, "mix.pth")
        assert BACKBONE_FILE in str(e.value) and HEAD_FILE in str(e.value)


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


# ------------------------------------------------------------------------------ weight files
def test_load_lpips_merges_files_and_finds_the_package_head(tmp_path: Path):
    from safetensors.torch import save_file

    w = random_lpips_weights(2)
    tv = {}
    for i, idx in enumerate((0, 3, 6, 8, 10)):
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
    # a file with a head keeps its own head
    assert torch.equal(load_lpips([tmp_path / "head.safetensors", tmp_path / "alex.pth"]).lin3, w["lin3"])
    # the backbone alone: the installed lpips package's head file is added, and named
    import importlib.util

    if importlib.util.find_spec("lpips") is None:
        pytest.skip("lpips not installed")
    alone = load_lpips(tmp_path / "alex.pth")
    assert alone.source.startswith(f"{tmp_path / 'alex.pth'} + ") and alone.source.endswith("alex.pth")
    assert not torch.equal(alone.lin0, net.lin0)


def test_weight_files_refused_by_name(tmp_path: Path, backbone_file):
    """Every refusal names the file and what is wrong in it: absent, not a checkpoint, not a flat state dict
    of tensors, no known key (listing the first eight it holds), a tensor missing or of the wrong shape."""
    with pytest.raises(InputValueError, match="^LPIPS: no weight files given"):
        load_lpips([])
    for missing in (tmp_path / "nope.pth", tmp_path / "absent.pth"):
        with pytest.raises(InputValueError, match=f"^LPIPS weights {missing}: no such file"):
            load_lpips(missing)
    obj = tmp_path / "obj.pth"
    torch.save({"a": _NotATensor()}, obj)
    with pytest.raises(InputValueError, match=r"obj\.pth: refused, not a tensor-only checkpoint"):
        _read(obj)
    pickled = tmp_path / "code.pth"
    torch.save({"model": types.SimpleNamespace(a=1)}, pickled)
    with pytest.raises(InputValueError, match=r"code\.pth.*weights_only"):
        load_lpips(pickled)
    text = tmp_path / "text.pth"
    text.write_text("hello")
    with pytest.raises(InputValueError, match=rf"^LPIPS weights {text}: not a torch checkpoint or safetensors file"):
        _read(text)
    bad_st = tmp_path / "bad.safetensors"
    bad_st.write_bytes(b"\x00" * 4)
    with pytest.raises(InputValueError, match=r"bad\.safetensors: not a torch checkpoint or safetensors file"):
        _read(bad_st)
    lst = tmp_path / "list.pth"
    torch.save([torch.zeros(1)], lst)
    with pytest.raises(InputValueError, match=r"list\.pth: .*state dict, got list"):
        _read(lst)
    nested = tmp_path / "nested.pth"
    torch.save({"a": {"b": torch.zeros(1)}}, nested)
    with pytest.raises(InputValueError, match=r"nested\.pth: .*got dict"):
        _read(nested)
    other = tmp_path / "other.pth"
    torch.save({f"k{i}": torch.zeros(1) for i in range(9)}, other)
    with pytest.raises(InputValueError, match=r"other\.pth: .*\['k0', .*'k7'\] \.\.\.$"):
        load_lpips(other)
    few = tmp_path / "few.pth"
    torch.save({"k0": torch.zeros(1)}, few)
    with pytest.raises(InputValueError, match=r"few\.pth: .*\['k0'\]$"):
        load_lpips(str(few))
    from safetensors.torch import save_file

    foreign = tmp_path / "other.safetensors"
    save_file({"encoder.weight": torch.zeros(2, 2)}, str(foreign))
    with pytest.raises(InputValueError, match=r"other\.safetensors.*encoder\.weight"):
        load_lpips(foreign)
    vgg = tmp_path / "vgg.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3), "features.28.weight": torch.zeros(512, 512, 3, 3)}, vgg)
    with pytest.raises(InputValueError, match=r"vgg\.pth.*missing.*conv1\.weight"):
        load_lpips(vgg)  # VGG's first conv is 3x3: taken as AlexNet's, then the rest is missing
    shape = tmp_path / "shape.pth"
    sd = torch.load(backbone_file, weights_only=True)
    sd["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    torch.save(sd, shape)
    with pytest.raises(InputValueError, match=r"shape\.pth.*conv1\.weight.*\[192, 64, 5, 5\]"):
        load_lpips(shape)


def test_lpips_weights_saved_on_a_gpu_load_onto_the_cpu(tmp_path):
    weights = {"features.0.weight": torch.arange(6.0).reshape(2, 3), "lin0.model.1.weight": torch.tensor([0.5, -1.0])}
    buf = io.BytesIO()
    torch.save(weights, buf)
    path = tmp_path / "alex.pth"
    path.write_bytes(_as_if_saved_on_cuda(buf.getvalue()))
    got = _read(path)  # map_location="cpu": no GPU needed, whether CUDA is installed or not
    assert sorted(got) == sorted(weights)
    for k, v in weights.items():
        assert got[k].device == torch.device("cpu") and torch.equal(got[k], v), k


def test_lpips_weights_never_unpickle_objects_even_when_torch_is_told_to(tmp_path, monkeypatch):
    # TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 turns torch.load's default to full unpickling (code may run);
    # the weights are loaded with weights_only=True named, so a file holding an object is still refused
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    path = tmp_path / "alex.pth"
    torch.save({"features.0.weight": torch.ones(2), "extra": argparse.Namespace(x=1)}, path)
    with pytest.raises(InputValueError, match=r"alex\.pth: refused, not a tensor-only checkpoint .*weights_only=True"):
        _read(path)
