"""Tests of ``controlgs_adapter.datasets.sanity.check_scene``: the fraction of points each camera sees, the
warning about a few blind cameras and the refusal of mostly blind ones (flipped axes), image sizes against
their cameras, required splits, and the points it projects."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from helpers.dataset_views import BACK, FRONT, looking, pinhole
from helpers.datasets_synth import GL_TO_CV, marker_image, project_gl, ring_poses, write_blender_ring, write_png

from controlgs_adapter.datasets import Frame, SceneData, check_scene, read_blender, sanity
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

#: the object the cameras of :func:`write_blender_ring` look at
POINTS = np.random.default_rng(0).uniform(-0.8, 0.8, size=(300, 3))


def _scene(poses: list[torch.Tensor], *, source: str = "mem") -> SceneData:
    """One black 8 x 6 frame (f = 10, centred) per pose, named v00, v01, ..."""
    frames = [Frame(f"v{i:02d}", pinhole(8, 6, w2c=p), torch.zeros(3, 6, 8)) for i, p in enumerate(poses)]
    return SceneData({"train": frames, "test": []}, source=source, format="builtin")


def _sizes(sizes: list[tuple[int, int]]) -> list[Frame]:
    """Frames v0, v1, ... of the given image sizes, each with an 8 x 6 camera."""
    return [Frame(f"v{i}", pinhole(8, 6, 4.0), torch.zeros(3, h, w)) for i, (w, h) in enumerate(sizes)]


# ----------------------------------------------------------------------------- fractions in front

def test_fractions_count_points_in_front_and_inside_the_image():
    """u = 4 x / z + 4, v = 4 y / z + 3: inside iff 0 <= u < 8 and 0 <= v < 6; depth 0 is behind. A camera
    exactly at the threshold is not blind."""
    pts = torch.tensor([[0.0, 0.0, 1.0],      # centre: inside
                        [-1.0, -0.75, 1.0],   # u = 0, v = 0: inside (left/top edges included)
                        [1.0, 0.0, 1.0],      # u = 8: outside (right edge excluded)
                        [0.0, 0.75, 1.0],     # v = 6: outside (bottom edge excluded)
                        [0.0, 0.0, -1.0],     # behind
                        [0.0, 0.0, 0.0],      # depth 0: not in front
                        [0.99, 0.74, 1.0],    # inside
                        [10.0, 0.0, 1.0]])    # outside
    data = SceneData({"train": looking(2), "test": []}, source="src", format="colmap")
    rep = check_scene(data, pts, required=("train",))
    assert rep["in_front"] == {"v0": 3 / 8, "v1": 3 / 8} and rep["blind"] == [] and rep["points"] == 8
    assert rep["splits"] == {"train": 2, "test": 0} and rep["images_checked"] == 2
    assert (rep["source"], rep["format"]) == ("src", "colmap")
    assert check_scene(data, pts, min_in_front=3 / 8)["blind"] == []
    with pytest.warns(RuntimeWarning, match=r"src: 1 of 2 cameras .* 8 points \(< 38% "):  # v1 sees 1 of 8
        assert check_scene(SceneData({"train": looking(2, flipped=1)}, source="src"), pts, min_in_front=0.375)["blind"] \
            == ["v1"]
    # left of or above the image (f = 10, c = (4, 3)): (-1, 0, 1) -> u = -6, (0, -1, 1) -> v = -7
    left_above = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [0.0, -1.0, 1.0]])
    assert check_scene(_scene([FRONT]), left_above, min_in_front=0.0)["in_front"] == {"v00": pytest.approx(1 / 3)}


def test_an_80x40_image_counts_points_by_its_width():
    """Every point projects to u in [44, 76], v in [4, 36]: inside the image (u < W) though u > H."""
    cam = Camera(torch.eye(4), torch.tensor([[40.0, 0.0, 40.0], [0.0, 40.0, 20.0], [0.0, 0.0, 1.0]]), 80, 40)
    uv = torch.rand(50, 2, generator=torch.Generator().manual_seed(0)) * 32.0 + torch.tensor([44.0, 4.0])
    pts = torch.cat([(uv - torch.tensor([40.0, 20.0])) / 40.0 * 3.0, torch.full((50, 1), 3.0)], dim=1)  # depth 3
    data = SceneData({"train": [Frame("a", cam, torch.zeros(3, 40, 80))]}, points=pts, source="synthetic", format="builtin")
    report = check_scene(data)
    assert report["in_front"] == {"a": 1.0} and report["blind"] == []


def test_fractions_match_an_independent_projection_of_a_blender_scene(tmp_path):
    poses = ring_poses(6)
    data = read_blender(write_blender_ring(tmp_path, poses))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        report = check_scene(data, torch.from_numpy(POINTS).float(), required=("train", "test"))
    f = 0.5 * 32 / math.tan(1.0 / 2)
    frames = data.splits["train"] + data.splits["test"]
    assert report["points"] == len(POINTS) and report["blind"] == []
    assert report["splits"] == {"train": 6, "test": 2} and report["images_checked"] == 8
    for frame, c2w in zip(frames, list(poses) + list(poses[-2:])):
        uv, depth = project_gl(c2w, f, f, 16, 12, POINTS)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 32) & (uv[:, 1] >= 0) & (uv[:, 1] < 24)
        assert report["in_front"][frame.name] == pytest.approx(inside.mean(), abs=1e-9)
        assert report["in_front"][frame.name] > 0.5


def test_default_min_in_front_is_5_percent_and_strict():
    """100 points: 5 straight ahead of v0 (5 %: not blind), 4 straight ahead of v1 (4 %: blind), 91 far to the
    side (outside both images or behind)."""
    pts = torch.cat([torch.tensor([[0.0, 0, 1]]).repeat(5, 1), torch.tensor([[0.0, 0, -1]]).repeat(4, 1),
                     torch.tensor([[10.0, 0, 1]]).repeat(91, 1)])
    data = SceneData({"train": looking(2, flipped=1)}, source="src")
    with pytest.warns(RuntimeWarning, match=r"^src: 1 of 2 cameras .* 100 points \(< 5% .*: v1$"):
        rep = check_scene(data, pts)
    assert rep["in_front"] == pytest.approx({"v0": 0.05, "v1": 0.04}, abs=1e-6) and rep["blind"] == ["v1"]
    assert check_scene(data, pts, min_in_front=0.035)["blind"] == []
    with pytest.raises(InputValueError, match=r"^src: 2 of 2 cameras see none"):
        check_scene(data, pts, min_in_front=0.051)


# ----------------------------------------------------------------------------- blind cameras

def test_a_few_blind_cameras_are_named_in_a_warning_pointing_at_the_caller(tmp_path):
    """At most half of the cameras blind: a RuntimeWarning naming up to five of them (", ..." after that),
    raised at the caller's line."""
    frames = [Frame(f"v{i}", pinhole(8, 6, w2c=BACK if i == 2 else FRONT), torch.zeros(3, 6, 8)) for i in range(3)]
    data = SceneData({"train": frames, "test": []}, source="three-views")
    pts = torch.tensor([[0.0, 0.0, 4.0]] * 5)
    with pytest.warns(RuntimeWarning, match=r"three-views: 1 of 3 cameras see almost none .*: v2$") as caught:
        report = check_scene(data, pts)
    assert report["blind"] == ["v2"] and caught[0].filename == __file__
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 2.0]])
    for n_seeing, n_blind, tail in ((3, 3, ": v03, v04, v05"), (6, 5, ": v06, v07, v08, v09, v10"),
                                    (7, 6, ": v07, v08, v09, v10, v11, ...")):
        with pytest.warns(RuntimeWarning, match=rf" {n_blind} of {n_seeing + n_blind} cameras") as rec:
            check_scene(_scene([FRONT] * n_seeing + [BACK] * n_blind), pts)
        assert str(rec[0].message).endswith(tail)
    poses = ring_poses(6)
    poses[4] = poses[4] @ GL_TO_CV
    with pytest.warns(RuntimeWarning, match=r"1 of 6 cameras see almost none.*train/r_4\.png"):
        report = check_scene(read_blender(write_blender_ring(tmp_path, poses, test=False)), torch.from_numpy(POINTS).float())
    assert report["blind"] == ["train/r_4.png"]


@pytest.mark.parametrize("fmt, hint", [("blender", "OpenGL axes"), ("instant_ngp", "OpenGL axes"),
                                       ("colmap", "not camera to world"), ("", "OpenCV axes")])
def test_mostly_blind_cameras_are_refused_with_the_formats_convention(fmt, hint):
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.0, 2.0]])
    with pytest.raises(InputValueError) as e:
        check_scene(SceneData({"train": looking(3, flipped=2)}, source="s", format=fmt), pts)
    msg = str(e.value)
    assert msg.startswith("s: 2 of 3 cameras see none of the scene") and hint in msg
    assert "5% of 2 points" in msg and "on average 67% lie behind" in msg


def test_points_in_the_camera_plane_are_behind_it():
    with pytest.raises(InputValueError, match=r"on average 100% lie behind"):
        check_scene(_scene([FRONT, FRONT]), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))


def test_opencv_poses_written_as_opengl_are_caught(tmp_path):
    """OpenCV camera-to-world poses written into a Blender file as if they were OpenGL: every camera then
    looks away from the object."""
    data = read_blender(write_blender_ring(tmp_path, [c2w @ GL_TO_CV for c2w in ring_poses(6)]))
    with pytest.raises(InputValueError, match=r"8 of 8 cameras see none .*flipped.*blender.*OpenGL axes"):
        check_scene(data, torch.from_numpy(POINTS).float())


# ----------------------------------------------------------------------------- which points

def test_which_points_are_projected():
    """The given points win over the scene's SfM points; no points (None or ``[0, 3]``) skips the check;
    at most 20,000 points are projected, an even stride through the given ones (20,001 take every 2nd)."""
    data = SceneData({"train": looking(1)}, points=torch.tensor([[0.0, 0.0, -1.0]]), source="s")
    with pytest.raises(InputValueError, match="1 of 1 cameras"):
        check_scene(data)  # the SfM points, behind the camera
    assert check_scene(data, torch.tensor([[0.0, 0.0, 1.0]]))["in_front"] == {"v0": 1.0}
    for report in (check_scene(data, torch.zeros(0, 3)), check_scene(SceneData({"train": looking(1)}))):
        assert report["in_front"] == {} and report["blind"] == [] and report["points"] == 0
    assert sanity._MAX_POINTS == 20_000
    n = 20_001
    pts = torch.zeros(n, 3)
    pts[:, 2] = 1.0
    pts[1::2, 0] = -10.0  # every odd point projects left of the image; the stride keeps only even ones
    report = check_scene(_scene([FRONT]), pts)
    assert report["points"] == 10_001 and report["in_front"]["v00"] == 1.0


def test_scene_points_are_used_and_the_check_skipped_without_any(tmp_path):
    data = read_blender(write_blender_ring(tmp_path, [c2w @ GL_TO_CV for c2w in ring_poses(4)]))
    assert check_scene(data)["in_front"] == {}  # no points: nothing to test against
    data.points = torch.from_numpy(POINTS).float()
    with pytest.raises(InputValueError, match="flipped"):
        check_scene(data)


@pytest.mark.parametrize("bad", [-0.1, 1.0, True, "0.5"])
def test_min_in_front_must_be_a_fraction(bad):
    with pytest.raises(InputValueError, match=rf"min_in_front.*got {bad!r}$"):
        check_scene(SceneData({"train": looking(1)}), min_in_front=bad)


def test_non_finite_points_are_refused():
    with pytest.raises(InputValueError, match="points contains 1 non-finite"):
        check_scene(_scene([FRONT]), torch.tensor([[0.0, 0.0, 1.0], [float("nan"), 0.0, 1.0]]))


# ----------------------------------------------------------------------------- splits and sizes

def test_required_splits_must_not_be_empty(tmp_path):
    """Default ``required=("train",)``: an empty test split passes, an empty train split is refused, naming the
    source and every split's size."""
    data = SceneData({"train": looking(1)}, source="s")
    with pytest.raises(InputValueError, match=r"^s: the 'test' split is empty \(splits: train=1\)$"):
        check_scene(data, required=("train", "test"))
    with pytest.raises(InputValueError, match=r"the 'train' split is empty \(splits: none\)$"):
        check_scene(SceneData({}))
    with pytest.raises(InputValueError, match=r"^src: the 'train' split is empty \(splits: train=0, test=2\)$"):
        check_scene(SceneData({"train": [], "test": looking(2)}, source="src"))
    blender = read_blender(write_blender_ring(tmp_path, ring_poses(3), test=False))
    assert check_scene(blender)["splits"] == {"train": 3, "test": 0}
    with pytest.raises(InputValueError, match=r"the 'test' split is empty \(splits: train=3, test=0\)"):
        check_scene(blender, required=("train", "test"))


@pytest.mark.parametrize("n_bad, tail", [(5, "v4 is 9x6, its camera 8x6"), (6, "v4 is 9x6, its camera 8x6; ...")])
def test_images_of_another_size_than_their_camera_are_named_five_at_most(n_bad, tail):
    data = SceneData({"train": _sizes([(9, 6)] * n_bad + [(8, 6)])}, source="src")
    with pytest.raises(FileFormatError) as e:
        check_scene(data)
    msg = str(e.value)
    assert msg.startswith(f"{n_bad} of {n_bad + 1} images do not match their camera's size: v0 is 9x6")
    assert msg.endswith(tail) and msg.count(" is 9x6") == 5


def test_an_image_files_size_is_read_from_its_header(tmp_path):
    """Files are named by path, in-memory images by frame name, across splits."""
    write_png(tmp_path / "a.png", marker_image(32, 24, [], rgba=False))
    write_png(tmp_path / "b.png", marker_image(32, 26, [], rgba=False))
    cam = pinhole(32, 24, 20.0)
    data = SceneData(splits={"train": [Frame("a.png", cam, tmp_path / "a.png"), Frame("b.png", cam, tmp_path / "b.png")],
                             "test": [Frame("c", cam, torch.zeros(3, 24, 33))]}, source="synthetic")
    with pytest.raises(FileFormatError, match=r"2 of 3 images.*b\.png is 32x26, its camera 32x24.*c is 33x24"):
        check_scene(data)
