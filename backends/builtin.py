"""Registers the built-in backends through the public hook (as any plug-in would)."""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl


@hookimpl(trylast=True)
def controlgs_register_backends() -> list:
    return []
