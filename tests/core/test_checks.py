"""check_number and brief: numbers of any size and values of any shape give the library's error, in one short line."""

from __future__ import annotations

import fractions
import math

import pytest

from controlgs_adapter.checks import brief, check_number
from controlgs_adapter.errors import InputValueError


@pytest.mark.parametrize("value", [10**400, -10**400, 10**5000, fractions.Fraction(10**400), math.nan, math.inf, -math.inf,
                                   True, "3", None, [1], b"1"], ids=lambda v: type(v).__name__)
@pytest.mark.parametrize("integer", [False, True])
def test_check_number_refuses_what_is_not_a_finite_number_in_range(value: object, integer: bool) -> None:
    with pytest.raises(InputValueError, match=r"^view must be an? (integer|finite number) in \[0, 10\], got ") as e:
        check_number("view", value, integer=integer, low=0, high=10)
    assert "\n" not in str(e.value) and len(str(e.value)) < 200


def test_check_number_takes_ints_of_any_size_within_the_range() -> None:
    assert check_number("n", 2**80, integer=True, low=0) == 2**80
    assert check_number("n", 2**80 + 1, integer=True, high=2**80 + 1) == 2**80 + 1
    with pytest.raises(InputValueError, match="n must be an integer"):
        check_number("n", 2**80 + 2, integer=True, high=2**80 + 1)
    assert check_number("x", 10**300, low=0) == 1e300  # within float range: converted


def test_brief_never_raises_and_stays_short() -> None:
    nested: list = []
    for _ in range(100_000):
        nested = [nested]
    assert brief(nested) == "[[[[...]]]]"
    assert brief(10**5000) == "an int of about 5001 digits"  # repr() itself raises past 4300 digits
    assert len(brief("a" * 10_000)) < 80 and brief("a") == "'a'"

    class Broken:
        def __repr__(self) -> str:
            raise RuntimeError("no repr")

    assert brief(Broken()).startswith("<Broken")
