"""End to end on own captures: `controlgs train` and `eval` on a capture written in each dataset format, and on a non-square one."""

from __future__ import annotations

import json
from importlib.util import find_spec

import pytest
from helpers.capture import cropped_capture
import torch
from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp

from controlgs_adapter import ControlGS
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.cli import main
from controlgs_adapter.scene import builtin_backbone_dir


# ------------------------------------------------------------------------------ the adapter through the CLI
MODEL = builtin_backbone_dir("ar")


# cheap downstream path (the PSF optics cost ~0.5 s per image whatever its size)
FAST = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0"]


needs_cli_run = pytest.mark.skipif(find_spec("skimage") is None or find_spec("matplotlib") is None
                                   or not (MODEL / "point_cloud").is_dir(),
                                   reason="needs the demo extra (scikit-image, matplotlib) and the baked built-in backbone")


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
    cams, images = cropped_capture()
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
    cams, images = cropped_capture(48, crop=(48, 28))
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    r = _train_eval(tmp_path, data, "wide")
    assert r["info"]["test_sizes"] == ["48x28"]
    assert all(torch.isfinite(torch.tensor(m["psnr"]["grid"])).all() for m in r["methods"].values())
