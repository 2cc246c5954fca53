"""Tests of ``controlgs_adapter.scene.backbone``: the baked built-in backbones (folders, loading, their build record)
and ``build_builtin_backbone`` (its arguments, defaults and scores recorded in build.json)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.metrics import psnr
from controlgs_adapter.scene import (
    arc_cameras,
    backbone as sb,
    build_builtin_backbone,
    builtin_backbone_dir,
    diorama_planes,
    load_builtin_backbone,
    load_builtin_scene,
    render_planes,
)

pytest.importorskip("skimage")  # the built-in textures
pytest.importorskip("matplotlib")


def test_builtin_backbone_folders_default_to_ar():
    assert builtin_backbone_dir() == builtin_backbone_dir("ar") == sb._DATA / "ar" != builtin_backbone_dir("vr")
    assert builtin_backbone_dir("vr") == sb._DATA / "vr"
    assert sb._DATA.parts[-3:] == ("controlgs_adapter", "data", "builtin_scene")
    with pytest.raises(InputValueError, match=r"variant.*'xr'"):
        builtin_backbone_dir("xr")


def test_a_backbone_that_is_not_baked_names_the_bake_command(tmp_path, monkeypatch):
    monkeypatch.setattr(sb, "_DATA", tmp_path)  # an installation without the baked files
    with pytest.raises(FileFormatError, match=r"the built-in 'vr' backbone is not baked.*--variant vr --out "):
        load_builtin_backbone("vr")


@pytest.mark.parametrize("variant", ["ar", "vr"])
def test_baked_backbones_reproduce_their_build_record(variant):
    """The shipped backbone loads from its Scaffold-GS folder and renders a held-out view at the
    PSNR that build.json recorded when it was trained (ground truth rendered afresh)."""
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
    assert not model.training and all(not m.training for m in model.modules())  # loaded for rendering


def test_build_builtin_backbone_records_its_arguments_and_scores(tmp_path, monkeypatch):
    import json

    from controlgs_adapter.metrics import psnr
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the scene's ground truth is cached here
    out = build_builtin_backbone("ar", out=tmp_path / "bb", resolution=16, iterations=2, max_anchors=40, n_offsets=2,
                                 feat_dim=8, point_spacing=0.3, seed=1, progress=False)
    assert out == tmp_path / "bb" and (out / "point_cloud" / "iteration_2").is_dir()
    assert len(list((tmp_path / "cache" / "controlgs-adapter" / "scene").iterdir())) == 1  # cache=True
    text = (out / "build.json").read_text()
    info = json.loads(text)
    assert text == json.dumps(info, indent=1)  # one key per line, one space of indent: meant to be read
    assert text.splitlines()[1].startswith(' "variant": "ar"')
    assert {k: info[k] for k in ("variant", "resolution", "iterations", "max_anchors", "n_offsets", "feat_dim",
                                 "point_spacing", "seed")} == {"variant": "ar", "resolution": 16, "iterations": 2,
                                                               "max_anchors": 40, "n_offsets": 2, "feat_dim": 8,
                                                               "point_spacing": 0.3, "seed": 1}
    model = load_scaffold_dir(out).eval()
    assert info["anchors"] == model.num_anchors <= 40
    # 32 views, every 8th held out: 4 test views, each scored on the saved model's render
    scene = load_builtin_scene("ar", 16, cache=True)
    assert len(info["test_psnr"]) == len(info["test_ssim"]) == 4
    with torch.no_grad():
        want = [float(psnr(model.render(c, None, scene.background).color.clamp(0, 1), g))
                for c, g in zip(scene.test_cameras, scene.test_images)]
    np.testing.assert_allclose(info["test_psnr"], want, atol=1e-3)
    assert abs(info["test_psnr_mean"] - sum(want) / 4) < 1e-3
    assert abs(info["test_ssim_mean"] - sum(info["test_ssim"]) / 4) < 1e-12
    assert all(0.0 < s <= 1.0 for s in info["test_ssim"]) and info["train_seconds"] >= 0.0


def test_build_builtin_backbone_records_its_defaults_and_shows_progress(tmp_path, monkeypatch, capfd):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    # resolution / iterations / max_anchors are cut down; variant, n_offsets, feat_dim, point_spacing, seed and
    # progress keep their documented defaults ("ar", 5, 32, 0.04, 0, a progress bar)
    out = build_builtin_backbone(out=tmp_path / "bb", resolution=16, iterations=1, max_anchors=20)
    info = json.loads((out / "build.json").read_text())
    assert {k: info[k] for k in ("variant", "n_offsets", "feat_dim", "point_spacing", "seed")} == \
        {"variant": "ar", "n_offsets": 5, "feat_dim": 32, "point_spacing": 0.04, "seed": 0}
    model = load_scaffold_dir(out)
    assert (model.n_offsets, model.feat_dim) == (5, 32)
    assert "training backbone" in capfd.readouterr().err  # the tqdm bar is on by default
