"""COLMAP reader: paths stay inside the scene folder, records are read by structure (no silent loss
or overwrite), and every refusal names the file and its line (text) or record (binary)."""

from __future__ import annotations

import re

import pytest
import torch

from controlgs_adapter.datasets import load_dataset, read_colmap
from controlgs_adapter.datasets.colmap import qvec_to_rotation
from controlgs_adapter.errors import FileFormatError, InputValueError
from helpers.dataset_files import (CAMERA_LINE, cameras_bin, colmap_text, image_line, images_bin, opened_under,
                                   outside, png, points_bin, recording)


def _scene(tmp_path, **kw):
    return colmap_text(tmp_path / "scene", **kw)


# ----------------------------------------------------------------------------- paths outside the folder

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


def test_every_image_is_read_with_or_without_points_and_a_final_points_line(tmp_path):
    names = [f"v{i}.png" for i in range(8)]
    lines = ["# Image list"]
    for i, n in enumerate(names):
        lines += [image_line(i + 1, n), "1.5 2.5 7 3.0 4.0 -1" if i % 2 else ""]
    root = _scene(tmp_path, images="\n".join(lines[:-1]) + "\n", names=names)  # the last POINTS2D line left out
    data = read_colmap(root, holdout=0)
    assert [f.name for f in data.splits["train"]] == names


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


# ----------------------------------------------------------------------------- binary records

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


def test_binary_files_read_when_ids_are_unique(tmp_path):
    root = _binary_scene(tmp_path, [(1, 1, 8, 6, (10, 10, 4, 3))], [(1, "a.png", 1), (2, "b.png", 1)],
                         [(1, (0.0, 0.0, 0.0)), (2, (1.0, 0.0, 0.0))])
    data = read_colmap(root, holdout=0)
    assert len(data.splits["train"]) == 2 and data.points is not None and data.points.shape == (2, 3)


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


# ----------------------------------------------------------------------------- float32 range

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


def test_a_point_beyond_float32_in_a_binary_file_names_the_record(tmp_path):
    root = _binary_scene(tmp_path, [(1, 1, 8, 6, (10, 10, 4, 3))], [(1, "a.png", 1)],
                         [(1, (0.0, 0.0, 0.0)), (2, (0.0, -1e300, 0.0))])
    with pytest.raises(FileFormatError, match=r"points3D\.bin: .* in 3D point record 1 \(POINT3D_ID 2, byte \d+\)"):
        read_colmap(root)


def test_a_huge_quaternion_is_normalised_not_collapsed_to_the_identity():
    half_turn_about_x = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    assert torch.allclose(qvec_to_rotation([0.0, 1e300, 0.0, 0.0]), half_turn_about_x)
