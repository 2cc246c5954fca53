"""Tests of ``controlgs_adapter.datasets.detect``."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers.datasets_synth import marker_image, ring_poses, write_json, write_png

from controlgs_adapter.datasets.detect import detect_format, load_dataset
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.scene.cameras import arc_cameras


def test_detect_format_order_and_refusals(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: dataset folder not found"):
        detect_format(tmp_path / "nowhere")
    root = tmp_path / "d"
    root.mkdir()
    with pytest.raises(FileFormatError, match=r"d: not a dataset folder in a known format \(it holds: nothing\)\. "
                                              r"Each format needs: colmap: sparse/0/"):
        detect_format(root)
    (root / "sub").mkdir()
    for i in range(11):
        (root / f"f{i:02d}.txt").write_text("")
    with pytest.raises(FileFormatError, match=r"it holds: f00.txt, f01.txt, .*f09.txt, \.\.\.\)"):
        detect_format(root)
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


def test_load_dataset_format_names_and_images_option(tmp_path):
    (tmp_path / "transforms.json").write_text("{}")
    with pytest.raises(InputValueError, match=r"format must be one of colmap, blender, instant_ngp \(or None to detect "
                                              r"it\), got 'ngp'"):
        load_dataset(tmp_path, format="ngp")
    with pytest.raises(InputValueError, match=r"images='imgs' applies to COLMAP datasets only; .* is read as instant_ngp"):
        load_dataset(tmp_path, format=" Instant-NGP ", images="imgs")
    with pytest.raises(InputValueError, match="images='imgs' applies to COLMAP datasets only; .* is read as blender"):
        load_dataset(tmp_path, format="BLENDER", images="imgs")
    # the forced reader runs: instant-ngp's own refusal of this empty file
    with pytest.raises(FileFormatError, match="'frames' must be a non-empty list"):
        load_dataset(tmp_path, format="instant-ngp")


W, H = 32, 24


ANGLE_X = 1.0


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


def _ngp(root):
    c2w = ring_poses(1)[0]
    write_png(root / "images" / "a.png", marker_image(W, H, [], rgba=False))
    write_json(root / "transforms.json", {"camera_angle_x": ANGLE_X, "frames": [{"file_path": "images/a.png",
                                                                                  "transform_matrix": c2w.tolist()}]})


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


# --------------------------------------------------------------------------- load_dataset default background
@pytest.mark.parametrize("kwargs, bg", [({}, 0.0), ({"white_background": True}, 1.0),
                                        ({"white_background": False}, 0.0)])
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


# --------------------------------------------------------------------------- datasets
def _ngp_2(root, n=10, transforms="transforms.json"):
    poses = ring_poses(n, phase=0.1)
    frames = []
    for i in range(n):
        write_png(root / "images" / f"img_{i:02d}.png", marker_image(8, 6, [], rgba=False, fill=(10 * i, 0, 0)))
        frames.append({"file_path": f"images/img_{i:02d}.png", "transform_matrix": poses[i].tolist()})
    write_json(root / transforms, {"fl_x": 9.0, "fl_y": 9.0, "cx": 4.0, "cy": 3.0, "w": 8.0, "h": 6.0, "frames": frames})


def _test_names(data):
    return [f.name for f in data.splits["test"]]


def test_load_dataset_passes_holdout_and_refuses_images_for_other_formats(tmp_path):
    _ngp_2(tmp_path)
    assert _test_names(load_dataset(tmp_path, holdout=3)) == ["images/img_00.png", "images/img_03.png",
                                                              "images/img_06.png", "images/img_09.png"]
    assert _test_names(load_dataset(tmp_path, format=" Instant-NGP ", holdout=0)) == []
    with pytest.raises(InputValueError, match=rf"^images='imgs' applies to COLMAP datasets only; {tmp_path} is read as instant_ngp$"):
        load_dataset(tmp_path, images="imgs")
    with pytest.raises(InputValueError, match=r"^format must be one of colmap, blender, instant_ngp \(or None to detect it\), got 'nerf'$"):
        load_dataset(tmp_path, format="nerf")
    # background overrides white_background through load_dataset too (ngp frames are RGB: check the setting)
    data = load_dataset(tmp_path, background=torch.tensor([0.2, 0.3, 0.4]), white_background=True)
    assert data.background.tolist() == pytest.approx([0.2, 0.3, 0.4])
    assert load_dataset(tmp_path).background.tolist() == [0.0, 0.0, 0.0]
    assert load_dataset(tmp_path, white_background=True).background.tolist() == [1.0, 1.0, 1.0]


def test_colmap_default_holdout_8_and_resolution_through_load_dataset(tmp_path):
    from helpers.scene_writers import write_colmap

    from controlgs_adapter.datasets.colmap import read_colmap

    cams = arc_cameras(10, size=16)
    images = [torch.full((3, 16, 16), i / 10.0) for i in range(10)]
    root = write_colmap(tmp_path / "c", cams, images)
    want = ["v00.png", "v08.png"]  # every 8th of v00..v09 by name
    assert _test_names(read_colmap(root)) == want
    assert _test_names(load_dataset(root)) == want
    assert _test_names(load_dataset(root, holdout=4)) == ["v00.png", "v04.png", "v08.png"]
    # resolution reaches read_colmap: it picks images_2 (8 x 8 files, still >= 8) and the cameras follow
    from helpers.scene_writers import save_png

    for i in range(10):
        save_png(root / "images_2" / f"v{i:02d}.png", torch.full((3, 8, 8), i / 10.0))
    assert load_dataset(root).splits["train"][0].camera.width == 16
    assert load_dataset(root, resolution=8).splits["train"][0].camera.width == 8
