"""The built-in scene: photographs on planes, ground truth rendered exactly by ray casting."""

from .cameras import arc_cameras, look_at
from .backbone import build_builtin_backbone, builtin_backbone_dir, load_builtin_backbone
from .diorama import SCENE_VERSION, VARIANTS, BuiltinScene, default_cache_dir, diorama_planes, load_builtin_scene
from .planes import TexturedPlane, plane_points, render_planes
from .textures import TEXTURES, TextureInfo, load_texture, mip_pyramid

__all__ = [
    "VARIANTS", "SCENE_VERSION", "BuiltinScene", "load_builtin_scene", "diorama_planes", "default_cache_dir",
    "TexturedPlane", "render_planes", "plane_points",
    "arc_cameras", "look_at",
    "TEXTURES", "TextureInfo", "load_texture", "mip_pyramid",
    "builtin_backbone_dir", "load_builtin_backbone", "build_builtin_backbone",
]
