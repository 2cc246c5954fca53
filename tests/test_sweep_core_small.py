"""Issue 15 s.5 sweep, core area: the small modules pinned against hand-computed numbers and their
documented contracts (checks, state, schedules, losses, backend helpers, ablations, extras, lock,
errors). Every expected value is written out with how it was obtained."""

from __future__ import annotations

import json
import math
import sys
import types

import pytest
import torch
from torch import nn

from controlgs_adapter import Camera, RuntimeState
from controlgs_adapter import checks, extras, lock
from controlgs_adapter.ablations import ABLATIONS
from controlgs_adapter.backend import Backend, anchor_ids_from_mask, get_attr_path, has_attrs, set_attr_path
from controlgs_adapter.errors import (ControlGSError, FileWriteError, InjectionMissedError, InputValueError,
                                      LifecycleError, MissingDependencyError, NonFiniteError, RunLockedError,
                                      ShapeError, StateError, StateRangeError, TargetError)
from controlgs_adapter.losses import LPIPS_UNAVAILABLE, ImageLoss, LossWeights, image_loss
from controlgs_adapter.builtin import controlgs_register_schedules
from controlgs_adapter.schedules import (BUILTIN_SCHEDULES, DisplaySchedule, FoveationSchedule, LensSchedule,
                                         ResampleSchedule, StrengthSchedule)

# ---------------------------------------------------------------------------------------------- checks


@pytest.mark.parametrize("kw, value, ok, words", [
    (dict(low=0.0), 0.0, True, None),  # closed lower bound takes the bound itself
    (dict(low=0.0, low_open=True), 0.0, False, "in (0, inf)"),
    (dict(low=0.0, low_open=True), 1e-300, True, None),
    (dict(high=1.0), 1.0, True, None),
    (dict(low=0.0, high=1.0, high_open=True), 1.0, False, "in [0, 1)"),
    (dict(low=0.0, high=1.0, high_open=True), 0.999, True, None),
    (dict(low=-2.0), -2.5, False, "in [-2, inf)"),
    (dict(high=3.0), 3.5, False, "in [-inf, 3]"),
    (dict(), float("nan"), False, "a finite number, got nan"),
    (dict(), float("inf"), False, "a finite number, got inf"),
    (dict(), True, False, "got True"),  # a bool is not a number here
    (dict(), "1", False, "got '1'"),
    (dict(integer=True, low=1), 1, True, None),
    (dict(integer=True, low=1), 0, False, "an integer in [1, inf)"),
    (dict(integer=True), 2.0, False, "an integer, got 2.0"),  # a float is not an integer, even 2.0
])
def test_check_number_bounds_and_messages(kw, value, ok, words):
    if ok:
        got = checks.check_number("x", value, **kw)
        assert got == value and type(got) is (int if kw.get("integer") else float)
    else:
        with pytest.raises(InputValueError) as e:
            checks.check_number("x", value, **kw)
        assert str(e.value).startswith("x must be ") and words in str(e.value)


def test_check_number_converts_numpy_and_int_values():
    np = pytest.importorskip("numpy")
    assert type(checks.check_number("x", np.int64(3), integer=True)) is int
    assert checks.check_number("x", 3) == 3.0 and type(checks.check_number("x", 3)) is float


def test_check_tensor_shapes_star_symbols_dtypes_and_bound_sizes():
    x = torch.zeros(2, 5, 3)
    assert checks.check_tensor("x", x, ["*", "H", 3]) == {"H": 5}
    assert checks.check_tensor("x", torch.zeros(5, 3), ["*", "H", 3]) == {"H": 5}  # "*" may be no dim at all
    assert checks.check_tensor("x", x, None) == {}
    assert checks.check_tensor("x", x, ["B", "H", 3], dims={"H": 5}) == {"B": 2, "H": 5}
    with pytest.raises(InputValueError, match="x must be a torch.Tensor, got list"):
        checks.check_tensor("x", [1.0])
    with pytest.raises(ShapeError, match=r"x must have shape \[\.\.\., H, 3\], got \[3\]"):
        checks.check_tensor("x", torch.zeros(3), ["*", "H", 3])
    with pytest.raises(ShapeError, match=r"x must have shape \[R, 2\], got \[2, 5, 3\]"):
        checks.check_tensor("x", x, ["R", 2])
    with pytest.raises(ShapeError, match=r"x must have size 4 in dim -1 \(shape \['\*', 'H', 4\]\), got \[2, 5, 3\]"):
        checks.check_tensor("x", x, ["*", "H", 4])
    with pytest.raises(ShapeError, match=r"x must have size 3 in dim -3"):
        checks.check_tensor("x", x, [3, 5, 3])
    with pytest.raises(ShapeError, match="dim 'H' must be 4, got 5"):
        checks.check_tensor("x", x, ["B", "H", 3], dims={"H": 4})
    with pytest.raises(ShapeError, match="dim 'S' must be 2, got 5"):  # one symbol twice: sizes must agree
        checks.check_tensor("x", x, ["S", "S", 3])
    with pytest.raises(InputValueError, match=r"x must have dtype in \['torch.float64'\], got torch.float32"):
        checks.check_tensor("x", x, dtypes=(torch.float64,))
    checks.check_tensor("x", x.double(), dtypes=(torch.float64,))


def test_check_finite_counts_and_value_checks_switch():
    x = torch.tensor([1.0, float("nan"), float("inf"), 2.0])
    with pytest.raises(InputValueError, match=r"^x contains 2 non-finite value\(s\) \(NaN/Inf\) out of 4$"):
        checks.check_finite("x", x)
    with pytest.raises(InputValueError, match="non-finite"):
        checks.check_tensor("x", x, finite=True)
    checks.check_tensor("x", x)  # finite=False (default): no value check
    checks.check_finite("i", torch.tensor([1, 2]))  # integer tensors hold no NaN
    assert checks.value_checks_enabled() is True  # the default
    with checks.value_checks(False):
        assert checks.value_checks_enabled() is False
        checks.check_finite("x", x)  # skipped
        with checks.value_checks(True):
            with pytest.raises(InputValueError):
                checks.check_finite("x", x)
        assert checks.value_checks_enabled() is False
    assert checks.value_checks_enabled() is True
    with pytest.raises(RuntimeError), checks.value_checks(False):  # restored even when the block raises
        raise RuntimeError
    assert checks.value_checks_enabled() is True


def test_check_image_and_same_device():
    assert checks.check_image("img", torch.zeros(2, 3, 4, 5)) == {"H": 4, "W": 5}
    with pytest.raises(ShapeError, match="img must have H, W >= 1, got H=0, W=5"):
        checks.check_image("img", torch.zeros(3, 0, 5))
    with pytest.raises(ShapeError, match="img must have H, W >= 1, got H=4, W=0"):
        checks.check_image("img", torch.zeros(3, 4, 0))
    with pytest.raises(InputValueError, match="dtype"):
        checks.check_image("img", torch.zeros(3, 4, 5, dtype=torch.float16))
    bad = torch.zeros(3, 2, 2)
    bad[0, 0, 0] = float("nan")
    with pytest.raises(InputValueError, match="img contains 1 non-finite"):
        checks.check_image("img", bad)  # finite by default
    checks.check_image("img", bad, finite=False)
    checks.check_same_device(a=torch.zeros(1), b=torch.zeros(2), c=None)
    with pytest.raises(InputValueError, match="tensors must be on one device, got a=cpu, b=meta"):
        checks.check_same_device(a=torch.zeros(1), b=torch.zeros(1, device="meta"))


# ---------------------------------------------------------------------------------------------- state


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


def _camera(w2c=None, k=None, w=64, h=48, **extra):
    k = torch.tensor([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], dtype=torch.float64) if k is None else k
    return Camera(torch.eye(4, dtype=torch.float64) if w2c is None else w2c, k, w, h, extra)


def test_camera_refuses_bad_sizes_intrinsics_and_non_rigid_poses():
    cam = _camera(w=torch.tensor(64), h=48)
    assert (cam.width, cam.height) == (64, 48) and type(cam.width) is int
    for kw, word in [(dict(w=0), "width must be an int >= 1 (pixels), got 0"), (dict(h=True), "height must be an int >= 1"),
                     (dict(w=64.0), "width must be an int >= 1")]:
        with pytest.raises(InputValueError, match=word.replace("(", r"\(").replace(")", r"\)")):
            _camera(**kw)
    k = torch.tensor([[50.0, 0, 32.0], [0, 40.0, 24.0], [0, 0, 1]], dtype=torch.float64)
    _camera(k=k.clone().index_put_((torch.tensor(0), torch.tensor(1)), torch.tensor(0.5, dtype=torch.float64)))  # skew ok
    for (i, j), v, word in [((0, 0), 0.0, "focal lengths"), ((1, 1), -1.0, "focal lengths"), ((2, 2), 1.00001, "must be [[fx"),
                            ((2, 0), 1e-8, "must be [[fx"), ((2, 1), -1e-8, "must be [[fx"), ((1, 0), 1e-8, "must be [[fx")]:
        bad = k.clone()
        bad[i, j] = v
        with pytest.raises(InputValueError, match="intrinsics") as e:
            _camera(k=bad)
        assert word in str(e.value), (i, j)
    _camera(k=k.clone().index_put_((torch.tensor(2), torch.tensor(2)), torch.tensor(1 + 5e-7, dtype=torch.float64)))
    with pytest.raises(InputValueError, match="floating-point"):
        Camera(torch.eye(4, dtype=torch.int64), k, 64, 48)
    with pytest.raises(ShapeError, match="intrinsics"):
        Camera(torch.eye(4), torch.eye(4), 64, 48)
    with pytest.raises(InputValueError, match="world_to_camera contains 1 non-finite"):
        Camera(torch.eye(4).index_put_((torch.tensor(0), torch.tensor(3)), torch.tensor(float("nan"))), k, 64, 48)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[3, 0] = 1e-5
    with pytest.raises(InputValueError, match="last row must be"):
        _camera(w2c=w2c)
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[3, 0] = 5e-7  # within the 1e-6 tolerance
    _camera(w2c=w2c)
    for scale, ok in [(1.0004, True), (1.002, False)]:  # |R R^T - I| = 2 (s - 1) + (s-1)^2 vs tol 1e-3
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[0, 0] = scale
        if ok:
            _camera(w2c=w2c)
        else:
            with pytest.raises(InputValueError, match="orthonormal"):
                _camera(w2c=w2c)
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64))
    with pytest.raises(InputValueError, match="det -1"):
        _camera(w2c=mirror)


def test_camera_centre_scaling_and_projection_by_hand():
    # R = rotation by +90 deg about z (x -> y), t = (1, 2, 3): centre = -R^T t = -(2, -1, 3) = (-2, 1, -3)
    w2c = torch.tensor([[0.0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]], dtype=torch.float64)
    cam = _camera(w2c=w2c, uid=7)
    assert torch.allclose(cam.center, torch.tensor([-2.0, 1.0, -3.0], dtype=torch.float64), atol=0)
    # world (1, 0, 1) -> camera R p + t = (0, 1, 1) + (1, 2, 3) = (1, 3, 4); u = 50 * 1/4 + 32, v = 40 * 3/4 + 24
    p = torch.tensor([[1.0, 0.0, 1.0]], dtype=torch.float64)
    assert cam.to_camera(p).tolist() == [[1.0, 3.0, 4.0]]
    uv, z = cam.project(p)
    assert uv.tolist() == [[44.5, 54.0]] and z.tolist() == [4.0]
    # a point on the camera plane: depth 0 is divided as 1e-12 (finite, not inf): u = 50 * 1 / 1e-12 + 32
    uv0, z0 = _camera().project(torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64))
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


# ---------------------------------------------------------------------------------------------- schedules


def test_schedule_defaults_flags_and_repr():
    table = {LensSchedule: ("lens", True, 0.0, math.sqrt(2.0)), ResampleSchedule: ("resample", False, 0.0, 3.0),
             DisplaySchedule: ("display", False, 0.0, 0.8), FoveationSchedule: ("foveation", True, 0.0, math.sqrt(2.0))}
    for cls, (name, per_anchor, lo, hi) in table.items():
        s = cls()
        assert (s.name, s.per_anchor, s.lo, s.hi) == (name, per_anchor, lo, hi)
        assert s.endpoints() == {"lo": lo, "hi": hi}
    assert BUILTIN_SCHEDULES == tuple(table)
    assert [type(s) for s in controlgs_register_schedules()] == list(table)
    base = StrengthSchedule()
    assert (base.lo, base.hi, base.per_anchor) == (0.0, 1.0, False)
    with pytest.raises(NotImplementedError):
        base.control(RuntimeState(), None)
    assert repr(LensSchedule()) == "LensSchedule(||p||_2: 0 -> 0, 1.41421 -> 1)"
    assert repr(ResampleSchedule(0.5, 2)) == "ResampleSchedule(log2(d): 0.5 -> 0, 2 -> 1)"


def test_schedule_endpoints_and_strength_by_hand():
    s = ResampleSchedule().with_endpoints(hi=2.0)
    assert type(s) is ResampleSchedule and (s.lo, s.hi) == (0.0, 2.0)
    assert (s.with_endpoints(lo=1.0).lo, s.with_endpoints(lo=1.0).hi) == (1.0, 2.0)
    # log2(2) = 1 -> (1 - 0) / (2 - 0) = 0.5; log2(8) = 3 -> 1.5 clamps to 1; d = 1 -> 0
    assert s.strength(RuntimeState(downsample=2.0), rows=2).tolist() == [0.5, 0.5]
    assert s.scalar_strength(3.0) == 1.0 and s.scalar_strength(-1.0) == 0.0 and s.scalar_strength(0.5) == 0.25
    lam = DisplaySchedule().strength(RuntimeState(power_saving=0.2), rows=3, dtype=torch.float64)
    assert lam.dtype == torch.float64 and lam.tolist() == [0.2 / 0.8] * 3  # rho / 0.8
    lam = DisplaySchedule().strength(RuntimeState(power_saving=0.4), torch.zeros(4, 2), dtype=torch.float64)
    assert lam.tolist() == [0.5] * 4  # a global schedule takes its row count from screen_xy
    assert DisplaySchedule().strength(RuntimeState(), rows=2, device="meta").device.type == "meta"
    # device: screen_xy's unless given
    assert LensSchedule().strength(RuntimeState(), torch.zeros(2, 2)).device.type == "cpu"
    assert LensSchedule().strength(RuntimeState(), torch.zeros(2, 2), device="meta").device.type == "meta"
    with pytest.raises(InputValueError, match="strength\\(\\) needs screen_xy or rows"):
        DisplaySchedule().strength(RuntimeState())
    with pytest.raises(ShapeError, match="screen_xy"):
        DisplaySchedule().strength(RuntimeState(), torch.zeros(4, 3))
    with pytest.raises(InputValueError, match="schedule 'foveation' is per anchor and needs screen_xy"):
        FoveationSchedule().strength(RuntimeState(gaze=(0.0, 0.0)), rows=3)
    # lens (lo 0.5, hi 1.5): radius 0 -> clamps to 0, 1 -> 0.5, (3, 4) radius 5 -> clamps to 1
    xy = torch.tensor([[0.0, 0.0], [0.6, 0.8], [3.0, 4.0]], dtype=torch.float64)
    assert LensSchedule(0.5, 1.5).strength(RuntimeState(), xy, dtype=torch.float64).tolist() == [0.0, 0.5, 1.0]
    # foveation about gaze (0.6, 0.8): distances 1, 0, 5 with default (0, sqrt 2)
    got = FoveationSchedule().strength(RuntimeState(gaze=(0.6, 0.8)), xy, dtype=torch.float64)
    assert torch.allclose(got, torch.tensor([1 / math.sqrt(2.0), 0.0, 1.0], dtype=torch.float64), rtol=1e-12, atol=0)
    for lo, hi, word in [("0", 1.0, "finite numbers"), (0.0, float("nan"), "finite numbers"), (1.0, 1, "must differ")]:
        with pytest.raises(InputValueError, match=word):
            LensSchedule(lo, hi)


# ---------------------------------------------------------------------------------------------- losses


def test_loss_weights_defaults_and_refusals():
    w = LossWeights()
    assert (w.l1, w.ssim, w.mse, w.lpips) == (0.8, 0.2, 10.0, 0.0)  # the paper's real-scene weights (Eq. 14)
    assert LossWeights(l1=0, ssim=0, mse=0).l1 == 0.0
    with pytest.raises(InputValueError, match=r"loss weight mse must be a finite number in \[0, inf\), got -1"):
        LossWeights(mse=-1)
    with pytest.raises(InputValueError) as e:
        LossWeights(lpips=0.1)
    assert str(e.value) == LPIPS_UNAVAILABLE + " (got lpips=0.1)"


def test_image_loss_by_hand():
    pred = torch.full((2, 3, 12, 12), 0.5, dtype=torch.float64)
    target = torch.full((2, 3, 12, 12), 0.25, dtype=torch.float64)
    # L1 and MSE only: 0.8 * 0.25 + 10 * 0.25^2 = 0.2 + 0.625
    got = image_loss(pred, target, LossWeights(ssim=0.0))
    assert math.isclose(float(got), 0.825, rel_tol=1e-14)
    # SSIM of two constant images (zero variances): (2ab + C1) / (a^2 + b^2 + C1), C1 = 0.01^2
    s = (2 * 0.5 * 0.25 + 1e-4) / (0.5**2 + 0.25**2 + 1e-4)
    got = image_loss(pred, target, LossWeights(l1=0.0, ssim=1.0, mse=0.0))
    assert math.isclose(float(got), 1.0 - s, rel_tol=1e-9)
    # defaults: 0.8 L1 + 0.2 (1 - SSIM) + 10 MSE
    assert math.isclose(float(image_loss(pred, target)), 0.825 + 0.2 * (1.0 - s), rel_tol=1e-9)
    assert math.isclose(float(ImageLoss(LossWeights(ssim=0.0))(pred, target)), 0.825, rel_tol=1e-14)
    assert float(image_loss(pred, pred)) == 0.0
    # sign matters for L1 (|d|), not a plain mean of differences: 0.8 * 0.25 + 10 * 0.0625
    assert math.isclose(float(image_loss(target, pred, LossWeights(ssim=0.0))), 0.825, rel_tol=1e-14)
    with pytest.raises(ShapeError):
        image_loss(pred, target[..., :11])


# ---------------------------------------------------------------------------------------------- backend


def test_attr_paths_on_modules_lists_and_plain_objects():
    seq = nn.Sequential(nn.Linear(2, 3), nn.ReLU())
    obj = types.SimpleNamespace(net=seq, layers=[types.SimpleNamespace(w=1), types.SimpleNamespace(w=2)], none=None)
    assert get_attr_path(obj, "net.0") is seq[0]
    assert get_attr_path(obj, "layers.1.w") == 2
    set_attr_path(obj, "layers.0.w", 5)
    set_attr_path(obj, "layers.1", "x")
    new = nn.Linear(2, 3)
    set_attr_path(obj, "net.0", new)
    set_attr_path(obj, "top", 9)
    assert obj.layers[0].w == 5 and obj.layers[1] == "x" and seq[0] is new and obj.top == 9
    assert has_attrs(obj, ["net.0.weight", "none", "layers"]) and not has_attrs(obj, ["net.0.weights"])
    assert not has_attrs(obj, ["net", "missing.x"])
    with pytest.raises(IndexError):
        get_attr_path(obj, "layers.2")


def test_anchor_ids_from_mask():
    mask = torch.tensor([False, True, True, False, True])
    assert anchor_ids_from_mask(mask).tolist() == [1, 2, 4]
    assert anchor_ids_from_mask(mask, 5).tolist() == [1, 2, 4]
    assert anchor_ids_from_mask(torch.zeros(3, dtype=torch.bool), 3).tolist() == []
    with pytest.raises(ShapeError, match="vis must have size 4"):
        anchor_ids_from_mask(mask, 4, name="vis")
    with pytest.raises(InputValueError, match="visible_mask must have dtype"):
        anchor_ids_from_mask(mask.long())


class _Toy(Backend):
    """Toy backend: two Sequential decoders."""

    name = "toy"

    def __init__(self, layout=None):
        self.layout = layout

    def matches(self, model):
        return hasattr(model, "dec_a")

    def decoder_paths(self, model):
        return ["dec_a", "dec_b"]

    def anchor_positions(self, model):
        return model.pos

    def input_layout(self, model, decoder_path):
        return self.layout


def _toy_model(n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return types.SimpleNamespace(pos=torch.rand(n, 3, generator=g),
                                 dec_a=nn.Sequential(nn.Linear(5, 4), nn.ReLU()), dec_b=nn.Sequential(nn.ReLU()))


def test_backend_defaults_and_check_decoder():
    b, m = _Toy(), _toy_model()
    assert b.first_linear_path(m, "dec_a") == "dec_a.0" and b.rows_per_anchor(m) == 1 and b.num_anchors(m) == 4
    assert b.default_targets(m) == ["dec_a", "dec_b"] and b.input_layout(m, "dec_a") is None
    assert b.rows_for(m, torch.tensor([True, False, False, True])).tolist() == [0, 3]
    with pytest.raises(ShapeError):
        b.rows_for(m, torch.tensor([True, False, True]))  # the mask must cover the model's 4 anchors
    assert b.make_hookable(m, "dec_a") is None and b.renderer(m) is None
    assert b.check_decoder(m, "dec_a") is m.dec_a[0]
    with pytest.raises(TargetError, match="toy: first layer of 'dec_b' must be a Linear, got ReLU"):
        b.check_decoder(m, "dec_b")
    with pytest.raises(TargetError, match="toy: decoder 'dec_c' has no first layer"):
        b.check_decoder(m, "dec_c")
    assert _Toy([("feat", 3), ("view", 2)]).check_decoder(m, "dec_a") is m.dec_a[0]
    with pytest.raises(TargetError) as e:
        _Toy([("feat", 3), ("view", 3)]).check_decoder(m, "dec_a")
    assert str(e.value) == "toy: dec_a[0] takes 5 inputs, the model's configuration gives 6 ([('feat', 3), ('view', 3)])"
    for name in ("matches", "decoder_paths", "anchor_positions"):
        with pytest.raises(NotImplementedError):
            getattr(Backend(), name)(m)


def test_backend_fingerprint_follows_positions_weights_and_selected_anchors():
    b = _Toy()
    m, same = _toy_model(seed=0), _toy_model(seed=0)
    same.dec_a.load_state_dict(m.dec_a.state_dict())
    fp = b.fingerprint(m)
    assert len(fp) == 16 and int(fp, 16) >= 0 and fp == b.fingerprint(same)
    with torch.no_grad():
        same.dec_a[0].bias[0] += 1e-3
    assert b.fingerprint(same) != fp  # decoder weights count
    moved = _toy_model(seed=0)
    moved.dec_a.load_state_dict(m.dec_a.state_dict())
    moved.pos[2, 1] += 1e-3
    assert b.fingerprint(moved) != fp  # positions count
    # anchor_ids: exactly the fingerprint of a model holding those anchors, in that order
    sub = types.SimpleNamespace(pos=m.pos[[3, 1]].clone(), dec_a=m.dec_a, dec_b=m.dec_b)
    assert b.fingerprint(m, torch.tensor([3, 1])) == b.fingerprint(sub)
    assert b.fingerprint(m, torch.tensor([1, 3])) != b.fingerprint(sub)


# ---------------------------------------------------------------------------------------------- the rest


def test_ablations_table_is_the_papers():
    assert ABLATIONS == {"wo_lens": (("resample", "display"), False), "wo_display": (("lens", "resample"), False),
                         "wo_resample": (("lens", "display"), False),
                         "state_blind": (("lens", "resample", "display"), True)}


def test_error_taxonomy_keeps_builtin_bases():
    pairs = [(ShapeError, ValueError), (InputValueError, ValueError), (StateRangeError, StateError),
             (StateError, InputValueError), (LifecycleError, RuntimeError), (TargetError, ValueError),
             (NonFiniteError, FloatingPointError), (NonFiniteError, InputValueError),
             (MissingDependencyError, ImportError), (FileWriteError, OSError), (RunLockedError, RuntimeError),
             (InjectionMissedError, RuntimeError)]
    for sub, base in pairs:
        assert issubclass(sub, base) and issubclass(sub, ControlGSError), sub


def test_extras_usable_only_for_real_file_backed_packages(monkeypatch):
    assert extras.EXTRAS["optics"] == (("optiland", "optiland", ()),)
    assert [e[:2] for e in extras.EXTRAS["demo"]] == [("skimage", "scikit-image"), ("matplotlib", "matplotlib")]
    monkeypatch.setitem(sys.modules, "cgs_standin_pkg", types.ModuleType("cgs_standin_pkg"))  # no __file__
    monkeypatch.setitem(extras.EXTRAS, "t", (("json", "json-dist", ("json.decoder",)),
                                             ("cgs_standin_pkg", "standin-dist", ()),
                                             ("cgs_no_such_module_xyz", "absent-dist", ()),
                                             ("json", "json-broken", ("json.no_such_sub",))))
    assert extras.missing_modules("t") == ["standin-dist", "absent-dist", "json-broken"]
    assert extras.missing_modules("t", only=("cgs_standin_pkg",)) == ["standin-dist"]
    assert extras.missing_modules("t", only=("other",)) == []
    extras.require("t", "the thing", only=("other",))
    with pytest.raises(MissingDependencyError) as e:
        extras.require("t", "the thing", only=("cgs_standin_pkg", "cgs_no_such_module_xyz"))
    assert str(e.value) == ("the thing needs standin-dist and absent-dist, which is not installed: "
                            "pip install 'controlgs-adapter[t]'")


def test_run_lock_records_the_holder_and_refuses_a_second_holder(tmp_path):
    import os

    folder = tmp_path / "run" / "deep"
    assert lock.lock_holder(folder) is None
    with lock.run_lock(folder) as path:
        assert path == folder / lock.LOCK_NAME == folder / ".lock"
        held = lock.lock_holder(folder)
        assert held["pid"] == os.getpid() and isinstance(held["time"], float) and held["command"]
        with pytest.raises(RunLockedError) as e:  # a second open file description of the same file
            with lock.run_lock(folder):
                pass
        assert f"pid {os.getpid()} on {held['host']} since " in str(e.value) and str(folder) in str(e.value)
    assert path.read_text() == "" and lock.lock_holder(folder) is None  # emptied on release
    with lock.run_lock(folder):  # released: it can be taken again
        pass
    (tmp_path / "f").write_text("x")
    with pytest.raises(FileWriteError, match="cannot create the run folder's lock file"):
        with lock.run_lock(tmp_path / "f"):
            pass


def test_lock_holder_descriptions(tmp_path):
    (tmp_path / ".lock").write_text("{not json")
    assert lock.lock_holder(tmp_path) is None
    assert lock._describe(None) == "another process (its lock file is unreadable)"
    assert lock._describe({"pid": 5, "host": "h", "time": "x"}) == "pid 5 on h since ? (?)"
    (tmp_path / ".lock").write_text(json.dumps({"pid": 5, "host": "h", "time": 0, "command": "c"}))
    import time as _time
    want = _time.strftime("%Y-%m-%d %H:%M:%S", _time.localtime(0))
    assert lock._describe(lock.lock_holder(tmp_path)) == f"pid 5 on h since {want} (c)"


def test_value_objects_are_frozen():
    import dataclasses

    from controlgs_adapter.controlgs import Target
    from controlgs_adapter.plugins import PluginInfo
    from controlgs_adapter.training import TrainConfig

    objs = [(LossWeights(), "l1"), (RuntimeState(), "downsample"), (TrainConfig(), "lr"),
            (Target("d", "d.0", 3, 4, False), "fc1"), (PluginInfo("stage", "n", "p", "s", None), "name")]
    for obj, field in objs:
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, field, 1)
    assert hash(LossWeights()) == hash(LossWeights(0.8, 0.2, 10.0, 0.0))  # frozen dataclasses hash by value
