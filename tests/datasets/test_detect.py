"""Tests of ``controlgs_adapter.datasets.detect``: which reader a folder calls for, the ``format`` option that
forces one, and the options ``load_dataset`` passes on (holdout, images, resolution, background)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers.datasets_synth import GL_TO_CV, ring_poses, write_blender_ring, write_json, write_ngp_ring, write_png
from helpers.scene_writers import rotation_to_quaternion, save_png, write_colmap

from controlgs_adapter.datasets.colmap import read_colmap
from controlgs_adapter.datasets.detect import detect_format, load_dataset
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.scene.cameras import arc_cameras

W, H = 32, 24
ANGLE_X = 1.0


def _test_names(data) -> list[str]:
    return [f.name for f in data.splits["test"]]


def test_detect_format_checks_colmap_then_blender_then_instant_ngp(tmp_path):
    root = tmp_path / "d"
    root.mkdir()
    (root / "transforms.json").write_text("{}")
    assert detect_format(root) == "instant_ngp"
    (root / "transforms_train.json").write_text("{}")
    assert detect_format(root) == "blender"
    (root / "sparse").mkdir()
    (root / "sparse" / "cameras.txt").write_text("")
    assert detect_format(root) == "colmap"
    (root / "sparse" / "cameras.txt").unlink()
    (root / "sparse" / "0").mkdir()
    (root / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    assert detect_format(root) == "colmap"
    assert detect_format(write_blender_ring(tmp_path / "blender", ring_poses(3))) == "blender"
    assert detect_format(write_ngp_ring(tmp_path / "ngp", n=1)) == "instant_ngp"


def test_a_folder_in_no_known_format_is_refused_listing_what_it_holds(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        detect_format(tmp_path / "nowhere")
    with pytest.raises(FileFormatError, match="missing: dataset folder not found"):
        load_dataset(tmp_path / "missing")
    root = tmp_path / "d"
    root.mkdir()
    with pytest.raises(FileFormatError, match=r"d: not a dataset folder .*\(it holds: nothing\)\. .*colmap: sparse/0/"):
        detect_format(root)
    (root / "photos").mkdir()
    (root / "notes.txt").write_text("x")
    with pytest.raises(FileFormatError, match=r"it holds: notes\.txt, photos/\).*sparse/0.*transforms_train\.json.*"
                                              r"transforms\.json"):
        load_dataset(root)
    for i in range(11):
        (root / f"f{i:02d}.txt").write_text("")
    with pytest.raises(FileFormatError, match=r"it holds: f00.txt, f01.txt, .*f09.txt, \.\.\.\)"):
        detect_format(root)


def test_the_format_option_forces_the_reader(tmp_path):
    """Any case, spaces, ``-`` for ``_``; an unknown name or ``images`` for a format other than COLMAP is
    refused naming the value."""
    write_blender_ring(tmp_path, ring_poses(3), width=8, height=6)
    write_ngp_ring(tmp_path)
    assert load_dataset(tmp_path).format == "blender"
    assert load_dataset(tmp_path, format="instant-ngp").format == "instant_ngp"
    assert _test_names(load_dataset(tmp_path, format=" Instant-NGP ", holdout=0)) == []
    for bad in ("llff", "nerf"):
        with pytest.raises(InputValueError, match=rf"^format must be one of colmap, blender, instant_ngp .*'{bad}'$"):
            load_dataset(tmp_path, format=bad)
    for fmt, read_as in ((None, "blender"), (" Instant-NGP ", "instant_ngp"), ("BLENDER", "blender")):
        with pytest.raises(InputValueError, match=rf"^images='imgs' .*COLMAP.*; {tmp_path} is read as {read_as}$"):
            load_dataset(tmp_path, format=fmt, images="imgs")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "transforms.json").write_text("{}")
    with pytest.raises(FileFormatError, match="'frames' must be a non-empty list"):  # the forced reader's own refusal
        load_dataset(empty, format="instant-ngp")


def test_load_dataset_passes_holdout_resolution_and_background(tmp_path):
    """Every holdout-th frame by name is a test view (default 8); ``resolution`` reaches the COLMAP reader (it
    picks images_2 at 8 px and the cameras follow); ``background`` overrides ``white_background``."""
    ngp = write_ngp_ring(tmp_path / "ngp")
    assert _test_names(load_dataset(ngp)) == ["images/img_00.png", "images/img_08.png"]
    assert _test_names(load_dataset(ngp, holdout=3)) == ["images/img_00.png", "images/img_03.png",
                                                         "images/img_06.png", "images/img_09.png"]
    assert load_dataset(ngp).background.tolist() == [0.0, 0.0, 0.0]
    assert load_dataset(ngp, white_background=True).background.tolist() == [1.0, 1.0, 1.0]
    data = load_dataset(ngp, background=torch.tensor([0.2, 0.3, 0.4]), white_background=True)
    assert data.background.tolist() == pytest.approx([0.2, 0.3, 0.4])
    blender = load_dataset(write_blender_ring(tmp_path / "blender", ring_poses(3)), white_background=True)
    assert blender.format == "blender" and torch.equal(blender.background, torch.ones(3))
    root = write_colmap(tmp_path / "c", arc_cameras(10, size=16), [torch.full((3, 16, 16), i / 10.0) for i in range(10)])
    assert _test_names(read_colmap(root)) == _test_names(load_dataset(root)) == ["v00.png", "v08.png"]
    assert _test_names(load_dataset(root, holdout=4)) == ["v00.png", "v04.png", "v08.png"]
    for i in range(10):
        save_png(root / "images_2" / f"v{i:02d}.png", torch.full((3, 8, 8), i / 10.0))
    assert load_dataset(root).splits["train"][0].camera.width == 16
    assert load_dataset(root, resolution=8).splits["train"][0].camera.width == 8


@pytest.mark.parametrize("kwargs, bg", [({}, 0.0), ({"white_background": True}, 1.0), ({"white_background": False}, 0.0)])
def test_load_dataset_composites_rgba_over_black_by_default(tmp_path, kwargs, bg):
    px = np.zeros((6, 8, 4), dtype=np.uint8)
    px[..., :3] = 200
    px[:3, :, 3] = 0      # top half transparent: shows the background
    px[3:, :, 3] = 255    # bottom half opaque: 200 / 255
    write_png(tmp_path / "train" / "r_0.png", px)
    write_json(tmp_path / "transforms_train.json",
               {"camera_angle_x": 0.8, "frames": [{"file_path": "train/r_0", "transform_matrix": ring_poses(1)[0].tolist()}]})
    image = load_dataset(tmp_path, **kwargs).views("train").image(0)
    torch.testing.assert_close(image[:, :3], torch.full((3, 3, 8), bg), rtol=0, atol=1e-6)
    torch.testing.assert_close(image[:, 3:], torch.full((3, 3, 8), 200 / 255), rtol=0, atol=1e-6)


def _write_colmap_poses(root, c2ws_gl, names, fx, fy, cx, cy):
    """A COLMAP text model: one PINHOLE camera; each image's world-to-camera in OpenCV axes."""
    (root / "sparse" / "0").mkdir(parents=True)
    (root / "sparse" / "0" / "cameras.txt").write_text(f"# CAMERA_ID MODEL WIDTH HEIGHT PARAMS\n"
                                                       f"1 PINHOLE {W} {H} {fx!r} {fy!r} {cx!r} {cy!r}\n")
    lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME"]
    for i, (c2w, name) in enumerate(zip(c2ws_gl, names)):
        w2c = np.linalg.inv(c2w @ GL_TO_CV)
        lines += [" ".join(map(repr, [i + 1, *rotation_to_quaternion(w2c[:3, :3]), *w2c[:3, 3].tolist(), 1])) + f" {name}", ""]
    (root / "sparse" / "0" / "images.txt").write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("other", ["blender", "instant_ngp"])
def test_one_scene_in_each_format_gives_the_same_cameras_and_images(tmp_path, other):
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
    _write_colmap_poses(tmp_path / "colmap", poses, names, fx, fy, cx, cy)
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
