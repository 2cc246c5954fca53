"""A tiny capture of the built-in scene (its cameras and exact ground truth) written as a user's dataset
in each format the readers take: COLMAP text with the scene's surface points as ``points3D``, Blender
and instant-ngp (no points)."""

from __future__ import annotations

import functools
from pathlib import Path

import torch

try:  # the independent format writers (kept in tests/helpers/ or, before that, at the top of tests/)
    from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp
except ImportError:  # pragma: no cover - the older location
    from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp

from controlgs_adapter.scene import load_builtin_scene
from controlgs_adapter.state import Camera

FORMATS = ("colmap", "blender", "instant_ngp")


@functools.lru_cache(maxsize=4)
def capture(size: int = 24, views: int = 8) -> tuple[list, list[torch.Tensor], torch.Tensor]:
    """``(cameras, images, points)``: ``views`` views of the built-in AR scene at ``size`` px (view 0 is
    the test view in every format at holdout 8) and points on its surfaces (made once per size; not to
    be changed in place)."""
    scene = load_builtin_scene("ar", size, views=views, test_every=views, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    images = list(torch.cat([scene.test_images, scene.train_images]))
    xyz, _ = scene.points(0.15)
    return cams, images, xyz


def write_points3d(root: Path, points: torch.Tensor) -> None:
    """``root/sparse/0/points3D.txt``: one grey point per row of ``points``, empty tracks."""
    lines = ["# 3D point list"] + [f"{i + 1} {x!r} {y!r} {z!r} 128 128 128 0" for i, (x, y, z) in
                                   enumerate(points.double().tolist())]
    (root / "sparse" / "0" / "points3D.txt").write_text("\n".join(lines) + "\n")


def write_capture(root: Path, fmt: str, size: int = 24) -> Path:
    """The capture as a ``fmt`` dataset folder under ``root``; returns it."""
    cams, images, points = capture(size)
    if fmt == "colmap":
        folder = write_colmap(root, cams, images)
        write_points3d(folder, points)
        return folder
    if fmt == "blender":
        return write_blender(root, cams, images, test=[0])
    return write_instant_ngp(root, cams, images)


def cropped_capture(size: int = 32, crop: tuple[int, int] | None = None) -> tuple[list, list[torch.Tensor]]:
    """8 views of the built-in scene (view 0 is the test view in every format); ``crop = (w, h)``
    cuts a centred window out of each image with matching intrinsics."""
    scene = load_builtin_scene("ar", size, views=8, test_every=8, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    images = list(torch.cat([scene.test_images, scene.train_images]))
    if crop is None:
        return cams, images
    w, h = crop
    x0, y0 = (size - w) // 2, (size - h) // 2
    out = []
    for c in cams:
        k = c.intrinsics.clone()
        k[0, 2] -= x0
        k[1, 2] -= y0
        out.append(Camera(c.world_to_camera, k, w, h))
    return out, [img[:, y0:y0 + h, x0:x0 + w].contiguous() for img in images]
