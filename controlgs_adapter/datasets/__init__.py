"""Posed-image datasets: the formats the Scaffold-GS family trains on, read into cameras and lazily
loaded images at a working resolution (nerfstudio's dataparser pattern)."""

from .base import DEFAULT_CACHE_BYTES, Frame, PosedImages, SceneData, area_resize, working_size
from .images import image_size, load_frame_image, read_image, undistort, undistort_points
from .colmap import read_colmap
from .blender import opengl_c2w_to_w2c, read_blender
from .instant_ngp import read_instant_ngp
from .sanity import check_scene
from .detect import FORMATS, detect_format, load_dataset

__all__ = ["Frame", "SceneData", "PosedImages", "DEFAULT_CACHE_BYTES", "working_size", "area_resize",
           "read_image", "image_size", "load_frame_image", "undistort", "undistort_points", "read_colmap",
           "read_blender", "opengl_c2w_to_w2c", "read_instant_ngp", "check_scene", "load_dataset", "detect_format",
           "FORMATS"]
