"""Posed-image datasets: the formats the Scaffold-GS family trains on, read into cameras and lazily
loaded images at a working resolution (nerfstudio's dataparser pattern)."""

from .base import DEFAULT_CACHE_BYTES, Frame, PosedImages, SceneData, area_resize, working_size
from .images import image_size, load_frame_image, read_image

__all__ = ["Frame", "SceneData", "PosedImages", "DEFAULT_CACHE_BYTES", "working_size", "area_resize",
           "read_image", "image_size", "load_frame_image"]
