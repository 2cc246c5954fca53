"""Registers the built-in downstream stages through the public hook (as any plug-in would)."""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl

from .display import DisplayMapping
from .foveation import Foveation
from .lens import LensPrewarp
from .oled import OLEDEmission
from .optics.stage import PSFOptics
from .resample import AreaResample
from .stage import Stage


@hookimpl(trylast=True)
def controlgs_register_stages() -> list[type[Stage]]:
    return [Foveation, LensPrewarp, AreaResample, DisplayMapping, OLEDEmission, PSFOptics]
