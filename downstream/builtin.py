"""Registers the built-in downstream stages through the public hook (as any plug-in would)."""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl


@hookimpl(trylast=True)
def controlgs_register_stages() -> list:
    return []
