"""End to end: `controlgs demo` at a tiny size writes every report file with finite numbers;
the report's tables and findings agree with the JSON."""

import json

import pytest
import torch

pytest.importorskip("skimage")
pytest.importorskip("matplotlib")

from controlgs_adapter.cli import main
from controlgs_adapter.evaluation import GridResult
from controlgs_adapter.report import markdown_tables
from controlgs_adapter.scene import builtin_backbone_dir


@pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(), reason="built-in backbone not baked")
def test_tiny_demo_writes_the_report(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "report"
    rc = main(["demo", "--out", str(out), "--resolution", "16", "--iterations", "2", "--psf-fraction", "0.5",
               "--test-views", "1", "--checkpoint-every", "1", "--no-progress", "--no-ablations"])
    assert rc == 0
    for name in ("results.json", "report.md", "heatmap.png", "comparison.png", "condition_response.png",
                 "controlgs.controlgs.safetensors"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    data = json.loads((out / "results.json").read_text())
    assert set(data["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    for m in data["methods"].values():
        grid = torch.tensor(m["psnr"]["grid"], dtype=torch.float64)
        assert grid.shape == (4, 5) and bool(torch.isfinite(grid).all())
        assert m["psnr"]["mean"] == pytest.approx(float(grid.mean()), rel=1e-9)
    assert data["info"]["iterations"] == 2
    back = GridResult.from_json(data)
    assert back.mean("controlgs", "psnr") == data["methods"]["controlgs"]["psnr"]["mean"]


def test_markdown_tables_state_what_was_measured():
    g = torch.Generator().manual_seed(0)
    per_view = {m: {"psnr": torch.rand(4, 5, 2, generator=g, dtype=torch.float64) * 5 + 20,
                    "ssim": torch.rand(4, 5, 2, generator=g, dtype=torch.float64)} for m in ("no_ss", "ss", "controlgs")}
    per_view["controlgs"]["psnr"][0, 0] = per_view["ss"]["psnr"][0, 0] - 1.0  # one losing cell
    per_view["controlgs"]["psnr"][1:] = per_view["ss"]["psnr"][1:] + 0.5
    per_view["controlgs"]["psnr"][0, 1:] = per_view["ss"]["psnr"][0, 1:] + 0.5
    r = GridResult((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8), per_view)
    md = markdown_tables(r)
    assert "ControlGS better than SS-backbone in 19/20 settings" in md
    want = f"{r.mean('controlgs', 'psnr'):.2f}"
    assert f"| ControlGS | {want}" in md or f"| ControlGS | **{want}**" in md


def test_grid_result_json_round_trip_is_exact(tmp_path):
    g = torch.Generator().manual_seed(1)
    per_view = {m: {"psnr": torch.rand(4, 5, 3, generator=g, dtype=torch.float64) * 30,
                    "ssim": torch.rand(4, 5, 3, generator=g, dtype=torch.float64)} for m in ("no_ss", "ss", "controlgs")}
    r = GridResult((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8), per_view, "exact",
                   {"test_views": 3, "test_sizes": ["48x27"]})
    back = GridResult.from_json(json.loads(json.dumps(r.to_json())))
    assert back == r and back.info == r.info and back.optics_mode == "exact"
    other = GridResult.from_json(r.to_json())
    other.per_view["ss"]["psnr"][0, 0, 0] += 1e-12
    assert back != other
    from controlgs_adapter.errors import InputValueError

    with pytest.raises(InputValueError, match="GridResult"):
        GridResult.from_json({"downsample": [1.0]})


def test_grid_invariants_zero_adapter_equals_ss(tmp_path):
    """An adapter at initialisation (zero conditions) is the backbone: its grid equals the
    SS-backbone's exactly; at d = 1 the no-SS render is the SS render."""
    from controlgs_adapter import ControlGS
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    xyz, rgb = scene.points(0.3)
    with torch.random.fork_rng(devices=[]):  # decoder weights: a fixed draw whose Gaussians are visible
        torch.manual_seed(1)
        model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.4, color_fit_steps=10).eval()
        with torch.no_grad():
            model.mlp_opacity[2].bias.fill_(1.0)
    with torch.no_grad():
        assert float(model.render(scene.test_cameras[0]).alpha.mean()) > 0.05
    cgs = ControlGS.wrap(model, cond_dim=4)
    path = cgs.save(tmp_path / "zero.safetensors")
    cgs.unwrap()
    r = evaluate_grid(model, scene.views("test"), {"controlgs": path}, downsample=(1.0, 4.0),
                      power_saving=(0.0, 0.6), optics_mode="fast", extra_metrics=False, progress=False)
    for k in ("psnr", "ssim"):
        assert torch.equal(r.per_view["controlgs"][k], r.per_view["ss"][k])
        assert torch.equal(r.per_view["no_ss"][k][0], r.per_view["ss"][k][0])
        assert not torch.equal(r.per_view["no_ss"][k][1], r.per_view["ss"][k][1])


@pytest.mark.parametrize("variant", ["ar", "vr"])
def test_baked_backbones_reproduce_their_build_record(variant):
    """The shipped backbone loads from its Scaffold-GS folder and renders a held-out view at the
    PSNR that build.json recorded when it was trained (ground truth rendered afresh)."""
    from controlgs_adapter.metrics import psnr
    from controlgs_adapter.scene import arc_cameras, diorama_planes, load_builtin_backbone, render_planes

    folder = builtin_backbone_dir(variant)
    if not (folder / "point_cloud").is_dir():
        pytest.skip("built-in backbone not baked")
    record = json.loads((folder / "build.json").read_text())
    cam = arc_cameras(32, size=record["resolution"])[8]  # test view 1 (views i % 8 == 0 are the test split)
    gt = render_planes(diorama_planes(variant), cam, samples=4)[0].float()
    model = load_builtin_backbone(variant)
    with torch.no_grad():
        img = model.render(cam, None, torch.zeros(3)).color.clamp(0, 1)
    assert float(psnr(img, gt)) == pytest.approx(record["test_psnr"][1], abs=0.02)
