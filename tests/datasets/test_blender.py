"""NeRF-synthetic (Blender) reader: paths stay inside the dataset folder, every number is a number,
poses are whole rigid transforms that fit float32, and refusals name the file and frame."""

from __future__ import annotations

import json

import pytest

from controlgs_adapter.datasets import load_dataset, read_blender
from controlgs_adapter.errors import FileFormatError
from helpers.dataset_files import C2W, blender, frame, opened_under, outside, png, recording


def _root(tmp_path):
    return tmp_path / "scene"


# ----------------------------------------------------------------------------- paths outside the folder

@pytest.mark.parametrize("file_path", ["../outside/sentinel", "./train/../../outside/sentinel.png", "ABS"])
def test_a_file_path_leading_outside_the_folder_is_refused_naming_the_frame(tmp_path, file_path):
    out = outside(tmp_path)
    file_path = str(out / "sentinel") if file_path == "ABS" else file_path
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame(file_path)])
    with recording() as opened, pytest.raises(FileFormatError) as e:
        read_blender(root)
    assert "transforms_train.json: frames[1]" in str(e.value) and "sentinel" in str(e.value)
    assert opened_under(out, opened) == []


def test_a_symlinked_image_pointing_outside_the_folder_is_refused(tmp_path):
    out = outside(tmp_path)
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame("./train/r_1")], images=["r_0"])
    (root / "train" / "r_1.png").symlink_to(out / "sentinel.png")
    with recording() as opened, pytest.raises(FileFormatError,
                                              match=r"transforms_train\.json: frames\[1\]: file_path .*leads outside"):
        load_dataset(root)
    assert opened_under(out, opened) == []


def test_a_transforms_file_symlinked_outside_the_folder_is_refused(tmp_path):
    out = outside(tmp_path)
    root = blender(_root(tmp_path), [frame("./train/r_0")])
    (root / "transforms_test.json").symlink_to(out / "sentinel.json")
    with recording() as opened, pytest.raises(FileFormatError, match=r"scene: the file 'transforms_test\.json' leads outside"):
        read_blender(root)
    assert opened_under(out, opened) == []


# ----------------------------------------------------------------------------- entries

def test_a_duplicated_frame_is_refused_naming_both(tmp_path):
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame("./train/r_1"), frame("train/r_0.png")])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[2\] .*listed twice \('train/r_0\.png'\), "
                                              r"also in frames\[0\]"):
        read_blender(root)


def test_a_last_row_other_than_0001_is_refused(tmp_path):
    bad = [row[:] for row in C2W]
    bad[3] = [0.0, 0.0, 0.5, 1.0]
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame("./train/r_1", bad)])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[1\] .*last row must be \[0, 0, 0, 1\], "
                                              r"got \[0\.0, 0\.0, 0\.5, 1\.0\]"):
        read_blender(root)


@pytest.mark.parametrize("value", ["4.0", True, None, [4.0]])
def test_a_non_number_in_the_transform_matrix_is_refused(tmp_path, value):
    bad = [row[:] for row in C2W]
    bad[2][3] = value
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame("./train/r_1", bad)])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[1\] .*transform_matrix must hold numbers"):
        read_blender(root)


@pytest.mark.parametrize("angle", ["0.69", True])
def test_a_non_number_field_of_view_is_refused(tmp_path, angle):
    root = blender(_root(tmp_path), [frame("./train/r_0")], angle=angle)
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: camera_angle_x must be a number"):
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
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame("./train/r_1", far)])
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[1\] \('\./train/r_1'\): .*float32"):
        read_blender(root)
    root = blender(tmp_path / "narrow", [frame("./train/r_0")], angle=1e-300)  # focal 0.5 W / tan(1e-300 / 2)
    with pytest.raises(FileFormatError, match=r"transforms_train\.json: frames\[0\] \('\./train/r_0'\): intrinsics .*float32"):
        read_blender(root)


def test_a_well_formed_folder_still_reads(tmp_path):
    root = blender(_root(tmp_path), [frame("./train/r_0"), frame("train/r_1.png")])
    png(root / "test" / "r_2.png")
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [frame("./test/r_2")]}))
    data = read_blender(root)
    assert [f.name for f in data.splits["train"]] == ["train/r_0.png", "train/r_1.png"]
    assert [f.name for f in data.splits["test"]] == ["test/r_2.png"]
