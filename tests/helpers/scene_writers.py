"""Independent writers of tiny datasets in the formats the readers accept (COLMAP text, Blender,
instant-ngp), from cameras (OpenCV world-to-camera, pinhole intrinsics) and sRGB images. Written from
each format's documentation, not with the library's code."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch
from PIL import Image


def save_png(path: Path, image: torch.Tensor) -> None:
    """sRGB ``[3, H, W]`` in [0, 1] -> 8-bit PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arr = (image.clamp(0, 1) * 255.0).round().to(torch.uint8).permute(1, 2, 0).numpy()
    Image.fromarray(arr).save(path)


def rotation_to_quaternion(r: np.ndarray) -> tuple[float, float, float, float]:
    """3x3 rotation -> (qw, qx, qy, qz), qw >= 0 (Shepperd's method)."""
    t = np.trace(r)
    if t > 0:
        s = 2.0 * math.sqrt(t + 1.0)
        q = (0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (r[j, i] + r[i, j]) / s
        v[k] = (r[k, i] + r[i, k]) / s
        q = ((r[k, j] - r[j, k]) / s, *v)
    q = np.asarray(q) * (1.0 if q[0] >= 0 else -1.0)
    return tuple(float(x) for x in q / np.linalg.norm(q))


def opengl_c2w(camera) -> list[list[float]]:
    """OpenCV world-to-camera -> OpenGL camera-to-world (y up, z backward), as NeRF JSON files hold it."""
    c2w = np.linalg.inv(camera.world_to_camera.double().numpy())
    c2w[:3, 1:3] *= -1.0
    return c2w.tolist()


def _names(n: int) -> list[str]:
    return [f"v{i:02d}.png" for i in range(n)]


def write_colmap(root: Path, cameras, images) -> Path:
    """``sparse/0/{cameras,images,points3D}.txt`` (one PINHOLE camera per image) + ``images/``."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    cams, imgs = ["# Camera list"], ["# Image list"]
    for i, (cam, img, name) in enumerate(zip(cameras, images, _names(len(cameras))), start=1):
        k = cam.intrinsics.double().tolist()
        cams.append(f"{i} PINHOLE {cam.width} {cam.height} {k[0][0]!r} {k[1][1]!r} {k[0][2]!r} {k[1][2]!r}")
        w2c = cam.world_to_camera.double().numpy()
        q = rotation_to_quaternion(w2c[:3, :3])
        t = w2c[:3, 3].tolist()
        imgs.append(f"{i} {' '.join(repr(x) for x in (*q, *t))} {i} {name}")
        imgs.append("")  # the 2D points line
        save_png(root / "images" / name, img)
    (sparse / "cameras.txt").write_text("\n".join(cams) + "\n")
    (sparse / "images.txt").write_text("\n".join(imgs) + "\n")
    (sparse / "points3D.txt").write_text("# 3D point list\n")
    return root


def write_blender(root: Path, cameras, images, test: list[int]) -> Path:
    """``transforms_{train,test}.json`` (``camera_angle_x``; centred principal point) + PNGs."""
    for split, idx in (("train", [i for i in range(len(cameras)) if i not in test]), ("test", test)):
        frames = []
        for i in idx:
            name = _names(len(cameras))[i]
            save_png(root / split / name, images[i])
            frames.append({"file_path": f"./{split}/{name[:-4]}", "transform_matrix": opengl_c2w(cameras[i])})
        cam = cameras[idx[0]]
        angle = 2.0 * math.atan(cam.width / (2.0 * float(cam.intrinsics[0, 0])))
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    return root


def write_instant_ngp(root: Path, cameras, images) -> Path:
    """``transforms.json`` with global ``fl_x, fl_y, cx, cy, w, h`` + ``images/``."""
    cam = cameras[0]
    k = cam.intrinsics.double()
    meta = {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]), "cy": float(k[1, 2]),
            "w": cam.width, "h": cam.height, "frames": []}
    for cam, img, name in zip(cameras, images, _names(len(cameras))):
        save_png(root / "images" / name, img)
        meta["frames"].append({"file_path": f"images/{name}", "transform_matrix": opengl_c2w(cam)})
    (root / "transforms.json").write_text(json.dumps(meta))
    return root
