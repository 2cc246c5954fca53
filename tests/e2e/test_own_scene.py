"""End to end on own captures: `controlgs train` and `eval` on a capture written in each dataset format, and on a non-square one."""

from __future__ import annotations

import json
from importlib.util import find_spec

import pytest
import torch
from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp

from controlgs_adapter import ControlGS
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.cli import main
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
from controlgs_adapter.state import Camera


# ------------------------------------------------------------------------------ the adapter through the CLI
MODEL = builtin_backbone_dir("ar")


# cheap downstream path (the PSF optics cost ~0.5 s per image whatever its size)
FAST = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0"]


needs_cli_run = pytest.mark.skipif(find_spec("skimage") is None or find_spec("matplotlib") is None
                                   or not (MODEL / "point_cloud").is_dir(),
                                   reason="needs the demo extra (scikit-image, matplotlib) and the baked built-in backbone")


def _capture(size: int = 32, crop: tuple[int, int] | None = None) -> tuple[list[Camera], list[torch.Tensor]]:
    """8 views of the built-in scene (view 0 is the test view in every format); ``crop = (w, h)``
    cuts a centred window out of each image with matching intrinsics."""
    scene = load_builtin_scene("ar", size, views=8, test_every=8, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    images = list(torch.cat([scene.test_images, scene.train_images]))
    if crop is None:
        return cams, images
    w, h = crop
    x0, y0 = (size - w) // 2, (size - h) // 2
    out = []
    for c in cams:
        k = c.intrinsics.clone()
        k[0, 2] -= x0
        k[1, 2] -= y0
        out.append(Camera(c.world_to_camera, k, w, h))
    return out, [img[:, y0:y0 + h, x0:x0 + w].contiguous() for img in images]


def _train_eval(tmp_path, data, name: str, *extra: str) -> dict:
    run, report = tmp_path / f"run-{name}", tmp_path / f"report-{name}"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3",
                 "--no-ablations", *FAST, *extra]) == 0
    record = json.loads((run / "run.json").read_text())
    assert record["family"] == "scaffold_gs" and record["iterations"] == 3 and record["effects"] == ["display", "resample"]
    assert (record["seeds"], record["seed"], record["holdout"]) == (1, 0, 8)  # one seed, the defaults
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress"]) == 0
    for f in ("results.json", "report.md", "heatmap.png", "comparison.png", "condition_response.png"):
        assert (report / f).is_file() and (report / f).stat().st_size > 0, f
    cgs = ControlGS.load(run / "controlgs.controlgs.safetensors", load_model_dir(MODEL))
    assert set(cgs.modules) == {"resample", "display"}
    cgs.unwrap()
    return json.loads((report / "results.json").read_text())


@needs_cli_run
def test_three_formats_train_eval_and_agree(tmp_path, capsys):
    cams, images = _capture()
    folders = {"colmap": write_colmap(tmp_path / "colmap", cams, images),
               "blender": write_blender(tmp_path / "blender", cams, images, test=[0]),
               "instant_ngp": write_instant_ngp(tmp_path / "ngp", cams, images)}
    results = {fmt: _train_eval(tmp_path, path, fmt, "--resolution", "32") for fmt, path in folders.items()}
    out = capsys.readouterr().out
    assert out.count("scene check: ") == 3 and "anchors are in view of 8/8 cameras" in out
    ref = results["colmap"]
    assert ref["info"]["test_sizes"] == ["32x32"] and set(ref["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    for fmt, r in results.items():
        assert r["info"]["test_views"] == 1, fmt
        for m, metrics in ref["methods"].items():
            for k, v in metrics.items():
                assert r["methods"][m][k]["mean"] == pytest.approx(v["mean"], abs=1e-6), (fmt, m, k)


@needs_cli_run
def test_non_square_capture(tmp_path):
    cams, images = _capture(48, crop=(48, 28))
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    r = _train_eval(tmp_path, data, "wide")
    assert r["info"]["test_sizes"] == ["48x28"]
    assert all(torch.isfinite(torch.tensor(m["psnr"]["grid"])).all() for m in r["methods"].values())
