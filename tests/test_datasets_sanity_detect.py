"""check_scene (flipped axes, image sizes, empty splits) and load_dataset's format detection, on
scenes written in the test (tests/_datasets_synth.py)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from _datasets_synth import marker_image, project_gl, ring_poses, write_json, write_png
from controlgs_adapter.datasets import Frame, SceneData, check_scene, detect_format, load_dataset, read_blender
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

W, H = 32, 24
ANGLE_X = 1.0
POINTS = np.random.default_rng(0).uniform(-0.8, 0.8, size=(300, 3))   # the object the cameras look at
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _write_blender(root, poses, *, test=True):
    """A NeRF-synthetic folder with ``poses`` (camera to world as written in the files): all in
    train, the last two also in test when ``test``."""
    for split, ps in (("train", poses), ("test", poses[-2:] if test else None)):
        if ps is None:
            continue
        frames = []
        for n, c2w in enumerate(ps):
            write_png(root / split / f"r_{n}.png", marker_image(W, H, [], rgba=True))
            frames.append({"file_path": f"./{split}/r_{n}", "transform_matrix": np.asarray(c2w).tolist()})
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": ANGLE_X, "frames": frames})


def test_check_scene_reports_per_camera_fractions_like_an_independent_projection(tmp_path):
    poses = ring_poses(6)
    _write_blender(tmp_path, poses)
    data = read_blender(tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report = check_scene(data, torch.from_numpy(POINTS).float(), required=("train", "test"))
    f = 0.5 * W / math.tan(ANGLE_X / 2)
    frames = data.splits["train"] + data.splits["test"]
    c2ws = list(poses) + list(poses[-2:])
    assert report["points"] == len(POINTS) and report["blind"] == []
    assert report["splits"] == {"train": 6, "test": 2} and report["images_checked"] == 8
    for frame, c2w in zip(frames, c2ws):
        uv, depth = project_gl(c2w, f, f, W / 2, H / 2, POINTS)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        assert report["in_front"][frame.name] == pytest.approx(inside.mean(), abs=1e-9)
        assert report["in_front"][frame.name] > 0.5


def test_forgetting_the_opengl_flip_is_caught(tmp_path):
    """OpenCV camera-to-world poses written into a Blender file as if they were OpenGL: every camera
    then looks away from the object."""
    cv_poses = [c2w @ _GL_TO_CV for c2w in ring_poses(6)]
    _write_blender(tmp_path, cv_poses)
    data = read_blender(tmp_path)
    with pytest.raises(InputValueError, match=r"8 of 8 cameras see none of the scene in front of them.*"
                                              r"probably flipped \(OpenGL vs OpenCV\).*blender.*OpenGL axes"):
        check_scene(data, torch.from_numpy(POINTS).float())


def test_a_few_blind_cameras_are_named_in_a_warning(tmp_path):
    poses = ring_poses(6)
    poses[4] = poses[4] @ _GL_TO_CV
    _write_blender(tmp_path, poses, test=False)
    data = read_blender(tmp_path)
    with pytest.warns(RuntimeWarning, match=r"1 of 6 cameras see almost none.*train/r_4\.png"):
        report = check_scene(data, torch.from_numpy(POINTS).float())
    assert report["blind"] == ["train/r_4.png"]


def test_check_scene_uses_the_scene_points_and_skips_without_any(tmp_path):
    _write_blender(tmp_path, [c2w @ _GL_TO_CV for c2w in ring_poses(4)])
    data = read_blender(tmp_path)
    assert check_scene(data)["in_front"] == {}                 # no points: nothing to test against
    data.points = torch.from_numpy(POINTS).float()
    with pytest.raises(InputValueError, match="flipped"):
        check_scene(data)


def test_image_size_mismatch_names_the_file(tmp_path):
    write_png(tmp_path / "a.png", marker_image(W, H, [], rgba=False))
    write_png(tmp_path / "b.png", marker_image(W, H + 2, [], rgba=False))
    k = torch.tensor([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    cam = Camera(torch.eye(4), k, W, H)
    data = SceneData(splits={"train": [Frame("a.png", cam, tmp_path / "a.png"), Frame("b.png", cam, tmp_path / "b.png")],
                             "test": [Frame("c", cam, torch.zeros(3, H, W + 1))]}, source="synthetic")
    with pytest.raises(FileFormatError, match=rf"2 of 3 images.*b\.png is {W}x{H + 2}, its camera {W}x{H}.*c is {W + 1}x{H}"):
        check_scene(data)


def test_empty_split_is_an_error(tmp_path):
    _write_blender(tmp_path, ring_poses(3), test=False)
    data = read_blender(tmp_path)
    assert check_scene(data)["splits"] == {"train": 3, "test": 0}
    with pytest.raises(InputValueError, match=r"the 'test' split is empty \(splits: train=3, test=0\)"):
        check_scene(data, required=("train", "test"))


# ------------------------------------------------------------------------------------------ detect

def _ngp(root):
    c2w = ring_poses(1)[0]
    write_png(root / "images" / "a.png", marker_image(W, H, [], rgba=False))
    write_json(root / "transforms.json", {"camera_angle_x": ANGLE_X, "frames": [{"file_path": "images/a.png",
                                                                                  "transform_matrix": c2w.tolist()}]})


def test_detect_each_format(tmp_path):
    for sub in ("sparse/0", "sparse"):
        (tmp_path / sub.replace("/", "_") / sub).mkdir(parents=True)
        (tmp_path / sub.replace("/", "_") / sub / "cameras.txt").write_text("# empty\n")
        assert detect_format(tmp_path / sub.replace("/", "_")) == "colmap"
    _write_blender(tmp_path / "blender", ring_poses(3))
    _ngp(tmp_path / "ngp")
    assert detect_format(tmp_path / "blender") == "blender"
    assert detect_format(tmp_path / "ngp") == "instant_ngp"
    data = load_dataset(tmp_path / "blender", white_background=True)
    assert data.format == "blender" and torch.equal(data.background, torch.ones(3))
    data = load_dataset(tmp_path / "ngp", holdout=0)
    assert data.format == "instant_ngp" and len(data.splits["train"]) == 1


def test_format_forces_the_reader(tmp_path):
    _write_blender(tmp_path, ring_poses(3))
    _ngp(tmp_path)
    assert load_dataset(tmp_path).format == "blender"
    assert load_dataset(tmp_path, format="instant-ngp").format == "instant_ngp"
    with pytest.raises(InputValueError, match="format must be one of colmap, blender, instant_ngp"):
        load_dataset(tmp_path, format="llff")
    with pytest.raises(InputValueError, match="images='images_4' applies to COLMAP"):
        load_dataset(tmp_path, images="images_4")


def test_unknown_or_missing_folder(tmp_path):
    (tmp_path / "photos").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(FileFormatError, match=r"not a dataset folder.*notes\.txt, photos/.*sparse/0.*"
                                              r"transforms_train\.json.*transforms\.json"):
        load_dataset(tmp_path)
    with pytest.raises(FileFormatError, match="dataset folder not found"):
        load_dataset(tmp_path / "missing")


# -------------------------------------------------------------------------------- cross-format

def _quaternion(r: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of the rotation ``r`` [3, 3] (largest-component branch for accuracy)."""
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = np.zeros(4)
        q[0], q[1 + i] = (r[k, j] - r[j, k]) / s, 0.25 * s
        q[1 + j], q[1 + k] = (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
    return np.asarray(q)


def _write_colmap(root, c2ws_gl, names, fx, fy, cx, cy):
    """COLMAP text model by hand: one PINHOLE camera; each image's world-to-camera in OpenCV axes."""
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "sparse" / "0" / "cameras.txt").write_text(f"# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n"
                                                       f"1 PINHOLE {W} {H} {fx!r} {fy!r} {cx!r} {cy!r}\n")
    lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"]
    for i, (c2w, name) in enumerate(zip(c2ws_gl, names)):
        w2c = np.linalg.inv(c2w @ _GL_TO_CV)
        lines += [" ".join(map(repr, [i + 1, *_quaternion(w2c[:3, :3]).tolist(), *w2c[:3, 3].tolist(), 1])) + f" {name}", ""]
    (root / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("other", ["blender", "instant_ngp"])
def test_same_scene_as_colmap_gives_the_same_cameras_and_images(tmp_path, other):
    poses = ring_poses(6, phase=0.7)
    poses[2] = poses[2] @ np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]])  # rolled: trace > 0
    names = [f"img_{i}.png" for i in range(6)]
    rng = np.random.default_rng(5)
    if other == "blender":   # centred principal point, square pixels: all Blender can say
        f = 0.5 * W / math.tan(ANGLE_X / 2)
        fx, fy, cx, cy = f, f, W / 2, H / 2
    else:
        fx, fy, cx, cy = 29.5, 31.25, 15.3, 12.9
    for name in names:
        px = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)
        write_png(tmp_path / "colmap" / "images" / name, px)
        write_png(tmp_path / other / "images" / name, px)
    _write_colmap(tmp_path / "colmap", poses, names, fx, fy, cx, cy)
    frames = [{"file_path": f"images/{n}", "transform_matrix": c2w.tolist()} for n, c2w in zip(names, poses)]
    if other == "blender":
        write_json(tmp_path / other / "transforms_train.json", {"camera_angle_x": ANGLE_X, "frames": frames})
    else:
        write_json(tmp_path / other / "transforms.json",
                   {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": W, "h": H, "frames": frames})
    a = load_dataset(tmp_path / "colmap", holdout=0)
    b = load_dataset(tmp_path / other, holdout=0)
    assert (a.format, b.format) == ("colmap", other)
    va, vb = a.views("train", resolution=16), b.views("train", resolution=16)
    assert [f.name for f in a.splits["train"]] == names and [f.name.split("/")[-1] for f in b.splits["train"]] == names
    for i in range(len(names)):
        ca, cb = va.camera(i), vb.camera(i)
        assert (ca.width, ca.height) == (cb.width, cb.height) == (16, 12)
        np.testing.assert_allclose(ca.world_to_camera.numpy(), cb.world_to_camera.numpy(), atol=1e-5)
        np.testing.assert_allclose(ca.intrinsics.numpy(), cb.intrinsics.numpy(), atol=1e-5)
        assert torch.equal(va.image(i), vb.image(i))


def test_views_first_keeps_the_leading_frames_in_order():
    k = torch.tensor([[20.0, 0, 8.0], [0, 20.0, 6.0], [0, 0, 1]])
    frames = [Frame(f"f{i}", Camera(torch.eye(4), k, 16, 12), torch.full((3, 12, 16), i / 10)) for i in range(5)]
    data = SceneData({"test": frames})
    assert [f.name for f in data.views("test", first=3).frames] == ["f0", "f1", "f2"]
    assert [f.name for f in data.views("test", first=0).frames] == ["f0"]  # at least one
    assert len(data.views("test")) == 5 and len(data.views("test", first=9)) == 5
    cam, img = data.views("test", first=2, resolution=8)[1]
    assert (cam.width, cam.height) == (8, 6) and torch.allclose(img, torch.full((3, 6, 8), 0.1))


@pytest.mark.parametrize("first", ["2", 1.5, True, float("nan")])
def test_views_first_must_be_an_integer(first):
    k = torch.tensor([[20.0, 0, 8.0], [0, 20.0, 6.0], [0, 0, 1]])
    data = SceneData({"test": [Frame("f0", Camera(torch.eye(4), k, 16, 12), torch.zeros(3, 12, 16))]})
    with pytest.raises(InputValueError, match="first"):
        data.views("test", first=first)
