"""Strength schedules (paper Eqs. 10-11). Placeholder: filled in by the core issue."""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl


@hookimpl(trylast=True)
def controlgs_register_schedules() -> list:
    return []
