"""The honest report (issue 14 §5): the ideal-render bound, FLIP, LPIPS from local weights, seeds.

References: the pipeline run by hand on the ground truth; NVIDIA's flip-evaluator through its own
PNG loader and command line; the ``lpips`` package's own network (with a stand-in for torchvision,
which does not import beside this torch); GridResults built from known numbers."""

import json
import math
import re
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.evaluation import IDEAL, GridResult
from controlgs_adapter.metrics import flip
from controlgs_adapter.perceptual import LPIPS, load_lpips
from controlgs_adapter.report import markdown_tables, read_results, seed_summary, write_report

GRID = ((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8))


def _image(seed: int, h: int = 20, w: int = 28) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(3, h, w, generator=g, dtype=torch.float64)


# ---------------------------------------------------------------- the ideal-render bound

def test_ideal_bound_is_the_ground_truth_through_the_pipeline():
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.metrics import psnr, ssim
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.state import RuntimeState
    from controlgs_adapter.training import DEFAULT_EFFECTS

    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    views = scene.views("test")
    model = NeuralGaussianModel.from_points(*scene.points(0.3), feat_dim=8, n_offsets=2, voxel_size=0.4,
                                            color_fit_steps=1).eval()
    # no baselines and no adapters: nothing is rendered, only the ground truth goes through E_s
    r = evaluate_grid(model, views, {}, downsample=(2.0,), power_saving=(0.4,), baselines=(), progress=False)
    assert r.methods == [IDEAL] and r.metrics == ["psnr", "ssim", "flip"]
    pipe = Pipeline.from_config(dict(DEFAULT_EFFECTS))
    pipe["optics"].mode = "fast"
    pipe.eval()
    for v in range(len(views)):
        _, gt = views[v]
        with torch.no_grad():
            eye = pipe(gt, RuntimeState(downsample=2.0, power_saving=0.4), reference=gt).clamp(0, 1).double()
        want = {"psnr": float(psnr(eye, gt.double())), "ssim": float(ssim(eye, gt.double())), "flip": flip(eye, gt.double())}
        for k, value in want.items():
            assert float(r.per_view[IDEAL][k][0, 0, v]) == pytest.approx(value, rel=1e-9, abs=1e-12), k
        assert want["psnr"] < 60  # the pipeline is not the identity: the bound means something


def _constructed(methods=("no_ss", "ss", IDEAL, "controlgs"), offset: float = 0.0, views: int = 2) -> GridResult:
    g = torch.Generator().manual_seed(3)
    base = {"no_ss": 18.0, "ss": 20.0, IDEAL: 22.0, "controlgs": 21.0, "wo_lens": 20.9}
    per_view = {m: {"psnr": base[m] + offset + 0.1 * torch.rand(4, 5, views, generator=g, dtype=torch.float64),
                    "ssim": torch.rand(4, 5, views, generator=g, dtype=torch.float64),
                    "flip": torch.rand(4, 5, views, generator=g, dtype=torch.float64)} for m in methods}
    return GridResult(*GRID, per_view)


def test_ideal_row_in_results_json_and_report(tmp_path):
    r = _constructed()
    r.per_view["controlgs"]["psnr"][3, 4] = r.per_view[IDEAL]["psnr"][3, 4] + 0.5  # one cell above the bound
    write_report(tmp_path, r, info={"scene": "test"})
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["methods"][IDEAL]["psnr"]["mean"] == pytest.approx(r.mean(IDEAL, "psnr"), rel=1e-12)
    md = (tmp_path / "report.md").read_text()
    assert f"| Ideal render (GT through E_s) | {r.mean(IDEAL, 'psnr'):.2f} |" in md  # a row, never bold
    assert "PSNR of Ideal render (GT through E_s):" in md and "PSNR of ControlGS minus Ideal render" in md
    assert "ControlGS is above that bound in 1/20 settings" in md
    assert "LPIPS was not computed" in md and "--lpips-weights" in md
    assert (tmp_path / "heatmap.png").stat().st_size > 0
    assert read_results(data)[0] == GridResult.from_json(data)


# ---------------------------------------------------------------- FLIP

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


# ---------------------------------------------------------------- LPIPS

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


def _random_lpips() -> LPIPS:
    from controlgs_adapter.perceptual import _expected

    g = torch.Generator().manual_seed(0)
    return LPIPS({k: torch.rand(s, generator=g) * 0.1 for k, s in _expected().items()}, "random")


def test_lpips_invariants():
    net = _random_lpips()
    x, y = torch.rand(3, 3, 35, 40), torch.rand(3, 3, 35, 40)
    with torch.no_grad():
        assert torch.equal(net(x, x), torch.zeros(3))
        assert torch.allclose(net(x, y), net(y, x), rtol=0, atol=1e-7)
        assert bool((net(x, y) > 0).all()) and net(x[0], y[0]).shape == ()
    with pytest.raises(ShapeError, match="31x31"):
        net(torch.rand(3, 20, 40), torch.rand(3, 20, 40))


def test_lpips_refuses_wrong_files(tmp_path, backbone_file):
    vgg = tmp_path / "vgg.pth"
    torch.save({"features.0.weight": torch.zeros(64, 3, 3, 3), "features.28.weight": torch.zeros(512, 512, 3, 3)}, vgg)
    with pytest.raises(InputValueError, match=r"vgg\.pth.*missing.*conv1\.weight"):
        load_lpips(vgg)  # VGG's first conv is 3x3: taken as AlexNet's, then the rest is missing
    other = tmp_path / "other.safetensors"
    from safetensors.torch import save_file

    save_file({"encoder.weight": torch.zeros(2, 2)}, str(other))
    with pytest.raises(InputValueError, match=r"other\.safetensors.*encoder\.weight"):
        load_lpips(other)
    pickled = tmp_path / "code.pth"
    torch.save({"model": types.SimpleNamespace(a=1)}, pickled)
    with pytest.raises(InputValueError, match=r"code\.pth.*weights_only"):
        load_lpips(pickled)
    bad = tmp_path / "shape.pth"
    sd = torch.load(backbone_file, weights_only=True)
    sd["features.3.weight"] = torch.zeros(192, 64, 3, 3)
    torch.save(sd, bad)
    with pytest.raises(InputValueError, match=r"shape\.pth.*conv1\.weight.*\[192, 64, 5, 5\]"):
        load_lpips(bad)
    with pytest.raises(InputValueError, match="no such file"):
        load_lpips(tmp_path / "absent.pth")


# ---------------------------------------------------------------- seeds

def _seed_result(seed: int, values: dict[str, float]) -> GridResult:
    """Every view and cell of a method holds one known PSNR (so its overall mean is that number)."""
    per_view = {m: {"psnr": torch.full((4, 5, 2), v, dtype=torch.float64)} for m, v in values.items()}
    return GridResult(*GRID, per_view, info={"seed": seed})


def test_seeds_mean_std_and_which_differences_exceed_the_spread(tmp_path):
    runs = [_seed_result(0, {"ss": 20.0, "controlgs": 21.0, "wo_lens": 21.0, "state_blind": 20.0}),
            _seed_result(1, {"ss": 20.0, "controlgs": 21.2, "wo_lens": 21.1, "state_blind": 20.2})]
    s = seed_summary(runs)
    assert s["controlgs"]["psnr"]["mean"] == pytest.approx(21.1)
    assert s["controlgs"]["psnr"]["std"] == pytest.approx(math.sqrt(0.02))  # sample std of (21.0, 21.2)
    assert s["ss"]["psnr"]["std"] == 0.0
    md = markdown_tables(runs)
    assert "| ControlGS | **21.10 ± 0.14** |" in md and "| SS-backbone | 20.00 ± 0.00 |" in md
    # ControlGS - SS = 1.1, pooled std sqrt((0.02 + 0) / 2) = 0.1: exceeds 2 x 0.1
    assert "ControlGS minus SS-backbone: PSNR +1.1 (exceeds the spread, pooled std 0.1)" in md
    # w/o Lens - ControlGS = -0.05, pooled sqrt((0.005 + 0.02) / 2) = 0.112: within
    assert "w/o Lens minus ControlGS: PSNR -0.05 (within the spread, pooled std 0.11)" in md
    # state-blind - ControlGS = -1.0, pooled 0.141: exceeds
    assert "w/o State-Aware minus ControlGS: PSNR -1 (exceeds the spread, pooled std 0.14)" in md
    assert "over 2 seeds" in md
    write_report(tmp_path, runs)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["seeds"] == [0, 1] and data["summary"]["controlgs"]["psnr"]["per_seed"] == [21.0, 21.2]
    assert read_results(data) == runs
    assert "One seed: no spread was measured" in markdown_tables(runs[0])


def test_seed_folders_and_pooling_checks(tmp_path):
    from controlgs_adapter.commands.demo import seed_runs
    from controlgs_adapter.commands.eval import seed_folders

    assert seed_runs(tmp_path, 3, None) == [(3, tmp_path)]
    assert seed_runs(tmp_path, 3, 2) == [(3, tmp_path / "seed-3"), (4, tmp_path / "seed-4")]
    with pytest.raises(InputValueError, match="--seeds"):
        seed_runs(tmp_path, 0, 0)
    assert seed_folders(tmp_path, 0, None) == [(0, tmp_path)]
    for s in (10, 2):
        (tmp_path / f"seed-{s}").mkdir()
    assert seed_folders(tmp_path, 0, None) == [(2, tmp_path / "seed-2"), (10, tmp_path / "seed-10")]
    with pytest.raises(InputValueError, match="pooled"):
        markdown_tables([_seed_result(0, {"ss": 1.0}), _seed_result(1, {"controlgs": 1.0})])
