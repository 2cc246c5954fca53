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
