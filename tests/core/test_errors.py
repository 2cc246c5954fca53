"""The error types: each subclasses ControlGSError and the built-in an ``except`` clause would name."""

from __future__ import annotations

import warnings

import pytest

from controlgs_adapter import cli
from controlgs_adapter.errors import (
    ControlGSError,
    FileWriteError,
    InjectionMissedError,
    InputValueError,
    LifecycleError,
    MissingDependencyError,
    NonFiniteError,
    RunLockedError,
    ShapeError,
    StateError,
    StateRangeError,
    TargetError,
    warn_user,
)


def test_error_taxonomy_keeps_builtin_bases():
    pairs = [(ShapeError, ValueError), (InputValueError, ValueError), (StateRangeError, StateError),
             (StateError, InputValueError), (LifecycleError, RuntimeError), (TargetError, ValueError),
             (NonFiniteError, FloatingPointError), (NonFiniteError, InputValueError),
             (MissingDependencyError, ImportError), (FileWriteError, OSError), (RunLockedError, RuntimeError),
             (InjectionMissedError, RuntimeError)]
    for sub, base in pairs:
        assert issubclass(sub, base) and issubclass(sub, ControlGSError), sub
    assert not issubclass(LifecycleError, StateError)  # a lifecycle error is no state error


def test_warn_user_skips_only_the_librarys_own_folders():
    from controlgs_adapter.errors import _OWN, _between

    assert any(p.endswith("controlgs_adapter/") for p in _OWN)
    assert _between(cli.__file__) and not _between(__file__)


def test_library_warnings_land_on_the_users_line():
    from controlgs_adapter.downstream.optics.stage import PSFOptics

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        PSFOptics(stretch=True)
    assert [w.category for w in caught] == [DeprecationWarning] and caught[0].filename == __file__


@pytest.mark.parametrize("category", [RuntimeWarning, UserWarning])
def test_warn_user_keeps_the_category(category):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_user("x", category)
    assert caught[0].category is category and caught[0].filename == __file__
