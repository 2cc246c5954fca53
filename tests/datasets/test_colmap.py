"""Tests of ``controlgs_adapter.datasets.colmap``: cameras, poses and points against pycolmap and worked-out values, the
image folder picked for a resolution, the split, and refusals naming the file and line (text) or record (binary):
paths leading outside the scene, repeated ids, malformed or truncated records, values beyond float32."""

from __future__ import annotations

import math
import re
import struct

import numpy as np
import pytest
import torch
from helpers.colmap_models import MODELS, H, W, needs_cv2, needs_pycolmap, opencv_k, reconstruction, write_reconstruction
from helpers.dataset_files import (
    CAMERA_LINE,
    cameras_bin,
    colmap_text,
    image_line,
    images_bin,
    opened_under,
    outside,
    png,
    points_bin,
    recording,
)
from helpers.scene_writers import save_png
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image

from controlgs_adapter.datasets import load_dataset, read_colmap, undistort_points
from controlgs_adapter.datasets.colmap import (
    CAMERA_MODELS,
    _BinFile,
    _read_cameras_bin,
    _read_cameras_txt,
    _read_images_bin,
    _read_points_bin,
    qvec_to_rotation,
)
from controlgs_adapter.errors import FileFormatError, InputValueError

#: the distortion each camera of :data:`MODELS` gives its frames (k1, k2, p1, p2, k3)
EXPECTED_DIST = {1: None, 2: None, 3: (-0.12, 0.0, 0.0, 0.0, 0.0), 4: (0.08, -0.03, 0.0, 0.0, 0.0),
                 5: (-0.15, 0.04, 0.003, -0.002, 0.0)}


def _scene(tmp_path, **kw):
    return colmap_text(tmp_path / "scene", **kw)


def _colmap_txt(root, cameras: str, images: str, points: str | None = "1 0.5 -1 2 10 20 30 0.1 1 0\n",
                sizes: dict[str, tuple[int, int]] | None = None):
    """A text model from the given ``cameras.txt`` / ``images.txt`` / ``points3D.txt`` records and a black image
    of each size in ``sizes`` (name -> (w, h))."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    (sparse / "cameras.txt").write_text("# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n" + cameras)
    (sparse / "images.txt").write_text("# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n" + images)
    if points is not None:
        (sparse / "points3D.txt").write_text(points)
    (root / "images").mkdir(exist_ok=True)
    for name, (w, h) in (sizes or {}).items():
        Image.fromarray(np.zeros((h, w, 3), np.uint8)).save(root / "images" / name)
    return root


#: one PINHOLE 8 x 6 camera (fx 10, fy 12, centre (4, 3))
_CAM = "1 PINHOLE 8 6 10 12 4 3\n"
#: b.png (identity rotation, t = (1, 2, 3)) without 2D points, a.png (180 degrees about z) with one
_IMGS = "1 1 0 0 0 1 2 3 1 b.png\n\n2 0 0 0 1 0 0 0 1 a.png\n1.0 2.0 -1\n"


def _binary_scene(tmp_path, cameras, images, points=None):
    root = tmp_path / "scene"
    sparse = root / "sparse" / "0"
    cameras_bin(sparse / "cameras.bin", cameras)
    images_bin(sparse / "images.bin", images)
    if points is not None:
        points_bin(sparse / "points3D.bin", points)
    for _, name, _ in images:
        png(root / "images" / name)
    return root


# ----------------------------------------------------------------------------- reading

def test_text_model_pose_intrinsics_split_and_points(tmp_path):
    root = _colmap_txt(tmp_path, _CAM, _IMGS, sizes={"a.png": (4, 3), "b.png": (4, 3)})
    scene = read_colmap(root, holdout=2, images="images")
    test, train = scene.splits["test"], scene.splits["train"]
    assert [f.name for f in test] == ["a.png"] and [f.name for f in train] == ["b.png"]  # index 0 of sorted names
    a, b = test[0].camera, train[0].camera
    assert (a.width, a.height) == (4, 3)
    assert a.intrinsics.tolist() == [[5.0, 0.0, 2.0], [0.0, 6.0, 1.5], [0.0, 0.0, 1.0]]  # half size
    # q = (0, 0, 0, 1): 180 degrees about z
    assert a.world_to_camera.tolist() == [[-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    assert b.world_to_camera[:3, 3].tolist() == [1.0, 2.0, 3.0] and b.world_to_camera[:3, :3].tolist() == np.eye(3).tolist()
    assert scene.points.tolist() == [[0.5, -1.0, 2.0]] and scene.points.dtype == torch.float32
    assert scene.format == "colmap" and scene.source == str(root)
    assert len(read_colmap(root, holdout=0).splits["test"]) == 0
    assert scene.background.tolist() == [0.0, 0.0, 0.0]
    assert read_colmap(root, background=(0.5, 0.25, 1.0)).background.tolist() == [0.5, 0.25, 1.0]


def test_colmap_text_image_names_may_hold_spaces(tmp_path):
    """COLMAP's ``images.txt`` line is ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` with NAME last (COLMAP's
    "Output format" page): the name is the rest of the line, and a photo named ``my photo 2.png`` (spaces
    are common in users' file names; the binary format stores it as a C string) must be read as that name,
    with its pose and camera, not refused as a line with too many fields. Written directly: identity
    rotation, t = (0.25, -0.5, 3), a PINHOLE 4 x 3 camera."""
    name = "my photo 2.png"
    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("# Camera list\n1 PINHOLE 4 3 5.0 6.0 2.0 1.5\n")
    (sparse / "images.txt").write_text(f"# Image list\n7 1 0 0 0 0.25 -0.5 3 1 {name}\n\n")
    save_png(tmp_path / "images" / name, torch.full((3, 3, 4), 0.5))

    scene = read_colmap(tmp_path, holdout=0)
    (frame,) = scene.splits["train"]
    assert frame.name == name and frame.source == tmp_path / "images" / name
    w2c = torch.eye(4)
    w2c[:3, 3] = torch.tensor([0.25, -0.5, 3.0])
    assert torch.equal(frame.camera.world_to_camera, w2c)
    assert torch.equal(frame.camera.intrinsics, torch.tensor([[5.0, 0.0, 2.0], [0.0, 6.0, 1.5], [0.0, 0.0, 1.0]]))
    assert (frame.camera.width, frame.camera.height) == (4, 3)


def test_every_image_is_read_with_or_without_points_and_a_final_points_line(tmp_path):
    names = [f"v{i}.png" for i in range(8)]
    lines = ["# Image list"]
    for i, n in enumerate(names):
        lines += [image_line(i + 1, n), "1.5 2.5 7 3.0 4.0 -1" if i % 2 else ""]
    root = _scene(tmp_path, images="\n".join(lines[:-1]) + "\n", names=names)  # the last POINTS2D line left out
    data = read_colmap(root, holdout=0)
    assert [f.name for f in data.splits["train"]] == names


def test_binary_files_read_when_ids_are_unique(tmp_path):
    root = _binary_scene(tmp_path, [(1, 1, 8, 6, (10, 10, 4, 3))], [(1, "a.png", 1), (2, "b.png", 1)],
                         [(1, (0.0, 0.0, 0.0)), (2, (1.0, 0.0, 0.0))])
    data = read_colmap(root, holdout=0)
    assert len(data.splits["train"]) == 2 and data.points is not None and data.points.shape == (2, 3)


def _one_image(root, fx: float = 10.0, fy: float = 10.0, points: list | None = None):
    """One PINHOLE 4 x 3 camera (centre (2, 1.5)) and one image a.png as text files. ``points``: ``(xyz, track
    length)`` written as points3D.bin from COLMAP's documented layout (u64 count; per point: u64 id, 3 f64 xyz,
    3 u8 rgb, f64 error, u64 track length, then (u32 image id, u32 point2D index) per element)."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(f"# Camera list\n1 PINHOLE 4 3 {fx!r} {fy!r} 2.0 1.5\n")
    (sparse / "images.txt").write_text("# Image list\n1 1 0 0 0 0 0 0 1 a.png\n\n")
    save_png(root / "images" / "a.png", torch.full((3, 3, 4), 0.5))
    if points is not None:
        raw = struct.pack("<Q", len(points))
        for pid, (xyz, track) in enumerate(points):
            raw += struct.pack("<Q3d3BdQ", pid + 1, *xyz, 10, 20, 30, 0.5, track)
            raw += b"".join(struct.pack("<II", 1, j) for j in range(track))
        (sparse / "points3D.bin").write_bytes(raw)
    return root


@pytest.mark.parametrize("points", [[], [((0.5, -1.5, 2.0), 1)], [((1.0, 2.0, 3.0), 2), ((-4.0, 5.5, 0.25), 0)]],
                         ids=["none", "one", "last-without-track"])
def test_points3d_bin_reads_every_point(tmp_path, points):
    """No point is an empty ``[0, 3]`` cloud; a point observed by no image (track length 0) is still a valid
    record, also as the file's last."""
    data = read_colmap(_one_image(tmp_path, points=points), holdout=0)
    assert data.points is not None and data.points.dtype == torch.float32 and tuple(data.points.shape) == (len(points), 3)
    assert data.points.tolist() == [list(xyz) for xyz, _ in points]


def test_colmap_focal_length_below_one_pixel_is_accepted(tmp_path):
    """``read_colmap`` refuses a camera whose focal lengths are not > 0 (its error says "must be > 0"); any
    positive focal length is a valid pinhole camera, including one under a pixel (an extreme fisheye-like
    crop, or a model written in normalised units): PINHOLE fx = 0.5, fy = 0.75 on a 4 x 3 camera and image
    (scale 1) gives K = [[0.5, 0, 2], [0, 0.75, 1.5], [0, 0, 1]]. fx = 0 is refused."""
    scene = read_colmap(_one_image(tmp_path / "ok", 0.5, 0.75), holdout=0)
    (frame,) = scene.splits["train"]
    assert torch.equal(frame.camera.intrinsics, torch.tensor([[0.5, 0.0, 2.0], [0.0, 0.75, 1.5], [0.0, 0.0, 1.0]]))

    with pytest.raises(FileFormatError, match=r"focal lengths 0\.0, 0\.75 \(must be > 0\)"):
        read_colmap(_one_image(tmp_path / "zero", 0.0, 0.75), holdout=0)


@pytest.mark.parametrize("size, ok", [((4, 3), True), ((4, 4), True), ((5, 3), True), ((2, 2), True), ((6, 3), True), ((8, 3), False),
                                      ((4, 5), False), ((16, 12), True), ((9, 6), True), ((10, 6), True), ((12, 6), False),
                                      ((3, 4), True), ((13, 6), False)])  # 3 x 4: lo = hi = 1/2 exactly
def test_colmap_image_size_must_be_the_camera_divided_by_one_factor(tmp_path, size, ok):
    root = _colmap_txt(tmp_path, _CAM, "1 1 0 0 0 0 0 0 1 a.png\n\n", sizes={"a.png": size})
    if ok:
        cam = read_colmap(root, holdout=0).splits["train"][0].camera
        k = cam.intrinsics.tolist()
        assert k[0] == pytest.approx([10 * size[0] / 8, 0, 4 * size[0] / 8]) and k[1] == pytest.approx([0, 12 * size[1] / 6, 3 * size[1] / 6])
    else:
        with pytest.raises(FileFormatError, match="which is not its camera's 8x6"):
            read_colmap(root, holdout=0)


def test_qvec_to_rotation():
    # q = (cos 45deg, 0, 0, sin 45deg): 90 degrees about z, x -> y
    s = math.sqrt(0.5)
    assert torch.allclose(qvec_to_rotation([s, 0.0, 0.0, s]),
                          torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-15)
    # not normalised: (2, 0, 0, 0) is the identity; a huge one is normalised, not collapsed to the identity
    assert torch.equal(qvec_to_rotation([2.0, 0.0, 0.0, 0.0]), torch.eye(3, dtype=torch.float64))
    half_turn_about_x = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    assert torch.allclose(qvec_to_rotation([0.0, 1e300, 0.0, 0.0]), half_turn_about_x)
    for bad in ([0.0, 0.0, 0.0, 0.0], [1e-13, 0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0, 1.0]):
        with pytest.raises(InputValueError, match="finite non-zero quaternion"):
            qvec_to_rotation(bad)
    qvec_to_rotation([1e-11, 0.0, 0.0, 0.0])  # norm above 1e-12: accepted




@needs_pycolmap
# ----------------------------------------------------------------------------- against pycolmap and OpenCV

@pytest.mark.parametrize("text", [False, True], ids=["bin", "txt"])
def test_cameras_poses_points_match_pycolmap(tmp_path, text):
    rec = reconstruction()
    scene = read_colmap(write_reconstruction(tmp_path, rec, text=text), holdout=0)
    assert scene.format == "colmap" and scene.splits["test"] == []
    frames = scene.splits["train"]
    assert [f.name for f in frames] == sorted(im.name for im in rec.images.values())
    by_name = {im.name: im for im in rec.images.values()}
    for f in frames:
        im = by_name[f.name]
        cam = rec.camera(im.camera_id)
        k = f.camera.intrinsics.double()
        fx, fy = cam.focal_length_x, cam.focal_length_y
        assert torch.allclose(k, torch.tensor([[fx, 0, cam.principal_point_x], [0, fy, cam.principal_point_y],
                                               [0, 0, 1]], dtype=torch.float64), atol=1e-5)
        assert (f.camera.width, f.camera.height) == (W, H)
        expected_dist = EXPECTED_DIST[im.camera_id]
        assert f.distortion is None if expected_dist is None else f.distortion == pytest.approx(expected_dist)
        w2c = torch.from_numpy(im.cam_from_world().matrix())
        assert torch.allclose(f.camera.world_to_camera[:3].double(), w2c, atol=1e-6)
        assert f.source == tmp_path / "images" / f.name
    xyz = np.stack([p.xyz for p in rec.points3D.values()])
    assert scene.points.dtype == torch.float32
    assert np.allclose(np.sort(scene.points.numpy(), axis=0), np.sort(xyz, axis=0), atol=1e-6)


@needs_pycolmap
def test_binary_and_text_read_identically_and_bin_is_preferred(tmp_path):
    rec = reconstruction(seed=3)
    a = read_colmap(write_reconstruction(tmp_path / "a", rec), holdout=3)
    b = read_colmap(write_reconstruction(tmp_path / "b", rec, text=True, sparse="sparse"), holdout=3)
    for split in ("train", "test"):
        for fa, fb in zip(a.splits[split], b.splits[split], strict=True):
            assert fa.name == fb.name and fa.distortion == pytest.approx(fb.distortion)
            assert torch.allclose(fa.camera.world_to_camera, fb.camera.world_to_camera, atol=1e-6)
            assert torch.allclose(fa.camera.intrinsics, fb.camera.intrinsics, atol=1e-5)
    assert torch.allclose(a.points, b.points, atol=1e-6)
    # a text model beside the binary one (different focal lengths) is not read
    other = reconstruction(seed=3, models={cid: (m, [2 * p[0], *p[1:]]) for cid, (m, p) in MODELS.items()})
    other.write_text(str(tmp_path / "a" / "sparse" / "0"))
    for fa, fb in zip(read_colmap(tmp_path / "a", holdout=3).splits["train"], a.splits["train"]):
        assert torch.equal(fa.camera.intrinsics, fb.camera.intrinsics)


@needs_pycolmap
@needs_cv2
def test_projections_match_pycolmap_and_opencv(tmp_path):
    import cv2

    rec = reconstruction(n_images=5)
    scene = read_colmap(write_reconstruction(tmp_path, rec), holdout=0)
    by_name = {im.name: im for im in rec.images.values()}
    pts = np.random.default_rng(2).normal(scale=0.8, size=(50, 3))
    for f in scene.splits["train"]:
        im = by_name[f.name]
        colmap_px = np.stack([im.project_point(p) for p in pts])  # distorted, pixel centres at i + 0.5
        ours, depth = f.camera.project(torch.from_numpy(pts).float())
        assert (depth > 0).all()
        if f.distortion is None:
            np.testing.assert_allclose(ours.numpy(), colmap_px, atol=1e-4)
            continue
        k_cv = opencv_k(f.camera.intrinsics)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)
        cv_px = cv2.undistortPoints((colmap_px - 0.5)[:, None], k_cv, np.array(f.distortion), P=k_cv,
                                    criteria=crit)[:, 0] + 0.5
        np.testing.assert_allclose(ours.numpy(), cv_px, atol=1e-4)
        assert np.abs(ours.numpy() - colmap_px).max() > 0.2  # the distortion is not negligible
        inv = undistort_points(torch.from_numpy(colmap_px), f.camera.intrinsics, f.distortion)
        np.testing.assert_allclose(inv.numpy(), ours.double().numpy(), atol=1e-4)


@needs_pycolmap
def test_split_every_eighth_by_sorted_name(tmp_path):
    rec = reconstruction(n_images=17, models={1: MODELS[2]})
    root = write_reconstruction(tmp_path, rec)
    scene = read_colmap(root)
    names = sorted(im.name for im in rec.images.values())
    assert [f.name for f in scene.splits["test"]] == [names[0], names[8], names[16]]
    assert [f.name for f in scene.splits["train"]] == [n for i, n in enumerate(names) if i % 8]
    assert [f.name for f in read_colmap(root, holdout=5).splits["test"]] == names[::5]
    everything = read_colmap(root, holdout=0)
    assert everything.splits["test"] == [] and len(everything.splits["train"]) == 17


@needs_pycolmap
def test_downscaled_folders_chosen_and_intrinsics_scaled(tmp_path):
    big = (80, 60)
    rec = reconstruction(n_images=4, models={1: ("PINHOLE", [70.0, 72.0, 40.4, 29.6])}, size=big)
    # Mip-NeRF 360 style: sides rounded (60 / 8 = 7.5 -> 8)
    folders = {"images": big, "images_2": (40, 30), "images_4": (20, 15), "images_8": (10, 8)}
    root = write_reconstruction(tmp_path, rec, folders=folders)
    for resolution, folder in ((10, "images_8"), (16, "images_4"), (21, "images_2"), (40, "images_2"),
                               (41, "images"), (500, "images")):
        frames = read_colmap(root, resolution=resolution).splits["train"]
        assert all(f.source.parent.name == folder for f in frames), resolution
    assert read_colmap(root).splits["train"][0].source.parent.name == "images"
    for folder, (w, h) in folders.items():
        f = read_colmap(root, images=folder, holdout=0).splits["train"][0]
        assert (f.camera.width, f.camera.height) == (w, h)
        sx, sy = w / big[0], h / big[1]
        expected = torch.tensor([[70.0 * sx, 0, 40.4 * sx], [0, 72.0 * sy, 29.6 * sy], [0, 0, 1]])
        assert torch.allclose(f.camera.intrinsics, expected, atol=1e-5)
    # a folder lacking an image is not chosen by resolution
    (root / "images_8" / rec.image(100).name).unlink()
    assert read_colmap(root, resolution=10).splits["train"][0].source.parent.name == "images_4"
    # an image whose size is not the camera's divided by one factor is refused by name
    bad = root / "images_4" / rec.image(101).name
    Image.new("RGB", (20, 20)).save(bad)
    with pytest.raises(FileFormatError, match=r"images_4/img_.*20x20.*80x60"):
        read_colmap(root, images="images_4")
    with pytest.raises(FileFormatError, match="images_16"):
        read_colmap(root, images="images_16")


@needs_pycolmap
@pytest.mark.parametrize("model", ["FULL_OPENCV", "OPENCV_FISHEYE", "FOV"])
def test_unsupported_models_refused(tmp_path, model):
    import pycolmap

    n = len(pycolmap.Camera.create_from_model_name(1, model, 1.0, W, H).params)
    params = [40.0, 41.0, 20.0, 15.0] + [0.01] * (n - 4)
    rec = reconstruction(n_images=3, models={1: MODELS[2], 7: (model, params)})
    for text in (False, True):
        root = write_reconstruction(tmp_path / str(text), rec, text=text)
        with pytest.raises(FileFormatError, match=f"camera 7 .* {model} model.*image_undistorter"):
            read_colmap(root)
    # an exotic camera that no image uses is harmless
    rec2 = reconstruction(n_images=3, models={1: MODELS[2]})
    cam = pycolmap.Camera.create_from_model_name(9, model, 1.0, W, H)
    rec2.add_camera_with_trivial_rig(cam)
    assert len(read_colmap(write_reconstruction(tmp_path / "unused", rec2), holdout=0).splits["train"]) == 3


@needs_pycolmap
@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-10, 10, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3))
def test_quaternion_rotation_is_orthonormal_and_matches_pycolmap(q):
    import pycolmap

    r = qvec_to_rotation(q)  # (w, x, y, z)
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
    assert torch.det(r).item() == pytest.approx(1.0, abs=1e-12)
    xyzw = np.array([q[1], q[2], q[3], q[0]])
    ref = pycolmap.Rotation3d(xyzw / np.linalg.norm(xyzw)).matrix()
    np.testing.assert_allclose(r.numpy(), ref, atol=1e-10)




# ----------------------------------------------------------------------------- argument and model refusals

@pytest.mark.parametrize("kw, pattern", [
    ({"holdout": -1}, r"holdout.*got -1$"),
    ({"holdout": True}, r"holdout.*got True$"),
    ({"holdout": 2.0}, r"holdout.*got 2\.0$"),
    ({"holdout": 1.5}, r"holdout.*got 1\.5$"),
    ({"resolution": 1}, r"resolution.*got 1$"),
    ({"resolution": False}, r"resolution.*got False$"),
    ({"images": ""}, r"images.*got ''$"),
    ({"images": "/abs"}, r"images.*got '/abs'$"),
    ({"background": (0.5, 0.5)}, r"background.*got \(0\.5, 0\.5\)$"),
    ({"background": (0.5, 0.5, float("nan"))}, r"background.*got \(0\.5, 0\.5, nan\)$"),
])
def test_colmap_argument_refusals_name_the_argument_and_value(tmp_path, kw, pattern):
    root = _colmap_txt(tmp_path, _CAM, _IMGS, sizes={"a.png": (8, 6), "b.png": (8, 6)})
    with pytest.raises(InputValueError, match=pattern):
        read_colmap(root, **kw)


@pytest.mark.parametrize("cams, imgs, points, sizes, words", [
    (_CAM, _IMGS.replace("b.png", "a.png"), None, {}, "image name 'a.png' appears twice in the images file"),
    (_CAM, _IMGS.replace(" 1 b.png", " 7 b.png"), None, {}, "image 'b.png' refers to camera 7, which is not in the file"),
    ("1 PINHOLE 0 6 10 12 4 3\n", _IMGS, None, {"a.png": (8, 6), "b.png": (8, 6)}, "the camera of image 'a.png' is invalid"),
    ("1 PINHOLE 8 6 nan 12 4 3\n", _IMGS, None, {"a.png": (8, 6), "b.png": (8, 6)}, "the camera of image 'a.png' is invalid"),
    ("1 PINHOLE 8 6 10 0 4 3\n", _IMGS, None, {"a.png": (8, 6), "b.png": (8, 6)},
     "the camera of image 'a.png' has focal lengths 10.0, 0.0 (must be > 0)"),
    (_CAM, _IMGS.replace("2 0 0 0 1", "2 0 0 0 0"), None, {"a.png": (8, 6), "b.png": (8, 6)},
     "image 'a.png' has a bad quaternion [0.0, 0.0, 0.0, 0.0]"),
    (_CAM, _IMGS.replace("1 1 0 0 0 1 2 3", "1 1 0 0 0 1 inf 3"), None, {"a.png": (8, 6), "b.png": (8, 6)},
     "image 'b.png' has a non-finite translation [1.0, inf, 3.0]"),
    (_CAM, _IMGS, "1 nan 0 0 1 1 1 0\n", {}, "points3D.txt: non-finite 3D point coordinates"),
    (_CAM, _IMGS, "1 0 0 0 1 1 1\n", {}, "points3D.txt:1: expected POINT3D_ID X Y Z R G B ERROR TRACK..."),
    (_CAM, "1 1 0 0 0 1 2 3 1\n", None, {}, "images.txt:2: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"),
    ("1 PINHOLE 8\n", _IMGS, None, {}, "cameras.txt:2: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS... with a known"),
    ("1 PINHOLE_X 8 6 1 1 1 1\n", _IMGS, None, {}, "with a known COLMAP model"),
    (_CAM, _IMGS, None, {"a.png": (8, 6), "b.png": (8, 3)},
     "b.png: image is 8x3, which is not its camera's 8x6 (in "),
])
def test_colmap_model_refusals_name_the_file(tmp_path, cams, imgs, points, sizes, words):
    root = _colmap_txt(tmp_path, cams, imgs, points=points, sizes=sizes)
    with pytest.raises(FileFormatError) as e:
        read_colmap(root, holdout=0)
    assert words in str(e.value)


@needs_pycolmap
def test_model_and_text_errors_name_the_file(tmp_path):
    rec = reconstruction(n_images=3)
    root = write_reconstruction(tmp_path, rec, text=True)
    cams = root / "sparse" / "0" / "cameras.txt"
    good = cams.read_text()
    cams.write_text(good + "9 PINHOLE 40 30 1 2 3\n")  # one parameter short
    with pytest.raises(FileFormatError, match=r"cameras.txt:\d+: expected 4 parameters for a PINHOLE camera"):
        read_colmap(root)
    cams.write_text(good + "9 PINHOLE 40 thirty 1 2 3 4\n")
    with pytest.raises(FileFormatError, match=r"cameras.txt:\d+"):
        read_colmap(root)
    cams.write_text(good)
    (root / "sparse" / "0" / "points3D.txt").unlink()
    assert read_colmap(root).points is None  # cameras need no points
    (root / "sparse" / "0" / "images.txt").unlink()
    with pytest.raises(FileFormatError, match="no images.bin/.txt"):
        read_colmap(root)
    with pytest.raises(FileFormatError, match="no COLMAP model"):
        read_colmap(tmp_path / "images")


def test_colmap_folders_and_encodings_refused(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: scene folder not found"):
        read_colmap(tmp_path / "nowhere")
    root = _colmap_txt(tmp_path / "s", _CAM, _IMGS, sizes={"a.png": (8, 6)})
    with pytest.raises(FileFormatError, match=r"images: 1 of the 2 images in .*0 are missing \(first: b.png\)"):
        read_colmap(root)
    with pytest.raises(FileFormatError, match="images_2: images folder not found"):
        read_colmap(root, images="images_2")
    (root / "sparse" / "0" / "cameras.txt").write_bytes(b"1 PINHOLE 8 6 10 12 4 3 \xff\n")
    with pytest.raises(FileFormatError, match="cameras.txt: not a UTF-8 text file"):
        read_colmap(root)
    # the model may sit in sparse/ directly
    flat = tmp_path / "flat"
    _colmap_txt(flat, _CAM, _IMGS, points=None, sizes={"a.png": (8, 6), "b.png": (8, 6)})
    (flat / "sparse" / "0").rename(flat / "sparse0")
    (flat / "sparse").rmdir()
    (flat / "sparse0").rename(flat / "sparse")
    assert read_colmap(flat, holdout=0).points is None and len(read_colmap(flat, holdout=0).splits["train"]) == 2




@needs_pycolmap
def test_missing_images_are_counted_naming_the_first(tmp_path):
    rec = reconstruction(n_images=10)
    root = write_reconstruction(tmp_path, rec)
    gone = sorted(im.name for im in rec.images.values())[2:5]
    for name in gone:
        (root / "images" / name).unlink()
    with pytest.raises(FileFormatError, match=rf"3 of the 10 images .* missing \(first: {', '.join(gone)}\)"):
        read_colmap(root)


# ----------------------------------------------------------------------------- paths outside the scene

@pytest.mark.parametrize("name", ["../../outside/sentinel.png", "ABS"])
def test_an_image_name_leading_outside_the_scene_is_refused_naming_the_line(tmp_path, name):
    out = outside(tmp_path)
    name = str(out / "sentinel.png") if name == "ABS" else name
    images = f"# Image list\n{image_line(1, 'a.png')}\n\n{image_line(2, name)}\n\n"
    root = _scene(tmp_path, images=images, names=["a.png"])
    with recording() as opened, pytest.raises(FileFormatError) as e:
        read_colmap(root)
    assert re.search(r"images\.txt:4: image name '[^']*sentinel\.png'", str(e.value))
    assert "outside the dataset folder" in str(e.value) or "absolute" in str(e.value)
    assert opened_under(out, opened) == []


def test_a_symlinked_image_pointing_outside_the_scene_is_refused(tmp_path):
    out = outside(tmp_path)
    root = _scene(tmp_path, names=["a.png", "b.png"])
    (root / "images" / "b.png").unlink()
    (root / "images" / "b.png").symlink_to(out / "sentinel.png")
    with recording() as opened, pytest.raises(FileFormatError, match=r"images\.txt:4: image name 'b\.png' leads outside"):
        load_dataset(root)
    assert opened_under(out, opened) == []


def test_a_symlink_that_stays_inside_the_scene_is_followed(tmp_path):
    root = _scene(tmp_path, names=["a.png", "b.png"])
    png(root / "originals" / "b.png")
    (root / "images" / "b.png").unlink()
    (root / "images" / "b.png").symlink_to(root / "originals" / "b.png")
    with recording() as opened:
        data = read_colmap(root, holdout=0)
    assert [f.name for f in data.splits["train"]] == ["a.png", "b.png"]
    assert opened_under(root / "originals", opened) != []  # the record sees the header read through the link


def test_an_images_folder_outside_the_scene_is_refused(tmp_path):
    out = outside(tmp_path)
    png(out / "a.png")
    root = _scene(tmp_path, names=["a.png"])
    with pytest.raises(InputValueError, match=r"images must be the name of a folder under the scene root, got '\.\./"):
        read_colmap(root, images="../../outside")
    (root / "images_2").symlink_to(out, target_is_directory=True)
    with recording() as opened, pytest.raises(FileFormatError, match=r"scene: the images folder 'images_2' leads outside"):
        read_colmap(root, images="images_2")
    with recording() as opened2, pytest.raises(FileFormatError, match=r"scene: the images folder 'images_2' leads outside"):
        read_colmap(root, resolution=4)  # picking a downscaled folder looks at none outside either
    assert opened_under(out, opened + opened2) == []


def test_a_model_file_symlinked_outside_the_scene_is_refused(tmp_path):
    out = outside(tmp_path)
    root = _scene(tmp_path, names=["a.png"])
    (root / "sparse" / "0" / "points3D.txt").symlink_to(out / "sentinel.txt")
    with recording() as opened, pytest.raises(FileFormatError, match=r"points3D\.txt: the model file .* leads outside"):
        read_colmap(root)
    assert opened_under(out, opened) == []




# ----------------------------------------------------------------------------- text records

def test_an_images_file_without_its_points2d_lines_is_refused_not_halved(tmp_path):
    names = [f"v{i}.png" for i in range(8)]
    images = "# Image list\n" + "".join(f"{image_line(i + 1, n)}\n" for i, n in enumerate(names))
    root = _scene(tmp_path, images=images, names=names)
    with pytest.raises(FileFormatError, match=r"images\.txt:3: expected the POINTS2D line .* of IMAGE_ID 1 \(line 2\)"):
        read_colmap(root)


def test_a_header_count_that_differs_from_the_records_is_refused(tmp_path):
    images = f"# Number of images: 3, mean observations per image: 0\n{image_line(1, 'a.png')}\n\n{image_line(2, 'b.png')}\n\n"
    root = _scene(tmp_path, images=images, names=["a.png", "b.png"])
    with pytest.raises(FileFormatError, match=r"images\.txt:1: the header declares 3 images but the file holds 2"):
        read_colmap(root)


def test_a_repeated_image_id_is_refused_naming_both_lines(tmp_path):
    images = f"{image_line(1, 'a.png')}\n\n{image_line(1, 'b.png')}\n\n"
    root = _scene(tmp_path, images=images, names=["a.png", "b.png"])
    with pytest.raises(FileFormatError, match=r"images\.txt:3: IMAGE_ID 1 appears twice \(first: .*images\.txt:1\)"):
        read_colmap(root)


def test_a_repeated_camera_id_is_refused_naming_both_lines(tmp_path):
    root = _scene(tmp_path, cameras=f"# cams\n{CAMERA_LINE}\n1 PINHOLE 8 6 20 20 4 3\n", names=["a.png"])
    with pytest.raises(FileFormatError, match=r"cameras\.txt:3: CAMERA_ID 1 appears twice \(first: .*cameras\.txt:2\)"):
        read_colmap(root)


def test_a_repeated_point_id_is_refused_naming_both_lines(tmp_path):
    root = _scene(tmp_path, points="# points\n5 0 0 0 1 1 1 0\n5 1 1 1 1 1 1 0\n", names=["a.png"])
    with pytest.raises(FileFormatError, match=r"points3D\.txt:3: POINT3D_ID 5 appears twice \(first: line 2\)"):
        read_colmap(root)


@pytest.mark.parametrize("cameras, images, points, where", [
    ("1 PINHOLE 8 6 1e300 10 4 3\n", None, None, r"cameras\.txt:1: the camera of image 'a\.png' does not fit float32"),
    (None, f"{image_line(1, 'a.png', t=(0.0, 1e300, 4.0))}\n\n", None,
     r"images\.txt:1: image 'a\.png' has a translation beyond float32"),
    (None, None, "1 0 1e300 0 1 1 1 0\n", r"points3D\.txt: non-finite 3D point coordinates \(or beyond float32\) at line 1"),
])
def test_values_beyond_float32_are_refused_naming_the_file_and_line(tmp_path, cameras, images, points, where):
    root = _scene(tmp_path, cameras=cameras, images=images, points=points, names=["a.png"])
    with pytest.raises(FileFormatError, match=where):
        read_colmap(root)




# ----------------------------------------------------------------------------- binary records

def test_camera_model_ids_and_parameter_counts_follow_colmap():
    # COLMAP's camera models (src/colmap/sensor/models.h: the CameraModelId enum, and each model's focal +
    # principal point + extra parameter counts, e.g. SIMPLE_DIVISION 1 + 2 + 1, EUCM 2 + 2 + 2;
    # EQUIRECTANGULAR 2 metadata parameters): id -> (name, #params)
    documented = {0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
                  4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
                  8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
                  11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16), 12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5),
                  14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6), 17: ("EQUIRECTANGULAR", 2)}
    assert CAMERA_MODELS == documented


@pytest.mark.parametrize("model_id, name, n", [(1, "PINHOLE", 4), (4, "OPENCV", 8), (6, "FULL_OPENCV", 12),
                                               (7, "FOV", 5), (10, "THIN_PRISM_FISHEYE", 12), (14, "SIMPLE_FISHEYE", 3),
                                               (17, "EQUIRECTANGULAR", 2)])
def test_binary_cameras_read_every_model_with_its_documented_parameter_count(tmp_path, model_id, name, n):
    # record: u32 id, i32 model, u64 width, u64 height, n f64 params; two cameras back to back, so a
    # wrong count misplaces the second record
    p = tmp_path / "cameras.bin"
    params = [float(i + 1) for i in range(n)]
    rec = (struct.pack("<IiQQ", 2, model_id, 40, 30) + struct.pack(f"<{n}d", *params)
           + struct.pack("<IiQQ", 9, 0, 8, 6) + struct.pack("<3d", 5.0, 4.0, 3.0))
    p.write_bytes(struct.pack("<Q", 2) + rec)
    cams = _read_cameras_bin(p)
    assert (cams[2].model, cams[2].width, cams[2].height, cams[2].params) == (name, 40, 30, tuple(params))
    assert (cams[9].model, cams[9].params) == ("SIMPLE_PINHOLE", (5.0, 4.0, 3.0))


def test_colmap_binary_unknown_model_id_and_non_utf8_name(tmp_path):
    p = tmp_path / "cameras.bin"
    p.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 3, 18, 8, 6) + struct.pack("<3d", 1, 2, 3))
    with pytest.raises(FileFormatError, match=r"cameras.bin: camera 3 has unknown model id 18 \(known: 0..17\)"):
        _read_cameras_bin(p)
    p.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 3, 0, 8, 6) + struct.pack("<3d", 1, 2, 3))
    cam = _read_cameras_bin(p)[3]
    assert (cam.model, cam.width, cam.height, cam.params) == ("SIMPLE_PINHOLE", 8, 6, (1.0, 2.0, 3.0))
    q = tmp_path / "images.bin"
    head = struct.pack("<I4d3dI", 5, 1, 0, 0, 0, 1, 2, 3, 3)
    q.write_bytes(struct.pack("<Q", 1) + head + b"\xffname\0" + struct.pack("<Q", 0))
    with pytest.raises(FileFormatError, match="images.bin: the name of image 5 at byte .* is not UTF-8"):
        _read_images_bin(q)
    q.write_bytes(struct.pack("<Q", 1) + head + b"x.png\0" + struct.pack("<Q", 1) + b"\0" * 24)
    im = _read_images_bin(q)[5]
    assert (im.qvec, im.tvec, im.camera_id, im.name) == ((1.0, 0.0, 0.0, 0.0), (1.0, 2.0, 3.0), 3, "x.png")


def test_binary_record_counts_that_exactly_fill_the_file_are_accepted(tmp_path):
    # an image record is at least 64 (head) + 1 (empty name's NUL) + 8 (2D point count) = 73 bytes: one
    # image with an empty name and no 2D points fills the file exactly after its u64 count
    imgs = tmp_path / "images.bin"
    head = struct.pack("<I4d3dI", 4, 1.0, 0.0, 0.0, 0.0, 0.5, -1.0, 2.0, 3)
    imgs.write_bytes(struct.pack("<Q", 1) + head + b"\0" + struct.pack("<Q", 0))
    im = _read_images_bin(imgs)[4]
    assert (im.name, im.qvec, im.tvec, im.camera_id) == ("", (1.0, 0.0, 0.0, 0.0), (0.5, -1.0, 2.0), 3)
    # a 3D point is 8 (id) + 24 (xyz) + 3 (rgb) + 8 (error) + 8 (track length) = 51 bytes with no track
    pts = tmp_path / "points3D.bin"
    point = (struct.pack("<Q", 7) + struct.pack("<3d", 1.5, -2.5, 4.0) + bytes([10, 20, 30])
             + struct.pack("<d", 0.25) + struct.pack("<Q", 0))
    pts.write_bytes(struct.pack("<Q", 1) + point)
    assert np.array_equal(_read_points_bin(pts), [[1.5, -2.5, 4.0]])
    # a second point with a track of two (image_id, point2D_idx) u32 pairs: 16 more bytes
    point2 = (struct.pack("<Q", 8) + struct.pack("<3d", -1.0, 0.0, 2.0) + bytes(3) + struct.pack("<d", 0.0)
              + struct.pack("<Q", 2) + struct.pack("<4I", 1, 0, 2, 5))
    pts.write_bytes(struct.pack("<Q", 2) + point2 + point)
    assert np.array_equal(_read_points_bin(pts), [[-1.0, 0.0, 2.0], [1.5, -2.5, 4.0]])
    # no point at all: an empty [0, 3] array
    pts.write_bytes(struct.pack("<Q", 0))
    empty = _read_points_bin(pts)
    assert empty.shape == (0, 3)
    # one byte short of the declared record: refused naming the count
    pts.write_bytes(struct.pack("<Q", 1) + point[:-1])
    with pytest.raises(FileFormatError, match=r"points3D.bin: declares 1 3D points \(at least 51 bytes each\) but only "
                                              r"50 bytes follow"):
        _read_points_bin(pts)


@pytest.mark.parametrize("which", ["cameras", "images", "points"])
def test_binary_files_refuse_a_repeated_id_naming_the_record(tmp_path, which):
    cams = [(1, 1, 8, 6, (10, 10, 4, 3))] + ([(1, 1, 8, 6, (20, 20, 4, 3))] if which == "cameras" else [])
    imgs = [(1, "a.png", 1), (1 if which == "images" else 2, "b.png", 1)]
    pts = [(4, (0.0, 0.0, 0.0)), (4 if which == "points" else 5, (1.0, 0.0, 0.0))]
    root = _binary_scene(tmp_path, cams, imgs, pts)
    label = {"cameras": r"cameras\.bin: camera record 1 \(CAMERA_ID 1, byte \d+\): CAMERA_ID 1",
             "images": r"images\.bin: image record 1 \(IMAGE_ID 1, byte \d+\): IMAGE_ID 1",
             "points": r"points3D\.bin: 3D point record 1 \(byte \d+\): POINT3D_ID 4"}[which]
    with pytest.raises(FileFormatError, match=label + r" appears twice \(first: .*record 0"):
        read_colmap(root)


def test_a_point_beyond_float32_in_a_binary_file_names_the_record(tmp_path):
    root = _binary_scene(tmp_path, [(1, 1, 8, 6, (10, 10, 4, 3))], [(1, "a.png", 1)],
                         [(1, (0.0, 0.0, 0.0)), (2, (0.0, -1e300, 0.0))])
    with pytest.raises(FileFormatError, match=r"points3D\.bin: .* in 3D point record 1 \(POINT3D_ID 2, byte \d+\)"):
        read_colmap(root)


def test_truncated_track_of_the_last_3d_point_names_that_record_s_byte(tmp_path):
    """COLMAP's points3D.bin layout (u64 count; per point u64 id, 3 f64 xyz, 3 u8 rgb, f64 error, u64 track
    length, then (u32 image_id, u32 point2D_idx) per track element): a record is 51 + 8 * track bytes.
    The first point (track 2) is 67 bytes at byte 8, so the second starts at byte 75; it declares a track
    of 3 but holds 2: the file is 8 + 67 + 51 + 16 = 142 bytes and the error names byte 75."""
    first = (struct.pack("<Q3d", 1, 0.5, 1.5, 2.5) + bytes([1, 2, 3]) + struct.pack("<dQ", 0.1, 2)
             + struct.pack("<4I", 1, 0, 2, 0))
    second = (struct.pack("<Q3d", 2, -1.0, 0.0, 1.0) + bytes(3) + struct.pack("<dQ", 0.2, 3)
              + struct.pack("<4I", 1, 1, 2, 1))
    p = tmp_path / "points3D.bin"
    p.write_bytes(struct.pack("<Q", 2) + first + second)
    assert p.stat().st_size == 142
    with pytest.raises(FileFormatError, match=r"points3D.bin: truncated COLMAP binary file: the track of 3D point 1 "
                                              r"at byte 75 runs past the end \(142 bytes\)"):
        _read_points_bin(p)
    p.write_bytes(struct.pack("<Q", 2) + first + second + struct.pack("<2I", 3, 2))  # the whole track: reads
    assert np.array_equal(_read_points_bin(p), [[0.5, 1.5, 2.5], [-1.0, 0.0, 1.0]])


def test_binary_file_helpers_refuse_what_runs_past_the_end(tmp_path):
    p = tmp_path / "x.bin"
    p.write_bytes(b"ab\0cd")
    with _BinFile(p) as f:
        assert f.cstring("a name") == "ab" and f.off == 3
        with pytest.raises(FileFormatError, match=r"x.bin: truncated COLMAP binary file: the tail at byte 3 runs past "
                                                  r"the end \(5 bytes\)"):
            f.skip(3, "the tail")
        f.skip(2, "the tail")  # exactly the 2 bytes left
        f.finish()
        with pytest.raises(FileFormatError, match="truncated COLMAP binary file: another name at byte 5"):
            f.cstring("another name")  # no NUL left
    with _BinFile(p) as f:
        f.skip(1, "one byte")
        with pytest.raises(FileFormatError, match="x.bin: 4 unexpected bytes after the last record"):
            f.finish()
    with pytest.raises(FileFormatError, match="cannot read the file"):
        _BinFile(tmp_path)  # a folder, not a file
    with pytest.raises(FileFormatError, match="cannot read the file"):
        _read_cameras_txt(tmp_path)


@needs_pycolmap
def test_truncated_and_oversized_binary_files_refused(tmp_path):
    rec = reconstruction(n_images=4)
    root = write_reconstruction(tmp_path, rec)
    sparse = root / "sparse" / "0"
    readers = {"cameras.bin": _read_cameras_bin, "images.bin": _read_images_bin, "points3D.bin": _read_points_bin}
    for name, reader in readers.items():
        data = (sparse / name).read_bytes()
        reader(sparse / name)  # the whole file reads
        # every truncation in the first records, every 4th byte after (a new file each: rewriting one is slow)
        for n in sorted(set(range(min(len(data), 160))) | set(range(160, len(data), 4))):
            cut = tmp_path / f"cut{n}_{name}"
            cut.write_bytes(data[:n])
            with pytest.raises(FileFormatError, match=f"cut{n}_{name}"):
                reader(cut)
        cut = tmp_path / f"long_{name}"
        cut.write_bytes(data + b"\0")
        with pytest.raises(FileFormatError, match="unexpected bytes"):
            reader(cut)
    # a tiny file declaring 1e11 records is refused at once, through the public reader
    for name in readers:
        scene = tmp_path / f"huge_{name}"
        write_reconstruction(scene, rec)
        (scene / "sparse" / "0" / name).write_bytes(np.uint64(10**11).tobytes() + b"\1" * 64)
        with pytest.raises(FileFormatError, match=rf"{name}: declares 100000000000 "):
            read_colmap(scene)
    # a huge declared count of 2D points inside an image record
    data = bytearray((sparse / "images.bin").read_bytes())
    first_name_end = data.index(b"\0", 8 + 64)
    data[first_name_end + 1:first_name_end + 9] = np.uint64(10**11).tobytes()
    (sparse / "images.bin").write_bytes(bytes(data))
    with pytest.raises(FileFormatError, match="images.bin: declares 100000000000 2D points of image"):
        read_colmap(root)
