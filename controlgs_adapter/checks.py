"""Input checks for the public API (kornia/gsplat style): each raises with the argument's name,
what was expected and what came.

Shapes are given as sequences whose items are ints (exact), strings (symbolic: equal names must
agree) or ``"*"`` (any number of leading dims, only first).

Checks of tensor *values* (NaN/Inf, ranges) read the tensor on the host: one device sync each.
:func:`value_checks` turns them off for a block (the training step does, and checks its loss and
parameters once instead); shape, dtype and device checks always run.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import numbers
import reprlib
from typing import Iterator, Sequence

import torch

from .errors import InputValueError, ShapeError

__all__ = ["check_tensor", "check_image", "check_finite", "check_same_device", "check_number", "value_checks",
           "value_checks_enabled", "brief"]

_VALUE_CHECKS: contextvars.ContextVar[bool] = contextvars.ContextVar("controlgs_value_checks", default=True)


@contextlib.contextmanager
def value_checks(enabled: bool) -> Iterator[None]:
    """Turn the value checks (:func:`check_finite` and the range checks that consult
    :func:`value_checks_enabled`) on or off inside the block (per thread / task)."""
    token = _VALUE_CHECKS.set(bool(enabled))
    try:
        yield
    finally:
        _VALUE_CHECKS.reset(token)


def value_checks_enabled() -> bool:
    """False inside ``value_checks(False)``: skip checks that would read tensor values on the host."""
    return _VALUE_CHECKS.get()


def check_tensor(
    name: str,
    x: object,
    shape: Sequence[int | str] | None = None,
    *,
    dtypes: Sequence[torch.dtype] | None = None,
    finite: bool = False,
    dims: dict[str, int] | None = None,
) -> dict[str, int]:
    """Validate ``x`` and return the sizes bound to the symbolic dims of ``shape``.

    Example: ``check_tensor("image", img, ["*", 3, "H", "W"], dtypes=(torch.float32, torch.float64))``.
    ``dims`` pre-binds symbolic names (e.g. ``{"H": 64}``).
    """
    if not isinstance(x, torch.Tensor):
        raise InputValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    bound: dict[str, int] = dict(dims or {})
    if shape is not None:
        spec = list(shape)
        star = bool(spec) and spec[0] == "*"
        fixed = spec[1:] if star else spec
        if (x.dim() < len(fixed)) if star else (x.dim() != len(fixed)):
            wanted = ("[..., " if star else "[") + ", ".join(map(str, fixed)) + "]"
            raise ShapeError(f"{name} must have shape {wanted}, got {list(x.shape)}")
        for i, (want, got) in enumerate(zip(fixed, x.shape[x.dim() - len(fixed):])):
            if isinstance(want, int) and want != got:
                raise ShapeError(
                    f"{name} must have size {want} in dim {i - len(fixed)} (shape {list(shape)}), got {list(x.shape)}"
                )
            if isinstance(want, str):
                if want in bound and bound[want] != got:
                    raise ShapeError(f"{name}: dim '{want}' must be {bound[want]}, got {got} (shape {list(x.shape)})")
                bound[want] = int(got)
    if dtypes is not None and x.dtype not in tuple(dtypes):
        raise InputValueError(f"{name} must have dtype in {[str(d) for d in dtypes]}, got {x.dtype}")
    if finite:
        check_finite(name, x)
    return bound


def check_finite(name: str, x: torch.Tensor) -> None:
    """Raise if ``x`` holds NaN or Inf, saying how many (skipped inside ``value_checks(False)``)."""
    if (x.is_floating_point() or x.is_complex()) and _VALUE_CHECKS.get():
        bad = ~torch.isfinite(x)
        if bool(bad.any()):
            raise InputValueError(f"{name} contains {int(bad.sum())} non-finite value(s) (NaN/Inf) out of {x.numel()}")


def check_image(name: str, x: object, *, finite: bool = True) -> dict[str, int]:
    """An image ``[..., 3, H, W]`` of float32/float64 with H, W >= 1."""
    b = check_tensor(name, x, ["*", 3, "H", "W"], dtypes=(torch.float32, torch.float64), finite=finite)
    if b["H"] < 1 or b["W"] < 1:
        raise ShapeError(f"{name} must have H, W >= 1, got H={b['H']}, W={b['W']}")
    return b


def check_same_device(**tensors: torch.Tensor) -> None:
    """All named tensors live on one device."""
    devs = {k: v.device for k, v in tensors.items() if isinstance(v, torch.Tensor)}
    if len(set(devs.values())) > 1:
        raise InputValueError("tensors must be on one device, got " + ", ".join(f"{k}={d}" for k, d in devs.items()))


def check_number(name: str, value: object, *, integer: bool = False, low: float | None = None,
                 high: float | None = None, low_open: bool = False, high_open: bool = False) -> float | int:
    """A finite real number (an int if ``integer``) in the given range; bools and strings are
    refused. Returns it as ``int``/``float``; raises :class:`InputValueError` naming ``name``
    (also for ints of any size, NaN and infinities)."""
    kind = "an integer" if integer else "a finite number"
    rng = ""
    if low is not None or high is not None:
        rng = " in " + ("(" if low_open else "[") + ("-inf" if low is None else f"{low:g}") + ", " + \
              ("inf" if high is None else f"{high:g}") + (")" if high_open or high is None else "]")
    v: float | int | None = None  # None: not a number of the wanted kind
    if not isinstance(value, bool):
        try:
            if integer and isinstance(value, numbers.Integral):
                v = int(value)  # any size: compared with the bounds exactly, never converted to float
            elif not integer and isinstance(value, numbers.Real):
                v = float(value)
        except (OverflowError, ValueError, TypeError, ArithmeticError):
            v = None  # beyond float range (10**400) or a number type that cannot convert
    if v is None or not ((isinstance(v, int) or math.isfinite(v)) and (low is None or (v > low if low_open else v >= low))
                         and (high is None or (v < high if high_open else v <= high))):
        raise InputValueError(f"{name} must be {kind}{rng}, got {brief(value)}")
    return v


_BRIEF = reprlib.Repr()
_BRIEF.maxlevel, _BRIEF.maxstring, _BRIEF.maxother, _BRIEF.maxlong = 3, 60, 60, 40
_BRIEF.maxlist = _BRIEF.maxtuple = _BRIEF.maxdict = _BRIEF.maxset = 6


def brief(value: object) -> str:
    """``repr(value)`` cut to about 60 characters, for error messages: never raises, whatever the value
    (an int of any size, a deeply nested list, a failing ``__repr__``)."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 128:
        return f"an int of about {int(value.bit_length() * 0.30103) + 1} digits"
    try:
        return _BRIEF.repr(value)
    except Exception:  # noqa: BLE001 - a message must not fail (RecursionError included)
        return f"<{type(value).__name__}>"
