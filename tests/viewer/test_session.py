"""Tests of ``controlgs_adapter.viewer.session``: the view state (``parse_state`` on good, bad and hostile values),
orbiting cameras about the scene centre, the strength heat overlay, PNG encoding, the render caches, and a session
on the built-in scene (strengths, difference images, metrics, superseded work)."""

from __future__ import annotations

import base64
import dataclasses
import io
import json
import math
from typing import Any

import numpy as np
import pytest
import torch
from helpers.banks import affine_bank
from helpers.viewer_sessions import SIZE, builtin_session, decode_png
from PIL import Image

from controlgs_adapter import plugins
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.visual_angles import VisualAngles
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import evaluate_grid
from controlgs_adapter.rendering import FunctionRenderer
from controlgs_adapter.state import Camera
from controlgs_adapter.viewer import OPTICS_MODES, STAGES, Superseded, ViewerSession
from controlgs_adapter.viewer import session as vs
from controlgs_adapter.viewer.session import (
    ViewState,
    _Cache,
    _rotation,
    _shared_copy,
    encode_png,
    heat_overlay,
    orbit_camera,
    parse_state,
    scene_centre,
)

needs_optics = pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")

HUGE = 10**400  # what json.loads makes of a 401-digit number
K16 = torch.tensor([[10.0, 0.0, 8.0], [0.0, 10.0, 8.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A 16 px session with the ControlGS adapter, its state-blind ablation and one on the foveation and display
    modules."""
    return builtin_session(tmp_path_factory.mktemp("viewer"), {"controlgs": {}, "blind": {"state_blind": True},
                                                               "fov": {"modules": ("foveation", "display")}})


def _nested(depth: int) -> Any:
    out: Any = 0.5
    for _ in range(depth):
        out = [out]
    return out


def _looking(centre: tuple[float, ...], forward: tuple[float, ...]) -> Camera:
    """A 16 x 16 float64 camera at ``centre`` looking along the horizontal unit ``forward`` (OpenCV axes, y down)."""
    f = torch.tensor(forward, dtype=torch.float64)
    d = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    r = torch.linalg.cross(d, f)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = torch.stack([r, d, f])
    w2c[:3, 3] = -(w2c[:3, :3] @ torch.tensor(centre, dtype=torch.float64))
    return Camera(w2c, K16.double(), 16, 16)


def _look_at(eye: tuple[float, float, float], target: tuple[float, float, float], size: int = 12) -> Camera:
    """A float32 pinhole camera at ``eye`` looking at ``target`` (OpenCV axes: x right, y down, z forward)."""
    c, t = torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64)
    z = (t - c) / (t - c).norm()
    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    if abs(float(z[1])) > 0.9:
        up = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    r = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = r, -(r @ c)
    k = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]])
    return Camera(w2c.float(), k, size, size)


def _cam_at_minus_z(dist: float = 4.0) -> Camera:
    """Identity rotation (OpenCV: x right, y down, z forward) at world (0, 0, -dist): looks at the origin."""
    w2c = torch.eye(4)
    w2c[2, 3] = dist
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, 8, 8)


def _pixel_point(cam: Camera, px: float, py: float, z: float = 1.0) -> list[float]:
    """World point seen at pixel centre (px + 0.5, py + 0.5) by an identity camera (fx = fy = 8)."""
    k = cam.intrinsics
    return [(px + 0.5 - float(k[0, 2])) / float(k[0, 0]) * z, (py + 0.5 - float(k[1, 2])) / float(k[1, 1]) * z, z]


def _heat_in_loops(pixels: list[tuple[int, int, float]], w: int, h: int) -> torch.Tensor:
    """heat_overlay's documented map in float64 loops: per pixel the mean strength of the anchors in
    the k x k window (k = 2 max(1, round(max(h, w) / 48)) + 1, clipped at the borders), coloured on the
    4-stop heat map; alpha 0.55 min(1, 4 k^2 (anchors in the window) / (window pixels in the image))."""
    heat = [[0.0, 0.0, 0.2], [0.45, 0.05, 0.55], [0.9, 0.35, 0.1], [1.0, 0.95, 0.3]]
    r = max(1, round(max(h, w) / 48))
    k = 2 * r + 1
    out = torch.zeros(4, h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            inside = [(u, v) for v in range(y - r, y + r + 1) for u in range(x - r, x + r + 1) if 0 <= u < w and 0 <= v < h]
            hits = [s for (u, v, s) in pixels if (u, v) in inside]
            lam = min(max(sum(hits) / len(hits), 0.0), 1.0) if hits else 0.0
            t = lam * 3
            i = min(math.floor(t), 2)
            for c in range(3):
                out[c, y, x] = heat[i][c] + (t - i) * (heat[i + 1][c] - heat[i][c])
            out[3, y, x] = 0.55 * min(1.0, k * k * 4.0 * len(hits) / len(inside))
    return out


# ----------------------------------------------------------------------------- the view state

def test_view_state_defaults_and_constants() -> None:
    d = parse_state({}, 3)
    assert d == ViewState() and parse_state({}, 2) == ViewState()
    assert (d.view, d.azimuth, d.elevation, d.downsample, d.power_saving, d.optics, d.stages, d.gaze) == (
        0, 0.0, 0.0, 2.0, 0.4, "fast", STAGES, None)
    assert STAGES == ("lens", "resample", "display", "oled", "optics", "foveation") and OPTICS_MODES == ("distortion", "fast", "exact")
    assert (vs.DOWNSAMPLE_RANGE, vs.POWER_SAVING_RANGE, vs.AZIMUTH_RANGE, vs.ELEVATION_RANGE, vs.DIFF_GAIN) == (
        (1.0, 8.0), (0.0, 0.8), (-180.0, 180.0), (-80.0, 80.0), 2.0)
    assert d.to_json() == {"view": 0, "azimuth": 0.0, "elevation": 0.0, "downsample": 2.0, "power_saving": 0.4,
                           "optics": "fast", "stages": list(STAGES), "gaze": None}
    assert not d.orbit and d.effects == {s: True for s in STAGES}
    r = d.runtime
    assert (r.downsample, r.power_saving, r.gaze) == (2.0, 0.4, None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        ViewState().view = 1  # type: ignore[misc]


def test_parse_state_values_effects_and_json_round_trip() -> None:
    """Stages in any order, duplicates kept once, in pipeline order (an empty list switches everything off); any
    azimuth or elevation is an orbit; the JSON form (lists, not tuples) parses back to the same state."""
    s = parse_state({"view": 1, "azimuth": -30, "elevation": 12.5, "downsample": 3.7, "power_saving": 0.25,
                     "optics": "exact", "stages": ["optics", "lens"], "gaze": [0.5, -1]}, 2)
    assert (s.view, s.azimuth, s.elevation, s.downsample, s.power_saving, s.optics) == (1, -30.0, 12.5, 3.7, 0.25, "exact")
    assert s.stages == ("lens", "optics") and s.gaze == (0.5, -1.0) and s.orbit
    assert s.effects == {"lens": True, "resample": False, "display": False, "oled": False, "optics": True, "foveation": False}
    assert s.runtime.downsample == 3.7 and s.runtime.gaze is None  # the session turns the click into degrees
    js = s.to_json()
    assert js["stages"] == ["lens", "optics"] and js["gaze"] == [0.5, -1.0]
    assert parse_state(json.loads(json.dumps(js)), 2) == s
    assert parse_state({"stages": ["optics", "lens", "optics"]}, 1).stages == ("lens", "optics")
    assert parse_state({"stages": []}, 1).stages == ()
    for optics in OPTICS_MODES:
        assert parse_state({"optics": optics}, 1).optics == optics
    assert parse_state({"elevation": 5}, 1).orbit and ViewState(azimuth=0.0, elevation=-5.0).orbit and ViewState(azimuth=3.0).orbit
    lens = ViewState(stages=("lens",), gaze=(0.25, -0.5))
    assert lens.effects == {"lens": True, "resample": False, "display": False, "oled": False, "optics": False,
                            "foveation": False}
    assert lens.runtime.gaze is None and lens.gaze == (0.25, -0.5)


def test_parse_state_bounds_are_inclusive() -> None:
    lo = parse_state({"view": 0, "azimuth": -180, "elevation": -80, "downsample": 1, "power_saving": 0,
                      "gaze": [-1, -1]}, 3)
    hi = parse_state({"view": 2, "azimuth": 180, "elevation": 80, "downsample": 8, "power_saving": 0.8,
                      "gaze": [1, 1]}, 3)
    assert (lo.view, lo.azimuth, lo.elevation, lo.downsample, lo.power_saving, lo.gaze) == (0, -180.0, -80.0, 1.0, 0.0, (-1.0, -1.0))
    assert (hi.view, hi.azimuth, hi.elevation, hi.downsample, hi.power_saving, hi.gaze) == (2, 180.0, 80.0, 8.0, 0.8, (1.0, 1.0))
    assert isinstance(hi.view, int) and not isinstance(hi.view, bool)
    for field, low, high in (("downsample", 1.0, 8.0), ("power_saving", 0.0, 0.8), ("azimuth", -180.0, 180.0),
                             ("elevation", -80.0, 80.0)):
        for v in (low - 1e-6, high + 1e-6):
            with pytest.raises(InputValueError, match=f"^{field} "):
                parse_state({field: v}, 1)


@pytest.mark.parametrize("data, pattern", [
    ({"view": -1}, r"^view .*\[0, 2\], got -1$"),
    ({"view": 3}, r"^view .*\[0, 2\], got 3$"),
    ({"view": 0.5}, r"^view must be an integer .*got 0\.5$"),
    ({"azimuth": -180.5}, r"^azimuth .*\[-180, 180\], got -180\.5$"),
    ({"azimuth": 200}, r"^azimuth .*got 200$"),
    ({"elevation": 80.5}, r"^elevation .*\[-80, 80\], got 80\.5$"),
    ({"elevation": -90}, r"^elevation .*got -90$"),
    ({"power_saving": -0.1}, r"^power_saving .*\[0, 0\.8\], got -0\.1$"),
    ({"power_saving": 0.9}, r"^power_saving .*got 0\.9$"),
    ({"downsample": 8.01}, r"^downsample .*\[1, 8\], got 8\.01$"),
    ({"downsample": 0.5}, r"^downsample .*got 0\.5$"),
    ({"downsample": "2"}, r"^downsample .*got '2'$"),
    ({"downsample": True}, r"^downsample .*got True$"),
    ({"downsample": float("nan")}, r"^downsample .*got nan$"),
    ({"stages": ["lens", 3]}, r"^stages must be a list .*got \['lens', 3\]$"),
    ({"stages": ("lens",)}, r"^stages must be a list .*got \('lens',\)$"),
    ({"stages": "lens"}, r"^stages must be a list .*got 'lens'$"),
    ({"stages": ["lens", "bloom"]}, r"^stages: unknown \['bloom'\]"),
    ({"gaze": "ab"}, r"^gaze .*got 'ab'$"),
    ({"gaze": [0, 0, 0]}, r"^gaze .*got \[0, 0, 0\]$"),
    ({"gaze": [0]}, r"^gaze .*got \[0\]$"),
    ({"gaze": [0, 1.5]}, r"^gaze y .*got 1\.5$"),
    ({"gaze": [-1.5, 0]}, r"^gaze x .*got -1\.5$"),
    ({"gaze": [2, 0]}, r"^gaze x .*got 2$"),
    ({"b": 1, "a": 2, "view": 0}, r"^unknown state field\(s\) \['a', 'b'\]; fields: view, azimuth, "),
    ({"zoom": 2}, r"^unknown state field\(s\) \['zoom'\]"),
    ({"optics": None}, r"^optics .*got None$"),
    ({"optics": "blur"}, r"^optics .*got 'blur'$"),
    ("view", r"^the state must be a JSON object .*got str$"),
    ([1, 2], r"^the state must be a JSON object .*got list$"),
])
def test_parse_state_refusals_name_the_field_and_value(data: Any, pattern: str) -> None:
    with pytest.raises(InputValueError, match=pattern):
        parse_state(data, 3)


@pytest.mark.parametrize("field", ["view", "azimuth", "elevation", "downsample", "power_saving"])
@pytest.mark.parametrize("value", [HUGE, -HUGE, float("nan"), float("inf"), True, "1", None, [1], {"a": 1}, _nested(500)],
                         ids=lambda v: type(v).__name__)
def test_parse_state_refuses_hostile_numbers(field: str, value: Any) -> None:
    with pytest.raises(InputValueError, match=rf"^{field} must be an? (integer|finite number) in ") as e:
        parse_state({field: value}, 2)
    assert "\n" not in str(e.value) and len(str(e.value)) < 200


def test_parse_state_takes_the_numbers_json_makes_of_a_long_literal() -> None:
    body = json.loads('{"downsample": 1' + "0" * 400 + ', "view": 1}')
    assert body["downsample"] == HUGE
    with pytest.raises(InputValueError, match=r"downsample must be a finite number in \[1, 8\], got an int of about 401"):
        parse_state(body, 2)
    assert parse_state({"view": 1, "downsample": 8}, 2).downsample == 8.0


@pytest.mark.parametrize("data, field", [({"gaze": [HUGE, 0]}, "gaze x"), ({"gaze": [0, float("-inf")]}, "gaze y"),
                                         ({"gaze": _nested(500)}, "gaze"), ({"gaze": [_nested(500), 0]}, "gaze x"),
                                         ({"stages": _nested(500)}, "stages"), ({"stages": [_nested(500)]}, "stages"),
                                         ({"optics": _nested(500)}, "optics"), ({"optics": {"fast": 1}}, "optics"),
                                         ({"optics": HUGE}, "optics")])
def test_parse_state_refuses_hostile_values_in_one_short_line(data: dict[str, Any], field: str) -> None:
    with pytest.raises(InputValueError, match=rf"^{field}[ :]") as e:
        parse_state(data, 2)
    assert "\n" not in str(e.value) and len(str(e.value)) < 300


# ----------------------------------------------------------------------------- orbit, rotation and scene centre

def test_orbit_camera_directions() -> None:
    cam, o = _cam_at_minus_z(), torch.zeros(3, dtype=torch.float64)
    # azimuth 90 about the up axis -y (right-handed): (0, 0, -4) -> (4, 0, 0), to the scene's right (+x);
    # the camera keeps its up row (0, 1, 0) and now looks along -x; x row = y row cross z row = (0, 0, 1)
    right = orbit_camera(cam, o, 90.0, 0.0)
    assert torch.allclose(right.center.double(), torch.tensor([4.0, 0.0, 0.0], dtype=torch.float64), atol=1e-5)
    want = torch.tensor([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 4.0], [0.0, 0.0, 0.0, 1.0]])
    assert torch.allclose(right.world_to_camera, want, atol=1e-6)
    assert right.world_to_camera.dtype == cam.world_to_camera.dtype
    assert (right.width, right.height) == (8, 8) and torch.equal(right.intrinsics, cam.intrinsics)
    # elevation 90: up, i.e. to world -y (OpenCV y points down): (0, -4, 0), looking along +y
    up = orbit_camera(cam, o, 0.0, 90.0)
    assert torch.allclose(up.center.double(), torch.tensor([0.0, -4.0, 0.0], dtype=torch.float64), atol=1e-5)
    assert torch.allclose(up.world_to_camera[2, :3], torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert torch.allclose(up.world_to_camera[0, :3], torch.tensor([1.0, 0.0, 0.0]), atol=1e-6)  # right unchanged
    # about another centre: the camera turns about it, not about the origin
    c = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # 5 in front of the camera
    moved = orbit_camera(cam, c, -90.0, 0.0)  # to the left: (-5, 0, 1)
    assert torch.allclose(moved.center.double(), torch.tensor([-5.0, 0.0, 1.0], dtype=torch.float64), atol=1e-5)
    # azimuth then elevation: 90 right then 90 up from (0, 0, -4) ends above the centre
    both = orbit_camera(cam, o, 90.0, 90.0)
    assert torch.allclose(both.center.double(), torch.tensor([0.0, -4.0, 0.0], dtype=torch.float64), atol=1e-5)
    # a float64 pose stays float64: 30 degrees about up (-y) takes (0, 0, -4) to 4 (sin 30, 0, -cos 30) exactly
    cam64 = Camera(cam.world_to_camera.double(), cam.intrinsics, 8, 8)
    turned = orbit_camera(cam64, o, 30.0, 0.0)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    assert turned.world_to_camera.dtype == torch.float64
    assert torch.allclose(turned.center.double(), torch.tensor([4 * s, 0.0, -4 * c], dtype=torch.float64), rtol=0, atol=1e-14)


def test_orbit_camera_never_attaches_the_camera_to_its_inputs_graph():
    """Orbiting is a viewer move: a centre or camera pose that requires grad gives a camera whose pose does
    not (and the same pose as from detached inputs)."""
    cam = _look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    centre = torch.tensor([0.1, -0.2, 0.3], requires_grad=True)
    w2c = cam.world_to_camera.clone().requires_grad_(True)
    live = Camera(w2c, cam.intrinsics, cam.width, cam.height)
    out = orbit_camera(live, centre, 30.0, -10.0)
    want = orbit_camera(cam, centre.detach(), 30.0, -10.0)
    assert not out.world_to_camera.requires_grad
    assert torch.equal(out.world_to_camera, want.world_to_camera)


def test_orbit_camera_turns_about_the_scene_centre(small: Any) -> None:
    _, scene = small
    cam = scene.test_cameras[0]
    centre = scene_centre(scene.test_cameras + scene.train_cameras, None)
    assert torch.allclose(centre, torch.tensor([0.0, 0.35, 0.0], dtype=torch.float64), atol=1e-4)  # the arc's target
    same = orbit_camera(cam, centre, 0.0, 0.0)
    assert torch.allclose(same.world_to_camera, cam.world_to_camera, atol=1e-6)
    up = -cam.world_to_camera[1, :3].double()
    for az, el in ((40.0, 0.0), (0.0, 30.0), (-120.0, -20.0)):
        moved = orbit_camera(cam, centre, az, el)
        c0, c1 = cam.center.double(), moved.center.double()
        assert abs(float((c1 - centre).norm() - (c0 - centre).norm())) < 1e-4          # same distance
        look = moved.to_camera(centre[None].float())[0]
        assert abs(float(look[0])) < 1e-3 and abs(float(look[1])) < 1e-3                # still looks at it
        if el:
            assert (float((c1 - c0) @ up) > 0) == (el > 0)                               # elevation > 0: up


def test_rotation_is_rodrigues_exact_in_float64():
    """The viewer's Rodrigues rotation keeps its axis' float64: about z it is the closed form to 1e-15, and
    about a skew axis orthonormal to 1e-14 with the axis fixed (float32 would leave ~1e-8 errors)."""
    t = math.radians(37.0)
    want = torch.tensor([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]],
                        dtype=torch.float64)
    r = _rotation(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), 37.0)
    assert r.dtype == torch.float64 and torch.allclose(r, want, rtol=0, atol=1e-15)
    r90 = _rotation(torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64), 90.0)  # the axis is normalised
    assert torch.allclose(r90, torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64), atol=1e-12)
    r30 = _rotation(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), 30.0)
    c, s = 3**0.5 / 2, 0.5
    assert torch.allclose(r30, torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=torch.float64), atol=1e-12)
    axis = torch.tensor([0.3, -0.7, 0.64], dtype=torch.float64)
    r = _rotation(axis, 123.4)
    assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-14)
    assert torch.allclose(r @ axis, axis, rtol=0, atol=1e-14)


def test_scene_centre_is_where_the_axes_meet_and_never_joins_the_poses_graph():
    """Cameras looking at one point: the centre is that point (least squares of the axes, exact here);
    poses that require grad (a camera being optimised) give a plain tensor, the same as detached poses."""
    target = (0.3, -0.2, 0.5)
    cams = [_look_at(e, target) for e in ((0.0, 0.0, -3.0), (3.0, 0.5, 0.0), (-1.0, -2.0, 2.0))]
    live = [Camera(c.world_to_camera.clone().requires_grad_(True), c.intrinsics, c.width, c.height) for c in cams]
    got = scene_centre(live, None)
    assert not got.requires_grad and got.grad_fn is None
    assert got.dtype == torch.float64 and got.shape == (3,)
    assert torch.allclose(got, torch.tensor(target, dtype=torch.float64), atol=1e-5)
    assert torch.equal(got, scene_centre(cams, None))


def test_scene_centre_falls_back_to_the_median_then_the_origin():
    """Axes meeting in front: their meeting point; meeting behind, parallel or one camera: the anchors'
    per-axis median; no anchors either: the origin."""
    t = (0.5, -1.0, 2.0)
    front = [_looking((t[0] - 3, t[1], t[2]), (1.0, 0.0, 0.0)), _looking((t[0], t[1], t[2] - 3), (0.0, 0.0, 1.0))]
    behind = [_looking((t[0] - 3, t[1], t[2]), (-1.0, 0.0, 0.0)), _looking((t[0], t[1], t[2] - 3), (0.0, 0.0, -1.0))]
    parallel = [_looking((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), _looking((1.0, 0.0, 0.0), (0.0, 0.0, 1.0))]
    points = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [5.0, -2.0, 3.0]])
    median = torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(scene_centre(front, points), torch.tensor(t, dtype=torch.float64), atol=1e-12, rtol=0)
    for cams in (behind, parallel, front[:1]):
        torch.testing.assert_close(scene_centre(cams, points), median, atol=0, rtol=0)
        assert torch.equal(scene_centre(cams, None), torch.zeros(3, dtype=torch.float64))
        assert torch.equal(scene_centre(cams, torch.zeros(0, 3)), torch.zeros(3, dtype=torch.float64))
        assert scene_centre(cams, torch.ones(2, 3)).dtype == torch.float64
    # two converging cameras: (0, 0, -4) looking +z and (4, 0, 0) looking -x meet at the origin
    w2c = torch.tensor([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 4.0], [0.0, 0.0, 0.0, 1.0]])
    got = scene_centre([_cam_at_minus_z(), Camera(w2c, _cam_at_minus_z().intrinsics, 8, 8)], points)
    assert torch.allclose(got, torch.zeros(3, dtype=torch.float64), atol=1e-6)


# ----------------------------------------------------------------------------- heat overlay and PNG encoding

def test_heat_overlay_pixels() -> None:
    cam = Camera(torch.eye(4), torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]), 8, 8)
    # k = 2 max(1, round(8 / 48)) + 1 = 3: each anchor spreads over its 3x3 neighbourhood
    pos = torch.tensor([_pixel_point(cam, 2, 5), _pixel_point(cam, 6, 0), _pixel_point(cam, 2, 1), _pixel_point(cam, 2, 1),
                        [0.0, 0.0, -1.0],                                 # behind the camera
                        _pixel_point(cam, 9, 2),                          # right of the image
                        _pixel_point(cam, -1, 2),                         # left of it
                        _pixel_point(cam, 5, 5)])                         # a non-finite strength
    strength = torch.tensor([0.5, 1.0, 0.2, 0.6, 1.0, 1.0, 1.0, float("nan")])
    out = heat_overlay(pos, strength, cam)
    assert out.shape == (4, 8, 8)
    # the map's colours: black-blue (0, 0, 0.2), purple (0.45, 0.05, 0.55), orange (0.9, 0.35, 0.1), yellow (1, 0.95, 0.3)
    # lam 0.5 -> t = 1.5: halfway between purple and orange; lam 1: yellow; two anchors in a pixel: the mean 0.4
    # -> t = 1.2: purple + 0.2 (orange - purple)
    cases = (((2, 5), [0.675, 0.2, 0.325]), ((6, 0), [1.0, 0.95, 0.3]), ((2, 1), [0.54, 0.11, 0.46]))
    for (x, y), colour in ((xy, torch.tensor(c)) for xy, c in cases):
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                if 0 <= x + dx < 8 and 0 <= y + dy < 8:
                    assert torch.allclose(out[:3, y + dy, x + dx], colour, atol=1e-6), (x + dx, y + dy)
                    assert out[3, y + dy, x + dx] == pytest.approx(0.55)
    covered = torch.zeros(8, 8, dtype=torch.bool)
    covered[4:7, 1:4] = covered[0:2, 5:8] = covered[0:3, 1:4] = True
    assert torch.equal(out[3] > 0, covered)  # nothing from the culled anchors
    assert torch.allclose(out[:3, ~covered], torch.tensor([[0.0], [0.0], [0.2]]), atol=1e-7)  # lam 0: the first colour
    # the window: k = 2 max(1, round(size / 48)) + 1 (72 / 48 = 1.5 -> 2)
    for size, half in ((72, 2), (96, 2), (8, 1), (144, 3)):  # k = 2 max(1, round(size / 48)) + 1; 72 / 48 = 1.5 -> 2
        cam = Camera(torch.eye(4), torch.tensor([[8.0, 0.0, size / 2], [0.0, 8.0, size / 2], [0.0, 0.0, 1.0]]), size, size)
        c = size // 2
        out = heat_overlay(torch.tensor([_pixel_point(cam, c, c)]), torch.tensor([1.0]), cam)
        row = (out[3, c] > 0).nonzero().squeeze(1)
        assert row.tolist() == list(range(c - half, c + half + 1)), size


@pytest.mark.parametrize("w,h", [(20, 12), (100, 30)])  # k = 3 and k = 5
def test_heat_overlay_against_loops(w, h):
    f, cx, cy = 10.0, w / 2, h / 2
    cam = Camera(torch.eye(4), torch.tensor([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]]), w, h)
    landing = [(0, 0, 0.2), (3, 2, 0.9), (3, 2, 0.5), (w - 1, h - 1, 1.0), (w // 2, h // 2, 0.35), (7, 5, 1.7)]
    pts = [[(u + 0.5 - cx) / f * z, (v + 0.5 - cy) / f * z, z] for (u, v, _), z in zip(landing, (1.0, 2.0, 1.0, 3.0, 1.0, 1.0))]
    strength = [s for (_, _, s) in landing]
    # dropped: behind the camera, left of / below the image, a NaN strength
    pts += [[0.0, 0.0, -1.0], [(-0.5 - cx) / f, 0.0, 1.0], [0.0, (h + 0.5 - cy) / f, 1.0], [(5.5 - cx) / f, (5.5 - cy) / f, 1.0]]
    strength += [1.0, 1.0, 1.0, float("nan")]
    got = heat_overlay(torch.tensor(pts, dtype=torch.float64), torch.tensor(strength), cam)
    assert got.shape == (4, h, w)
    torch.testing.assert_close(got.double(), _heat_in_loops(landing, w, h), atol=1e-5, rtol=0)


@pytest.mark.parametrize("channels,mode", [(3, "RGB"), (4, "RGBA")])
def test_encode_png_rounds_to_nearest_and_clamps(channels, mode):
    import base64


    # x * 255: 127.5 -> 128, 127.49 -> 127, 0.51 -> 1, 0.49 -> 0, 254.6 -> 255; out of [0, 1] clamps
    values = torch.tensor([127.5, 127.49, 0.51, 0.49, 254.6, -20.0, 300.0, 255.0]) / 255.0
    image = values.view(1, 2, 4).expand(channels, 2, 4).clone()
    image[0, 0, 0] = 1.0  # channels differ: the channel order shows
    png = Image.open(io.BytesIO(base64.b64decode(encode_png(image))))
    assert png.mode == mode and png.size == (4, 2)
    got = torch.from_numpy(np.asarray(png).astype(np.int64)).permute(2, 0, 1)
    want = torch.tensor([128, 127, 1, 0, 255, 0, 255, 255]).view(1, 2, 4).expand(channels, 2, 4).clone()
    want[0, 0, 0] = 255
    assert torch.equal(got, want)
    rgba = torch.cat([torch.full((3, 2, 3), 0.5), torch.full((1, 2, 3), 0.2)])
    assert torch.equal(decode_png(encode_png(rgba))[..., 3], torch.full((2, 3), 51.0))  # round(0.2 * 255)


def test_encode_png_compresses() -> None:
    """Low compression (level 1), not none: a flat 64 x 64 image is well under its 12 kB of raw pixels."""
    png = base64.b64decode(encode_png(torch.full((3, 64, 64), 0.5)))
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) < 1000
    assert len(base64.b64decode(encode_png(torch.full((3, 64, 64), 0.5), level=0))) > 12000  # stored: raw size


# ----------------------------------------------------------------------------- caches and copies

def test_cache_evicts_the_least_recently_used():

    made: list[str] = []
    cache = _Cache(2)

    def get(key: str) -> str:
        return cache.get_or(key, lambda: made.append(key) or key.upper())

    assert [get("a"), get("b"), get("a")] == ["A", "B", "A"] and made == ["a", "b"]  # a hit makes nothing
    get("c")  # over the size: b (used least recently) goes, a (just used) stays
    assert list(cache) == ["a", "c"] and made == ["a", "b", "c"]
    get("b")
    assert list(cache) == ["c", "b"] and made == ["a", "b", "c", "b"]


def test_shared_copy_shares_tensors_not_modules() -> None:
    model = torch.nn.Sequential(torch.nn.Linear(2, 2), torch.nn.BatchNorm1d(2))
    model.extra = torch.ones(3)  # type: ignore[assignment]  # a plain tensor attribute
    cp = _shared_copy(model)
    assert cp is not model and cp[0] is not model[0]
    assert cp[0].weight is model[0].weight and cp[1].running_mean is model[1].running_mean and cp.extra is model.extra

    class Plain:
        def __init__(self) -> None:
            self.t = torch.zeros(2)
            self.mlp = torch.nn.Linear(1, 1)

    p = Plain()
    q = _shared_copy(p)
    assert q is not p and q.t is p.t and q.mlp is not p.mlp


# ----------------------------------------------------------------------------- the session

def test_the_session_pipelines_simulate_its_lens() -> None:
    """``lens=``: every pipeline the page asks for holds that lens's bank (the optics) and chief rays (the lens
    stage, no fitted LUT: with a warning); without it, the shipped Cardboard bank."""
    from controlgs_adapter.downstream.bank_maps import BankMap
    from controlgs_adapter.downstream.optics.bank import PSFBank
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    bank = affine_bank([[1.02, 0.0], [0.0, 0.98]], [0.01, 0.0])
    views = load_builtin_scene("ar", SIZE, views=4, test_every=4, samples=1).views("test")
    model = load_builtin_backbone("ar")
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        pipe = ViewerSession(model, views, {}, lens=bank)._pipeline(ViewState())
    assert pipe["optics"].bank is bank and isinstance(pipe["lens"].map, BankMap) and pipe["lens"].map.bank is bank
    assert ViewerSession(model, views, {})._pipeline(ViewState())["optics"].bank is PSFBank.default()


def test_small_refuses_baseline_names_and_no_views():
    with pytest.raises(InputValueError, match=r"adapter names \['ss'\] clash with the baselines \('no_ss', 'ss'\)"):
        ViewerSession(None, [object()], {"controlgs": "a.safetensors", "ss": "b.safetensors"})
    with pytest.raises(InputValueError, match=r"adapter names \['no_ss'\] clash"):
        ViewerSession(None, [object()], {"no_ss": "a.safetensors"})
    with pytest.raises(InputValueError, match="the viewer needs at least one view"):
        ViewerSession(None, [], {})


def test_render_matches_evaluate_grid(small: Any) -> None:
    """Each method's PSNR / SSIM and extra metrics are evaluate_grid's at the same state; the images have the
    display size (the no-SS render the reduced one); global strengths are their closed forms, the lens strength
    a per-anchor range; extra metrics of an older render are superseded."""
    session, _ = small
    state = parse_state({"view": 0, "downsample": 2.6, "power_saving": 0.3}, 1)
    out = session.render(state, tag=7)
    assert [m["name"] for m in out["methods"]] == ["no_ss", "ss", "controlgs", "blind", "fov"] and out["has_truth"]
    grid = evaluate_grid(session.model, session.views, session.adapter_files, downsample=[2.6], power_saving=[0.3],
                         ideal=False, progress=False)
    extra = session.extra(7)
    for m in out["methods"]:
        for k in ("psnr", "ssim"):
            assert m["metrics"][k] == pytest.approx(float(grid.per_view[m["name"]][k][0, 0, 0]), abs=1e-9)
        for k, v in extra[m["name"]].items():
            assert v == pytest.approx(float(grid.per_view[m["name"]][k][0, 0, 0]), abs=1e-9)
        assert decode_png(m["eye"]).shape == (SIZE, SIZE, 3) and decode_png(m["diff"]).shape == (SIZE, SIZE, 3)
    no_ss, _, cgs = out["methods"][:3]
    assert decode_png(no_ss["rendered"]).shape == (round(SIZE / 2.6), round(SIZE / 2.6), 3)
    assert cgs["strengths"]["resample"] == pytest.approx(torch.log2(torch.tensor(2.6)).item() / 3, abs=1e-6)
    assert cgs["strengths"]["display"] == pytest.approx(0.3 / 0.8, abs=1e-6)
    assert 0.0 <= cgs["strengths"]["lens"]["min"] <= cgs["strengths"]["lens"]["mean"] <= cgs["strengths"]["lens"]["max"] <= 1
    overlay = decode_png(cgs["overlay"])
    assert overlay.shape == (SIZE, SIZE, 4) and overlay[..., 3].max() > 0
    with pytest.raises(Superseded):
        session.extra(6)


def test_session_render_strengths_diffs_and_extra(small: Any) -> None:
    session, _ = small
    cam = session.cameras[0]
    square = VisualAngles.of_bank(PSFBank.default())  # a square image spans the Cardboard display
    for click in ((0.0, 0.0), (0.5, -0.25), (1.0, 1.0)):
        rs = session.runtime(parse_state({"downsample": 4.0, "gaze": list(click)}, 1), cam)
        inside = [min(max(v, -0.999), 0.999) for v in click]
        want = square.directions(torch.tensor(inside, dtype=torch.float64)).tolist()
        assert rs.downsample == 4.0 and rs.gaze == pytest.approx(tuple(want), abs=1e-12) and square.in_field(rs.gaze)
    out = session.render(parse_state({"downsample": 4.0, "power_saving": 0.8, "gaze": [0.0, 0.0]}, 1), tag=11)
    assert out["size"] == [SIZE, SIZE] and out["has_truth"] and out["server_ms"] >= 0
    by = {m["name"]: m for m in out["methods"]}
    assert by["no_ss"]["rendered_size"] == [SIZE // 4, SIZE // 4] and by["ss"]["rendered_size"] == [SIZE, SIZE]
    assert by["ss"]["strengths"] == {} and by["ss"]["overlay"] is None
    # resample log2(4) / log2(8) = 2/3, display 0.8 / 0.8 = 1; the state-blind ablation: 1 for every module
    s = by["controlgs"]["strengths"]
    assert s["resample"] == pytest.approx(2 / 3, abs=1e-6) and s["display"] == pytest.approx(1.0, abs=1e-6)
    lens = s["lens"]
    assert set(lens) == {"mean", "min", "max"} and lens["min"] < lens["mean"] < lens["max"]
    assert by["blind"]["strengths"] == {"lens": 1.0, "resample": 1.0, "display": 1.0}
    fov = by["fov"]["strengths"]
    assert set(fov) == {"foveation", "display"} and isinstance(fov["foveation"], dict)
    for name in ("controlgs", "blind", "fov"):  # the lens (else foveation) strength as an RGBA overlay
        assert decode_png(by[name]["overlay"]).shape == (SIZE, SIZE, 4)
    # difference image: |eye - gt| x 2, clipped, within one PNG level
    tag, eyes, gt = session._last
    assert tag == 11 and gt is not None
    for name, eye in eyes.items():
        want = ((eye - gt).abs() * 2.0).clamp(0, 1).permute(1, 2, 0) * 255
        assert (decode_png(by[name]["diff"]) - want).abs().max() <= 0.51, name
        assert float(eye.min()) >= 0 and float(eye.max()) <= 1
    extra = session.extra(11)
    assert set(extra) == set(by) if session.extra_metrics else extra == {}


def test_session_extra_without_truth_or_metrics(small: Any) -> None:
    session, _ = small
    truth, metrics = session.truth, session.extra_metrics
    try:
        session.truth = None
        session.render(parse_state({"azimuth": 30}, 1), tag=21)
        assert session.extra(21) == {}  # no ground truth off the dataset views
        session.truth = truth
        session.render(parse_state({}, 1), tag=22)
        session.extra_metrics = {"neg": lambda a, b: float("nan"), "one": lambda a, b: 1.0}
        got = session.extra(22)
        assert got["ss"] == {"neg": None, "one": 1.0} and len(got) == 5  # non-finite values: None
        calls: list[int] = []
        session.extra(22, lambda: calls.append(1))
        assert len(calls) == 5  # one check per method
        session.extra_metrics = {}
        assert session.extra(22) == {}
    finally:
        session.truth, session.extra_metrics = truth, metrics


def test_strengths_of_a_camera_that_sees_no_anchor(small: Any) -> None:
    """Looking away from the scene: no visible anchor; per-anchor strengths report 0 (mean, min, max), the
    state-blind ablation its constant 1, global ones their value; no overlay pixel."""
    session, _ = small
    cam = session.cameras[0]
    w2c = cam.world_to_camera.clone()  # turned half a circle about its own y axis: the scene is behind it
    w2c[:3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0])) @ w2c[:3, :3]
    w2c[:3, 3] = -(w2c[:3, :3] @ cam.center)
    blind_cam = Camera(w2c, cam.intrinsics, cam.width, cam.height)
    rs = parse_state({"downsample": 4.0, "power_saving": 0.4}, 1).runtime
    copy_, cgs = session.adapters["controlgs"]
    assert int(torch.as_tensor(session.renderer.visible(copy_, blind_cam)).sum()) == 0  # the case under test
    strengths, overlay = session._strengths(cgs, copy_, blind_cam, rs)
    assert strengths["lens"] == {"mean": 0.0, "min": 0.0, "max": 0.0}
    assert strengths["resample"] == pytest.approx(2 / 3, abs=1e-6) and strengths["display"] == pytest.approx(0.5, abs=1e-6)
    assert float(decode_png(overlay)[..., 3].max()) == 0.0
    copy_, cgs = session.adapters["blind"]
    strengths, _ = session._strengths(cgs, copy_, blind_cam, rs)
    assert strengths == {"lens": 1.0, "resample": 1.0, "display": 1.0}


def test_session_with_a_renderer_of_its_own_and_no_adapter(small: Any) -> None:
    session, scene = small
    calls: list[int] = []

    def render(m: Any, c: Any, v: Any, bg: Any) -> torch.Tensor:
        calls.append(c.width)
        return m.render(c, v, bg).color

    plain = ViewerSession(session.model, scene.views("test"), {}, renderer=FunctionRenderer(render,
                          visible=lambda m, c: m.visible_anchors(c)))
    assert plain.methods == ["no_ss", "ss"] and plain.info()["orbit_truth"] is False
    out = plain.render(parse_state({"downsample": 4.0}, 1))  # default tag 0
    assert sorted(calls) == [SIZE // 4, SIZE] and isinstance(out["server_ms"], float)
    assert plain.extra(0) == {} or set(plain.extra(0)) == {"no_ss", "ss"}
    assert plain.background is not None and torch.equal(plain.background, scene.views("test").background)


def test_state_independent_renders_are_cached(small: Any) -> None:
    session, _ = small
    session.render(parse_state({"downsample": 2.0}, 2))
    frames, small = len(session._frames), len(session._small)
    a = session.render(parse_state({"downsample": 2.01, "power_saving": 0.7}, 2))  # same display size, same view
    assert (len(session._frames), len(session._small)) == (frames, small)
    b = session.render(parse_state({"downsample": 2.01, "power_saving": 0.1}, 2))
    assert a["methods"][1]["rendered"] == b["methods"][1]["rendered"] and a["methods"][1]["eye"] != b["methods"][1]["eye"]


def test_stages_off_and_orbit(small: Any) -> None:
    session, _ = small
    out = session.render(parse_state({"stages": ["resample", "display"], "downsample": 3}, 2))
    assert out["methods"][1]["stages_run"] == ["resample", "display"]
    assert decode_png(out["methods"][1]["eye"]).shape == (SIZE, SIZE, 3)  # oled off: boxes at S for the metrics
    orbit = session.render(parse_state({"azimuth": 25, "elevation": 10}, 2))
    assert orbit["has_truth"] and orbit["methods"][0]["metrics"] is not None
    truth, session.truth = session.truth, None
    try:
        blind = session.render(parse_state({"azimuth": 26}, 2))
    finally:
        session.truth = truth
    assert not blind["has_truth"] and blind["gt"] is None and all(m["metrics"] is None for m in blind["methods"])


def test_check_drops_work_between_methods(small: Any) -> None:
    session, _ = small
    calls = []

    def check() -> None:
        calls.append(1)
        if len(calls) == 2:
            raise Superseded("newer")

    with pytest.raises(Superseded):
        session.render(parse_state({"downsample": 5.5}, 2), check)
    assert len(calls) == 2  # stopped after the first method


def test_frame_cache_keeps_the_16_most_recent_cameras(small: Any) -> None:
    session, _ = small
    session._frames.clear()
    first = session._frame(parse_state({"azimuth": 1.0}, 1))
    for az in range(2, 18):  # 16 more cameras: the first one is evicted by the 17th
        session._frame(parse_state({"azimuth": float(az)}, 1))
    assert len(session._frames) == 16
    assert (0, 1.0, 0.0) not in session._frames and (0, 2.0, 0.0) in session._frames
    again = session._frame(parse_state({"azimuth": 1.0}, 1))
    assert again is not first and torch.equal(again[2], first[2])  # rendered anew, the same image
    assert session._frame(parse_state({"azimuth": 1.0}, 1)) is again  # now cached


def test_no_ss_cache_keeps_the_32_most_recent_renders(small: Any) -> None:
    session, scene = small
    plain = ViewerSession(session.model, scene.views("test"), {})  # the two baselines only: cheap renders
    for az in range(1, 34):  # 33 orbit cameras, one no-SS render each: the first is evicted by the 33rd
        plain.render(parse_state({"azimuth": float(az), "stages": []}, 1))
    assert len(plain._small) == 32
    keys = [k[:3] for k in plain._small]
    assert (0, 1.0, 0.0) not in keys and (0, 2.0, 0.0) in keys and (0, 33.0, 0.0) in keys


@needs_optics
def test_viewer_renders_with_the_optics_mode_of_the_state(small: Any) -> None:
    """The state's ``optics`` (distortion, fast) is the optics stage's mode of that render: the
    session's PSNR / SSIM are :func:`evaluate_grid`'s at the same mode (session.render's docstring: "as
    evaluate_grid computes them"), and the modes give different eye images (the pipeline is cached per
    stage set, so a mode that never reached it would leave every render at the first one's)."""
    session, _ = small
    eyes = {}
    for mode in ("distortion", "fast"):
        out = session.render(parse_state({"downsample": 2.0, "power_saving": 0.2, "optics": mode}, 1))
        ss = next(m for m in out["methods"] if m["name"] == "ss")
        grid = evaluate_grid(session.model, session.views, {}, downsample=[2.0], power_saving=[0.2],
                             optics_mode=mode, baselines=("ss",), ideal=False, extra_metrics=False, progress=False)
        for k in ("psnr", "ssim"):
            assert ss["metrics"][k] == pytest.approx(float(grid.per_view["ss"][k][0, 0, 0]), abs=1e-9), (mode, k)
        eyes[mode] = ss["eye"]
    assert eyes["distortion"] != eyes["fast"]


def test_session_info(small: Any) -> None:
    """``info()`` lists the views, the methods (baselines, then the adapters; an adapter without a label of
    its own shows its name), stages, optics modes, defaults, ranges and device."""
    session, _ = small
    info = session.info()
    assert info["name"] == "tiny" and info["views"] == [f"test view 0 ({SIZE}x{SIZE})"]
    assert [m["name"] for m in info["methods"]] == ["no_ss", "ss", "controlgs", "blind", "fov"]
    assert info["methods"][3] == {"name": "blind", "label": "blind"}
    assert info["stages"] == list(STAGES) and info["optics_modes"] == list(OPTICS_MODES)
    assert info["defaults"] == ViewState().to_json() and info["diff_gain"] == 2.0
    assert info["ranges"] == {"downsample": (1.0, 8.0), "power_saving": (0.0, 0.8), "azimuth": (-180.0, 180.0),
                              "elevation": (-80.0, 80.0)}
    assert info["orbit_truth"] is True and info["device"] == "cpu"
    assert info["extra_metrics"] == list(session.extra_metrics)



def test_a_lens_conditioned_in_its_xy_frame_shows_the_larger_strength_magnitude(tmp_path: Any) -> None:
    """An adapter trained for a decentred lens keeps its (x, y) frame in the viewer: the lens strength
    reported and overlaid is max(|lambda_x|, |lambda_y|) over the visible anchors."""
    lens = affine_bank([[0.75, 0.125], [-0.25, 1.5]], [0.0625, -0.125], axis=(0.25, -0.125))
    session, _ = builtin_session(tmp_path, {"xy": {"lens": lens, "modules": ("lens", "display")}})
    state = parse_state({"power_saving": 0.3}, 1)
    out = session.render(state, tag=1)
    got = next(m for m in out["methods"] if m["name"] == "xy")
    copy_, cgs = session.adapters["xy"]
    assert cgs.lens_frame.mode == "xy"
    cam = session._frame(state)[0]
    pair = cgs.strengths(state.runtime, cam, cgs.anchor_ids(session.renderer.visible(copy_, cam)))["lens"]
    want = pair.abs().amax(-1)
    assert pair.shape[1] == 2 and float(pair.min()) < 0
    assert got["strengths"]["lens"] == pytest.approx(
        {"mean": float(want.mean()), "min": float(want.min()), "max": float(want.max())}, abs=1e-6)
    assert decode_png(got["overlay"]).shape == (SIZE, SIZE, 4)


def test_session_band_scores_follow_the_gaze_through_the_foveation_stage(small: Any) -> None:
    """With a gaze and the foveation stage, each method's PSNR / SSIM per eccentricity band about the clicked
    direction (those of its eye image over the bands measured through the Cardboard lens); without either, none."""
    from controlgs_adapter.evaluation import band_masks, band_scores

    session, _ = small
    click = {"downsample": 2.0, "gaze": [0.5, -0.25]}
    out = session.render(parse_state(click, 1), tag=21)
    _, eyes, gt = session._last
    assert gt is not None and "foveation" in out["methods"][0]["stages_run"]
    assert session.info()["bands"] == [["foveal", 0.0, 5.0], ["parafoveal", 5.0, 15.0], ["periphery", 15.0, None]]
    gaze = session.runtime(parse_state(click, 1), session.cameras[0]).gaze
    masks = band_masks(VisualAngles.of_bank(PSFBank.default()), SIZE, SIZE, gaze)
    for m in out["methods"]:
        want = band_scores(eyes[m["name"]], gt, masks)
        assert set(m["bands"]) == set(want)
        for k, v in want.items():
            assert (m["bands"][k] is None) if math.isnan(v) else m["bands"][k] == pytest.approx(v, abs=1e-12), k
    assert all(m["bands"] is None for m in session.render(parse_state({"downsample": 2.0}, 1))["methods"])
    no_stage = session.render(parse_state({**click, "stages": ["resample", "display"]}, 1))
    assert all(m["bands"] is None for m in no_stage["methods"])
