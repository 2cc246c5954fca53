"""COLMAP reconstructions written by pycolmap (the reference the COLMAP reader is tested against), one camera of
every supported model, and OpenCV's intrinsics convention. pycolmap and OpenCV are test extras: tests that need
them carry :data:`needs_pycolmap` / :data:`needs_cv2`."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from PIL import Image

needs_pycolmap = pytest.mark.skipif(importlib.util.find_spec("pycolmap") is None, reason="needs pycolmap (test extra)")
needs_cv2 = pytest.mark.skipif(importlib.util.find_spec("cv2") is None, reason="needs OpenCV (test extra)")

#: the size of every camera and image (non-square: catches swapped axes)
W, H = 40, 30

#: one camera of every supported model: id -> (model, params) at W x H
MODELS = {
    1: ("SIMPLE_PINHOLE", [42.0, 20.3, 14.6]),
    2: ("PINHOLE", [41.0, 43.5, 19.2, 15.7]),
    3: ("SIMPLE_RADIAL", [40.0, 20.5, 15.2, -0.12]),
    4: ("RADIAL", [44.0, 19.6, 14.9, 0.08, -0.03]),
    5: ("OPENCV", [45.0, 43.0, 20.7, 15.4, -0.15, 0.04, 0.003, -0.002]),
}


def reconstruction(n_images: int = 10, models: dict[int, tuple[str, list[float]]] | None = None, seed: int = 0,
                   size: tuple[int, int] = (W, H)) -> Any:
    """A pycolmap reconstruction: cameras of ``models``, images named out of order with random poses (cameras
    looking at the origin from ~4 units), some with 2D points, and 3D points with tracks."""
    import pycolmap

    rng = np.random.default_rng(seed)
    models = MODELS if models is None else models
    rec = pycolmap.Reconstruction()
    for cid, (model, params) in models.items():
        cam = pycolmap.Camera.create_from_model_name(cid, model, 1.0, *size)
        cam.params = params
        rec.add_camera_with_trivial_rig(cam)
    cam_ids = list(models)
    for i in range(n_images):
        q = rng.normal(size=4)
        r = pycolmap.Rotation3d(q / np.linalg.norm(q)).matrix()
        t = np.array([0.0, 0.0, 4.0]) + rng.normal(scale=0.2, size=3)
        kps = rng.uniform(0, min(size), size=(25 if i % 2 else 0, 2))  # images without 2D points too
        img = pycolmap.Image(name=f"img_{(7 * i) % n_images:03d}.png", keypoints=kps,
                             camera_id=cam_ids[i % len(cam_ids)], image_id=100 + i)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(r), t))
    for j in range(25):
        track = pycolmap.Track()
        for i in range(1, n_images, 2):
            if (i + j) % 3 == 0:
                track.add_element(100 + i, j)
        rec.add_point3D(rng.normal(scale=0.5, size=3), track)
    return rec


def write_reconstruction(root: Path, rec: Any, *, text: bool = False, sparse: str = "sparse/0",
                         folders: dict[str, tuple[int, int]] | None = None) -> Path:
    """Write ``rec`` under ``root/sparse`` (binary, or text) and a random PNG per image in each folder
    (name -> size, default ``images`` at W x H)."""
    d = root / sparse
    d.mkdir(parents=True, exist_ok=True)
    (rec.write_text if text else rec.write_binary)(str(d))
    rng = np.random.default_rng(1)
    for folder, (w, h) in (folders or {"images": (W, H)}).items():
        (root / folder).mkdir(exist_ok=True)
        for im in rec.images.values():
            Image.fromarray(rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)).save(root / folder / im.name)
    return root


def opencv_k(k: torch.Tensor) -> np.ndarray:
    """The library's intrinsics (pixel centres at i + 0.5) as OpenCV's (centres at i)."""
    k = k.double().numpy().copy()
    k[0, 2] -= 0.5
    k[1, 2] -= 0.5
    return k
