"""The argument checks: numbers (bounds, open ends, ints of any size, hostile values), tensors (shapes
with symbols, dtypes, finiteness), images and devices, each refusal one short line naming the argument;
``brief`` shows any value in a few characters."""

from __future__ import annotations

import fractions
import math

import pytest
import torch

from controlgs_adapter import checks
from controlgs_adapter.checks import brief, check_number
from controlgs_adapter.errors import InputValueError, ShapeError


@pytest.mark.parametrize("value", [10**400, -10**400, 10**5000, fractions.Fraction(10**400), math.nan, math.inf, -math.inf,
                                   True, "3", None, [1], b"1"], ids=lambda v: type(v).__name__)
@pytest.mark.parametrize("integer", [False, True])
def test_check_number_refuses_what_is_not_a_finite_number_in_range(value: object, integer: bool) -> None:
    with pytest.raises(InputValueError, match=r"^view must be an? (integer|finite number) in \[0, 10\], got ") as e:
        check_number("view", value, integer=integer, low=0, high=10)
    assert "\n" not in str(e.value) and len(str(e.value)) < 200


def test_check_number_returns_ints_of_any_size_and_floats() -> None:
    assert check_number("n", 2**80, integer=True, low=0) == 2**80
    assert check_number("n", 2**80 + 1, integer=True, high=2**80 + 1) == 2**80 + 1
    with pytest.raises(InputValueError, match=rf"n must be an integer in \[-inf, 1\.20893e\+24\], got {2**80 + 2}$"):
        check_number("n", 2**80 + 2, integer=True, high=2**80 + 1)
    assert check_number("x", 10**300, low=0) == 1e300  # within float range: converted
    np = pytest.importorskip("numpy")
    assert type(check_number("x", np.int64(3), integer=True)) is int
    assert check_number("x", 3) == 3.0 and type(check_number("x", 3)) is float


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


@pytest.mark.parametrize("kw, value, ok, words", [
    (dict(low=0.0), 0.0, True, None),  # closed lower bound takes the bound itself
    (dict(low=0.0, low_open=True), 0.0, False, "in (0, inf), got 0.0"),
    (dict(low=0.0, low_open=True), 1e-300, True, None),
    (dict(high=1.0), 1.0, True, None),
    (dict(low=0.0, high=1.0, high_open=True), 1.0, False, "in [0, 1), got 1.0"),
    (dict(low=0.0, high=1.0, high_open=True), 0.999, True, None),
    (dict(low=-2.0), -2.5, False, "in [-2, inf), got -2.5"),
    (dict(high=3.0), 3.5, False, "in [-inf, 3], got 3.5"),
    (dict(), float("nan"), False, "got nan"),
    (dict(), float("inf"), False, "got inf"),
    (dict(), True, False, "got True"),  # a bool is not a number here
    (dict(), "1", False, "got '1'"),
    (dict(integer=True, low=1), 1, True, None),
    (dict(integer=True, low=1), 0, False, "in [1, inf), got 0"),
    (dict(integer=True), 2.0, False, "an integer, got 2.0"),  # a float is not an integer, even 2.0
])
def test_check_number_bounds_and_messages(kw, value, ok, words):
    if ok:
        got = checks.check_number("x", value, **kw)
        assert got == value and type(got) is (int if kw.get("integer") else float)
    else:
        with pytest.raises(InputValueError) as e:
            checks.check_number("x", value, **kw)
        assert str(e.value).startswith("x must be ") and str(e.value).endswith(words)


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
    with pytest.raises(InputValueError, match=r"^x contains 2 non-finite.*out of 4$"):
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
    with pytest.raises(InputValueError, match="one device, got a=cpu, b=meta"):
        checks.check_same_device(a=torch.zeros(1), b=torch.zeros(1, device="meta"))
