"""Up-front dataset checks: the warning about cameras that see little of the scene points at the caller."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.datasets import Frame, SceneData, check_scene
from controlgs_adapter.state import Camera


def _camera(turn: bool) -> Camera:
    """4 units from the origin, facing it; ``turn``: facing away (the origin at depth -4)."""
    w2c = torch.eye(4)
    if turn:  # half a turn about y
        w2c[0, 0] = w2c[2, 2] = -1.0
    w2c[2, 3] = -4.0 if turn else 4.0
    return Camera(w2c, torch.tensor([[10.0, 0, 4], [0, 10.0, 3], [0, 0, 1]]), 8, 6)


def test_the_blind_camera_warning_points_at_the_callers_line():
    frames = [Frame(f"v{i}", _camera(turn=(i == 2)), torch.zeros(3, 6, 8)) for i in range(3)]
    data = SceneData({"train": frames, "test": []}, source="three-views")
    with pytest.warns(RuntimeWarning, match=r"three-views: 1 of 3 cameras see almost none .*: v2$") as caught:
        report = check_scene(data, torch.zeros(5, 3))
    assert report["blind"] == ["v2"]
    assert caught[0].filename == __file__


import numpy as np
from helpers.datasets_synth import marker_image, ring_poses, write_json, write_png

from controlgs_adapter.datasets import read_blender
from controlgs_adapter.errors import FileFormatError, InputValueError


def _cam(w: int, h: int, fx: float = 10.0, fy: float = 12.0, cx: float | None = None, cy: float | None = None) -> Camera:
    k = torch.tensor([[fx, 0.0, w / 2.0 if cx is None else cx], [0.0, fy, h / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, w, h)


def _looking(n: int, flipped: int = 0) -> list[Frame]:
    """``n`` cameras at the origin looking down +z (8 x 6, f = 4, centre (4, 3)); the last ``flipped`` look down -z."""
    out = []
    for i in range(n):
        cam = _cam(8, 6, fx=4.0, fy=4.0)
        if i >= n - flipped:
            cam.world_to_camera[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))
        out.append(Frame(f"v{i}", cam, torch.zeros(3, 6, 8)))
    return out


def test_check_scene_fractions_and_image_borders_by_hand():
    from controlgs_adapter.datasets.sanity import check_scene

    # u = 4 x / z + 4, v = 4 y / z + 3: inside iff 0 <= u < 8 and 0 <= v < 6
    pts = torch.tensor([[0.0, 0.0, 1.0],      # centre: inside
                        [-1.0, -0.75, 1.0],   # u = 0, v = 0: inside (left/top edges included)
                        [1.0, 0.0, 1.0],      # u = 8: outside (right edge excluded)
                        [0.0, 0.75, 1.0],     # v = 6: outside (bottom edge excluded)
                        [0.0, 0.0, -1.0],     # behind
                        [0.0, 0.0, 0.0],      # depth 0: not in front
                        [0.99, 0.74, 1.0],    # inside
                        [10.0, 0.0, 1.0]])    # outside
    data = SceneData({"train": _looking(2), "test": []}, source="src", format="colmap")
    rep = check_scene(data, pts, required=("train",))
    assert rep["in_front"] == {"v0": 3 / 8, "v1": 3 / 8} and rep["blind"] == [] and rep["points"] == 8
    assert rep["splits"] == {"train": 2, "test": 0} and rep["images_checked"] == 2
    assert (rep["source"], rep["format"]) == ("src", "colmap")
    # a camera exactly at the threshold is not blind
    assert check_scene(data, pts, min_in_front=3 / 8)["blind"] == []
    with pytest.warns(RuntimeWarning, match=r"src: 1 of 2 cameras see almost none of the 8 points \(< 38% in front"):
        assert check_scene(SceneData({"train": _looking(2, flipped=1)}, source="src"), pts, min_in_front=0.375)["blind"] \
            == ["v1"]


def test_check_scene_points_choice_stride_and_refusals():
    from controlgs_adapter.datasets import sanity

    data = SceneData({"train": _looking(1)}, points=torch.tensor([[0.0, 0.0, -1.0]]), source="s")
    with pytest.raises(InputValueError, match="1 of 1 cameras"):
        sanity.check_scene(data)  # the SfM points, behind the camera
    assert sanity.check_scene(data, torch.tensor([[0.0, 0.0, 1.0]]))["in_front"] == {"v0": 1.0}  # given points win
    assert sanity.check_scene(data, torch.zeros(0, 3))["points"] == 0
    assert sanity.check_scene(SceneData({"train": _looking(1)}))["in_front"] == {}  # no points: skipped
    n = sanity._MAX_POINTS + 1
    assert sanity.check_scene(data, torch.tensor([[0.0, 0.0, 1.0]]).repeat(n, 1))["points"] == (n + 1) // 2
    for bad in (-0.1, 1.0, True, "0.5"):
        with pytest.raises(InputValueError, match=f"min_in_front must be a fraction in \\[0, 1\\), got {bad!r}"):
            sanity.check_scene(data, min_in_front=bad)
    with pytest.raises(InputValueError, match=r"^s: the 'test' split is empty \(splits: train=1\)$"):
        sanity.check_scene(data, required=("train", "test"))
    with pytest.raises(InputValueError, match=r"the 'train' split is empty \(splits: none\)$"):
        sanity.check_scene(SceneData({}))
    frames = [Frame(f"w{i}", _cam(8, 6), torch.zeros(3, 6, 7)) for i in range(7)]
    with pytest.raises(FileFormatError, match=r"^7 of 8 images do not match their camera's size: w0 is 7x6, its camera "
                                              r"8x6; .*w4 is 7x6, its camera 8x6; \.\.\.$"):
        sanity.check_scene(SceneData({"train": _looking(1) + frames}))


W, H = 32, 24


ANGLE_X = 1.0


POINTS = np.random.default_rng(0).uniform(-0.8, 0.8, size=(300, 3))   # the object the cameras look at


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


def test_check_scene_uses_the_scene_points_and_skips_without_any(tmp_path):
    _write_blender(tmp_path, [c2w @ _GL_TO_CV for c2w in ring_poses(4)])
    data = read_blender(tmp_path)
    assert check_scene(data)["in_front"] == {}                 # no points: nothing to test against
    data.points = torch.from_numpy(POINTS).float()
    with pytest.raises(InputValueError, match="flipped"):
        check_scene(data)


def test_empty_split_is_an_error(tmp_path):
    _write_blender(tmp_path, ring_poses(3), test=False)
    data = read_blender(tmp_path)
    assert check_scene(data)["splits"] == {"train": 3, "test": 0}
    with pytest.raises(InputValueError, match=r"the 'test' split is empty \(splits: train=3, test=0\)"):
        check_scene(data, required=("train", "test"))


def _two_cameras() -> SceneData:
    """Two 8 x 6 cameras at the origin (f = 4, centre (4, 3)): v0 looks down +z, v1 down -z."""
    frames = []
    for i, flip in enumerate((1.0, -1.0)):
        w2c = torch.eye(4)
        w2c[:3, :3] = torch.diag(torch.tensor([1.0, flip, flip]))
        k = torch.tensor([[4.0, 0, 4], [0, 4.0, 3], [0, 0, 1]])
        frames.append(Frame(f"v{i}", Camera(w2c, k, 8, 6), torch.zeros(3, 6, 8)))
    return SceneData({"train": frames}, source="src")


def test_check_scene_default_min_in_front_is_5_percent():
    from controlgs_adapter.datasets.sanity import check_scene

    # 100 points: 5 straight ahead of v0 (5 % -> not blind: the threshold is strict), 4 straight ahead of
    # v1 (4 % -> blind), 91 far to the side (outside both images or behind)
    pts = torch.cat([torch.tensor([[0.0, 0, 1]]).repeat(5, 1), torch.tensor([[0.0, 0, -1]]).repeat(4, 1),
                     torch.tensor([[10.0, 0, 1]]).repeat(91, 1)])
    data = _two_cameras()
    with pytest.warns(RuntimeWarning, match=r"^src: 1 of 2 cameras see almost none of the 100 points \(< 5% in front, "
                                            r"inside the image\): v1$"):
        rep = check_scene(data, pts)
    assert rep["in_front"] == pytest.approx({"v0": 0.05, "v1": 0.04}, abs=1e-6) and rep["blind"] == ["v1"]
    assert check_scene(data, pts, min_in_front=0.035)["blind"] == []
    with pytest.raises(InputValueError, match=r"^src: 2 of 2 cameras see none of the scene"):
        check_scene(data, pts, min_in_front=0.051)
    # default required=("train",): an empty test split passes, an empty train split is refused
    with pytest.raises(InputValueError, match=r"^src: the 'train' split is empty \(splits: train=0, test=2\)$"):
        check_scene(SceneData({"train": [], "test": data.splits["train"]}, source="src"))


W_2, H_2, F = 8, 6, 10.0


#: OpenCV camera at the origin looking down +z, and one turned round (looking down -z)
FRONT = torch.eye(4)


BACK = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))


def _camera_2(w2c: torch.Tensor = FRONT, w: int = W_2, h: int = H_2, f: float = F) -> Camera:
    k = torch.tensor([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
    return Camera(w2c.clone(), k, w, h)


def _scene(poses: list[torch.Tensor], *, source: str = "mem") -> SceneData:
    frames = [Frame(f"v{i:02d}", _camera_2(p), torch.zeros(3, H_2, W_2)) for i, p in enumerate(poses)]
    return SceneData({"train": frames, "test": []}, source=source, format="builtin")


def _blind_warning(n_seeing: int, n_blind: int) -> str:
    data = _scene([FRONT] * n_seeing + [BACK] * n_blind)
    pts = torch.tensor([[0.0, 0.0, 1.0], [0.1, 0.1, 2.0]])
    with pytest.warns(RuntimeWarning) as rec:
        check_scene(data, pts)
    return str(rec[0].message)


def test_check_scene_counts_points_left_of_or_above_the_image_as_outside():
    """A point in front of the camera but projecting to u < 0 (or v < 0) is not "inside the image":
    by hand with f = 10, c = (4, 3): (0, 0, 1) -> (4, 3) inside, (-1, 0, 1) -> u = -6, (0, -1, 1) -> v = -7."""
    pts = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 1.0], [0.0, -1.0, 1.0]])
    report = check_scene(_scene([FRONT]), pts, min_in_front=0.0)
    assert report["in_front"] == {"v00": pytest.approx(1 / 3)}


def test_check_scene_refuses_non_finite_points():
    pts = torch.tensor([[0.0, 0.0, 1.0], [float("nan"), 0.0, 1.0]])
    with pytest.raises(InputValueError, match="points contains 1 non-finite"):
        check_scene(_scene([FRONT]), pts)


def test_check_scene_with_no_points_reports_no_fractions():
    """``in_front`` is documented empty without points; an empty ``[0, 3]`` tensor is no points."""
    report = check_scene(_scene([FRONT, BACK]), torch.zeros(0, 3))
    assert report["in_front"] == {} and report["blind"] == [] and report["points"] == 0


def test_check_scene_projects_an_even_stride_of_at_most_20000_points():
    """sanity.py's ``_MAX_POINTS`` doc comment: at most 20,000 points per camera, an even stride
    through the given ones; 20,001 points take every 2nd (10,001), and the fraction is that of those."""
    n = 20_001
    pts = torch.zeros(n, 3)
    pts[:, 2] = 1.0
    pts[1::2, 0] = -1.0          # every odd point projects left of the image; the stride keeps only even ones
    report = check_scene(_scene([FRONT]), pts)
    assert report["points"] == len(range(0, n, 2)) == 10_001
    assert report["in_front"]["v00"] == 1.0


def test_check_scene_warning_names_up_to_five_blind_cameras_and_marks_more():
    """Five blind cameras are all named with nothing after them; a sixth is left out as ", ..."."""
    msg = _blind_warning(6, 5)
    assert msg.endswith(": v06, v07, v08, v09, v10")
    msg = _blind_warning(7, 6)
    assert msg.endswith(": v07, v08, v09, v10, v11, ...")


def test_check_scene_counts_points_in_the_camera_plane_as_behind():
    """Depth 0 is not in front (Camera.project: "Depth <= 0 is behind"): points in the plane of every
    camera make all of them blind and the message reports 100 % behind."""
    pts = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(InputValueError, match=r"on average 100% lie behind the cameras"):
        check_scene(_scene([FRONT, FRONT]), pts)
