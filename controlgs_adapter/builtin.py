"""Registers the built-in strength schedules through the public hook (as any plug-in would).

The other built-ins register from their own packages: backends (``backends/builtin.py``), stages
(``downstream/builtin.py``) and rasterizers (``rendering/builtin.py``).
"""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl
from controlgs_adapter.schedules import BUILTIN_SCHEDULES, StrengthSchedule


@hookimpl(trylast=True)
def controlgs_register_schedules() -> list[StrengthSchedule]:
    return [cls() for cls in BUILTIN_SCHEDULES]
