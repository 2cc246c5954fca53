"""End to end through the CLI on a user's scene: the same tiny capture (the built-in scene's cameras
and ground truth) written as COLMAP text, Blender and instant-ngp datasets, the built-in backbone's
Scaffold-GS folder as the model: train, eval, the report, the adapter loads on the model folder, and
the three formats give the same numbers. Non-square images go through the same path."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("skimage")
pytest.importorskip("matplotlib")

from _scene_writers import write_blender, write_colmap, write_instant_ngp
from controlgs_adapter import ControlGS
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.cli import main
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
from controlgs_adapter.state import Camera

MODEL = builtin_backbone_dir("ar")
pytestmark = pytest.mark.skipif(not (MODEL / "point_cloud").is_dir(), reason="built-in backbone not baked")
# cheap downstream path (the PSF optics cost ~0.5 s per image whatever its size)
FAST = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0"]


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


def test_non_square_capture(tmp_path):
    cams, images = _capture(48, crop=(48, 28))
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    r = _train_eval(tmp_path, data, "wide")
    assert r["info"]["test_sizes"] == ["48x28"]
    assert all(torch.isfinite(torch.tensor(m["psnr"]["grid"])).all() for m in r["methods"].values())


def test_user_errors_are_one_line(tmp_path, capsys):
    cams, images = _capture(16)
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    assert main(["train", "--model", str(tmp_path), "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    flipped = json.loads((data / "transforms.json").read_text())
    for f in flipped["frames"]:  # camera to world given in OpenCV axes: the scene is behind every camera
        for row in f["transform_matrix"][:3]:
            row[1], row[2] = -row[1], -row[2]
    (data / "transforms.json").write_text(json.dumps(flipped))
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("controlgs train: error: ") for line in err), err
    assert "--model" in err[0] and "not a trained model folder" in err[1] and "flipped" in err[2]


def test_seeds_train_each_seed_on_a_users_scene(tmp_path):
    """``--seeds 2 --seed 5`` on ``--model/--data`` trains seed-5/ and seed-6/ with their own seeds: each
    adapter equals the one a single run with that ``--seed`` writes (and the two differ)."""
    from controlgs_adapter.formats.adapter import read_tensors

    cams, images = _capture(16)
    data = write_colmap(tmp_path / "colmap", cams, images)
    common = ["--model", str(MODEL), "--data", str(data), "--iterations", "2", "--no-ablations", *FAST]
    assert main(["train", *common, "--out", str(tmp_path / "multi"), "--seeds", "2", "--seed", "5"]) == 0
    assert main(["train", *common, "--out", str(tmp_path / "single"), "--seed", "6"]) == 0
    name = "controlgs.controlgs.safetensors"
    five = read_tensors(tmp_path / "multi" / "seed-5" / name)
    six = read_tensors(tmp_path / "multi" / "seed-6" / name)
    alone = read_tensors(tmp_path / "single" / name)
    assert five.keys() == six.keys() == alone.keys()
    assert all(torch.equal(six[k], alone[k]) for k in six)
    assert not all(torch.equal(five[k], six[k]) for k in five)
