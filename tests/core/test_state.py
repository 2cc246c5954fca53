"""RuntimeState and Camera: the run-time state's ranges and conversions; the camera's checks (sizes,
intrinsics, rigid poses, focal lengths with a representable field of view), its centre, projection,
normalised screen positions, field of view, rescaling and the conversion from a Scaffold-GS camera.
Also the OLED and resampling stages at a state, and the splatter's projection and compositing."""

from __future__ import annotations

import math
import types
from typing import Any

import pytest
from helpers.scaffold_cameras import scaffold_camera
import torch
from hypothesis import given
from hypothesis import strategies as st

from controlgs_adapter.downstream.oled import OLEDEmission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import AreaResample
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import InputValueError, ShapeError, StateError, StateRangeError
from controlgs_adapter.state import FOCAL_RATIO, MAX_PIXELS, Camera, RuntimeState

D = F64 = torch.float64
HUGE = 10**400  # beyond float range: float(HUGE) raises OverflowError


# ------------------------------------------------------------------------------ RuntimeState
def test_runtime_state_defaults_and_conversions() -> None:
    s = RuntimeState()
    assert (s.downsample, s.power_saving, s.gaze) == (1.0, 0.0, None)
    s = RuntimeState(downsample=2, power_saving=torch.tensor(0.25), gaze=torch.tensor([89.5, -12.0]))
    assert (s.downsample, s.power_saving, s.gaze) == (2.0, 0.25, (89.5, -12.0))  # gaze in degrees
    assert type(s.downsample) is float and type(s.power_saving) is float
    assert RuntimeState(downsample=1.0, power_saving=0.999999).power_saving == 0.999999  # below the open bound
    assert RuntimeState(downsample=10**300).downsample == 1e300  # an int within float range is converted
    assert RuntimeState(downsample=torch.tensor(4.0), power_saving=0.5).downsample == 4.0


STATE_REFUSALS = [  # id, keyword arguments, what the message shows after the field's name
    ("d huge", dict(downsample=HUGE), r">= 1.*got an int of about 401 digits"),
    ("d -huge", dict(downsample=-HUGE), r">= 1.*got an int of about 401 digits"),
    ("d 10**5000", dict(downsample=10**5000), r"got an int of about 5001 digits"),
    ("d nan", dict(downsample=math.nan), r">= 1.*got nan"),
    ("d inf", dict(downsample=math.inf), r">= 1.*got inf"),
    ("d -inf", dict(downsample=-math.inf), r">= 1.*got -inf"),
    ("d 0.5", dict(downsample=0.5), r">= 1.*got 0\.5"),
    ("d 0.999", dict(downsample=0.999), r">= 1.*got 0\.999"),
    ("d True", dict(downsample=True), r"real number, got True"),
    ("d '2'", dict(downsample="2"), r"real number, got '2'"),
    ("d 'abc'", dict(downsample="abc"), r"real number, got 'abc'"),
    ("d None", dict(downsample=None), r"real number, got None"),
    ("d b'2'", dict(downsample=b"2"), r"real number, got b'2'"),
    ("d [2.0]", dict(downsample=[2.0]), r"real number, got \[2\.0\]"),
    ("d 1j", dict(downsample=1j), r"real number, got 1j"),
    ("d complex tensor", dict(downsample=torch.tensor(2.0 + 0j)), r"real number"),
    ("rho -0.1", dict(power_saving=-0.1), r"in \[0, 1\), got -0\.1"),
    ("rho -1e-9", dict(power_saving=-1e-9), r"in \[0, 1\), got -1e-09"),
    ("rho 1.0", dict(power_saving=1.0), r"in \[0, 1\), got 1\.0"),
    ("rho nan", dict(power_saving=math.nan), r"in \[0, 1\), got nan"),
    ("rho huge", dict(power_saving=HUGE), r"in \[0, 1\), got an int of about 401 digits"),
    ("rho None", dict(power_saving=None), r"real number, got None"),
    ("rho '0.2'", dict(power_saving="0.2"), r"real number, got '0\.2'"),
    ("gaze (huge, 0)", dict(gaze=(HUGE, 0.0)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(1000"),
    ("gaze (0, -huge)", dict(gaze=(0.0, -HUGE)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(0\.0, -1000"),
    ("gaze (nan, 0)", dict(gaze=(math.nan, 0.0)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(nan, 0\.0\)"),
    ("gaze (0, nan)", dict(gaze=(0.0, math.nan)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(0\.0, nan\)"),
    ("gaze (90, 0)", dict(gaze=(90.0, 0.0)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(90\.0, 0\.0\)"),
    ("gaze (0, 90.0001)", dict(gaze=(0.0, 90.0001)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(0\.0, 90\.0001\)"),
    ("gaze (-90, 0)", dict(gaze=(-90.0, 0.0)), r"\(azimuth, elevation\) in \(-90, 90\) degrees, got \(-90\.0, 0\.0\)"),
    ("gaze (True, 0)", dict(gaze=(True, 0.0)), r"real number, got True"),
    ("gaze (0, True)", dict(gaze=(0.0, True)), r"real number, got True"),
    ("gaze ('0', 0)", dict(gaze=("0", 0.0)), r"real number, got '0'"),
    ("gaze ('a', 0)", dict(gaze=("a", 0.0)), r"real number, got 'a'"),
    ("gaze (None, 0)", dict(gaze=(None, 0.0)), r"real number, got None"),
    ("gaze [[[0]]]", dict(gaze=[[[0.0]]]), r"a pair \(azimuth, elevation\) in degrees.*got \[\[\[0\.0\]\]\]"),
    ("gaze 5", dict(gaze=5), r"a pair \(azimuth, elevation\) in degrees.*got 5"),
    ("gaze 0.5", dict(gaze=0.5), r"a pair \(azimuth, elevation\) in degrees.*got 0\.5"),
    ("gaze 'ab'", dict(gaze="ab"), r"a pair \(azimuth, elevation\) in degrees.*got 'ab'"),
    ("gaze (0,)", dict(gaze=(0.0,)), r"a pair \(azimuth, elevation\) in degrees.*got \(0\.0,\)"),
    ("gaze (0, 0, 0)", dict(gaze=(0.0, 0.0, 0.0)), r"a pair \(azimuth, elevation\) in degrees.*got \(0\.0, 0\.0, 0\.0\)"),
    ("gaze {'x': 0}", dict(gaze={"x": 0}), r"a pair \(azimuth, elevation\) in degrees.*got \{'x': 0\}"),
]


@pytest.mark.parametrize("kw, shown", [c[1:] for c in STATE_REFUSALS], ids=[c[0] for c in STATE_REFUSALS])
def test_runtime_state_refuses_values_outside_its_range_in_one_short_line(kw: dict[str, Any], shown: str) -> None:
    (field,) = kw
    with pytest.raises(StateRangeError, match=rf"^{field} must be .*{shown}") as e:
        RuntimeState(**kw)
    assert isinstance(e.value, StateError) and isinstance(e.value, ValueError)
    assert "\n" not in str(e.value) and len(str(e.value)) < 200


# ------------------------------------------------------------------------------ Camera: checks
K = torch.tensor([[50.0, 0.0, 32.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]], dtype=F64)  # a 64 x 48 camera


def _camera(w2c: torch.Tensor | None = None, k: torch.Tensor | None = None, w: Any = 64, h: Any = 48, **extra: Any) -> Camera:
    """A float64 camera, identity pose and ``K`` unless given."""
    return Camera(torch.eye(4, dtype=F64) if w2c is None else w2c, K if k is None else k, w, h, extra)


def _k(**cells: float) -> torch.Tensor:
    """``K`` with cells ``kij`` replaced."""
    k = K.clone()
    for key, v in cells.items():
        k[int(key[1]), int(key[2])] = v
    return k


def _w2c(**cells: float) -> torch.Tensor:
    """The identity pose with cells ``mij`` replaced."""
    m = torch.eye(4, dtype=F64)
    for key, v in cells.items():
        m[int(key[1]), int(key[2])] = v
    return m


CAMERA_REFUSALS = [  # id, Camera arguments, error, message
    ("width 'abc'", dict(w="abc"), InputValueError, r"^width must be an int >= 1 \(pixels\), got 'abc'"),
    ("width 0", dict(w=0), InputValueError, r"^width must be an int >= 1 \(pixels\), got 0"),
    ("width -3", dict(w=-3), InputValueError, r"^width must be an int >= 1 \(pixels\), got -3"),
    ("width 1.5", dict(w=1.5), InputValueError, r"^width must be an int >= 1 \(pixels\), got 1\.5"),
    ("width 64.0", dict(w=64.0), InputValueError, r"^width must be an int >= 1 \(pixels\), got 64\.0"),
    ("width 16.0", dict(w=16.0), InputValueError, r"^width must be an int >= 1 \(pixels\), got 16\.0"),
    ("width None", dict(w=None), InputValueError, r"^width must be an int >= 1 \(pixels\), got None"),
    ("width True", dict(w=True), InputValueError, r"^width must be an int >= 1 \(pixels\), got True"),
    ("width inf", dict(w=math.inf), InputValueError, r"^width must be an int >= 1 \(pixels\), got inf"),
    ("width huge", dict(w=HUGE), InputValueError, rf"^width must be an int <= {MAX_PIXELS} \(pixels\), got an int of"),
    ("width max + 1", dict(w=MAX_PIXELS + 1), InputValueError, rf"^width must be an int <= {MAX_PIXELS}.*{MAX_PIXELS + 1}"),
    ("height 'x'", dict(h="x"), InputValueError, r"^height must be an int >= 1 \(pixels\), got 'x'"),
    ("height 0", dict(h=0), InputValueError, r"^height must be an int >= 1 \(pixels\), got 0"),
    ("height True", dict(h=True), InputValueError, r"^height must be an int >= 1 \(pixels\), got True"),
    ("height '16'", dict(h="16"), InputValueError, r"^height must be an int >= 1 \(pixels\), got '16'"),
    ("height huge", dict(h=HUGE), InputValueError, rf"^height must be an int <= {MAX_PIXELS}"),
    ("K zeros", dict(k=torch.zeros(3, 3, dtype=F64)), InputValueError, r"^intrinsics: focal lengths.*got fx = 0, fy = 0"),
    ("fx 0", dict(k=_k(k00=0.0)), InputValueError, r"^intrinsics: focal lengths.*got fx = 0, fy = 40"),
    ("fx < 0", dict(k=_k(k00=-50.0)), InputValueError, r"^intrinsics: focal lengths.*got fx = -50"),
    ("fy < 0", dict(k=_k(k11=-1.0)), InputValueError, r"^intrinsics: focal lengths.*got fx = 50, fy = -1"),
    ("K22 0", dict(k=_k(k22=0.0)), InputValueError, r"^intrinsics must be \[\[fx.*got .*\[0\.0, 0\.0, 0\.0\]\]"),
    ("K22 2", dict(k=_k(k22=2.0)), InputValueError, r"^intrinsics must be \[\[fx.*got .*\[0\.0, 0\.0, 2\.0\]\]"),
    ("K22 1.00001", dict(k=_k(k22=1.00001)), InputValueError, r"^intrinsics must be \[\[fx.*got .*1\.00001\]\]"),
    ("K20 0.5", dict(k=_k(k20=0.5)), InputValueError, r"^intrinsics must be \[\[fx.*got .*\[0\.5, 0\.0, 1\.0\]\]"),
    ("K20 1e-8", dict(k=_k(k20=1e-8)), InputValueError, r"^intrinsics must be \[\[fx.*got .*\[1e-08, 0\.0, 1\.0\]\]"),
    ("K21 -1e-8", dict(k=_k(k21=-1e-8)), InputValueError, r"^intrinsics must be \[\[fx.*got .*\[0\.0, -1e-08, 1\.0\]\]"),
    ("K10 1e-8", dict(k=_k(k10=1e-8)), InputValueError, r"^intrinsics must be \[\[fx.*got .*\[1e-08, 40\.0, 24\.0\]"),
    ("K nan", dict(k=_k(k02=math.nan)), InputValueError, r"^intrinsics contains 1 non-finite value"),
    ("K 3x4", dict(k=torch.zeros(3, 4, dtype=F64)), ShapeError, r"^intrinsics must have size 3 in dim -1.*got \[3, 4\]"),
    ("K 4x4", dict(k=torch.eye(4, dtype=F64)), ShapeError, r"^intrinsics must have size 3 in dim -2.*got \[4, 4\]"),
    ("K list", dict(k=K.tolist()), InputValueError, r"^intrinsics must be a torch\.Tensor, got list"),
    ("K int", dict(k=K.long()), InputValueError, r"^world_to_camera and intrinsics must be floating-point.*torch\.int64"),
    ("w2c int", dict(w2c=torch.eye(4, dtype=torch.int64)), InputValueError,
     r"^world_to_camera and intrinsics must be floating-point, got torch\.int64"),
    ("w2c zeros", dict(w2c=torch.zeros(4, 4, dtype=F64)), InputValueError, r"^world_to_camera: last row.*\[0\.0, 0\.0, 0\.0, 0\.0\]"),
    ("w2c last row 1", dict(w2c=_w2c(m30=1.0)), InputValueError, r"^world_to_camera: last row.*\[1\.0, 0\.0, 0\.0, 1\.0\]"),
    ("w2c last row 1e-5", dict(w2c=_w2c(m30=1e-5)), InputValueError, r"^world_to_camera: last row.*\[1e-05, 0\.0, 0\.0, 1\.0\]"),
    ("w2c scaled", dict(w2c=_w2c(m00=2.0, m11=2.0, m22=2.0)), InputValueError, r"^world_to_camera: .*orthonormal.*det 8"),
    ("w2c scaled 1.002", dict(w2c=_w2c(m00=1.002)), InputValueError, r"^world_to_camera: .*orthonormal.*up to 0\.004, det 1\.002"),
    ("w2c scaled 1.00075", dict(w2c=_w2c(m00=1.00075)), InputValueError, r"^world_to_camera: .*orthonormal.*up to 0\.0015"),
    ("w2c mirrored", dict(w2c=_w2c(m00=-1.0)), InputValueError, r"^world_to_camera: .*orthonormal.*det -1"),
    ("w2c sheared", dict(w2c=_w2c(m01=0.3)), InputValueError, r"^world_to_camera: .*orthonormal.*up to 0\.3"),
    ("w2c nan", dict(w2c=_w2c(m03=math.nan)), InputValueError, r"^world_to_camera contains 1 non-finite value"),
    ("w2c 3x4", dict(w2c=torch.eye(3, 4, dtype=F64)), ShapeError, r"^world_to_camera must have size 4 in dim -2.*got \[3, 4\]"),
    ("w2c None", dict(w2c=None, none_pose=True), InputValueError, r"^world_to_camera must be a torch\.Tensor, got NoneType"),
]


@pytest.mark.parametrize("kw, error, pattern", [c[1:] for c in CAMERA_REFUSALS], ids=[c[0] for c in CAMERA_REFUSALS])
def test_camera_refuses_bad_sizes_intrinsics_and_poses_naming_them(kw: dict[str, Any], error: type, pattern: str) -> None:
    kw = dict(kw)
    if kw.pop("none_pose", False):
        with pytest.raises(error, match=pattern):
            Camera(None, K, 64, 48)  # type: ignore[arg-type]
        return
    with pytest.raises(error, match=pattern):
        _camera(**kw)


def test_camera_accepts_what_lies_within_its_tolerances() -> None:
    """Float32 round-off of a composed pose and more passes: K's last row within 1e-6, a rotation whose
    R R^T is 5e-4 off the identity (a scale of 1.00025 or 1.0004), the pose's last row within 1e-6; a skew
    is allowed; a 0-d integer tensor is a size."""
    cam = _camera(w=torch.tensor(64), h=48)
    assert (cam.width, cam.height) == (64, 48) and type(cam.width) is int
    _camera(k=_k(k01=0.5))
    _camera(k=_k(k22=1 + 5e-7))
    _camera(w2c=_w2c(m30=5e-7))
    for scale in (1.00025, 1.0004):  # |R R^T - I| = 2 (s - 1) + (s - 1)^2 against a tolerance of 1e-3
        assert _camera(w2c=_w2c(m00=scale)).width == 64


@pytest.mark.parametrize("fx, fy, name", [(5e-324, 16.0, "fx"), (16.0, 5e-324, "fy"), (1e-300, 16.0, "fx"),
                                          (1e300, 16.0, "fx"), (16.0, 1e30, "fy"), (16.0 / FOCAL_RATIO / 2, 16.0, "fx")])
def test_camera_refuses_focal_lengths_without_a_representable_fov(fx: float, fy: float, name: str) -> None:
    k = torch.tensor([[fx, 0.0, 8.0], [0.0, fy, 6.0], [0.0, 0.0, 1.0]], dtype=F64)
    with pytest.raises(InputValueError, match=rf"intrinsics: focal length {name} = K\[\d, \d\] must be in"):
        Camera(torch.eye(4), k, 16, 12)


@pytest.mark.parametrize("ratio", [1.001 / FOCAL_RATIO, 1.0, FOCAL_RATIO / 1.001])
def test_fov_stays_inside_its_documented_range_at_the_focal_limits(ratio: float) -> None:
    for dtype in (torch.float32, torch.float64):
        k = torch.tensor([[16.0 * ratio, 0.0, 8.0], [0.0, 12.0 * ratio, 6.0], [0.0, 0.0, 1.0]], dtype=dtype)
        cam = Camera(torch.eye(4, dtype=dtype), k, 16, 12)
        for fov in cam.fov:
            assert 0.0 < fov < math.pi
        uv, _ = cam.project(torch.tensor([[0.5, -0.5, 1.0]], dtype=dtype))
        assert bool(torch.isfinite(uv).all())


def test_fov_per_axis_by_hand_and_from_scaffold_round_trip():
    """fov = (2 atan(W / 2fx), 2 atan(H / 2fy)) with fx != fy, and Camera.from_scaffold's FoVx, FoVy come
    back out (3DGS's cameras carry the two angles)."""
    cam = Camera(torch.eye(4), torch.tensor([[40.0, 0, 32.0], [0, 20.0, 24.0], [0, 0, 1]]), 64, 48)
    fx, fy = cam.fov
    assert math.isclose(fx, 2 * math.atan(0.8), rel_tol=1e-7) and math.isclose(fy, 2 * math.atan(1.2), rel_tol=1e-7)
    vc = types.SimpleNamespace(world_view_transform=torch.eye(4), image_width=80, image_height=45, FoVx=1.2, FoVy=0.7)
    got = Camera.from_scaffold(vc).fov
    assert math.isclose(got[0], 1.2, rel_tol=1e-6) and math.isclose(got[1], 0.7, rel_tol=1e-6)


# ------------------------------------------------------------------------------ Camera: geometry
def test_camera_centre_and_projection_by_hand():
    # R = rotation by +90 deg about z (x -> y), t = (1, 2, 3): centre = -R^T t = -(2, -1, 3) = (-2, 1, -3)
    w2c = torch.tensor([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=F64)
    cam = _camera(w2c=w2c, uid=7)
    assert torch.allclose(cam.center, torch.tensor([-2.0, 1.0, -3.0], dtype=F64), atol=0)
    assert cam.to_camera(cam.center[None]).tolist() == [[0.0, 0.0, 0.0]]
    # world (1, 0, 1) -> camera R p + t = (0, 1, 1) + (1, 2, 3) = (1, 3, 4); u = 50 * 1/4 + 32, v = 40 * 3/4 + 24
    p = torch.tensor([[1.0, 0.0, 1.0]], dtype=F64)
    assert cam.to_camera(p).tolist() == [[1.0, 3.0, 4.0]]
    uv, z = cam.project(p)
    assert uv.tolist() == [[44.5, 54.0]] and z.tolist() == [4.0]


def test_project_divides_by_the_signed_depth_and_clamps_tiny_depths():
    """``Camera.project`` docstring: a point at camera coordinates ``(x, y, -z)`` lands where ``(x, y, z)``
    does, mirrored through the principal point; only ``|depth| < 1e-12`` is clamped to ``1e-12`` (never
    inf or nan). Identity pose: world = camera coordinates."""
    cam = _camera()
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
    uv0, z0 = cam.project(torch.tensor([[1.0, 0.0, 0.0]], dtype=F64))  # on the camera plane: u = 50 * 1 / 1e-12 + 32
    assert z0.tolist() == [0.0] and math.isclose(float(uv0[0, 0]), 5e13, rel_tol=1e-9) and float(uv0[0, 1]) == 24.0


@given(st.floats(-3, 3), st.floats(-3, 3), st.floats(0.5, 20))
def test_normalized_screen_matches_pixel_convention(x, y, z):
    k = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, 64, 48)
    p = cam.normalized_screen(torch.tensor([[x, y, z]], dtype=F64))[0]
    u, v = 50 * x / z + 32, 50 * y / z + 24
    assert math.isclose(float(p[0]), 2 * u / 64 - 1, abs_tol=1e-9)
    assert math.isclose(float(p[1]), 2 * v / 48 - 1, abs_tol=1e-9)


def test_normalized_screen_puts_points_at_and_behind_the_camera_plane_at_inf():
    # depth exactly 0 (the camera centre itself, and a point beside it) and depth < 0: +inf, never nan or -inf
    k = torch.tensor([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, 64, 48)
    pts = torch.tensor([[0.0, 0.0, 0.0], [-1.0, 0.5, 0.0], [0.3, -0.2, -2.0], [0.3, -0.2, 2.0]], dtype=F64)
    p = cam.normalized_screen(pts)
    assert torch.equal(p[:3], torch.full((3, 2), float("inf"), dtype=F64))
    assert torch.allclose(p[3], torch.tensor([2 * (50 * 0.15 + 32) / 64 - 1, 2 * (50 * -0.1 + 24) / 48 - 1], dtype=F64))


@pytest.mark.parametrize("size, factor, want", [((64, 48), 3.0, (21, 16)), ((64, 48), 2.5, (26, 19)),
                                                ((64, 48), 1000.0, (1, 1)), ((103, 77), 2.0, (52, 38)),
                                                ((100, 60), 1.5, (67, 40)), ((10, 7), 3.0, (3, 2)), ((5, 3), 8.0, (1, 1))])
def test_scaled_rounds_each_side_to_the_nearest_pixel_and_rescales_each_axis(size, factor, want):
    """Camera.scaled(f): size round(size / f) per axis (never below one pixel), K's rows scaled by that
    axis's own ratio (a 64 x 48 camera at f = 3 becomes 21 x 16: x by 21/64, y by 16/48); the pose and a
    copy of ``extra`` are kept; the original camera is not changed."""
    w, h = size
    k = torch.tensor([[50.0, 0.0, w / 2], [0.0, 40.0, h / 2], [0.0, 0.0, 1.0]], dtype=F64)
    w2c = torch.tensor([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=F64)
    cam = Camera(w2c, k, w, h, {"uid": 2})
    small = cam.scaled(factor)
    assert (small.width, small.height) == want
    sx, sy = want[0] / w, want[1] / h
    assert torch.allclose(small.intrinsics, torch.tensor([[50.0 * sx, 0.0, w / 2 * sx], [0.0, 40.0 * sy, h / 2 * sy],
                                                          [0.0, 0.0, 1.0]], dtype=F64), rtol=1e-15, atol=0)
    assert small.extra == {"uid": 2} and small.extra is not cam.extra and torch.equal(small.world_to_camera, w2c)
    assert torch.equal(cam.intrinsics, k) and (cam.width, cam.height) == (w, h)
    corner = w2c[:3, :3].T @ (torch.tensor([w / 2 / 50, h / 2 / 40, 1.0], dtype=F64) - w2c[:3, 3])  # lands on (w, h)
    assert torch.allclose(cam.project(corner[None])[0], torch.tensor([[float(w), float(h)]], dtype=F64))
    assert torch.allclose(small.project(corner[None])[0], torch.tensor([[float(want[0]), float(want[1])]], dtype=F64))


@pytest.mark.parametrize("factor, pattern", [(0, "factor must be"), (-2, "factor must be"), (math.nan, "factor must be"),
                                             ("2", "factor must be"), (None, "factor must be"), (HUGE, "factor must be"),
                                             (5e-324, "factor 4.94066e-324 would give"), (1e-300, "factor 1e-300 would give")],
                         ids=["0", "-2", "nan", "'2'", "None", "huge", "5e-324", "1e-300"])
def test_scaled_refuses_bad_factors(factor: Any, pattern: str) -> None:
    cam = _camera()
    with pytest.raises(InputValueError, match=pattern):
        cam.scaled(factor)
    assert cam.scaled(2).width == 32


# ------------------------------------------------------------------------------ Camera.from_scaffold
@pytest.mark.parametrize("w, h", [(64, 48), (63, 37)])
def test_projection_matches_3dgs_ndc_to_pixel(w, h):
    vc = scaffold_camera(w, h, 1.1, 0.9)
    cam = Camera.from_scaffold(vc)
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.3, 0.5], [-0.5, 0.2, -0.4]], dtype=F64)
    hom = torch.cat([pts, torch.ones(3, 1, dtype=F64)], dim=1) @ vc.full_proj_transform
    ndc = hom[:, :3] / hom[:, 3:]
    # 3DGS's ndc2Pix puts pixel centres at integers: ((ndc + 1) * S - 1) / 2; this library at i + 0.5
    want = torch.stack([((ndc[:, 0] + 1) * w - 1) / 2 + 0.5, ((ndc[:, 1] + 1) * h - 1) / 2 + 0.5], dim=1)
    uv, depth = cam.project(pts.float())
    assert torch.allclose(uv.double(), want, atol=2e-4, rtol=0)
    assert (depth > 0).all()
    assert cam.intrinsics[0, 2].item() == w / 2 and cam.intrinsics[1, 2].item() == h / 2
    fx = w / (2 * math.tan(1.1 / 2))
    assert cam.intrinsics[0, 0].item() == pytest.approx(fx, rel=1e-6)


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
    del vc.uid
    assert Camera.from_scaffold(vc).extra == {}


FROM_SCAFFOLD_REFUSALS = [
    ("FoVx 0", dict(FoVx=0.0), r"FoVx must be a field of view in \(0, pi\).*got 0\.0"),
    ("FoVx pi", dict(FoVx=math.pi), r"FoVx must be a field of view in \(0, pi\).*got 3\.14159"),
    ("FoVx -0.5", dict(FoVx=-0.5), r"FoVx must be a field of view.*got -0\.5"),
    ("FoVx nan", dict(FoVx=math.nan), r"FoVx must be a field of view.*got nan"),
    ("FoVx huge", dict(FoVx=HUGE), r"FoVx must be a field of view.*got inf"),
    ("FoVx 'wide'", dict(FoVx="wide"), r"FoVx must be a real number, got 'wide'"),
    ("FoVy pi", dict(FoVy=math.pi), r"FoVy must be a field of view in \(0, pi\).*got 3\.14159"),
    ("FoVx 5e-324", dict(FoVx=5e-324), r"FoVx = 5e-324 rad gives a focal length of inf px for 16 px"),
    ("FoVy pi - 1e-15", dict(FoVy=math.pi - 1e-15), r"FoVy = 3\.14159\d* rad gives a focal length of .* for 12 px"),
    ("image_width huge", dict(image_width=HUGE), r"image_width must be an int <= \d+ \(pixels\), got an int of"),
    ("image_height 0", dict(image_height=0), r"image_height must be an int >= 1 \(pixels\), got 0"),
    ("uid huge", dict(uid=HUGE), r"uid must be an int < 2\^63.*got an int of"),
    ("uid -1", dict(uid=-1), r"uid must be an int >= 0, got -1"),
]


@pytest.mark.parametrize("kw, pattern", [c[1:] for c in FROM_SCAFFOLD_REFUSALS], ids=[c[0] for c in FROM_SCAFFOLD_REFUSALS])
def test_from_scaffold_refuses_sizes_ids_and_fovs_without_a_usable_focal_length(kw: dict[str, Any], pattern: str) -> None:
    vc = types.SimpleNamespace(**{"world_view_transform": torch.eye(4), "image_width": 16, "image_height": 12,
                                  "FoVx": 1.0, "FoVy": 1.0, "uid": 0, **kw})
    with pytest.raises(InputValueError, match=pattern):
        Camera.from_scaffold(vc)


# ------------------------------------------------------------------------------ stages at a state
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


def test_camera_refuses_meta_tensors_and_a_pose_beyond_float32() -> None:
    k = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]])
    with pytest.raises(InputValueError, match="^intrinsics is on the meta device"):
        Camera(torch.eye(4), k.to("meta"), 8, 6)
    with pytest.raises(InputValueError, match="^world_to_camera is on the meta device"):
        Camera(torch.eye(4, device="meta"), k, 8, 6)
    far = torch.eye(4, dtype=torch.float64)
    far[0, 3] = 1e300
    with pytest.raises(InputValueError, match="^world_to_camera holds values beyond float32"):
        Camera(far, k.double(), 8, 6)
