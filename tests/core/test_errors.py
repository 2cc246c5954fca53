"""The error types: each subclasses ControlGSError and the built-in an ``except`` clause would name."""

from __future__ import annotations

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
