"""controlgs-adapter: make neural-Gaussian renderers aware of the XR display/optics path (ControlGS).

The wrapper, states and schedules import eagerly; training, evaluation, the pipeline and the loaders
load on first use (``from controlgs_adapter import Trainer`` imports only what it needs).
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from . import errors
from ._version import __version__
from .controlgs import ControlGS
from .errors import (ControlGSError, FileFormatError, IncompatibleAdapterError, InputValueError, LifecycleError,
                     NoMatchingBackendError, ShapeError, StateError, StateRangeError, TargetError)
from .hookspecs import hookimpl
from .schedules import DisplaySchedule, FoveationSchedule, LensSchedule, ResampleSchedule, StrengthSchedule
from .state import Camera, RuntimeState

if TYPE_CHECKING:  # pragma: no cover
    from .backends.model_dir import load_model_dir as load_model_dir
    from .datasets.detect import load_dataset as load_dataset
    from .downstream.pipeline import Pipeline as Pipeline
    from .evaluation import GridResult as GridResult
    from .evaluation import evaluate_grid as evaluate_grid
    from .training import TrainConfig as TrainConfig
    from .training import Trainer as Trainer

#: public names loaded on first access: name -> module
_LAZY: dict[str, str] = {
    "Trainer": "controlgs_adapter.training", "TrainConfig": "controlgs_adapter.training",
    "Pipeline": "controlgs_adapter.downstream.pipeline",
    "GridResult": "controlgs_adapter.evaluation", "evaluate_grid": "controlgs_adapter.evaluation",
    "load_model_dir": "controlgs_adapter.backends.model_dir", "load_dataset": "controlgs_adapter.datasets.detect",
}

__all__ = ["__version__", "hookimpl", "Camera", "RuntimeState", "errors"]
__all__ += ["ControlGS", "StrengthSchedule", "LensSchedule", "ResampleSchedule", "DisplaySchedule", "FoveationSchedule"]
__all__ += ["ControlGSError", "FileFormatError", "IncompatibleAdapterError", "InputValueError", "LifecycleError",
            "NoMatchingBackendError", "ShapeError", "StateError", "StateRangeError", "TargetError"]
__all__ += list(_LAZY)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'controlgs_adapter' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
