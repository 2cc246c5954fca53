"""Registers the built-in backends through the public hook (as any plug-in would)."""

from __future__ import annotations

from controlgs_adapter.backend import Backend
from controlgs_adapter.hookspecs import hookimpl

from .compgs import CompGSBackend
from .contextgs import ContextGSBackend
from .hac import HACBackend
from .octree_gs import OctreeGSBackend
from .scaffold_gs import ScaffoldGSBackend


@hookimpl(trylast=True)
def controlgs_register_backends() -> list[Backend]:
    # ControlGS.wrap takes the first backend that matches: more specific families go before
    # scaffold_gs, which recognises anything with Scaffold-GS's decoder attribute names.
    return [OctreeGSBackend(), HACBackend(), ContextGSBackend(), CompGSBackend(), ScaffoldGSBackend()]
