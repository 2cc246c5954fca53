"""Downstream stages between the renderer and the eye (installed as ``controlgs_adapter.downstream``).

:class:`Pipeline` composes the registered stages, so it builds on the plug-in manager: it loads on
first access, and importing a stage (or the :class:`Stage` contract) does not load the registry.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .color import linear_to_srgb, primaries_to_rgb, rgb_to_primaries, srgb_to_linear
from .display import DisplayMapping, display_mapping, display_mapping_with_stats, display_power, display_power_watts
from .foveation import Foveation, foveation
from .lens import LensPrewarp, lens_prewarp
from .oled import OLEDEmission, oled_emission
from .resample import AreaResample, area_resample
from .stage import Stage, StageContext

if TYPE_CHECKING:  # pragma: no cover
    from .pipeline import Pipeline as Pipeline

__all__ = [
    "Stage", "StageContext", "Pipeline",
    "LensPrewarp", "AreaResample", "DisplayMapping", "OLEDEmission", "Foveation",
    "srgb_to_linear", "linear_to_srgb", "rgb_to_primaries", "primaries_to_rgb",
    "lens_prewarp", "area_resample", "display_power", "display_power_watts", "display_mapping",
    "display_mapping_with_stats", "oled_emission", "foveation",
]


def __getattr__(name: str) -> Any:
    if name != "Pipeline":
        raise AttributeError(f"module 'controlgs_adapter.downstream' has no attribute {name!r}")
    value = importlib.import_module("controlgs_adapter.downstream.pipeline").Pipeline
    globals()[name] = value
    return value
