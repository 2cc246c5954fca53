"""Exception taxonomy. Every error subclasses a built-in so existing ``except`` clauses keep working."""

from __future__ import annotations


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
