"""RuntimeState and Camera: hostile numbers (ints of any size, NaN, inf, wrong types) and focal lengths
whose field of view is not representable give the library's error naming the argument."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import pytest
import torch

from controlgs_adapter.errors import InputValueError, StateRangeError
from controlgs_adapter.state import FOCAL_RATIO, MAX_PIXELS, Camera, RuntimeState

HUGE = 10**400  # beyond float range: float(HUGE) raises OverflowError
HOSTILE = [HUGE, -HUGE, 10**5000, math.nan, math.inf, -math.inf, True, "2", None, b"2", [2.0]]


def _k(fx: float, fy: float | None = None, w: int = 16, h: int = 12) -> torch.Tensor:
    return torch.tensor([[fx, 0.0, w / 2], [0.0, fx if fy is None else fy, h / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)


@pytest.mark.parametrize("value", HOSTILE, ids=lambda v: type(v).__name__)
@pytest.mark.parametrize("field", ["downsample", "power_saving"])
def test_runtime_state_refuses_hostile_numbers(field: str, value: Any) -> None:
    with pytest.raises(StateRangeError, match=rf"^{field} must be a") as e:
        RuntimeState(**{field: value})
    assert "\n" not in str(e.value) and len(str(e.value)) < 200


@pytest.mark.parametrize("gaze", [(HUGE, 0.0), (0.0, -HUGE), (math.nan, 0.0), (True, 0.0), ("0", 0.0), [[[0.0]]], 5])
def test_runtime_state_refuses_hostile_gaze(gaze: Any) -> None:
    with pytest.raises(StateRangeError, match="^gaze must be "):
        RuntimeState(gaze=gaze)


def test_runtime_state_takes_big_finite_numbers() -> None:
    assert RuntimeState(downsample=10**300).downsample == 1e300
    assert RuntimeState(downsample=torch.tensor(4.0), power_saving=0.5).downsample == 4.0


@pytest.mark.parametrize("value", [0, -1, HUGE, MAX_PIXELS + 1, 16.0, True, "16", None, math.inf],
                         ids=lambda v: type(v).__name__ + ("-big" if isinstance(v, int) and v > 1 else ""))
@pytest.mark.parametrize("field", ["width", "height"])
def test_camera_refuses_hostile_sizes(field: str, value: Any) -> None:
    size = {"width": 16, "height": 12, field: value}
    with pytest.raises(InputValueError, match=rf"^{field} must be an int"):
        Camera(torch.eye(4), _k(16.0), size["width"], size["height"])


@pytest.mark.parametrize("fx, fy, name", [(5e-324, 16.0, "fx"), (16.0, 5e-324, "fy"), (1e-300, 16.0, "fx"),
                                          (1e300, 16.0, "fx"), (16.0, 1e30, "fy"), (16.0 / FOCAL_RATIO / 2, 16.0, "fx")])
def test_camera_refuses_focal_lengths_without_a_representable_fov(fx: float, fy: float, name: str) -> None:
    with pytest.raises(InputValueError, match=rf"intrinsics: focal length {name} = K\[\d, \d\] must be in"):
        Camera(torch.eye(4), _k(fx, fy), 16, 12)


@pytest.mark.parametrize("ratio", [1.001 / FOCAL_RATIO, 1.0, FOCAL_RATIO / 1.001])
def test_fov_stays_inside_its_documented_range_at_the_focal_limits(ratio: float) -> None:
    for dtype in (torch.float32, torch.float64):
        cam = Camera(torch.eye(4, dtype=dtype), _k(16.0 * ratio, 12.0 * ratio).to(dtype), 16, 12)
        for fov in cam.fov:
            assert 0.0 < fov < math.pi
        uv, _ = cam.project(torch.tensor([[0.5, -0.5, 1.0]], dtype=dtype))
        assert bool(torch.isfinite(uv).all())


@pytest.mark.parametrize("factor, word", [(0, "factor must be"), (-2, "factor must be"), (math.nan, "factor must be"),
                                          ("2", "factor must be"), (None, "factor must be"), (HUGE, "factor must be"),
                                          (5e-324, "factor 4.94066e-324 would give"), (1e-300, "factor 1e-300 would give")],
                         ids=repr)
def test_scaled_refuses_bad_factors(factor: Any, word: str) -> None:
    cam = Camera(torch.eye(4), _k(16.0), 16, 12)
    with pytest.raises(InputValueError, match=word):
        cam.scaled(factor)
    assert cam.scaled(2).width == 8


def test_from_scaffold_refuses_fovs_without_a_usable_focal_length() -> None:
    def scaffold(**kw: Any) -> Any:
        return SimpleNamespace(**{"world_view_transform": torch.eye(4), "image_width": 16, "image_height": 12,
                                  "FoVx": 1.0, "FoVy": 1.0, "uid": 0, **kw})

    assert Camera.from_scaffold(scaffold()).width == 16
    for kw, word in [(dict(FoVx=5e-324), "FoVx = 5e-324 rad gives a focal length of inf"),
                     (dict(FoVy=math.pi - 1e-15), "FoVy = 3.14159"), (dict(FoVx=HUGE), "FoVx must be a field of view"),
                     (dict(image_width=HUGE), "image_width must be an int <= "), (dict(uid=HUGE), "uid must be an int < 2"),
                     (dict(uid=-1), "uid must be an int >= 0")]:
        with pytest.raises(InputValueError, match=word):
            Camera.from_scaffold(scaffold(**kw))


import types
from typing import Callable

from hypothesis import given
from hypothesis import strategies as st

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.downstream.oled import OLEDEmission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import AreaResample
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import ControlGSError, LifecycleError, ShapeError, StateError
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.rendering.splatter_reference import rasterize_reference


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ============================================================================ API: run-time state, camera
EYE4, K = torch.eye(4), torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])


def _k_2(**cells: float) -> torch.Tensor:
    k = K.clone()
    for key, v in cells.items():
        k[int(key[1]), int(key[2])] = v
    return k


def _w2c(fn: Callable[[torch.Tensor], None]) -> torch.Tensor:
    m = EYE4.clone()
    fn(m)
    return m


STATE_CASES = [
    ({"downsample": None}, "downsample"), ({"downsample": "abc"}, "downsample"), ({"downsample": "4"}, "downsample"),
    ({"downsample": math.nan}, "downsample"), ({"downsample": math.inf}, "downsample"), ({"downsample": 0.5}, "downsample"),
    ({"downsample": True}, "downsample"), ({"downsample": [2]}, "downsample"), ({"downsample": 1j}, "downsample"),
    ({"power_saving": -0.1}, "power_saving"), ({"power_saving": 1.0}, "power_saving"), ({"power_saving": None}, "power_saving"),
    ({"power_saving": math.nan}, "power_saving"), ({"power_saving": "0.2"}, "power_saving"),
    ({"gaze": 5}, "gaze"), ({"gaze": "ab"}, "gaze"), ({"gaze": (0.0,)}, "gaze"), ({"gaze": (0.0, 0.0, 0.0)}, "gaze"),
    ({"gaze": (2.0, 0.0)}, "gaze"), ({"gaze": (math.nan, 0.0)}, "gaze"), ({"gaze": ("a", 0.0)}, "gaze"),
    ({"gaze": (None, 0.0)}, "gaze"), ({"gaze": {"x": 0}}, "gaze"),
]


CAMERA_CASES = [
    ("width='abc'", {"width": "abc"}, "width"), ("width=0", {"width": 0}, "width"), ("width=-3", {"width": -3}, "width"),
    ("width=1.5", {"width": 1.5}, "width"), ("width=None", {"width": None}, "width"), ("width=True", {"width": True}, "width"),
    ("height='x'", {"height": "x"}, "height"), ("height=0", {"height": 0}, "height"),
    ("K zeros", {"intrinsics": torch.zeros(3, 3)}, "intrinsics"), ("K22=0", {"intrinsics": _k_2(k22=0.0)}, "intrinsics"),
    ("K22=2", {"intrinsics": _k_2(k22=2.0)}, "intrinsics"), ("fx<0", {"intrinsics": _k_2(k00=-50.0)}, "intrinsics"),
    ("fy=0", {"intrinsics": _k_2(k11=0.0)}, "intrinsics"), ("K20!=0", {"intrinsics": _k_2(k20=0.5)}, "intrinsics"),
    ("K nan", {"intrinsics": _k_2(k02=math.nan)}, "intrinsics"), ("K 3x4", {"intrinsics": torch.zeros(3, 4)}, "intrinsics"),
    ("K list", {"intrinsics": K.tolist()}, "intrinsics"), ("K int", {"intrinsics": K.long()}, "intrinsics"),
    ("w2c zeros", {"world_to_camera": torch.zeros(4, 4)}, "world_to_camera"),
    ("w2c scaled", {"world_to_camera": _w2c(lambda m: m[:3, :3].mul_(2.0))}, "world_to_camera"),
    ("w2c mirrored", {"world_to_camera": _w2c(lambda m: m[0, 0].fill_(-1.0))}, "world_to_camera"),
    ("w2c last row", {"world_to_camera": _w2c(lambda m: m[3, 0].fill_(1.0))}, "world_to_camera"),
    ("w2c sheared", {"world_to_camera": _w2c(lambda m: m[0, 1].fill_(0.3))}, "world_to_camera"),
    ("w2c nan", {"world_to_camera": _w2c(lambda m: m[0, 3].fill_(math.nan))}, "world_to_camera"),
    ("w2c 3x4", {"world_to_camera": torch.eye(3, 4)}, "world_to_camera"),
    ("w2c None", {"world_to_camera": None}, "world_to_camera"),
]


@pytest.mark.parametrize("kw, name", STATE_CASES, ids=[f"{k}={v!r}" for (kw, _) in STATE_CASES for k, v in kw.items()])
def test_runtime_state(kw, name):
    _raises(lambda: RuntimeState(**kw), StateError, name)


@pytest.mark.parametrize("kw, name", [c[1:] for c in CAMERA_CASES], ids=[c[0] for c in CAMERA_CASES])
def test_camera(kw, name):
    args = {"world_to_camera": EYE4, "intrinsics": K, "width": 64, "height": 48, **kw}
    _raises(lambda: Camera(**args), (InputValueError, ShapeError), name)


@pytest.mark.parametrize("fov", [0.0, math.pi, -0.5, math.nan, "wide"])
def test_scaffold_camera_fov(fov):
    vc = types.SimpleNamespace(world_view_transform=torch.eye(4), image_width=64, image_height=48, FoVx=fov, FoVy=0.8)
    _raises(lambda: Camera.from_scaffold(vc), InputValueError, "FoVx")


D = torch.float64


def _camera(uid: int | None = None) -> Camera:
    """Non-square camera about 5 units from the origin, turned 0.1 rad about y, principal point off centre."""
    c, s = math.cos(0.1), math.sin(0.1)
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    w2c[:3, 3] = torch.tensor([-0.3, 0.2, 5.0])
    k = torch.tensor([[52.0, 0.0, 37.0], [0.0, 47.0, 21.0], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, 72, 40, {} if uid is None else {"uid": uid})


def _centre(cam: Camera) -> torch.Tensor:
    """Camera centre -R^T t in float64 from the world-to-camera matrix."""
    w2c = cam.world_to_camera.to(D)
    return -(w2c[:3, :3].T @ w2c[:3, 3])


def test_camera_centre_of_a_turned_camera_by_hand():
    cam = _camera()
    torch.testing.assert_close(cam.center.to(D), _centre(cam), rtol=0, atol=1e-6)
    torch.testing.assert_close(cam.to_camera(cam.center[None]), torch.zeros(1, 3), rtol=0, atol=1e-5)


def _scaffold_camera(w: int, h: int, fovx: float, fovy: float, uid: int | None = 3) -> types.SimpleNamespace:
    """A 3DGS/Scaffold-GS camera as its ``Camera`` class builds it: ``world_view_transform`` the
    transposed world-to-camera, ``full_proj_transform`` = view @ projection (row-vector convention)."""
    angle = 0.3
    r = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]],
                     dtype=torch.float64)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3], w2c[:3, 3] = r, torch.tensor([0.2, -0.1, 3.0], dtype=torch.float64)
    znear, zfar = 0.01, 100.0
    top, right = math.tan(fovy / 2) * znear, math.tan(fovx / 2) * znear
    p = torch.zeros(4, 4, dtype=torch.float64)  # 3DGS getProjectionMatrix (symmetric frustum)
    p[0, 0], p[1, 1] = 2 * znear / (2 * right), 2 * znear / (2 * top)
    p[3, 2], p[2, 2], p[2, 3] = 1.0, zfar / (zfar - znear), -(zfar * znear) / (zfar - znear)
    view = w2c.T
    cam = types.SimpleNamespace(world_view_transform=view.float(), full_proj_transform=(view @ p.T),
                                image_width=w, image_height=h, FoVx=fovx, FoVy=fovy)
    if uid is not None:
        cam.uid = uid
    return cam


@pytest.mark.parametrize("w, h", [(64, 48), (63, 37)])
def test_projection_matches_3dgs_ndc_to_pixel(w, h):
    vc = _scaffold_camera(w, h, 1.1, 0.9)
    cam = Camera.from_scaffold(vc)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.3, 0.5], [-0.5, 0.2, -0.4]], dtype=torch.float64)
    hom = torch.cat([pts, torch.ones(3, 1, dtype=torch.float64)], dim=1) @ vc.full_proj_transform
    ndc = hom[:, :3] / hom[:, 3:]
    # 3DGS's ndc2Pix puts pixel centres at integers: ((ndc + 1) * S - 1) / 2; this library at i + 0.5
    want = torch.stack([((ndc[:, 0] + 1) * w - 1) / 2 + 0.5, ((ndc[:, 1] + 1) * h - 1) / 2 + 0.5], dim=1)
    uv, depth = cam.project(pts.float())
    assert torch.allclose(uv.double(), want, atol=2e-4, rtol=0)
    assert (depth > 0).all()
    assert cam.intrinsics[0, 2].item() == w / 2 and cam.intrinsics[1, 2].item() == h / 2
    fx = w / (2 * math.tan(1.1 / 2))
    assert cam.intrinsics[0, 0].item() == pytest.approx(fx, rel=1e-6)


def test_uid_carried_and_picks_the_appearance_code():
    vc = _scaffold_camera(32, 24, 1.0, 0.8, uid=3)
    cam = Camera.from_scaffold(vc)
    assert cam.extra == {"uid": 3}
    assert Camera.from_scaffold(_scaffold_camera(32, 24, 1.0, 0.8, uid=None)).extra == {}
    with pytest.raises(InputValueError, match="uid"):
        Camera.from_scaffold(_scaffold_camera(32, 24, 1.0, 0.8, uid=-1))
    torch.manual_seed(0)
    model = NeuralGaussianModel(6, feat_dim=8, n_offsets=2, appearance_dim=4, num_cameras=5)
    with torch.no_grad():
        model._anchor.copy_(torch.randn(6, 3) * 0.3)
        model._anchor_feat.copy_(torch.randn(6, 8))
        model.embedding_appearance.embedding.weight.copy_(torch.randn(5, 4) * 3)
        model.mlp_opacity[2].bias.fill_(5.0)  # every Gaussian kept
    want = model.decode(Camera(cam.world_to_camera, cam.intrinsics, 32, 24, {"uid": 3})).colors
    code0 = model.decode(Camera(cam.world_to_camera, cam.intrinsics, 32, 24)).colors
    got = model.decode(cam).colors
    assert torch.equal(got, want)
    assert (got - code0).abs().max() > 1e-2  # the code matters: uid 0 would decode other colours


def test_scaled_rescales_each_axis_by_its_own_rounded_size():
    """Camera.scaled(f): size round(size / f) per axis, K's rows scaled by that axis's ratio (a 64 x 48
    camera at f = 3 becomes 21 x 16: x by 21/64, y by 16/48, not the same factor)."""
    k = torch.tensor([[50.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cam = Camera(torch.eye(4, dtype=torch.float64), k, 64, 48, {"uid": 2})
    small = cam.scaled(3.0)
    assert (small.width, small.height, small.extra) == (21, 16, {"uid": 2})
    want = torch.tensor([[50.0 * 21 / 64, 0.0, 32.0 * 21 / 64], [0.0, 40.0 * 16 / 48, 24.0 * 16 / 48], [0.0, 0.0, 1.0]],
                        dtype=torch.float64)
    assert torch.allclose(small.intrinsics, want, atol=1e-12, rtol=0)
    corner = torch.tensor([[0.64, 0.6, 1.0]], dtype=torch.float64)  # projects to pixel (64, 48): the corner
    assert torch.allclose(cam.project(corner)[0], torch.tensor([[64.0, 48.0]], dtype=torch.float64))
    assert torch.allclose(small.project(corner)[0], torch.tensor([[21.0, 16.0]], dtype=torch.float64))


def test_lifecycle_and_state_range_errors_are_distinct():
    from controlgs_adapter import RuntimeState

    with pytest.raises(StateRangeError) as e:
        RuntimeState(downsample=0.5)
    assert isinstance(e.value, StateError) and isinstance(e.value, ValueError)
    assert not issubclass(LifecycleError, StateError) and issubclass(LifecycleError, RuntimeError)


@pytest.mark.parametrize("size,factor,want", [((103, 77), 2.0, (52, 38)), ((100, 60), 1.5, (67, 40)),
                                              ((10, 7), 3.0, (3, 2)), ((5, 3), 8.0, (1, 1))])
def test_camera_scaled_rounds_each_side_to_the_nearest_pixel(size, factor, want):
    """round(W / f), round(H / f) (at least 1), intrinsics scaled by each axis's own ratio."""
    from controlgs_adapter import Camera

    w, h = size
    k = torch.tensor([[50.0, 0.0, w / 2], [0.0, 40.0, h / 2], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), k, w, h).scaled(factor)
    assert (cam.width, cam.height) == want
    torch.testing.assert_close(cam.intrinsics, torch.tensor([[50.0 * want[0] / w, 0.0, want[0] / 2],
                                                             [0.0, 40.0 * want[1] / h, want[1] / 2], [0.0, 0.0, 1.0]]))


@pytest.mark.parametrize("kw", [dict(downsample=0.5), dict(downsample=float("nan")), dict(power_saving=1.0),
                                dict(power_saving=-0.1), dict(gaze=(2.0, 0.0))])
def test_runtime_state_rejects_out_of_range(kw):
    with pytest.raises(StateError) as e:
        RuntimeState(**kw)
    assert next(iter(kw)) in str(e.value)


@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.5, 20))
def test_normalized_screen_matches_pixel_convention(x, y, z):
    k = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(torch.eye(4, dtype=torch.float64), k, 64, 48)
    p = cam.normalized_screen(torch.tensor([[x, y, z]], dtype=torch.float64))[0]
    u, v = 50 * x / z + 32, 50 * y / z + 24
    assert math.isclose(float(p[0]), 2 * u / 64 - 1, abs_tol=1e-9)
    assert math.isclose(float(p[1]), 2 * v / 48 - 1, abs_tol=1e-9)


def test_normalized_screen_puts_points_at_and_behind_the_camera_plane_at_inf():
    # depth exactly 0 (the camera centre itself, and a point beside it) and depth < 0: +inf, never nan or -inf
    k = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]], dtype=torch.float64)
    cam = Camera(torch.eye(4, dtype=torch.float64), k, 64, 48)
    pts = torch.tensor([[0.0, 0.0, 0.0], [-1.0, 0.5, 0.0], [0.3, -0.2, -2.0], [0.3, -0.2, 2.0]], dtype=torch.float64)
    p = cam.normalized_screen(pts)
    assert torch.equal(p[:3], torch.full((3, 2), float("inf"), dtype=torch.float64))
    assert torch.allclose(p[3], torch.tensor([2 * (50 * 0.15 + 32) / 64 - 1, 2 * (50 * -0.1 + 24) / 48 - 1],
                                             dtype=torch.float64))


def test_fov_per_axis_by_hand_and_from_scaffold_round_trip():
    """fov = (2 atan(W / 2fx), 2 atan(H / 2fy)) with fx != fy (by hand), and Camera.from_scaffold's FoVx,
    FoVy come back out (3DGS's cameras carry the two angles)."""
    import types

    cam = Camera(torch.eye(4), torch.tensor([[40.0, 0, 32.0], [0, 20.0, 24.0], [0, 0, 1]]), 64, 48)
    fx, fy = cam.fov
    assert math.isclose(fx, 2 * math.atan(0.8), rel_tol=1e-7) and math.isclose(fy, 2 * math.atan(1.2), rel_tol=1e-7)
    vc = types.SimpleNamespace(world_view_transform=torch.eye(4), image_width=80, image_height=45, FoVx=1.2, FoVy=0.7)
    got = Camera.from_scaffold(vc).fov
    assert math.isclose(got[0], 1.2, rel_tol=1e-6) and math.isclose(got[1], 0.7, rel_tol=1e-6)


def _camera_2(rot: torch.Tensor, t: tuple[float, float, float], f: float = 40.0, size: int = 32) -> Camera:
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = rot
    w2c[:3, 3] = torch.tensor(t, dtype=torch.float64)
    k = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return Camera(w2c, k, size, size)


# ------------------------------------------------------------------------------ camera rigidity
def test_camera_refuses_a_rotation_0_15_percent_off_orthonormal_and_accepts_float32_round_off():
    """``world_to_camera`` must be rigid: a rotation block whose R R^T is 1.5e-3 off the identity (a scale
    of 1.00075 on one axis) is refused; 5e-4 off (float32 round-off of a composed pose and more) passes."""
    off = torch.diag(torch.tensor([1.00075, 1.0, 1.0], dtype=torch.float64))
    with pytest.raises(InputValueError, match="orthonormal"):
        _camera_2(off, (0.0, 0.0, 0.0))
    near = torch.diag(torch.tensor([1.00025, 1.0, 1.0], dtype=torch.float64))
    assert _camera_2(near, (0.0, 0.0, 0.0)).width == 32


F64 = torch.float64


def test_project_divides_by_the_signed_depth_behind_the_camera():
    """``Camera.project`` docstring: a point at camera coordinates ``(x, y, -z)`` lands where ``(x, y, z)``
    does, mirrored through the principal point; only ``|depth| < 1e-12`` is clamped to ``1e-12``.
    By hand with fx = 50, fy = 40, cx = 32, cy = 24 (identity pose: world = camera coordinates)."""
    k = torch.tensor([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, 64, 48, {})
    pts = torch.tensor([[1.0, 3.0, -2.0], [1.0, 3.0, 2.0], [-4.0, 2.0, -0.5]], dtype=F64)
    uv, z = cam.project(pts)
    assert z.tolist() == [-2.0, 2.0, -0.5]
    # (1, 3, -2): u = 50 * 1 / -2 + 32 = 7, v = 40 * 3 / -2 + 24 = -36; its mirror (1, 3, 2): (57, 84)
    # (-4, 2, -0.5): u = 50 * -4 / -0.5 + 32 = 432, v = 40 * 2 / -0.5 + 24 = -136
    assert uv.tolist() == [[7.0, -36.0], [57.0, 84.0], [432.0, -136.0]]
    centre = torch.tensor([32.0, 24.0], dtype=F64)
    assert torch.equal(uv[0] - centre, -(uv[1] - centre))
    # a depth below 1e-12 in magnitude, on either side, is divided as +1e-12
    uv0, _ = cam.project(torch.tensor([[1e-12, 0.0, -1e-13], [1e-12, 0.0, 1e-13]], dtype=F64))
    assert torch.allclose(uv0, torch.tensor([[82.0, 24.0], [82.0, 24.0]], dtype=F64), rtol=1e-12, atol=0)


def _camera_3(w2c=None, k=None, w=64, h=48, **extra):
    k = torch.tensor([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], dtype=torch.float64) if k is None else k
    return Camera(torch.eye(4, dtype=torch.float64) if w2c is None else w2c, k, w, h, extra)


def test_runtime_state_defaults_bounds_and_conversions():
    s = RuntimeState()
    assert (s.downsample, s.power_saving, s.gaze) == (1.0, 0.0, None)
    s = RuntimeState(downsample=2, power_saving=torch.tensor(0.25), gaze=torch.tensor([1.0, -1.0]))
    assert (s.downsample, s.power_saving, s.gaze) == (2.0, 0.25, (1.0, -1.0))  # gaze bounds are inclusive
    assert type(s.downsample) is float and type(s.power_saving) is float
    RuntimeState(downsample=1.0, power_saving=0.999999)  # the open upper bound's neighbourhood is fine
    for kw, word in [(dict(downsample=0.999), "downsample must be a finite number >= 1"),
                     (dict(downsample=float("inf")), "downsample must be a finite"),
                     (dict(power_saving=float("nan")), "power_saving must be a finite"),
                     (dict(power_saving=1.0), "in [0, 1)"), (dict(power_saving=-1e-9), "in [0, 1)"),
                     (dict(downsample=True), "downsample must be a real number"),
                     (dict(power_saving="0.1"), "power_saving must be a real number"),
                     (dict(downsample=torch.tensor(2.0 + 0j)), "downsample must be a real number"),
                     (dict(gaze=(0.0, 1.0001)), "gaze must be None or (x, y) in [-1, 1]^2"),
                     (dict(gaze=(-1.0001, 0.0)), "gaze must be None or (x, y)"),
                     (dict(gaze=(0.0, float("nan"))), "gaze must be None or (x, y)"),
                     (dict(gaze=(0.0, 0.0, 0.0)), "gaze must be None or a pair"),
                     (dict(gaze="ab"), "gaze must be None or a pair"),
                     (dict(gaze=0.5), "gaze must be None or a pair"),
                     (dict(gaze=(0.0, True)), "gaze must be a real number")]:
        with pytest.raises(StateRangeError) as e:
            RuntimeState(**kw)
        assert word in str(e.value), kw


def test_camera_refuses_bad_sizes_intrinsics_and_non_rigid_poses():
    cam = _camera_3(w=torch.tensor(64), h=48)
    assert (cam.width, cam.height) == (64, 48) and type(cam.width) is int
    for kw, word in [(dict(w=0), "width must be an int >= 1 (pixels), got 0"), (dict(h=True), "height must be an int >= 1"),
                     (dict(w=64.0), "width must be an int >= 1")]:
        with pytest.raises(InputValueError, match=word.replace("(", r"\(").replace(")", r"\)")):
            _camera_3(**kw)
    k = torch.tensor([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], dtype=torch.float64)
    _camera_3(k=k.clone().index_put_((torch.tensor(0), torch.tensor(1)), torch.tensor(0.5, dtype=torch.float64)))  # skew ok
    for (i, j), v, word in [((0, 0), 0.0, "focal lengths"), ((1, 1), -1.0, "focal lengths"), ((2, 2), 1.00001, "must be [[fx"),
                            ((2, 0), 1e-8, "must be [[fx"), ((2, 1), -1e-8, "must be [[fx"), ((1, 0), 1e-8, "must be [[fx")]:
        bad = k.clone()
        bad[i, j] = v
        with pytest.raises(InputValueError, match="intrinsics") as e:
            _camera_3(k=bad)
        assert word in str(e.value), (i, j)
    _camera_3(k=k.clone().index_put_((torch.tensor(2), torch.tensor(2)), torch.tensor(1 + 5e-7, dtype=torch.float64)))
    with pytest.raises(InputValueError, match="floating-point"):
        Camera(torch.eye(4, dtype=torch.int64), k, 64, 48)
    with pytest.raises(ShapeError, match="intrinsics"):
        Camera(torch.eye(4), torch.eye(4), 64, 48)
    with pytest.raises(InputValueError, match="world_to_camera contains 1 non-finite"):
        Camera(torch.eye(4).index_put_((torch.tensor(0), torch.tensor(3)), torch.tensor(float("nan"))), k, 64, 48)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[3, 0] = 1e-5
    with pytest.raises(InputValueError, match="last row must be"):
        _camera_3(w2c=w2c)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[3, 0] = 5e-7  # within the 1e-6 tolerance
    _camera_3(w2c=w2c)
    for scale, ok in [(1.0004, True), (1.002, False)]:  # |R R^T - I| = 2 (s - 1) + (s-1)^2 vs tol 1e-3
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[0, 0] = scale
        if ok:
            _camera_3(w2c=w2c)
        else:
            with pytest.raises(InputValueError, match="orthonormal"):
                _camera_3(w2c=w2c)
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    with pytest.raises(InputValueError, match="det -1"):
        _camera_3(w2c=mirror)


def test_camera_centre_scaling_and_projection_by_hand():
    # R = rotation by +90 deg about z (x -> y), t = (1, 2, 3): centre = -R^T t = -(2, -1, 3) = (-2, 1, -3)
    w2c = torch.tensor([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=torch.float64)
    cam = _camera_3(w2c=w2c, uid=7)
    assert torch.allclose(cam.center, torch.tensor([-2.0, 1.0, -3.0], dtype=torch.float64), atol=0)
    # world (1, 0, 1) -> camera R p + t = (0, 1, 1) + (1, 2, 3) = (1, 3, 4); u = 50 * 1/4 + 32, v = 40 * 3/4 + 24
    p = torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64)
    assert cam.to_camera(p).tolist() == [[1.0, 3.0, 4.0]]
    uv, z = cam.project(p)
    assert uv.tolist() == [[44.5, 54.0]] and z.tolist() == [4.0]
    # a point on the camera plane: depth 0 is divided as 1e-12 (finite, not inf): u = 50 * 1 / 1e-12 + 32
    uv0, z0 = _camera_3().project(torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
    assert z0.tolist() == [0.0] and math.isclose(float(uv0[0, 0]), 5e13, rel_tol=1e-9) and float(uv0[0, 1]) == 24.0
    # scaled by 3: round(64 / 3) = 21, round(48 / 3) = 16 pixels; K rows rescaled by 21/64 and 16/48
    s = cam.scaled(3.0)
    assert (s.width, s.height) == (21, 16)
    want = torch.tensor([[50 * 21 / 64, 0, 32 * 21 / 64], [0, 40 / 3, 8.0], [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(s.intrinsics, want, rtol=1e-15, atol=0)
    assert s.extra == {"uid": 7} and s.extra is not cam.extra and torch.equal(s.world_to_camera, w2c)
    assert torch.equal(cam.intrinsics[0, 0], torch.tensor(50.0, dtype=torch.float64))  # not scaled in place
    s = cam.scaled(2.5)  # 64 / 2.5 = 25.6 -> 26 (rounded, not floored), 48 / 2.5 = 19.2 -> 19
    assert (s.width, s.height) == (26, 19)
    tiny_cam = cam.scaled(1000.0)
    assert (tiny_cam.width, tiny_cam.height) == (1, 1)  # never below one pixel


def test_camera_from_scaffold_by_hand():
    # 3DGS stores world_view_transform = w2c^T: the translation sits in its last ROW
    w2c = torch.tensor([[1.0, 0, 0, 0.5], [0, 1, 0, -0.25], [0, 0, 1, 2.0], [0, 0, 0, 1]])
    fovx, fovy = 2 * math.atan(0.5), 2 * math.atan(0.25)  # tan(fov/2) = 1/2 and 1/4
    vc = types.SimpleNamespace(world_view_transform=w2c.T.contiguous(), image_width=80, image_height=40,
                               FoVx=fovx, FoVy=fovy, uid=3)
    cam = Camera.from_scaffold(vc)
    assert torch.equal(cam.world_to_camera, w2c)
    # fx = W / (2 tan(FoVx / 2)) = 80 / 1 = 80; fy = 40 / 0.5 = 80; principal point (W/2, H/2) = (40, 20)
    assert torch.allclose(cam.intrinsics, torch.tensor([[80.0, 0, 40], [0, 80.0, 20], [0, 0, 1]]), rtol=1e-6, atol=0)
    assert cam.extra == {"uid": 3} and (cam.width, cam.height) == (80, 40)
    vc.uid = torch.tensor(5)  # a 0-d tensor id is read as its int
    assert Camera.from_scaffold(vc).extra == {"uid": 5} and type(Camera.from_scaffold(vc).extra["uid"]) is int
    vc.uid = 0  # the first training camera: 0 is a valid id (>= 0)
    assert Camera.from_scaffold(vc).extra == {"uid": 0}
    vc.uid = None
    assert Camera.from_scaffold(vc).extra == {}
    vc.uid = -1
    with pytest.raises(InputValueError, match="uid must be an int >= 0, got -1"):
        Camera.from_scaffold(vc)
    vc.uid, vc.image_height = 0, 0
    with pytest.raises(InputValueError, match="image_height must be an int >= 1"):
        Camera.from_scaffold(vc)
    vc.image_height, vc.FoVy = 40, math.pi
    with pytest.raises(InputValueError, match=r"FoVy must be a field of view in \(0, pi\)"):
        Camera.from_scaffold(vc)


def _img(values: list[float], h: int = 1, w: int = 1) -> torch.Tensor:
    """A [3, h, w] float64 image with channel c constant at values[c]."""
    return torch.tensor(values, dtype=D)[:, None, None].expand(3, h, w).clone()


def test_oled_stage_runs_only_when_downsampled():
    st = OLEDEmission()
    assert st.order == 40.0 and st.name == "oled"
    assert st.is_identity(RuntimeState(downsample=1.0))
    assert not st.is_identity(RuntimeState(downsample=1.5))
    out = st(_img([0.5, 0.5, 0.5], 1, 1), RuntimeState(downsample=2.0), StageContext((2, 2)))
    assert out.shape == (3, 2, 2)


def test_resample_stage_bounds_and_sizes():
    st = AreaResample()
    assert st.order == 20.0 and st.max_factor == 8.0
    img = torch.rand(3, 16, 16, dtype=D, generator=torch.Generator().manual_seed(0))
    ctx = StageContext((16, 16))
    assert st(img, RuntimeState(downsample=8.0), ctx).shape == (3, 2, 2)
    with pytest.raises(StateRangeError, match="exceeds this pipeline's max_factor 8.0"):
        st(img, RuntimeState(downsample=8.5), ctx)
    assert AreaResample(max_factor=1.0).max_factor == 1.0
    small = img[:, :8, :8]
    assert st(small, RuntimeState(downsample=2.0), ctx) is small  # already at the display size
    with pytest.raises(ShapeError, match="native size"):
        st(img[:, :12, :12], RuntimeState(downsample=2.0), ctx)
    assert st.is_identity(RuntimeState()) and not st.is_identity(RuntimeState(downsample=1.01))


class _WideOnly(Stage):
    """Runs only for a native size wider than 10 pixels (a stage whose cost depends on the size)."""

    name = "wide"

    def is_identity(self, state, ctx=None):
        return ctx is None or ctx.native_size[1] <= 10

    def process(self, image, state, ctx):
        return image


def test_active_passes_the_native_size_to_the_stages():
    p = Pipeline([_WideOnly()])
    assert p.active(RuntimeState(), reference=torch.rand(3, 4, 20)) == ["wide"]
    assert p.active(RuntimeState(), reference=torch.rand(3, 20, 4)) == []
    assert p.active(RuntimeState(), native_size=(4, 11)) == ["wide"]
    assert p.active(RuntimeState(), reference=torch.rand(3, 4, 20), native_size=(20, 4)) == []
    assert p.active(RuntimeState()) == []  # no size known: (0, 0)


BOTH = [rasterize, rasterize_reference]


def _camera_4(f: float = 20.0, width: int = 24, height: int = 16) -> Camera:
    """Identity pose, principal point at the image centre."""
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=F64)
    return Camera(torch.eye(4, dtype=F64), k, width, height)


def _one(mean: list[float], scale: list[float], q: list[float], o: float, color: list[float] | None = None
         ) -> tuple[torch.Tensor, ...]:
    return (torch.tensor([mean], dtype=F64), torch.tensor([scale], dtype=F64), torch.tensor([q], dtype=F64),
            torch.tensor([o], dtype=F64), torch.tensor([color or [1.0, 1.0, 1.0]], dtype=F64))


def _closed_form_alpha(cov: torch.Tensor, u0: float, v0: float, o: float, width: int, height: int) -> torch.Tensor:
    """``[H, W]`` alpha of one Gaussian with 2D covariance ``cov`` (low-pass included) at ``(u0, v0)``:
    ``o exp(-d^T cov^-1 d / 2)``, zero outside the 3 sqrt(lambda_max) square and below 1/255, clamped at 0.99."""
    xs = torch.arange(width, dtype=F64) + 0.5 - u0
    ys = torch.arange(height, dtype=F64) + 0.5 - v0
    d = torch.stack(torch.broadcast_tensors(xs[None, :], ys[:, None]), dim=-1)  # [H, W, 2]
    maha = torch.einsum("hwi,ij,hwj->hw", d, torch.linalg.inv(cov), d)
    alpha = (o * torch.exp(-0.5 * maha)).clamp(max=0.99)
    r = 3 * math.sqrt(float(torch.linalg.eigvalsh(cov)[-1]))
    return alpha * (d.abs() <= r).all(-1) * (alpha >= 1 / 255)


@pytest.mark.parametrize("fn", BOTH)
def test_near_plane_is_a_strict_cut_at_0_2(fn) -> None:  # type: ignore[no-untyped-def]
    cam = _camera_4()
    for z, seen in ((0.2, False), (0.2 + 1e-9, True), (0.21, True), (0.19, False)):
        out = fn(*_one([0.0, 0.0, z], [0.001, 0.001, 0.001], [1.0, 0, 0, 0], 0.9), cam)
        assert bool(out.visible[0]) is seen, z
        assert (float(out.alpha.max()) > 0) is seen, z


@pytest.mark.parametrize("fn", BOTH)
def test_jacobian_is_clamped_to_the_widened_frustum(fn) -> None:  # type: ignore[no-untyped-def]
    """A wide Gaussian whose mean lies outside the image: x/z = 1 and y/z = 0.7 enter the Jacobian clamped
    to the image widened by 15 % per side, (12 + 0.15 * 24) / 20 = 0.78 and (8 + 0.15 * 16) / 20 = 0.52;
    ``cov = s^2 (f/z)^2 [[1 + tx^2, tx ty], [tx ty, 1 + ty^2]] + 0.3 I`` (isotropic Sigma = s^2 I)."""
    cam, f, z, s, o = _camera_4(), 20.0, 2.0, 0.3, 0.9
    out = fn(*_one([1.0 * z, 0.7 * z, z], [s, s, s], [1.0, 0, 0, 0], o), cam)
    tx, ty = 0.78, 0.52
    g = (s * f / z) ** 2
    cov = torch.tensor([[g * (1 + tx * tx) + 0.3, g * tx * ty], [g * tx * ty, g * (1 + ty * ty) + 0.3]], dtype=F64)
    want = _closed_form_alpha(cov, f * 1.0 + 12, f * 0.7 + 8, o, 24, 16)
    assert int((want > 0).sum()) >= 10 and bool(out.visible[0])  # the footprint reaches into the image
    torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)
    # the same on the other sides (x/z = -1, y/z = -0.7): the lower limits
    out = fn(*_one([-1.0 * z, -0.7 * z, z], [s, s, s], [1.0, 0, 0, 0], o), cam)
    want = _closed_form_alpha(cov, 12 - f * 1.0, 8 - f * 0.7, o, 24, 16)
    torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("fn", BOTH)
def test_quaternion_is_w_x_y_z_and_normalised(fn) -> None:  # type: ignore[no-untyped-def]
    """(cos 45, 0, 0, sin 45) turns the local x axis onto y: the long axis (sx) lies along the image's
    rows' direction v; times 3 (unnormalised) is the same rotation."""
    cam, f, z, o = _camera_4(), 20.0, 2.0, 0.8
    sx, sy = 0.15, 0.04
    h = math.sqrt(0.5)
    want = _closed_form_alpha(torch.tensor([[(sy * f / z) ** 2 + 0.3, 0.0], [0.0, (sx * f / z) ** 2 + 0.3]], dtype=F64),
                              12.0, 8.0, o, 24, 16)
    for q in ([h, 0.0, 0.0, h], [3 * h, 0.0, 0.0, 3 * h]):
        out = fn(*_one([0.0, 0.0, z], [sx, sy, 0.01], q, o), cam)
        torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)
    # about x by 90 degrees: (cos 45, sin 45, 0, 0) turns local y onto z (depth): only sx shows, along u
    out = fn(*_one([0.0, 0.0, z], [sx, sy, 0.01], [h, h, 0.0, 0.0], o), cam)
    want = _closed_form_alpha(torch.tensor([[(sx * f / z) ** 2 + 0.3, 0.0], [0.0, (0.01 * f / z) ** 2 + 0.3]], dtype=F64),
                              12.0, 8.0, o, 24, 16)
    torch.testing.assert_close(out.alpha[0], want, rtol=1e-11, atol=1e-12)


@pytest.mark.parametrize("fn", BOTH)
def test_alpha_clamp_and_default_early_termination_by_hand(fn) -> None:  # type: ignore[no-untyped-def]
    """Three splats centred on pixel (12, 8)'s centre (G = 1 there), opacity 0.9878, at z = 2, 3, 4:
    alpha 0.9878 each, T after two = 0.0122^2 = 1.4884e-4 >= 1e-4 (drawn), after three 1.8e-6 < 1e-4:
    the third is not drawn by default; with transmittance_min = 0 it is. Opacity 1 is clamped to 0.99."""
    cam = _camera_4()
    u, v = 12.5, 8.5  # pixel (12, 8)'s centre: x / z = (12.5 - 12) / 20
    zs = [2.0, 3.0, 4.0]
    means = torch.tensor([[(u - 12) / 20 * z, (v - 8) / 20 * z, z] for z in zs], dtype=F64)
    scales = torch.full((3, 3), 0.01, dtype=F64)
    rot = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=F64)
    colors = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    a = 0.9878
    out = fn(means, scales, rot, torch.full((3,), a, dtype=F64), colors, cam)
    w = [a, a * (1 - a), a * (1 - a) ** 2]
    assert float(out.color[0, 8, 12]) == pytest.approx(w[0], abs=1e-12)
    assert float(out.color[1, 8, 12]) == pytest.approx(w[1], abs=1e-12)
    assert float(out.color[2, 8, 12]) == 0.0  # terminated before the third
    assert float(out.alpha[0, 8, 12]) == pytest.approx(1 - (1 - a) ** 2, abs=1e-12)
    assert float(out.depth[0, 8, 12]) == pytest.approx(2 * w[0] + 3 * w[1], abs=1e-11)
    exact = fn(means, scales, rot, torch.full((3,), a, dtype=F64), colors, cam, transmittance_min=0.0)
    assert float(exact.color[2, 8, 12]) == pytest.approx(w[2], abs=1e-12)
    assert float(exact.alpha[0, 8, 12]) == pytest.approx(1 - (1 - a) ** 3, abs=1e-12)
    # opacity 1: alpha clamped to 0.99, T = 0.01 of the background shows
    out = fn(means[:1], scales[:1], rot[:1], torch.ones(1, dtype=F64), colors[:1], cam,
             torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    assert float(out.alpha[0, 8, 12]) == pytest.approx(0.99, abs=1e-12)
    assert float(out.color[2, 8, 12]) == pytest.approx(0.01, abs=1e-12)  # 1 % of the blue background shows


def test_opacity_exactly_at_the_clamp_keeps_its_gradient() -> None:
    """Opacity 0.99 centred on a pixel centre: alpha = 0.99 there exactly (G = 1), on the clamp's kink. As
    ``torch.clamp`` (the reference), the clamp passes the gradient at equality: d alpha / d o = G = 1; only
    an alpha above 0.99 is frozen (zero gradient)."""
    cam = _camera_4(f=20.0, width=16, height=16)  # principal point (8, 8): pixel (8, 8)'s centre is x / z = 0.5 / 20
    z = 2.0
    for o, want in ((0.99, 1.0), (0.995, 0.0)):
        for fn in BOTH:
            op = torch.tensor([o], dtype=F64, requires_grad=True)
            g = _one([0.5 / 20 * z, 0.5 / 20 * z, z], [0.05] * 3, [1.0, 0, 0, 0], o)
            out = fn(g[0], g[1], g[2], op, g[4], cam)
            assert float(out.alpha[0, 8, 8].detach()) == pytest.approx(0.99, abs=1e-14)
            (grad,) = torch.autograd.grad(out.alpha[0, 8, 8], op)
            assert float(grad) == pytest.approx(want, abs=1e-12), (fn.__name__, o)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
