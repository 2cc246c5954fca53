"""Registers the built-in rasterizers through the public hook (as any plug-in would)."""

from __future__ import annotations

from controlgs_adapter.hookspecs import hookimpl
from controlgs_adapter.rendering.rasterizer import Rasterizer
from controlgs_adapter.rendering.rasterizers import GsplatRasterizer, TorchSplatter


@hookimpl(trylast=True)
def controlgs_register_rasterizers() -> list[Rasterizer]:
    # the automatic choice takes the first that can run the tensors: gsplat where it can, else torch
    return [GsplatRasterizer(), TorchSplatter()]
