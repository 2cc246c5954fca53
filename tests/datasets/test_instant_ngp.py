"""instant-ngp reader: the same path, number and pose checks as the Blender reader, a focal length
that disagrees with the field of view beside it is reported, and warnings point at the caller."""

from __future__ import annotations

import warnings

import pytest

from controlgs_adapter.datasets import load_dataset, read_instant_ngp
from controlgs_adapter.errors import FileFormatError
from helpers.dataset_files import C2W, frame, instant_ngp, opened_under, outside, recording


def _root(tmp_path):
    return tmp_path / "scene"


# ----------------------------------------------------------------------------- paths outside the folder

@pytest.mark.parametrize("file_path", ["../outside/sentinel.png", "images/../../outside/sentinel", "ABS"])
def test_a_file_path_leading_outside_the_folder_is_refused_naming_the_frame(tmp_path, file_path):
    out = outside(tmp_path)
    file_path = str(out / "sentinel.png") if file_path == "ABS" else file_path
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame(file_path)])
    with recording() as opened, pytest.raises(FileFormatError) as e:
        read_instant_ngp(root)
    assert "transforms.json: frames[1]" in str(e.value) and "sentinel" in str(e.value)
    assert opened_under(out, opened) == []


def test_a_symlinked_image_pointing_outside_is_refused_not_skipped(tmp_path):
    out = outside(tmp_path)
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("images/b.png")], images=["a"])
    (root / "images" / "b.png").symlink_to(out / "sentinel.png")
    with recording() as opened, pytest.raises(FileFormatError, match=r"transforms\.json: frames\[1\]: file_path "
                                                                     r"'images/b\.png' leads outside"):
        load_dataset(root)
    assert opened_under(out, opened) == []


def test_a_symlink_loop_is_refused_naming_the_frame(tmp_path):
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("images/loop.png")], images=["a"])
    (root / "images" / "loop.png").symlink_to(root / "images" / "loop.png")
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[1\]: file_path 'images/loop\.png' cannot be "
                                              r"resolved"):
        read_instant_ngp(root)


def test_a_transforms_name_leading_outside_the_folder_is_refused(tmp_path):
    out = outside(tmp_path)
    root = instant_ngp(_root(tmp_path), [frame("images/a.png")])
    with recording() as opened, pytest.raises(FileFormatError, match=r"scene: transforms '\.\./outside/sentinel\.json' "
                                                                     r"leads outside"):
        read_instant_ngp(root, transforms="../outside/sentinel.json")
    assert opened_under(out, opened) == []


# ----------------------------------------------------------------------------- entries

def test_a_duplicated_frame_is_refused_naming_both(tmp_path):
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("./images/b.png"), frame("images/./b.png")])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[2\] .*listed twice \('images/b\.png'\), "
                                              r"also in frames\[1\]"):
        read_instant_ngp(root)


def test_a_last_row_other_than_0001_is_refused(tmp_path):
    bad = [row[:] for row in C2W]
    bad[3] = [0.0, 1.0, 0.0, 1.0]
    root = instant_ngp(_root(tmp_path), [frame("images/a.png", bad)])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[0\] .*last row must be \[0, 0, 0, 1\]"):
        read_instant_ngp(root)


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
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("images/b.png", matrix, **keys)], **meta)
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
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("images/b.png", **keys)])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[1\] \('images/b\.png'\): " + words):
        read_instant_ngp(root)
    far = [row[:] for row in C2W]
    far[2][3] = 1e300
    root = instant_ngp(tmp_path / "far", [frame("images/a.png", far)])
    with pytest.raises(FileFormatError, match=r"transforms\.json: frames\[0\] \('images/a\.png'\): .*float32"):
        read_instant_ngp(root)


# ----------------------------------------------------------------------------- warnings

def test_a_focal_length_that_disagrees_with_the_field_of_view_is_reported_and_fl_x_used(tmp_path):
    # the 8 px wide image: camera_angle_x = 0.7 gives 0.5 * 8 / tan(0.35) = 10.958 px, fl_x says 20
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("images/b.png", fl_x=20.0, fl_y=20.0,
                                                                       camera_angle_x=0.7)])
    with pytest.warns(RuntimeWarning) as caught:
        data = read_instant_ngp(root, holdout=0)
    msg = str(caught[0].message)
    assert "transforms.json" in msg and "frames[1] ('images/b.png'): fl_x 20 px, camera_angle_x gives 10.958 px" in msg
    assert "fl_x / fl_y is used" in msg and "frames[0]" not in msg
    assert caught[0].filename == __file__
    assert float(data.splits["train"][1].camera.intrinsics[0, 0]) == 20.0


def test_an_agreeing_focal_length_and_field_of_view_give_no_warning(tmp_path):
    root = instant_ngp(_root(tmp_path), [frame("images/a.png")], fl_x=10.96, camera_angle_x=0.7, images=["a"])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_instant_ngp(root, holdout=0)


def test_the_missing_images_warning_points_at_the_callers_line(tmp_path):
    root = instant_ngp(_root(tmp_path), [frame("images/a.png"), frame("images/gone.png")], images=["a"])
    for read in (read_instant_ngp, load_dataset):
        with pytest.warns(RuntimeWarning, match=r"transforms\.json: 1 of 2 frames .* skipped: images/gone\.png") as caught:
            read(root, holdout=0)
        assert caught[0].filename == __file__
