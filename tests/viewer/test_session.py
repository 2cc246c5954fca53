"""parse_state on hostile request values: numbers of any size, NaN / inf, wrong types and any nesting give
the library's error naming the field, in one short line."""

from __future__ import annotations

import json
from typing import Any

import pytest

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.viewer.session import parse_state

HUGE = 10**400  # what json.loads makes of a 401-digit number


def _nested(depth: int) -> Any:
    out: Any = 0.5
    for _ in range(depth):
        out = [out]
    return out


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
