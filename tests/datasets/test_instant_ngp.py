"""Tests of ``controlgs_adapter.datasets.instant_ngp``: intrinsics from focal lengths or fields of view (global,
per frame, scaled to downscaled images), distortion, the split by name, missing images, and refusals naming the
file and frame (the Blender reader's path, number and pose checks, fisheye cameras, sizes that are not one scale)."""

from __future__ import annotations

import json
import math
import shutil
import warnings

import numpy as np
import pytest
import torch
from helpers.dataset_files import C2W, frame as make_frame, instant_ngp, opened_under, outside, recording
from helpers.datasets_synth import marker_image, project_gl, ring_poses, unproject_gl, write_json, write_ngp_ring, write_png
from PIL import Image

from controlgs_adapter.datasets import load_dataset, read_instant_ngp
from controlgs_adapter.errors import FileFormatError, InputValueError

W, H = 40, 30          # non-square: catches swapped axes
FL = (35.5, 36.25, 20.3, 14.6)   # global fl_x, fl_y, cx, cy (floats, off-centre)
_EYE = [[1.0, 0.0, 0.0, 0.5], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.0], [0.0, 0.0, 0.0, 1.0]]


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


def _distort(xy: np.ndarray, k1, k2, p1, p2, k3) -> np.ndarray:
    """OpenCV radial-tangential model on normalised coordinates ``[2]``."""
    x, y = xy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return np.array([x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                     y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y])


def _ngp(root, meta: dict, frames: list[dict], sizes: dict[str, tuple[int, int]]):
    """``root/transforms.json`` of ``meta`` and ``frames`` (each posed at :data:`_EYE` unless it says otherwise)
    and a black image of each size in ``sizes`` (name -> (w, h))."""
    root.mkdir(parents=True, exist_ok=True)
    for name, (w, h) in sizes.items():
        Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(root / name)
    (root / "transforms.json").write_text(json.dumps({**meta, "frames": [{"transform_matrix": _EYE, **f} for f in frames]}))
    return root


def _tiny_ngp(root, frame_extra: dict | None = None, missing: int = 0, n: int = 3, size=(8, 6), **top) -> None:
    """``n`` frames ``images/f<i>.png`` with images, then ``missing`` frames whose image is not there."""
    frames = []
    for i, c2w in enumerate(ring_poses(n + missing)):
        if i < n:
            write_png(root / "images" / f"f{i}.png", np.zeros((size[1], size[0], 3), dtype=np.uint8))
        frames.append({"file_path": f"images/f{i}.png", "transform_matrix": c2w.tolist(), **(frame_extra or {})})
    write_json(root / "transforms.json", {"fl_x": 9.0, "fl_y": 9.0, "w": size[0], "h": size[1], **top, "frames": frames})


def _root(tmp_path):
    return tmp_path / "scene"


# ----------------------------------------------------------------------------- cameras

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


def test_ngp_intrinsics_defaults_and_group_overrides(tmp_path):
    meta = {"fl_y": 6.0, "w": 8, "h": 4, "k1": 0.0, "k2": 0.0}
    frames = [{"file_path": "a.png"},
              {"file_path": "b.png", "camera_angle_x": math.pi / 2, "cx": 1.0, "k3": 0.01},
              {"file_path": "c.png", "camera_angle_y": math.pi / 2, "w": 16, "h": 8}]
    root = _ngp(tmp_path, meta, frames, {"a.png": (8, 4), "b.png": (4, 2), "c.png": (8, 4)})
    scene = read_instant_ngp(root, holdout=0)
    a, b, c = scene.splits["train"]
    assert a.camera.intrinsics.tolist() == [[6.0, 0.0, 4.0], [0.0, 6.0, 2.0], [0.0, 0.0, 1.0]]  # fx from fl_y; centre w/2, h/2
    assert a.distortion is None  # all-zero coefficients: pinhole
    # b: its own focal group (fx = 0.5 w / tan(pi/4) = 4; fy from fx), its own cx (cy from the top level's h/2): half size
    np.testing.assert_allclose(b.camera.intrinsics, [[2.0, 0.0, 0.5], [0.0, 2.0, 1.0], [0.0, 0.0, 1.0]], rtol=1e-6)
    assert b.distortion == (0.0, 0.0, 0.0, 0.0, 0.01)  # the frame's distortion group replaces the top level's
    # c: fy = 0.5 h / tan(pi/4) = 4 at 16 x 8, image at half size
    np.testing.assert_allclose(c.camera.intrinsics, [[2.0, 0.0, 4.0], [0.0, 2.0, 2.0], [0.0, 0.0, 1.0]], rtol=1e-6)
    assert scene.points is None and scene.format == "instant_ngp" and scene.source == str(root)
    assert torch.equal(scene.background, torch.zeros(3))  # default black


def test_a_one_pixel_image_is_a_valid_camera(tmp_path):
    """``w, h`` must be > 0: a 1 x 1 capture (w = h = 1) is a valid camera."""
    _tiny_ngp(tmp_path, size=(1, 1), cx=0.5, cy=0.5, fl_x=0.75, fl_y=0.5)   # focal lengths > 0, below 1 px
    cam = read_instant_ngp(tmp_path, holdout=0).splits["train"][0].camera
    assert (cam.width, cam.height) == (1, 1)
    assert cam.intrinsics.tolist() == [[0.75, 0.0, 0.5], [0.0, 0.5, 0.5], [0.0, 0.0, 1.0]]


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


def test_the_files_size_must_be_one_scale_of_the_images(tmp_path):
    """Downscaled images scale every projection by the one factor, each axis by its own within 1 px per side;
    beyond that the file is refused naming both sizes."""
    _ngp_scene(tmp_path / "wide", n=3, file_size=(80, 30))
    with pytest.raises(FileFormatError, match=r"transforms\.json.*80 x 30.*img_\d\d\.png is 40 x 30"):
        read_instant_ngp(tmp_path / "wide")

    def portrait(root, size):  # the file says 25 x 100
        write_png(root / "images" / "a.png", marker_image(size[0], size[1], [], rgba=False))
        write_json(root / "transforms.json", {"fl_x": 20.0, "fl_y": 21.0, "cx": 12.0, "cy": 50.0, "w": 25.0, "h": 100.0,
                                              "frames": [{"file_path": "images/a.png",
                                                          "transform_matrix": ring_poses(1)[0].tolist()}]})

    portrait(tmp_path / "bad", (26, 102))  # x scale 1.04, y scale 1.02
    with pytest.raises(FileFormatError, match=r"25 x 100.*26 x 102"):
        read_instant_ngp(tmp_path / "bad", holdout=0)
    portrait(tmp_path / "ok", (50, 200))  # one scale (2): the intrinsics doubled
    cam = read_instant_ngp(tmp_path / "ok", holdout=0).splits["train"][0].camera
    np.testing.assert_allclose(cam.intrinsics.numpy(), [[40.0, 0.0, 24.0], [0.0, 42.0, 100.0], [0.0, 0.0, 1.0]])
    # an 8 x 8 image whose file says w = 16: sx = 0.5; h = 18 gives h sx - 8 = 1.0 (at the 1 px limit) and
    # w sy - 8 = 16 * 8 / 18 - 8 = -0.89: accepted, each axis scaled by its own factor; h = 18.2 gives 1.1 px
    tol = tmp_path / "tol"
    tol.mkdir()
    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tol / "a.png")
    meta = {"fl_x": 20.0, "fl_y": 18.0, "cx": 8.0, "cy": 9.0, "w": 16, "h": 18,
            "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}
    (tol / "transforms.json").write_text(json.dumps(meta))
    cam = read_instant_ngp(tol, holdout=0).splits["train"][0].camera
    assert torch.allclose(cam.intrinsics, torch.tensor([[10.0, 0, 4.0], [0, 8.0, 4.0], [0, 0, 1]]))
    (tol / "transforms.json").write_text(json.dumps({**meta, "h": 18.2}))
    with pytest.raises(FileFormatError, match="the file says 16 x 18.2 but the image"):
        read_instant_ngp(tol, holdout=0)


# ----------------------------------------------------------------------------- split

def test_every_holdout_th_frame_by_name_is_a_test_view(tmp_path):
    """Default 8 (3DGS's ``--eval``), from the first frame in name order, whatever the file's order; 0: no test
    split; 1 and non-integers are refused. The transforms file is transforms.json unless another is named."""
    write_ngp_ring(tmp_path)
    want = ["images/img_00.png", "images/img_08.png"]
    assert [f.name for f in read_instant_ngp(tmp_path).splits["test"]] == want
    assert [f.name for f in load_dataset(tmp_path, format="instant_ngp").splits["test"]] == want
    assert len(read_instant_ngp(tmp_path).splits["train"]) == 8
    names = [f"images/{s}.png" for s in ("b", "k", "a", "f", "c", "j", "d", "h", "e", "g")]
    _ngp_scene(tmp_path / "shuffled", names=names)
    ordered = sorted(names)
    for holdout in (3, 8):
        data = read_instant_ngp(tmp_path / "shuffled", holdout=holdout)
        assert [f.name for f in data.splits["test"]] == ordered[::holdout]
        assert sorted(f.name for f in data.splits["train"]) == sorted(set(ordered) - set(ordered[::holdout]))
    data = read_instant_ngp(tmp_path / "shuffled", holdout=0)
    assert data.splits["test"] == [] and len(data.splits["train"]) == 10
    for bad in (1, -1, True, 2.0):
        with pytest.raises(InputValueError, match=f"holdout.*got {bad!r}$"):
            read_instant_ngp(tmp_path, holdout=bad)
    other = write_ngp_ring(tmp_path / "other", n=3, transforms="transforms_x.json")
    with pytest.raises(FileFormatError, match=r"transforms\.json: not found"):
        read_instant_ngp(other)
    assert len(read_instant_ngp(other, transforms="transforms_x.json", holdout=0).splits["train"]) == 3


# ----------------------------------------------------------------------------- missing images and warnings

def test_frames_whose_image_is_missing_are_skipped_with_a_warning(tmp_path):
    """The warning names how many and the first five (", ..." after that) and points at the caller's line,
    also through load_dataset; no image left is refused."""
    _ngp_scene(tmp_path, n=10)
    for i in (7, 3, 4):
        (tmp_path / "images" / f"img_{i:02d}.png").unlink()
    for read in (read_instant_ngp, load_dataset):
        with pytest.warns(RuntimeWarning, match=r"transforms\.json: 3 of 10 frames .* skipped: images/img_0[347]\.png") as rec:
            data = read(tmp_path, holdout=0)
        assert all(f"img_{i:02d}.png" in str(rec[0].message) for i in (3, 4, 7)) and rec[0].filename == __file__
    assert sorted(_by_index(data)) == [0, 1, 2, 5, 6, 8, 9]
    _tiny_ngp(tmp_path / "five", missing=5)
    with pytest.warns(RuntimeWarning) as rec:
        read_instant_ngp(tmp_path / "five")
    assert str(rec[0].message).endswith("5 of 8 frames list an image that is not there, skipped: "
                                        "images/f3.png, images/f4.png, images/f5.png, images/f6.png, images/f7.png")
    _tiny_ngp(tmp_path / "six", missing=6)
    with pytest.warns(RuntimeWarning) as rec:
        read_instant_ngp(tmp_path / "six")
    assert str(rec[0].message).endswith("skipped: images/f3.png, images/f4.png, images/f5.png, images/f6.png, "
                                        "images/f7.png, ...")
    shutil.rmtree(tmp_path / "images")
    with pytest.warns(RuntimeWarning), pytest.raises(FileFormatError, match="none of the 10 images"):
        read_instant_ngp(tmp_path)


def test_a_focal_length_that_disagrees_with_the_field_of_view_is_reported_and_fl_x_used(tmp_path):
    # the 8 px wide image: camera_angle_x = 0.7 gives 0.5 * 8 / tan(0.35) = 10.958 px, fl_x says 20
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame("images/b.png", fl_x=20.0, fl_y=20.0,
                                                                       camera_angle_x=0.7)])
    with pytest.warns(RuntimeWarning) as caught:
        data = read_instant_ngp(root, holdout=0)
    msg = str(caught[0].message)
    assert "transforms.json" in msg and "frames[1] ('images/b.png'): fl_x 20 px, camera_angle_x gives 10.958 px" in msg
    assert "fl_x / fl_y is used" in msg and "frames[0]" not in msg
    assert caught[0].filename == __file__
    assert float(data.splits["train"][1].camera.intrinsics[0, 0]) == 20.0


def test_an_agreeing_focal_length_and_field_of_view_give_no_warning(tmp_path):
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png")], fl_x=10.96, camera_angle_x=0.7, images=["a"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_instant_ngp(root, holdout=0)


# ----------------------------------------------------------------------------- camera and file refusals

@pytest.mark.parametrize("meta, frame, words", [
    ({"camera_model": "OPENCV_FISHEYE"}, {}, "camera_model 'OPENCV_FISHEYE' is not supported"),
    ({}, {"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not supported"),
    ({"is_fisheye": True}, {}, "is_fisheye set: fisheye cameras are not supported"),
    ({}, {"k4": 0.1}, "k4 set: fisheye cameras are not supported"),
    ({}, {"is_fisheye": True}, "is_fisheye set: fisheye cameras are not supported"),
    ({"w": 0}, {}, "w and h must be > 0, got 0.0 x 4.0"),
    ({"h": -4}, {}, "w and h must be > 0, got 8.0 x -4.0"),
    ({"w": 16, "h": 0}, {}, "w and h must be > 0, got 16.0 x 0.0"),
    ({"w": -16, "h": 8}, {}, "w and h must be > 0, got -16.0 x 8.0"),
    ({"fl_x": None}, {}, "fl_x must be a finite number, got None"),
    ({"fl_x": "5"}, {}, "fl_x must be a finite number, got '5'"),
    ({"fl_x": 0.0}, {}, "no usable focal length (give fl_x / fl_y > 0"),
    ({"fl_x": 9.0, "fl_y": 0.0}, {}, "no usable focal length (give fl_x / fl_y > 0"),
    ({"fl_x": -1.0, "fl_y": 2.0}, {}, "no usable focal length"),
    ({"fl_x": None}, {"fl_y": 1.0, "camera_angle_x": 0.0}, "camera_angle_x must be in (0, pi) radians, got 0.0"),
    ({}, {"camera_angle_y": 3.2}, "camera_angle_y must be in (0, pi) radians, got 3.2"),
    ({"fl_x": None}, {"cx": 1.0}, "fl_x must be a finite number"),
    ({"w": 8, "h": 2}, {}, "the file says 8 x 2 but the image"),
    ({"w": 6, "h": 4}, {}, "the file says 6 x 4 but the image"),
    ({}, {"transform_matrix": None}, "no 'transform_matrix'"),
    ({}, {"transform_matrix": [[2.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "not a rotation"),
    ({}, {"transform_matrix": [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]]}, "not a rotation"),  # mirrored
])
def test_ngp_camera_refusals_name_file_and_frame(tmp_path, meta, frame, words):
    root = _ngp(tmp_path, {"fl_x": 5.0, **meta}, [{"file_path": "a.png", **frame}], {"a.png": (8, 4)})
    with pytest.raises(FileFormatError) as e:
        read_instant_ngp(root, holdout=0)
    assert "transforms.json: frames[0] ('a.png')" in str(e.value) and words in str(e.value)


def test_file_level_refusals(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        read_instant_ngp(tmp_path / "nowhere")
    root = _ngp(tmp_path / "r", {"fl_x": 5.0}, [{"file_path": f"f{i}.png"} for i in range(8)],
                {"f0.png": (8, 4), "f7.png": (8, 4)})
    with pytest.warns(RuntimeWarning, match=r"transforms.json: 6 of 8 frames list an image that is not there, skipped: "
                                            r"f1.png, f2.png, f3.png, f4.png, f5.png, \.\.\.$"):
        scene = read_instant_ngp(root, holdout=2)
    assert [f.name for f in scene.splits["test"]] == ["f0.png"] and [f.name for f in scene.splits["train"]] == ["f7.png"]
    with pytest.raises(FileFormatError, match=r"other.json: not found \(an instant-ngp dataset needs other.json\)"):
        read_instant_ngp(root, transforms="other.json")
    gone = _ngp(tmp_path / "g", {"fl_x": 5.0}, [{"file_path": "x.png"}, {"file_path": "y.png"}], {})
    with pytest.warns(RuntimeWarning, match="skipped: x.png, y.png$"), \
            pytest.raises(FileFormatError, match=r"none of the 2 images its frames list exists \(first: .*g/x.png\)"):
        read_instant_ngp(gone)
    twice = _ngp(tmp_path / "t", {"fl_x": 5.0}, [{"file_path": "a.png"}, {"file_path": "./a"}], {"a.png": (8, 4)})
    with pytest.raises(FileFormatError, match="an image is listed twice \\('a.png'\\)"):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('{"frames": []}')
    with pytest.raises(FileFormatError, match=r"'frames' must be a non-empty list, got \[\]"):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('[1]')
    with pytest.raises(FileFormatError, match="transforms.json: expected a JSON object, got list"):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('{"frames": [')
    with pytest.raises(FileFormatError, match=r"transforms.json: cannot read it as JSON \("):
        read_instant_ngp(twice)
    (twice / "transforms.json").write_text('{"frames": [{"file_path": 3}]}')
    with pytest.raises(FileFormatError, match=r"transforms.json: frames\[0\] needs a 'file_path' string"):
        read_instant_ngp(twice)


@pytest.mark.parametrize("where, key, value, words", [
    ("matrix", None, "4", "transform_matrix must hold numbers"),
    ("matrix", None, False, "transform_matrix must hold numbers"),
    ("frame", "fl_x", "10", "fl_x must be a finite number, got '10'"),
    ("top", "cx", True, "cx must be a finite number, got True"),
    ("top", "k4", "0", "k4 must be a finite number, got '0'"),
    ("frame", "is_fisheye", "false", "is_fisheye must be a bool, got 'false'"),
])
def test_a_non_number_is_refused_naming_the_frame(tmp_path, where, key, value, words):
    matrix = [row[:] for row in C2W]
    keys, meta = {}, {}
    if where == "matrix":
        matrix[1][3] = value
    elif where == "frame":
        keys = {key: value}
    else:
        meta = {key: value}
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame("images/b.png", matrix, **keys)], **meta)
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[\d\] \('images/.\.png'\): .*" + words):
        read_instant_ngp(root)


def test_deep_nesting_is_refused_naming_the_file(tmp_path):
    root = instant_ngp(_root(tmp_path), [], raw='{"frames": [{"file_path": ' + "[" * 200_000 + "]" * 200_000 + "}]}")
    with pytest.raises(FileFormatError, match=r"transforms\.json: cannot read it as JSON \(nested too deeply\)"):
        read_instant_ngp(root)


@pytest.mark.parametrize("keys, words", [
    ({"fl_x": 1e300}, r"intrinsics .*float32"),
    ({"camera_angle_x": 1e-300, "camera_angle_y": 1e-300}, r"intrinsics .*float32"),
    ({"cx": -1e300}, r"intrinsics .*float32"),
])
def test_values_beyond_float32_are_refused_naming_the_file_and_frame(tmp_path, keys, words):
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame("images/b.png", **keys)])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[1\] \('images/b\.png'\): " + words):
        read_instant_ngp(root)
    far = [row[:] for row in C2W]
    far[2][3] = 1e300
    root = instant_ngp(tmp_path / "far", [make_frame("images/a.png", far)])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[0\] \('images/a\.png'\): .*float32"):
        read_instant_ngp(root)


def test_a_duplicated_frame_is_refused_naming_both(tmp_path):
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame("./images/b.png"), make_frame("images/./b.png")])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[2\] .*listed twice \('images/b\.png'\), "
                                              r"also in frames\[1\]"):
        read_instant_ngp(root)


def test_a_last_row_other_than_0001_is_refused(tmp_path):
    bad = [row[:] for row in C2W]
    bad[3] = [0.0, 1.0, 0.0, 1.0]
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png", bad)])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[0\] .*last row must be \[0, 0, 0, 1\]"):
        read_instant_ngp(root)


# ----------------------------------------------------------------------------- paths outside the folder

@pytest.mark.parametrize("file_path", ["../outside/sentinel.png", "images/../../outside/sentinel", "ABS"])
def test_a_file_path_leading_outside_the_folder_is_refused_naming_the_frame(tmp_path, file_path):
    out = outside(tmp_path)
    file_path = str(out / "sentinel.png") if file_path == "ABS" else file_path
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame(file_path)])
    with recording() as opened, pytest.raises(FileFormatError) as e:
        read_instant_ngp(root)
    assert "transforms.json: frames[1]" in str(e.value) and "sentinel" in str(e.value)
    assert opened_under(out, opened) == []


def test_a_symlinked_image_pointing_outside_is_refused_not_skipped(tmp_path):
    out = outside(tmp_path)
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame("images/b.png")], images=["a"])
    (root / "images" / "b.png").symlink_to(out / "sentinel.png")
    with recording() as opened, pytest.raises(FileFormatError, match=r"transforms\.json: frames\[1\]: file_path "
                                                                     r"'images/b\.png' leads outside"):
        load_dataset(root)
    assert opened_under(out, opened) == []


def test_a_symlink_loop_is_refused_naming_the_frame(tmp_path):
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png"), make_frame("images/loop.png")], images=["a"])
    (root / "images" / "loop.png").symlink_to(root / "images" / "loop.png")
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[1\]: file_path 'images/loop\.png' cannot be "
                                              r"resolved"):
        read_instant_ngp(root)


def test_a_transforms_name_leading_outside_the_folder_is_refused(tmp_path):
    out = outside(tmp_path)
    root = instant_ngp(_root(tmp_path), [make_frame("images/a.png")])
    with recording() as opened, pytest.raises(FileFormatError, match=r"scene: transforms '\.\./outside/sentinel\.json' "
                                                                     r"leads outside"):
        read_instant_ngp(root, transforms="../outside/sentinel.json")
    assert opened_under(out, opened) == []
