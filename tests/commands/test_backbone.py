"""``controlgs backbone train`` and what it runs (``build_backbone``, ``train_reference_model`` on a views
dataset): every option and ``--out`` refused before any work, anchors from sparse points or a grid, the
folder written whole or not at all, warnings as one line naming no library file."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest
import torch

from controlgs_adapter.backends.model_dir import load_model_dir
from controlgs_adapter.backends.models import train_backbone
from controlgs_adapter.backends.models.train_backbone import build_backbone, train_reference_model
from controlgs_adapter.cli import main
from controlgs_adapter.datasets import load_dataset
from controlgs_adapter.datasets.memory import posed_images
from controlgs_adapter.errors import FileWriteError, InputValueError, ShapeError
from controlgs_adapter.state import Camera

TINY = ["--iterations", "2", "--max-anchors", "20", "--resolution", "12", "--no-progress"]


def _look_at(eye: tuple[float, float, float], size: int = 12) -> Camera:
    """A ``size``-pixel camera at ``eye`` looking at the origin (OpenCV axes)."""
    e = torch.tensor(eye, dtype=torch.float64)
    z = -e / e.norm()
    up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64) if abs(float(z[2])) < 0.9 else torch.tensor([0.0, 1.0, 0.0],
                                                                                                         dtype=torch.float64)
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.stack([x, y, z])
    w2c[:3, 3] = -(w2c[:3, :3] @ e)
    f = size / (2.0 * math.tan(math.radians(25)))
    k = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    return Camera(w2c.float(), k, size, size)


def _scene(n: int = 9, size: int = 12) -> tuple[torch.Tensor, list[Camera], torch.Tensor]:
    """``(images [n, 3, size, size], cameras, points)``: random images seen from a ring around the origin."""
    g = torch.Generator().manual_seed(0)
    cams = [_look_at((3.0 * math.cos(a), 3.0 * math.sin(a), 0.5)) for a in torch.linspace(0, 2 * math.pi, n + 1)[:-1].tolist()]
    return torch.rand(n, 3, size, size, generator=g), cams, torch.rand(40, 3, generator=g) - 0.5


def _ngp(root, images, cams, extra_frames=()):
    """An instant-ngp folder of the images (PNG) and cameras, plus ``extra_frames`` entries."""
    from PIL import Image

    from controlgs_adapter.datasets.blender import opengl_c2w_to_w2c

    frames = []
    for i, (img, cam) in enumerate(zip(images, cams)):
        (root / "images").mkdir(parents=True, exist_ok=True)
        arr = (img.clamp(0, 1) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        Image.fromarray(arr).save(root / "images" / f"v{i:02d}.png")
        c2w = torch.linalg.inv(cam.world_to_camera.double())
        c2w[:3, 1:3] *= -1.0  # OpenCV -> OpenGL axes
        assert torch.allclose(opengl_c2w_to_w2c(c2w.tolist()).double(), cam.world_to_camera.double(), atol=1e-5)
        frames.append({"file_path": f"images/v{i:02d}.png", "transform_matrix": c2w.tolist()})
    k = cams[0].intrinsics
    meta = {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
            "w": cams[0].width, "h": cams[0].height, "frames": frames + list(extra_frames)}
    (root / "transforms.json").write_text(json.dumps(meta))
    return root


@pytest.fixture()
def ngp(tmp_path):
    images, cams, _ = _scene()
    return _ngp(tmp_path / "data", images, cams)


def _one_line_error(capsys, *words: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith("controlgs backbone: error: ") and err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


# ------------------------------------------------------------------------------ refused before any work

def test_an_out_folder_holding_files_is_refused_before_the_data_is_read(tmp_path, capsys):
    out = tmp_path / "model"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    assert main(["backbone", "train", "--data", str(tmp_path / "no-such-dataset"), "--out", str(out), *TINY]) == 2
    _one_line_error(capsys, f"--out {out}", "not empty", "keep.txt")
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and (out / "keep.txt").read_text() == "mine"


@pytest.mark.parametrize("option, value", [("--iterations", "0"), ("--max-anchors", "0"), ("--resolution", "1"),
                                           ("--holdout", "-1"), ("--seed", "-1"), ("--device", "nowhere")])
def test_bad_options_are_refused_naming_the_option_and_nothing_is_created(tmp_path, capsys, ngp, option, value):
    out = tmp_path / "model"
    options = list(TINY)
    if option in options:
        options[options.index(option) + 1] = value
    else:
        options += [option, value]
    assert main(["backbone", "train", "--data", str(ngp), "--out", str(out), *options]) == 2
    _one_line_error(capsys, option)
    assert not out.exists()


def test_out_inside_the_dataset_is_refused(tmp_path, capsys, ngp):
    assert main(["backbone", "train", "--data", str(ngp), "--out", str(ngp / "model"), *TINY]) == 2
    _one_line_error(capsys, "inside the dataset")
    assert not (ngp / "model").exists()


def test_a_missing_dataset_is_one_line(tmp_path, capsys):
    assert main(["backbone", "train", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "m"), *TINY]) == 2
    _one_line_error(capsys, "dataset folder not found")
    assert not (tmp_path / "m").exists()


# ------------------------------------------------------------------------------ what it writes

def test_an_empty_out_folder_is_filled_and_the_model_loads(tmp_path, capsys, ngp):
    out = tmp_path / "model"
    out.mkdir()
    assert main(["backbone", "train", "--data", str(ngp), "--out", str(out), *TINY, "--holdout", "3"]) == 0
    printed = capsys.readouterr().out
    info = json.loads((out / "build.json").read_text())
    assert (info["format"], info["anchors_from"], info["iterations"], info["resolution"]) == ("instant_ngp", "grid", 2, 12)
    assert info["test_views"] == 3 and len(info["test_psnr"]) == 3 and info["train_views"] == 6
    assert "no sparse points" in printed and "not modelled" in printed
    assert "--holdout 3 --resolution 12 --out RUN" in printed  # the next command reads the data the same way
    model = load_model_dir(out)
    assert model.num_anchors == info["anchors"] <= 20
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data", "model"]


def test_anchors_come_from_the_sparse_points_and_an_empty_point_file_falls_back_to_the_grid(tmp_path):
    images, cams, points = _scene()
    views = posed_images(images, cams)
    built = build_backbone(views, tmp_path / "a", points=points, iterations=1, max_anchors=30, feat_dim=4, n_offsets=2,
                           progress=False)
    assert built.info["anchors_from"] == "points" and built.info["anchors"] <= 30
    # every anchor is a voxel cell of one of the points
    cells = torch.round(points.double() / built.model.voxel_size)
    assert all(any(torch.equal(torch.round(a.double() / built.model.voxel_size), c) for c in cells)
               for a in built.model.get_anchor.detach())
    empty = build_backbone(views, tmp_path / "b", points=torch.zeros(0, 3), iterations=1, max_anchors=30, feat_dim=4,
                           n_offsets=2, progress=False)
    assert empty.info["anchors_from"] == "grid" and "test_psnr" not in empty.info


def test_an_interrupted_write_leaves_nothing(tmp_path, monkeypatch, capsys, ngp):
    def fail(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("controlgs_adapter.backends.scaffold_io.save_scaffold_dir", fail)
    out = tmp_path / "model"
    assert main(["backbone", "train", "--data", str(ngp), "--out", str(out), *TINY]) == 2
    _one_line_error(capsys, str(out), "No space left on device")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no model folder, no temporary folder
    images, cams, _ = _scene()
    with pytest.raises(FileWriteError, match="No space left"):
        build_backbone(posed_images(images, cams), out, iterations=1, max_anchors=10, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]


def test_replace_swaps_a_whole_backbone_folder_and_nothing_else(tmp_path):
    images, cams, points = _scene()
    views = posed_images(images, cams)
    out = tmp_path / "m"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with pytest.raises(InputValueError, match="not empty"):
        build_backbone(views, out, points=points, iterations=1, max_anchors=10, progress=False)
    assert [p.name for p in out.iterdir()] == ["old.txt"]
    with pytest.raises(InputValueError, match="holds old.txt, which is not part of a backbone folder"):
        build_backbone(views, out, points=points, iterations=1, max_anchors=10, progress=False, replace=True)
    assert [p.name for p in out.iterdir()] == ["old.txt"]  # a folder of other files is never swapped away
    (out / "old.txt").unlink()
    build_backbone(views, out, points=points, iterations=1, max_anchors=10, progress=False, replace=True)
    first = (out / "build.json").read_text()
    build_backbone(views, out, points=points, iterations=2, max_anchors=10, progress=False, replace=True)
    assert sorted(p.name for p in out.iterdir()) == ["build.json", "cfg_args", "point_cloud"]
    assert [p.name for p in (out / "point_cloud").iterdir()] == ["iteration_2"] and (out / "build.json").read_text() != first
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]


def test_a_warning_while_reading_the_data_is_one_line_naming_no_library_file(tmp_path):
    images, cams, _ = _scene()
    data = _ngp(tmp_path / "data", images, cams, extra_frames=[{"file_path": "images/gone.png",
                                                                "transform_matrix": torch.eye(4).tolist()}])
    # a fresh interpreter, as from a shell (the test harness records warnings instead of printing them)
    done = subprocess.run([sys.executable, "-m", "controlgs_adapter.cli", "backbone", "train", "--data", str(data),
                           "--out", str(tmp_path / "m"), *TINY], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    err = [line for line in done.stderr.splitlines() if "warning" in line]
    assert err == [f"controlgs backbone: warning: {data / 'transforms.json'}: 1 of 10 frames list an image that is not "
                   "there, skipped: images/gone.png"]


# ------------------------------------------------------------------------------ the trainer takes views

def test_views_and_the_images_tensor_train_the_same_model():
    images, cams, points = _scene()
    kw = dict(iterations=4, feat_dim=4, n_offsets=2, max_anchors=20, progress=False, seed=2)
    old = train_reference_model(images, cams, points, **kw).state_dict()
    new = train_reference_model(posed_images(images, cams), points=points, **kw).state_dict()
    assert old.keys() == new.keys() and all(torch.equal(old[k], new[k]) for k in old)


def test_a_dataset_is_trained_on_lazily_at_its_working_resolution(tmp_path, ngp):
    views = load_dataset(ngp, holdout=0).views("train", resolution=11)
    assert views.sizes == [(11, 11)] * 9
    model = train_reference_model(views, iterations=2, feat_dim=4, n_offsets=2, max_anchors=20, progress=False)
    assert 0 < model.num_anchors <= 20 and not model.training
    with pytest.raises(InputValueError, match="view 0 is 6x6 pixels; the loss's SSIM needs at least 11 on each side"):
        train_reference_model(load_dataset(ngp).views("train", resolution=6), iterations=1, progress=False)


def test_the_views_call_is_checked():
    images, cams, points = _scene()
    with pytest.raises(InputValueError, match="a views dataset brings its own cameras"):
        train_reference_model(posed_images(images, cams), cams, points, iterations=0, progress=False)
    with pytest.raises(InputValueError, match="views must be a dataset"):
        train_reference_model(42, iterations=0, progress=False)
    with pytest.raises(InputValueError, match="views is empty"):
        train_reference_model([], iterations=0, progress=False)

    class Wrong:  # an image that is not its camera's size: named when the view is first read
        background = None
        cameras = cams

        def __len__(self):
            return len(cams)

        def __getitem__(self, i):
            return cams[i], images[i][:, :6]

    with pytest.raises(ShapeError, match=r"view \d: image must be \[3, 12, 12\] \(its camera's size\), got \[3, 6, 12\]"):
        train_reference_model(Wrong(), points=points, iterations=1, progress=False)


def test_the_module_documents_both_calls():
    doc = train_backbone.train_reference_model.__doc__ or ""
    assert "views" in doc and "[V, 3, H, W]" in doc and "default 0" in doc


@pytest.mark.parametrize("option", ["--iterations", "--max-anchors", "--holdout", "--resolution"])
def test_a_count_beyond_int64_is_one_line_before_the_data_is_read(tmp_path, capsys, option):
    out = tmp_path / "out"
    assert main(["backbone", "train", "--data", str(tmp_path / "nodata"), "--out", str(out), option, "9" * 400]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs backbone: error: {option} must be an integer in "), err
    assert "401 digits" in err[0] and not out.exists()
