"""Downstream stages between the renderer and the eye (installed as ``controlgs_adapter.downstream``)."""

from .color import linear_to_srgb, primaries_to_rgb, rgb_to_primaries, srgb_to_linear
from .display import DisplayMapping, display_mapping, display_mapping_with_stats, display_power, display_power_watts
from .foveation import Foveation, foveation
from .lens import LensPrewarp, lens_prewarp
from .oled import OLEDEmission, oled_emission
from .pipeline import Pipeline
from .resample import AreaResample, area_resample
from .stage import Stage, StageContext

__all__ = [
    "Stage", "StageContext", "Pipeline",
    "LensPrewarp", "AreaResample", "DisplayMapping", "OLEDEmission", "Foveation",
    "srgb_to_linear", "linear_to_srgb", "rgb_to_primaries", "primaries_to_rgb",
    "lens_prewarp", "area_resample", "display_power", "display_power_watts", "display_mapping",
    "display_mapping_with_stats", "oled_emission", "foveation",
]
