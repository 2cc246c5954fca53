"""Rendering: the render protocol (:mod:`.protocol`, re-exported here), rasterizer plug-ins
(:mod:`.rasterizers`), the pure-torch EWA splatter (:mod:`.splatter`) and its float64 brute-force
reference (:mod:`.splatter_reference`)."""
from .protocol import (FunctionRenderer, ModelRenderer, Renderer, as_renderer, model_device, render_view,
                       renderer_for)

__all__ = ["Renderer", "ModelRenderer", "FunctionRenderer", "renderer_for", "as_renderer", "render_view",
           "model_device"]
