"""Dataset readers (COLMAP / Blender / instant-ngp conventions, docs in /work/shared/notes/datasets.md):
the refusals and boundaries no other test reaches, each pinned against the format's documentation or a
value worked out by hand (how is said next to each literal)."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
import torch

from controlgs_adapter.datasets.blender import opengl_c2w_to_w2c
from controlgs_adapter.datasets.colmap import (CAMERA_MODELS, _BinFile, _read_cameras_bin, _read_cameras_txt,
                                               _read_images_bin, _read_points_bin, qvec_to_rotation, read_colmap)
from controlgs_adapter.datasets.images import undistort_points
from controlgs_adapter.errors import FileFormatError, InputValueError


# ---------------------------------------------------------------- OpenGL camera-to-world -> OpenCV world-to-camera

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
        with pytest.raises(InputValueError, match=rf"finite 4x4 \(or 3x4\) matrix, got shape {re_escape(shape)}"):
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


def re_escape(s: str) -> str:
    import re

    return re.escape(s)


# ---------------------------------------------------------------- COLMAP binary files, written byte by byte

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


def test_points3d_binary_with_no_points_gives_an_empty_cloud(tmp_path):
    from PIL import Image

    sparse = tmp_path / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text("1 PINHOLE 8 6 10 12 4 3\n")
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 2 1 a.png\n\n")
    (sparse / "points3D.bin").write_bytes(struct.pack("<Q", 0))
    (tmp_path / "images").mkdir()
    Image.fromarray(np.zeros((6, 8, 3), np.uint8)).save(tmp_path / "images" / "a.png")
    scene = read_colmap(tmp_path, holdout=0)
    assert scene.points is not None and tuple(scene.points.shape) == (0, 3) and scene.points.dtype == torch.float32


# ---------------------------------------------------------------- COLMAP quaternions and undistortion helpers

def test_qvec_rotation_by_hand():
    # q = (cos 45deg, 0, 0, sin 45deg): 90 degrees about z, x -> y
    s = math.sqrt(0.5)
    assert torch.allclose(qvec_to_rotation([s, 0.0, 0.0, s]),
                          torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64), atol=1e-15)
    # not normalised: (2, 0, 0, 0) is the identity
    assert torch.equal(qvec_to_rotation([2.0, 0.0, 0.0, 0.0]), torch.eye(3, dtype=torch.float64))
    for bad in ([0.0, 0.0, 0.0, 0.0], [1e-13, 0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0, 1.0]):
        with pytest.raises(InputValueError, match="finite non-zero quaternion"):
            qvec_to_rotation(bad)
    qvec_to_rotation([1e-11, 0.0, 0.0, 0.0])  # norm above 1e-12: accepted


def test_undistort_points_refuses_a_bad_shape():
    k = torch.tensor([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]])
    for uv in (torch.zeros(3, 3), torch.zeros(2)):
        with pytest.raises(InputValueError, match=rf"uv must be \[N, 2\], got {re_escape(str(list(uv.shape)))}"):
            undistort_points(uv, k, (0.1, 0.0, 0.0, 0.0))
    # the identity without distortion
    uv = torch.tensor([[1.0, 2.0], [7.5, 0.5]])
    assert torch.allclose(undistort_points(uv, k, (0.0, 0.0, 0.0, 0.0)), uv)


# ---------------------------------------------------------------- the data fingerprint a checkpoint stores

def test_fingerprint_is_pinned_to_its_recipe():
    """A checkpoint records the fingerprint of its training views: the value must not drift between
    releases. Recipe: sha256 over each frame's name, "WxH", world-to-camera (float64, rounded to 6
    decimals) and intrinsics (float64, rounded to 4), first 16 hex digits."""
    import hashlib

    from controlgs_adapter.datasets.base import PosedImages
    from controlgs_adapter.datasets.memory import tensor_frames
    from controlgs_adapter.state import Camera

    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, 3] = torch.tensor([0.1234567, -2.0, 3.5], dtype=torch.float64)
    k = torch.tensor([[10.12345, 0.0, 4.0], [0.0, 11.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cams = [Camera(w2c.float(), k.float(), 8, 6), Camera(w2c.float(), (k * torch.tensor([[0.5], [0.5], [1.0]])).float(), 4, 3)]
    views = PosedImages(tensor_frames([torch.zeros(3, 6, 8), torch.zeros(3, 3, 4)], cams, prefix="fp"))
    h = hashlib.sha256()
    for name, cam in zip(("fp/0000", "fp/0001"), cams):
        h.update(name.encode())
        h.update(f"{cam.width}x{cam.height}".encode())
        h.update(cam.world_to_camera.double().numpy().round(6).tobytes())
        h.update(cam.intrinsics.double().numpy().round(4).tobytes())
    assert views.fingerprint() == h.hexdigest()[:16]
    # a pose change below the rounding (1e-7) keeps it, one above (1e-5) changes it
    near = Camera(cams[0].world_to_camera + 1e-8, cams[0].intrinsics, 8, 6)
    assert PosedImages(tensor_frames([torch.zeros(3, 6, 8), torch.zeros(3, 3, 4)], [near, cams[1]],
                                     prefix="fp")).fingerprint() == views.fingerprint()


# ---------------------------------------------------------------- instant-ngp: the file's w, h against the image's

def test_ngp_size_tolerance_is_one_pixel_per_side(tmp_path):
    """An 8 x 8 image whose file says w = 16: sx = 0.5. h = 18 gives h * sx - 8 = 1.0 (at the 1 px limit)
    and w * sy - 8 = 16 * 8 / 18 - 8 = -0.89: accepted, each axis scaled by its own factor (fy * 8/18,
    cy * 8/18); h = 18.2 gives 1.1 px: refused."""
    import json

    from PIL import Image

    from controlgs_adapter.datasets.instant_ngp import read_instant_ngp

    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "a.png")
    eye = np.eye(4).tolist()
    meta = {"fl_x": 20.0, "fl_y": 18.0, "cx": 8.0, "cy": 9.0, "w": 16, "h": 18,
            "frames": [{"file_path": "a.png", "transform_matrix": eye}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    cam = read_instant_ngp(tmp_path, holdout=0).splits["train"][0].camera
    assert torch.allclose(cam.intrinsics, torch.tensor([[10.0, 0, 4.0], [0, 8.0, 4.0], [0, 0, 1]]))
    (tmp_path / "transforms.json").write_text(json.dumps({**meta, "h": 18.2}))
    with pytest.raises(FileFormatError, match="the file says 16 x 18.2 but the image"):
        read_instant_ngp(tmp_path, holdout=0)


@pytest.mark.parametrize("w, h", [(0, 8), (16, 0), (-16, 8), (16, -1)])
def test_ngp_zero_or_negative_size_is_refused(tmp_path, w, h):
    import json

    from PIL import Image

    from controlgs_adapter.datasets.instant_ngp import read_instant_ngp

    Image.fromarray(np.zeros((8, 8, 3), np.uint8)).save(tmp_path / "a.png")
    meta = {"fl_x": 20.0, "w": w, "h": h, "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(FileFormatError, match=rf"w and h must be > 0, got {float(w)} x {float(h)}"):
        read_instant_ngp(tmp_path, holdout=0)
