"""Tests of ``controlgs_adapter.datasets.blender``: NeRF-synthetic cameras (OpenGL camera to world, the field of
view across the width), RGBA over the background, and refusals that name the file and frame: paths leading outside
the folder, duplicated or malformed entries, numbers that are not numbers or do not fit float32."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
import torch
from helpers.dataset_files import C2W, blender, frame as make_frame, opened_under, outside, png, recording
from helpers.datasets_synth import look_at_gl, marker_image, project_gl, ring_poses, unproject_gl, write_json, write_png
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from PIL import Image

from controlgs_adapter.datasets import load_dataset, opengl_c2w_to_w2c, read_blender
from controlgs_adapter.datasets.blender import resolve_background
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

W, H = 40, 30          # non-square: catches swapped axes
ANGLE_X = 0.9          # radians
_COORD = st.floats(-5.0, 5.0, allow_nan=False)
#: the colour of each camera's marker
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


_EYE = [[1.0, 0.0, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]]


def _one_frame(root, angle=math.pi / 2, frames=None) -> dict:
    """``root/train/r_0.png`` (8 x 4, transparent) listed with the pose :data:`_EYE`; returns the metadata."""
    (root / "train").mkdir(exist_ok=True)
    Image.fromarray(np.zeros((4, 8, 4), np.uint8), "RGBA").save(root / "train" / "r_0.png")
    meta = {"camera_angle_x": angle, "frames": frames or [{"file_path": "./train/r_0", "transform_matrix": _EYE}]}
    (root / "transforms_train.json").write_text(json.dumps(meta))
    return meta


def test_one_frame_camera_and_pose(tmp_path):
    """fov 90 deg over 8 px: f = 4, centre (4, 2); an OpenGL camera at (0.5, 0, 2) looking down -z is the
    OpenCV world-to-camera with y and z flipped, t = -R^T c; the scene records the folder, no points."""
    _one_frame(tmp_path)
    scene = read_blender(tmp_path, white_background=True)
    (f,) = scene.splits["train"]
    assert scene.splits["test"] == [] and f.name == "train/r_0.png" and scene.background.tolist() == [1.0, 1.0, 1.0]
    assert scene.source == str(tmp_path) and scene.points is None and scene.format == "blender"
    np.testing.assert_allclose(f.camera.intrinsics, [[4.0, 0.0, 4.0], [0.0, 4.0, 2.0], [0.0, 0.0, 1.0]], rtol=1e-6)
    assert f.camera.world_to_camera.tolist() == [[1, 0, 0, -0.5], [0, -1, 0, 0], [0, 0, -1, 2], [0, 0, 0, 1]]


def test_folder_file_and_image_refusals(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        read_blender(tmp_path / "nowhere")
    with pytest.raises(FileFormatError, match="no transforms_train.json"):
        read_blender(tmp_path)
    meta = _one_frame(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "frames": {}}))
    with pytest.raises(FileFormatError, match="transforms_train.json: 'frames' must be a list, got dict"):
        read_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "frames": [{"file_path": "train/r_1.jpg"}]}))
    with pytest.raises(FileFormatError, match=r"frames\[0\] image 'train/r_1.jpg' not found \(looked for .*r_1.jpg and "
                                              r"with .png appended\)"):
        read_blender(tmp_path)
    (tmp_path / "transforms_train.json").write_text(json.dumps({**meta, "frames": [{"file_path": "train/r_1.png"}]}))
    with pytest.raises(FileFormatError, match=r"r_1.png\)$"):
        read_blender(tmp_path)


@pytest.mark.parametrize("angle", [0.0, math.pi, "1", "0.69", True, None])
def test_the_field_of_view_must_be_a_number_in_0_pi(tmp_path, angle):
    _one_frame(tmp_path, angle=angle)
    with pytest.raises(FileFormatError, match=rf"transforms_train\.json: camera_angle_x .*got {re.escape(repr(angle))}$"):
        read_blender(tmp_path)


def test_background_is_a_finite_srgb_colour_kept_as_a_constant(tmp_path):
    """Default black (white with ``white_background``); a given colour overrides ``white_background``; a
    component out of [0, 1] or not finite is refused; the colour kept is detached."""
    torch.testing.assert_close(resolve_background(None), torch.zeros(3))
    torch.testing.assert_close(resolve_background(None, True), torch.ones(3))
    _one_frame(tmp_path)
    assert float(read_blender(tmp_path).views("train").image(0).abs().max()) == 0.0  # transparent: the background
    assert float(read_blender(tmp_path, white_background=True).views("train").image(0).min()) == 1.0
    assert read_blender(tmp_path, background=torch.tensor([0.2, 0.4, 0.6]), white_background=True).background.tolist() \
        == pytest.approx([0.2, 0.4, 0.6])
    for bad in ([0.0, 2.0, 0.0], [-0.25, 0.5, 0.5]):
        with pytest.raises(InputValueError, match=rf"background.*got {re.escape(str(bad))}"):
            read_blender(tmp_path, background=torch.tensor(bad))
    with pytest.raises(InputValueError, match="background"):
        read_blender(tmp_path, background=torch.tensor([float("nan"), 0.0, 0.0]))
    bg = torch.tensor([0.25, 0.5, 0.75], requires_grad=True)
    kept = read_blender(tmp_path, background=bg).background
    assert not kept.requires_grad and kept.tolist() == [0.25, 0.5, 0.75]



# ----------------------------------------------------------------------------- paths outside the folder

def _root(tmp_path):
    return tmp_path / "scene"


@pytest.mark.parametrize("file_path", ["../outside/sentinel", "./train/../../outside/sentinel.png", "ABS"])
def test_a_file_path_leading_outside_the_folder_is_refused_naming_the_frame(tmp_path, file_path):
    out = outside(tmp_path)
    file_path = str(out / "sentinel") if file_path == "ABS" else file_path
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame(file_path)])
    with recording() as opened, pytest.raises(FileFormatError) as e:
        read_blender(root)
    assert "transforms_train.json: frames[1]" in str(e.value) and "sentinel" in str(e.value)
    assert opened_under(out, opened) == []


def test_a_symlinked_image_pointing_outside_the_folder_is_refused(tmp_path):
    out = outside(tmp_path)
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame("./train/r_1")], images=["r_0"])
    (root / "train" / "r_1.png").symlink_to(out / "sentinel.png")
    with recording() as opened, pytest.raises(FileFormatError,
                                              match=r"transforms_train\.json: frames\[1\]: file_path .*leads outside"):
        load_dataset(root)
    assert opened_under(out, opened) == []


def test_a_transforms_file_symlinked_outside_the_folder_is_refused(tmp_path):
    out = outside(tmp_path)
    root = blender(_root(tmp_path), [make_frame("./train/r_0")])
    (root / "transforms_test.json").symlink_to(out / "sentinel.json")
    with recording() as opened, pytest.raises(FileFormatError, match=r"scene: the file 'transforms_test\.json' leads outside"):
        read_blender(root)
    assert opened_under(out, opened) == []


# ----------------------------------------------------------------------------- entries and numbers

def test_a_duplicated_frame_is_refused_naming_both(tmp_path):
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame("./train/r_1"), make_frame("train/r_0.png")])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[2\] .*listed twice \('train/r_0\.png'\), "
                                              r"also in frames\[0\]"):
        read_blender(root)


def test_a_last_row_other_than_0001_is_refused(tmp_path):
    bad = [row[:] for row in C2W]
    bad[3] = [0.0, 0.0, 0.5, 1.0]
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame("./train/r_1", bad)])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[1\] .*last row must be \[0, 0, 0, 1\], "
                                              r"got \[0\.0, 0\.0, 0\.5, 1\.0\]"):
        read_blender(root)


@pytest.mark.parametrize("value", ["4.0", True, None, [4.0]])
def test_a_non_number_in_the_transform_matrix_is_refused(tmp_path, value):
    bad = [row[:] for row in C2W]
    bad[2][3] = value
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame("./train/r_1", bad)])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[1\] .*transform_matrix must hold numbers"):
        read_blender(root)


def test_deep_nesting_and_oversized_integers_are_refused_naming_the_file(tmp_path):
    root = blender(_root(tmp_path), [], raw='{"frames": ' + "[" * 200_000 + "]" * 200_000 + "}")
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: cannot read it as JSON \(nested too deeply\)"):
        read_blender(root)
    (root / "transforms_train.json").write_text('{"camera_angle_x": ' + "1" * 400 + ', "frames": []}')
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: camera_angle_x must be a number"):
        read_blender(root)
    (root / "transforms_train.json").write_text('{"camera_angle_x": ' + "1" * 5000 + ', "frames": []}')
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: cannot read it as JSON"):
        read_blender(root)


def test_values_beyond_float32_are_refused_naming_the_file_and_frame(tmp_path):
    far = [row[:] for row in C2W]
    far[0][3] = 1e300
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame("./train/r_1", far)])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[1\] \('\./train/r_1'\): .*float32"):
        read_blender(root)
    root = blender(tmp_path / "narrow", [make_frame("./train/r_0")], angle=1e-300)  # focal 0.5 W / tan(1e-300 / 2)
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[0\] \('\./train/r_0'\): intrinsics .*float32"):
        read_blender(root)


def test_file_paths_with_and_without_png_name_the_frames(tmp_path):
    root = blender(_root(tmp_path), [make_frame("./train/r_0"), make_frame("train/r_1.png")])
    png(root / "test" / "r_2.png")
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [make_frame("./test/r_2")]}))
    data = read_blender(root)
    assert [f.name for f in data.splits["train"]] == ["train/r_0.png", "train/r_1.png"]
    assert [f.name for f in data.splits["test"]] == ["test/r_2.png"]


# ----------------------------------------------------------------------------- opengl_c2w_to_w2c

def test_opengl_identity_pose_is_the_yz_flip_and_translation_is_minus_rt_t():
    # c2w = identity in OpenGL axes: the OpenCV rotation is diag(1, -1, -1) (y and z columns negated),
    # its inverse is itself; with t = (1, 2, 3): -R^T t = -(1, -2, -3) = (-1, 2, 3)
    c2w = np.eye(4)
    c2w[:3, 3] = (1.0, 2.0, 3.0)
    w2c = opengl_c2w_to_w2c(c2w)
    assert w2c.dtype == torch.float32
    assert torch.equal(w2c, torch.tensor([[1.0, 0, 0, -1], [0, -1, 0, 2], [0, 0, -1, 3], [0, 0, 0, 1]]))
    assert torch.equal(opengl_c2w_to_w2c(c2w[:3]), w2c)  # a 3x4 matrix is the same pose


def test_opengl_pose_refusals_and_the_1e_3_orthonormality_tolerance():
    for bad, shape in ((np.eye(3), "[3, 3]"), (np.ones((2, 4)), "[2, 4]")):
        with pytest.raises(InputValueError, match=rf"finite 4x4 \(or 3x4\) matrix, got shape {re.escape(shape)}"):
            opengl_c2w_to_w2c(bad)
    nan = np.eye(4)
    nan[0, 3] = np.nan
    with pytest.raises(InputValueError, match=r"got shape \[4, 4\]"):
        opengl_c2w_to_w2c(nan)
    # a uniform scale s gives R^T R - I = s^2 - 1: 1.0004^2 - 1 = 8.0e-4 <= 1e-3 accepted,
    # 1.0006^2 - 1 = 1.2e-3 > 1e-3 refused
    opengl_c2w_to_w2c(np.diag([1.0004, 1.0004, 1.0004, 1.0]))
    with pytest.raises(InputValueError, match="not a rotation"):
        opengl_c2w_to_w2c(np.diag([1.0006, 1.0006, 1.0006, 1.0]))
    with pytest.raises(InputValueError, match="not a rotation"):  # orthonormal but mirrored (det -1)
        opengl_c2w_to_w2c(np.diag([-1.0, 1.0, 1.0, 1.0]))


def test_blender_pose_is_inverted_in_float64_even_from_a_float32_matrix():
    """The docstring promises the rigid inverse (``R^T``, ``-R^T t``) in float64, then float32: a float32 ``transform_matrix`` of a
    camera far from the origin looking back at it gives the correctly rounded world-to-camera matrix, whose
    x and y translation (a cancellation of terms in the thousands) stay near zero."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        centre = rng.uniform(-3000.0, 3000.0, 3)
        z_gl = centre / np.linalg.norm(centre)  # OpenGL: the camera looks along -z, here at the origin
        x = np.cross([0.0, 0.0, 1.0], z_gl)
        x /= np.linalg.norm(x)
        c2w = np.eye(4)
        c2w[:3, :3] = np.stack([x, np.cross(z_gl, x), z_gl], axis=1)
        c2w[:3, 3] = centre
        c2w32 = c2w.astype(np.float32)
        ref = c2w32.astype(np.float64)
        ref[:3, 1:3] *= -1.0  # OpenGL -> OpenCV camera axes
        rot = ref[:3, :3]
        w2c_ref = np.eye(4)
        w2c_ref[:3, :3] = rot.T  # the documented rigid inverse R^T, -R^T t, each entry summed in float64
        w2c_ref[:3, 3] = [-sum(rot[k, i] * ref[k, 3] for k in range(3)) for i in range(3)]
        got = opengl_c2w_to_w2c(c2w32)
        assert got.dtype == torch.float32
        np.testing.assert_allclose(got.numpy().astype(np.float64), w2c_ref, rtol=1e-7, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(eye=st.tuples(_COORD, _COORD, _COORD), target=st.tuples(_COORD, _COORD, _COORD), up=st.tuples(_COORD, _COORD, _COORD))
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
