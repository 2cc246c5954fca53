"""Synthetic posed-image scenes for the dataset tests, built independently of the library: OpenGL
look-at poses in numpy, the OpenGL pinhole projection, and JSON / PNG writers."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image


def look_at_gl(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world [4, 4] in OpenGL axes (x right, y up, camera looks down -z) at ``eye`` looking
    at ``target``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w


def project_gl(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, points: np.ndarray):
    """Continuous pixel coordinates ``[N, 2]`` and depth ``[N]`` of world ``points`` ``[N, 3]`` seen by
    an OpenGL camera: camera-space (x, y, z) with the view along -z, so depth = -z,
    u = cx + fx x / depth, v = cy - fy y / depth (image rows grow downwards)."""
    w2c = np.linalg.inv(c2w)
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    depth = -pc[:, 2]
    return np.stack([cx + fx * pc[:, 0] / depth, cy - fy * pc[:, 1] / depth], axis=-1), depth


def unproject_gl(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, uv, depth: float) -> np.ndarray:
    """The world point at continuous pixel ``uv`` and ``depth`` of an OpenGL camera (inverse of
    :func:`project_gl`)."""
    u, v = uv
    pc = np.array([(u - cx) / fx * depth, -(v - cy) / fy * depth, -depth, 1.0])
    return (c2w @ pc)[:3]


def ring_poses(n: int, radius: float = 4.0, height: float = 1.5, target=(0.0, 0.0, 0.0), phase: float = 0.3):
    """``n`` OpenGL look-at poses on a ring around ``target``."""
    out = []
    for i in range(n):
        a = phase + 2 * np.pi * i / n
        eye = np.array(target) + np.array([radius * np.cos(a), radius * np.sin(a), height + 0.2 * i])
        out.append(look_at_gl(eye, target))
    return out


def write_png(path: Path, pixels: np.ndarray) -> None:
    """Write ``[H, W, 3 | 4]`` uint8 as PNG (RGB or RGBA)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(pixels, "RGBA" if pixels.shape[-1] == 4 else "RGB").save(path)


def write_json(path: Path, obj) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=1))


def marker_image(width: int, height: int, marks: list[tuple[int, int, tuple[int, ...]]], rgba: bool = True,
                 fill: tuple[int, ...] | None = None) -> np.ndarray:
    """``[H, W, C]`` uint8: ``fill`` everywhere (default transparent black / black), ``colour`` at each
    ``(column, row, colour)`` of ``marks``."""
    c = 4 if rgba else 3
    img = np.zeros((height, width, c), dtype=np.uint8)
    if fill is not None:
        img[:] = fill
    for col, row, colour in marks:
        img[row, col] = colour
    return img


#: OpenGL camera axes to OpenCV ones (and back): y and z flipped
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def write_blender_ring(root: Path, poses, *, test: bool = True, width: int = 32, height: int = 24,
                       angle: float = 1.0) -> Path:
    """A NeRF-synthetic folder of transparent ``width x height`` images with ``poses`` (camera to world as
    written in the files, ``camera_angle_x`` = ``angle``): all in train, the last two also in test when
    ``test``."""
    for split, ps in (("train", poses), ("test", poses[-2:] if test else None)):
        if ps is None:
            continue
        frames = []
        for n, c2w in enumerate(ps):
            write_png(root / split / f"r_{n}.png", marker_image(width, height, [], rgba=True))
            frames.append({"file_path": f"./{split}/r_{n}", "transform_matrix": np.asarray(c2w).tolist()})
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": angle, "frames": frames})
    return root


def write_ngp_ring(root: Path, n: int = 10, transforms: str = "transforms.json") -> Path:
    """An instant-ngp folder of ``n`` 8 x 6 RGB frames ``images/img_XX.png`` on a ring (fl 9 px, centred)."""
    poses = ring_poses(n, phase=0.1)
    frames = []
    for i in range(n):
        write_png(root / "images" / f"img_{i:02d}.png", marker_image(8, 6, [], rgba=False, fill=(10 * i, 0, 0)))
        frames.append({"file_path": f"images/img_{i:02d}.png", "transform_matrix": poses[i].tolist()})
    write_json(root / transforms, {"fl_x": 9.0, "fl_y": 9.0, "cx": 4.0, "cy": 3.0, "w": 8.0, "h": 6.0, "frames": frames})
    return root
