"""controlgs-adapter: make neural-Gaussian renderers aware of the XR display/optics path (ControlGS).

The error types import eagerly; every other public name (the wrapper, states, schedules, ``hookimpl``,
training, evaluation, the pipeline, the loaders) loads on first use, and so does a submodule reached
as an attribute (``controlgs_adapter.plugins``). Importing one module of the package therefore
loads only what that module imports (docs/reference/conventions.md, "Layers").
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

from . import errors
from ._version import __version__
from .errors import (ControlGSError, FileFormatError, IncompatibleAdapterError, InputValueError, LifecycleError,
                     NoMatchingBackendError, ShapeError, StateError, StateRangeError, TargetError)

if TYPE_CHECKING:  # pragma: no cover
    from .backends.model_dir import load_model_dir as load_model_dir
    from .controlgs import ControlGS as ControlGS
    from .datasets.detect import load_dataset as load_dataset
    from .downstream.pipeline import Pipeline as Pipeline
    from .evaluation import GridResult as GridResult
    from .evaluation import evaluate_grid as evaluate_grid
    from .hookspecs import hookimpl as hookimpl
    from .schedules import DisplaySchedule as DisplaySchedule
    from .schedules import FoveationSchedule as FoveationSchedule
    from .schedules import LensSchedule as LensSchedule
    from .schedules import ResampleSchedule as ResampleSchedule
    from .schedules import StrengthSchedule as StrengthSchedule
    from .state import Camera as Camera
    from .state import RuntimeState as RuntimeState
    from .training import TrainConfig as TrainConfig
    from .training import Trainer as Trainer

#: public names loaded on first access: name -> module
_LAZY: dict[str, str] = {
    "hookimpl": "controlgs_adapter.hookspecs",
    "Camera": "controlgs_adapter.state", "RuntimeState": "controlgs_adapter.state",
    "ControlGS": "controlgs_adapter.controlgs",
    **{name: "controlgs_adapter.schedules" for name in (
        "StrengthSchedule", "LensSchedule", "ResampleSchedule", "DisplaySchedule", "FoveationSchedule")},
    "Trainer": "controlgs_adapter.training", "TrainConfig": "controlgs_adapter.training",
    "Pipeline": "controlgs_adapter.downstream.pipeline",
    "GridResult": "controlgs_adapter.evaluation", "evaluate_grid": "controlgs_adapter.evaluation",
    "load_model_dir": "controlgs_adapter.backends.model_dir", "load_dataset": "controlgs_adapter.datasets.detect",
}

__all__ = ["__version__", "errors"]
__all__ += ["ControlGSError", "FileFormatError", "IncompatibleAdapterError", "InputValueError", "LifecycleError",
            "NoMatchingBackendError", "ShapeError", "StateError", "StateRangeError", "TargetError"]
__all__ += list(_LAZY)


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is not None:
        value = getattr(importlib.import_module(module), name)
    elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        value = importlib.import_module(f"{__name__}.{name}")  # a submodule reached as an attribute
    else:
        raise AttributeError(f"module 'controlgs_adapter' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
