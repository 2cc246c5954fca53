"""Registers the built-in downstream stages through the public hook (as any plug-in would)."""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl


@hookimpl(trylast=True)
def controlgs_register_stages() -> list:
    from .display import DisplayStage
    from .foveation import FoveationStage
    from .lens import LensPrewarp
    from .oled import OLEDStage
    from .optics.stage import OpticsStage
    from .resample import ResampleStage

    return [FoveationStage, LensPrewarp, ResampleStage, DisplayStage, OLEDStage, OpticsStage]
