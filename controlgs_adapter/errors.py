"""Exception taxonomy. Every error subclasses a built-in so existing ``except`` clauses keep working.
:func:`warn_user` issues the library's warnings, attributed to the caller's line."""

from __future__ import annotations

import contextlib
import os
import sys
import warnings

#: folders of the library's own code (the package, and the real folders its linked subpackages live in)
_OWN = tuple(sorted({os.path.join(d, "") for base in (os.path.dirname(os.path.abspath(__file__)),)
                     for d in (base, os.path.realpath(base), os.path.realpath(os.path.join(base, "backends")),
                               os.path.realpath(os.path.join(base, "downstream")))}))
_CONTEXTLIB = os.path.abspath(contextlib.__file__)


def _between(filename: str) -> bool:
    """True for a frame between the user and the warning: the library's own code, ``contextlib`` (the
    exit of a ``with`` block) and torch (an ``nn.Module`` call into the library)."""
    path = os.path.abspath(filename)
    if path.startswith(_OWN) or path == _CONTEXTLIB:
        return True
    torch = sys.modules.get("torch")
    where = getattr(torch, "__file__", None)
    return where is not None and path.startswith(os.path.join(os.path.dirname(os.path.abspath(where)), ""))


def warn_user(message: str, category: type[Warning] = RuntimeWarning) -> None:
    """``warnings.warn`` attributed to the first caller outside the library (the user's line, so that
    Python's ``file:line`` points at their code and the warning filters see their module), skipping
    the library's frames and the ``contextlib`` / torch frames between them and the user."""
    frame = sys._getframe(1)
    level = 2
    while frame.f_back is not None and _between(frame.f_code.co_filename):
        frame = frame.f_back
        level += 1
    warnings.warn(message, category, stacklevel=level)


class ControlGSError(Exception):
    """Root of every error raised by controlgs-adapter."""


class ShapeError(ControlGSError, ValueError):
    """A tensor argument has the wrong shape."""


class InputValueError(ControlGSError, ValueError):
    """An argument has a wrong value: NaN/Inf, out of range, empty, wrong dtype or device."""


class StateError(InputValueError):
    """A run-time state is invalid (base of :class:`StateRangeError`)."""


class StateRangeError(StateError):
    """A run-time state (downsample, power saving, gaze) is outside its physical range."""


class LifecycleError(ControlGSError, RuntimeError):
    """An object is used in the wrong phase of its life: a ``conditioned`` block inside another,
    a ``ControlGS`` used after ``unwrap``, a decoder wrapped twice."""


class NoMatchingBackendError(ControlGSError, TypeError):
    """No registered backend recognises the model passed to ``ControlGS.wrap``."""


class TargetError(ControlGSError, ValueError):
    """A requested target decoder does not exist or cannot take an injector."""


class IncompatibleAdapterError(ControlGSError, ValueError):
    """An adapter file does not fit the model it is loaded onto (each mismatch is listed)."""


class FileFormatError(ControlGSError, ValueError):
    """A file is missing, truncated, foreign or of an unsupported format version."""


class PluginLoadError(ControlGSError, RuntimeError):
    """An installed plug-in failed to load (raised only in strict mode)."""


class RunLockedError(ControlGSError, RuntimeError):
    """A run folder is in use by another process (its lock file names the holder)."""


class NonFiniteError(InputValueError, FloatingPointError):
    """Training produced a non-finite loss or parameter, or a file would hold non-finite values."""


class MissingDependencyError(ControlGSError, ImportError):
    """An optional dependency (an ``extra`` of the package) is not installed."""


class FileWriteError(ControlGSError, OSError):
    """A file could not be written (unwritable folder, disk full, a folder in the way)."""


class InjectionMissedError(ControlGSError, RuntimeError):
    """A render inside ``ControlGS.conditioned`` never called the wrapped decoders (the renderer
    uses another object than the one ``ControlGS.wrap`` changed)."""
