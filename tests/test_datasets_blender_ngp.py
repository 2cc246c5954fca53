"""Blender (NeRF-synthetic) and instant-ngp readers against scenes built in the test: OpenGL look-at
poses and the OpenGL pinhole projection in numpy (tests/_datasets_synth.py), markers drawn where that
projection puts known points, RGBA composited analytically."""

from __future__ import annotations

import math
import shutil

import numpy as np
import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from _datasets_synth import look_at_gl, marker_image, project_gl, ring_poses, unproject_gl, write_json, write_png
from controlgs_adapter.datasets import opengl_c2w_to_w2c, read_blender, read_instant_ngp
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

W, H = 40, 30          # non-square: catches swapped axes
ANGLE_X = 0.9          # radians
COLOURS = [(255, 0, 0, 255), (0, 255, 0, 255), (0, 0, 255, 255), (255, 255, 0, 255), (0, 255, 255, 255)]


def _blender_focal(width: int) -> float:
    """NeRF-synthetic's definition: the horizontal field of view spans the image width."""
    return 0.5 * width / math.tan(ANGLE_X / 2)


def _blender_scene(root, poses=None):
    """Five cameras (3 train, 2 test); camera c sees its own marker point at pixel ``MARKS[c]``.
    Returns (poses, points [5, 3], marks)."""
    poses = ring_poses(5) if poses is None else poses
    f = _blender_focal(W)
    marks = [(5, 4), (33, 25), (20, 15), (0, 29), (39, 0)]
    points = np.stack([unproject_gl(c2w, f, f, W / 2, H / 2, (i + 0.5, j + 0.5), 3.5)
                       for c2w, (i, j) in zip(poses, marks)])
    for split, idx in (("train", [0, 1, 2]), ("test", [3, 4])):
        frames = []
        for n, c in enumerate(idx):
            write_png(root / split / f"r_{n}.png", marker_image(W, H, [(*marks[c], COLOURS[c])]))
            # train paths without an extension (appended), test paths with one (kept)
            frames.append({"file_path": f"./{split}/r_{n}" + ("" if split == "train" else ".png"),
                           "transform_matrix": poses[c].tolist()})
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": ANGLE_X, "frames": frames})
    return poses, points, marks


def test_blender_cameras_project_like_opengl_and_hit_the_drawn_markers(tmp_path):
    poses, points, marks = _blender_scene(tmp_path)
    data = read_blender(tmp_path)
    assert data.format == "blender" and data.points is None
    assert [f.name for f in data.splits["train"]] == ["train/r_0.png", "train/r_1.png", "train/r_2.png"]
    assert [f.name for f in data.splits["test"]] == ["test/r_0.png", "test/r_1.png"]
    f = _blender_focal(W)
    frames = data.splits["train"] + data.splits["test"]
    for c, frame in enumerate(frames):
        cam = frame.camera
        assert (cam.width, cam.height) == (W, H)
        uv, depth = cam.project(torch.from_numpy(points).float())
        uv_ref, depth_ref = project_gl(poses[c], f, f, W / 2, H / 2, points)
        np.testing.assert_allclose(uv.numpy(), uv_ref, atol=1e-3)
        np.testing.assert_allclose(depth.numpy(), depth_ref, atol=1e-4)
        np.testing.assert_allclose(cam.center.numpy(), poses[c][:3, 3], atol=1e-5)
        # the camera's own point lands on the centre of the pixel where its marker was drawn
        np.testing.assert_allclose(uv[c].numpy(), np.array(marks[c]) + 0.5, atol=1e-3)
    for split in ("train", "test"):
        views = data.views(split)
        for k, (cam, image) in enumerate(views):
            c = k if split == "train" else 3 + k
            i, j = marks[c]
            np.testing.assert_allclose(image[:, j, i].numpy(), np.array(COLOURS[c][:3]) / 255.0)
            assert float(image.sum()) == pytest.approx(sum(COLOURS[c][:3]) / 255.0)  # the rest is background


def test_blender_field_of_view_spans_the_image_width(tmp_path):
    """Points on the edges of the horizontal field of view project onto the image's left and right
    borders, at mid height (principal point at the centre)."""
    poses, _, _ = _blender_scene(tmp_path)
    cam = read_blender(tmp_path).splits["train"][1].camera
    d, t = 2.0, math.tan(ANGLE_X / 2)
    edges = np.stack([(poses[1] @ np.array([s * t * d, 0.0, -d, 1.0]))[:3] for s in (-1.0, 1.0)])
    uv, _ = cam.project(torch.from_numpy(edges).float())
    np.testing.assert_allclose(uv.numpy(), [[0.0, H / 2], [W, H / 2]], atol=1e-3)


@pytest.mark.parametrize("background, white, expected_bg", [
    (None, False, (0.0, 0.0, 0.0)),
    (None, True, (1.0, 1.0, 1.0)),
    (torch.tensor([0.1, 0.7, 0.3]), True, (0.1, 0.7, 0.3)),   # the argument overrides white_background
])
def test_blender_rgba_is_composited_over_the_background(tmp_path, background, white, expected_bg):
    rng = np.random.default_rng(0)
    px = rng.integers(0, 256, size=(H, W, 4), dtype=np.uint8)
    px[0, 0, 3], px[0, 1, 3] = 0, 255
    write_png(tmp_path / "train" / "r_0.png", px)
    write_json(tmp_path / "transforms_train.json",
               {"camera_angle_x": ANGLE_X, "frames": [{"file_path": "train/r_0", "transform_matrix": ring_poses(1)[0].tolist()}]})
    data = read_blender(tmp_path, background=background, white_background=white)
    image = data.views("train").image(0).numpy().transpose(1, 2, 0)
    a = px[..., 3:] / 255.0
    expected = px[..., :3] / 255.0 * a + np.array(expected_bg) * (1.0 - a)
    np.testing.assert_allclose(image, expected, atol=1e-6)
    assert data.splits["test"] == []


def test_blender_missing_image_names_it(tmp_path):
    _blender_scene(tmp_path)
    (tmp_path / "train" / "r_1.png").unlink()
    with pytest.raises(FileFormatError, match=r"transforms_train\.json.*r_1"):
        read_blender(tmp_path)
    with pytest.raises(FileFormatError, match="not found"):
        read_blender(tmp_path / "nowhere")


def test_blender_refuses_a_test_view_that_is_a_training_view(tmp_path):
    poses, _, _ = _blender_scene(tmp_path)
    write_json(tmp_path / "transforms_test.json",
               {"camera_angle_x": ANGLE_X, "frames": [{"file_path": "train/r_2.png", "transform_matrix": poses[2].tolist()}]})
    with pytest.raises(FileFormatError, match=r"transforms_test\.json: lists training images too \(train/r_2\.png\)"):
        read_blender(tmp_path)


def test_blender_refuses_a_non_rigid_transform(tmp_path):
    poses, _, _ = _blender_scene(tmp_path)
    bad = poses[0].copy()
    bad[:3, :3] *= 2.0
    write_json(tmp_path / "transforms_train.json",
               {"camera_angle_x": ANGLE_X, "frames": [{"file_path": "train/r_0", "transform_matrix": bad.tolist()}]})
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[0\].*not a rotation"):
        read_blender(tmp_path)


# ---------------------------------------------------------------------------------------------- ngp

FL = (35.5, 36.25, 20.3, 14.6)   # global fl_x, fl_y, cx, cy (floats, off-centre)


def _ngp_scene(root, n=10, *, extra_top=None, top=None, per_frame=None, size=(W, H), file_size=None, names=None):
    """``n`` frames ``images/img_XX.png`` listed in shuffled order; global intrinsics ``FL`` and
    distortion at ``file_size`` (default the image size) plus ``extra_top``, or ``top`` instead;
    ``per_frame`` {index: extra keys}. Returns the poses by index."""
    poses = ring_poses(n, phase=0.1)
    fw, fh = file_size or size
    rng = np.random.default_rng(1)
    frames = []
    for i in rng.permutation(n):
        name = names[i] if names else f"images/img_{i:02d}.png"
        write_png(root / name, marker_image(size[0], size[1], [], rgba=False, fill=(10 * i, 0, 0)))
        frames.append({"file_path": name, "transform_matrix": poses[i].tolist(), **((per_frame or {}).get(i, {}))})
    top = {"fl_x": FL[0], "fl_y": FL[1], "cx": FL[2], "cy": FL[3], "w": float(fw), "h": float(fh),
           "k1": 0.01, "k2": -0.002, "p1": 0.0005, "p2": -0.0003, "aabb_scale": 16, **(extra_top or {})} if top is None else top
    write_json(root / "transforms.json", {**top, "frames": frames})
    return poses


def _by_index(data):
    return {int(f.name[-6:-4]): f for split in data.splits.values() for f in split}


def test_ngp_global_and_per_frame_intrinsics_and_distortion(tmp_path):
    own = {"fl_x": 30.0, "fl_y": 31.0, "cx": 19.0, "cy": 16.0, "k1": -0.05}
    poses = _ngp_scene(tmp_path, per_frame={2: own, 5: {"camera_angle_x": 1.1}, 7: {"fl_x": 33.0}})
    frames = _by_index(read_instant_ngp(tmp_path, holdout=0))
    pts = np.random.default_rng(2).uniform(-1, 1, size=(20, 3))
    fov_f = 0.5 * W / math.tan(1.1 / 2)
    # a frame's focal keys replace the global ones as a group; one focal length serves both axes
    expected_k = {2: (30.0, 31.0, 19.0, 16.0), 5: (fov_f, fov_f, FL[2], FL[3]), 7: (33.0, 33.0, FL[2], FL[3])}
    for i, frame in frames.items():
        fx, fy, cx, cy = expected_k.get(i, FL)
        uv, depth = frame.camera.project(torch.from_numpy(pts).float())
        uv_ref, depth_ref = project_gl(poses[i], fx, fy, cx, cy, pts)
        np.testing.assert_allclose(uv.numpy(), uv_ref, atol=1e-3)
        np.testing.assert_allclose(depth.numpy(), depth_ref, atol=1e-4)
        # a frame's distortion keys replace the global ones as a group (absent k2 p1 p2 are zero there)
        assert frame.distortion == ((-0.05, 0.0, 0.0, 0.0, 0.0) if i == 2 else (0.01, -0.002, 0.0005, -0.0003, 0.0))


def test_ngp_camera_angles_span_the_image(tmp_path):
    poses = _ngp_scene(tmp_path, n=2, top={"camera_angle_x": 1.0, "camera_angle_y": 0.6})
    frame = _by_index(read_instant_ngp(tmp_path, holdout=0))[1]
    assert frame.distortion is None
    d, tx, ty = 3.0, math.tan(0.5), math.tan(0.3)
    pts = np.stack([(poses[1] @ np.array([x, y, -d, 1.0]))[:3] for x, y in ((tx * d, 0), (-tx * d, 0), (0, ty * d))])
    uv, _ = frame.camera.project(torch.from_numpy(pts).float())
    np.testing.assert_allclose(uv.numpy(), [[W, H / 2], [0, H / 2], [W / 2, 0]], atol=1e-3)


def test_ngp_intrinsics_scale_to_downscaled_images(tmp_path):
    """The file describes 80 x 60 captures; the images are 40 x 30: every projection halves."""
    poses = _ngp_scene(tmp_path, n=3, file_size=(80, 60))
    pts = np.random.default_rng(3).uniform(-1, 1, size=(10, 3))
    for i, frame in _by_index(read_instant_ngp(tmp_path, holdout=0)).items():
        assert (frame.camera.width, frame.camera.height) == (W, H)
        uv, _ = frame.camera.project(torch.from_numpy(pts).float())
        uv_full, _ = project_gl(poses[i], *FL, pts)
        np.testing.assert_allclose(uv.numpy(), uv_full * 0.5, atol=1e-3)


def test_ngp_non_uniform_size_mismatch_is_refused_naming_the_file(tmp_path):
    _ngp_scene(tmp_path, n=3, file_size=(80, 30))
    with pytest.raises(FileFormatError, match=r"transforms\.json.*80 x 30.*img_\d\d\.png is 40 x 30"):
        read_instant_ngp(tmp_path)


def test_ngp_missing_images_are_reported_and_skipped(tmp_path):
    _ngp_scene(tmp_path, n=10)
    for i in (7, 3, 4):
        (tmp_path / "images" / f"img_{i:02d}.png").unlink()
    with pytest.warns(RuntimeWarning, match=r"3 of 10 frames.*img_0[347]\.png") as rec:
        data = read_instant_ngp(tmp_path, holdout=0)
    msg = str(rec[0].message)
    assert all(f"img_{i:02d}.png" in msg for i in (3, 4, 7))
    assert sorted(_by_index(data)) == [0, 1, 2, 5, 6, 8, 9]
    shutil.rmtree(tmp_path / "images")
    with pytest.warns(RuntimeWarning), pytest.raises(FileFormatError, match="none of the 10 images"):
        read_instant_ngp(tmp_path)


def test_ngp_split_every_holdout_th_by_name(tmp_path):
    names = [f"images/{s}.png" for s in ("b", "k", "a", "f", "c", "j", "d", "h", "e", "g")]
    _ngp_scene(tmp_path, names=names)
    ordered = sorted(names)
    for holdout in (3, 8):
        data = read_instant_ngp(tmp_path, holdout=holdout)
        assert [f.name for f in data.splits["test"]] == ordered[::holdout]
        assert sorted(f.name for f in data.splits["train"]) == sorted(set(ordered) - set(ordered[::holdout]))
    data = read_instant_ngp(tmp_path, holdout=0)
    assert data.splits["test"] == [] and len(data.splits["train"]) == 10
    with pytest.raises(InputValueError, match="holdout"):
        read_instant_ngp(tmp_path, holdout=1)


def test_ngp_ignores_the_scene_box_keys(tmp_path):
    """aabb_scale / scale / offset place the scene in instant-ngp's grid: the cameras do not change."""
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    _ngp_scene(tmp_path / "a", n=3)
    _ngp_scene(tmp_path / "b", n=3, extra_top={"aabb_scale": 128, "scale": 0.33, "offset": [0.5, 0.2, -0.1]})
    for fa, fb in zip(read_instant_ngp(tmp_path / "a", holdout=0).splits["train"],
                      read_instant_ngp(tmp_path / "b", holdout=0).splits["train"]):
        assert torch.equal(fa.camera.world_to_camera, fb.camera.world_to_camera)
        assert torch.equal(fa.camera.intrinsics, fb.camera.intrinsics)


@pytest.mark.parametrize("key, value", [("is_fisheye", True), ("k4", 0.01), ("camera_model", "OPENCV_FISHEYE")])
def test_ngp_refuses_fisheye_and_a_missing_file(tmp_path, key, value):
    _ngp_scene(tmp_path, n=2, per_frame={1: {key: value}})
    with pytest.raises(FileFormatError, match=rf"transforms\.json: frames\[\d\] \('images/img_01\.png'\).*{key}"):
        read_instant_ngp(tmp_path)
    with pytest.raises(FileFormatError, match=r"other\.json: not found"):
        read_instant_ngp(tmp_path, transforms="other.json")


# ------------------------------------------------------------------------------------ axis property

_coord = st.floats(-5.0, 5.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(eye=st.tuples(_coord, _coord, _coord), target=st.tuples(_coord, _coord, _coord),
       up=st.tuples(_coord, _coord, _coord))
def test_opengl_to_opencv_keeps_the_centre_and_looks_at_the_target(eye, target, up):
    eye, target, up = map(np.array, (eye, target, up))
    fwd = target - eye
    n_fwd, n_up = np.linalg.norm(fwd), np.linalg.norm(up)
    assume(n_fwd > 0.5 and n_up > 0.5 and np.linalg.norm(np.cross(fwd, up)) > 0.2 * n_fwd * n_up)  # a proper look-at
    c2w = look_at_gl(eye, target, up)
    k = torch.tensor([[50.0, 0, 20.0], [0, 50.0, 15.0], [0, 0, 1]])
    cam = Camera(opengl_c2w_to_w2c(c2w), k, W, H)
    np.testing.assert_allclose(cam.center.numpy(), eye, atol=1e-4)
    # the target at positive depth on the principal point; up appears above it, right of it to the right
    right = np.cross(fwd, up)
    up_img = np.cross(right, fwd)
    probe = np.stack([target, target + 0.1 * up_img / np.linalg.norm(up_img), target + 0.1 * right / np.linalg.norm(right)])
    uv, depth = cam.project(torch.from_numpy(probe).float())
    assert float(depth[0]) == pytest.approx(np.linalg.norm(fwd), rel=1e-4)
    np.testing.assert_allclose(uv[0].numpy(), [20.0, 15.0], atol=1e-3)
    assert float(uv[1, 1]) < 15.0 and float(uv[2, 0]) > 20.0


def _distort(xy: np.ndarray, k1, k2, p1, p2, k3) -> np.ndarray:
    """OpenCV radial-tangential model on normalised coordinates ``[2]``."""
    x, y = xy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return np.array([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                     y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y])


def test_ngp_distorted_capture_is_undistorted_onto_the_pinhole_projection(tmp_path):
    """A 3x3 marker drawn where the distorted capture shows a known point ends up, after loading,
    where the read pinhole camera projects that point (the distortion moves it by 1.6 pixels)."""
    fx, fy, cx, cy, dist = 30.0, 30.0, 20.0, 15.0, (0.5, 0.1, 0.004, -0.003, 0.05)
    c2w = ring_poses(1)[0]
    col, row = 32, 24                                  # marker centre at the pixel centre (32.5, 24.5)
    target = np.array([(col + 0.5 - cx) / fx, (row + 0.5 - cy) / fy])
    xy = target.copy()
    for _ in range(200):                               # fixed point: distort(xy) = target
        xy = xy + (target - _distort(xy, *dist))
    np.testing.assert_allclose(_distort(xy, *dist), target, atol=1e-10)
    point = unproject_gl(c2w, fx, fy, cx, cy, (cx + fx * xy[0], cy + fy * xy[1]), 3.0)
    img = np.zeros((H, W, 3), dtype=np.uint8)
    img[row - 1:row + 2, col - 1:col + 2] = 255
    write_png(tmp_path / "images" / "a.png", img)
    write_json(tmp_path / "transforms.json", {
        "fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": W, "h": H, **dict(zip(("k1", "k2", "p1", "p2", "k3"), dist)),
        "frames": [{"file_path": "images/a.png", "transform_matrix": c2w.tolist()}]})
    views = read_instant_ngp(tmp_path, holdout=0).views("train")
    cam, image = views[0]
    uv, _ = cam.project(torch.from_numpy(point[None]).float())
    assert np.linalg.norm(uv[0].numpy() - (col + 0.5, row + 0.5)) > 1.5   # distortion matters here
    weight = image[0].double()
    jj, ii = torch.meshgrid(torch.arange(H, dtype=torch.float64) + 0.5, torch.arange(W, dtype=torch.float64) + 0.5,
                            indexing="ij")
    centroid = np.array([float((weight * ii).sum() / weight.sum()), float((weight * jj).sum() / weight.sum())])
    np.testing.assert_allclose(centroid, uv[0].numpy(), atol=0.3)
