"""Tiny dataset folders written directly (COLMAP text and binary, Blender, instant-ngp) for the readers'
refusal tests, a sentinel image outside them, and a record of every file the process opens.

The record is one interpreter hook on `open` events (installed once: such hooks cannot be removed) that appends the path of
each ``open`` event to :data:`OPENED`; :func:`recording` clears it for one test."""

from __future__ import annotations

import contextlib
import json
import os
import struct
import sys
from pathlib import Path
from typing import Any, Iterator, Sequence

from PIL import Image

#: paths of the files opened since the last :func:`recording` (as given to ``open``)
OPENED: list[str] = []


def _record_opens(event: str, args: tuple[Any, ...]) -> None:
    if event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
        OPENED.append(os.fsdecode(args[0]))


sys.addaudithook(_record_opens)

W, H = 8, 6  # size of every image written here


@contextlib.contextmanager
def recording() -> Iterator[list[str]]:
    """Clear :data:`OPENED`, then yield it (it fills as files are opened)."""
    OPENED.clear()
    yield OPENED


def opened_under(folder: Path, opened: Sequence[str]) -> list[str]:
    """The entries of ``opened`` that resolve to ``folder`` or a file below it."""
    top = os.path.realpath(folder)
    return [p for p in opened if os.path.realpath(p) == top or os.path.realpath(p).startswith(top + os.sep)]


def png(path: Path, width: int = W, height: int = H) -> Path:
    """A grey RGB PNG of ``width x height`` at ``path`` (folders created)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (width, height), (128, 128, 128)).save(path)
    return path


def outside(tmp_path: Path) -> Path:
    """``tmp_path/outside/`` holding ``sentinel.png`` (a valid image the size of the dataset's) and
    ``sentinel.json`` / ``sentinel.txt``: files a reader must never open. Returns the folder."""
    folder = tmp_path / "outside"
    png(folder / "sentinel.png")
    (folder / "sentinel.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": []}))
    (folder / "sentinel.txt").write_text("# 3D point list\n1 0 0 0 1 1 1 0\n")
    return folder


# ------------------------------------------------------------------------------------------- COLMAP

CAMERA_LINE = f"1 PINHOLE {W} {H} 10 10 4 3"


def image_line(image_id: int, name: str, *, camera_id: int = 1, t: tuple[float, float, float] = (0.0, 0.0, 4.0),
               q: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)) -> str:
    """An images.txt record's first line (``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``)."""
    return f"{image_id} {' '.join(repr(v) for v in (*q, *t))} {camera_id} {name}"


def colmap_text(root: Path, *, cameras: str | None = None, images: str | None = None, points: str | None = None,
                names: Sequence[str] = ("a.png", "b.png", "c.png")) -> Path:
    """``root/sparse/0/{cameras,images[,points3D]}.txt`` and ``root/images/<names>``. Default files:
    one PINHOLE camera and one record per name (image line + an empty POINTS2D line)."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True, exist_ok=True)
    if cameras is None:
        cameras = f"# Camera list\n{CAMERA_LINE}\n"
    if images is None:
        images = "# Image list\n" + "".join(f"{image_line(i + 1, n)}\n\n" for i, n in enumerate(names))
    (sparse / "cameras.txt").write_text(cameras)
    (sparse / "images.txt").write_text(images)
    if points is not None:
        (sparse / "points3D.txt").write_text(points)
    for n in names:
        png(root / "images" / n)
    return root


def cameras_bin(path: Path, cameras: Sequence[tuple[int, int, int, int, Sequence[float]]]) -> None:
    """COLMAP cameras.bin: ``(camera_id, model_id, width, height, params)`` records."""
    out = struct.pack("<Q", len(cameras))
    for cam_id, model_id, w, h, params in cameras:
        out += struct.pack("<IiQQ", cam_id, model_id, w, h) + struct.pack(f"<{len(params)}d", *params)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(out)


def images_bin(path: Path, images: Sequence[tuple[int, str, int]]) -> None:
    """COLMAP images.bin: ``(image_id, name, camera_id)`` records, identity rotation, t = (0, 0, 4),
    one 2D point each."""
    out = struct.pack("<Q", len(images))
    for image_id, name, cam_id in images:
        out += struct.pack("<I4d3dI", image_id, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0, cam_id)
        out += name.encode() + b"\0" + struct.pack("<Q", 1) + struct.pack("<ddq", 1.0, 2.0, -1)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(out)


def points_bin(path: Path, points: Sequence[tuple[int, tuple[float, float, float]]]) -> None:
    """COLMAP points3D.bin: ``(point3D_id, xyz)`` records, grey, error 0, empty track."""
    out = struct.pack("<Q", len(points))
    for point_id, xyz in points:
        out += struct.pack("<Q3d3Bd", point_id, *xyz, 128, 128, 128, 0.0) + struct.pack("<Q", 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(out)


# ---------------------------------------------------------------------------------- NeRF JSON formats

#: camera to world, OpenGL axes: identity rotation, 4 units along +z (looking at the origin)
C2W = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 4.0], [0.0, 0.0, 0.0, 1.0]]


def frame(file_path: str, matrix: Any = None, **keys: Any) -> dict[str, Any]:
    """A frames[] entry with ``file_path`` and ``transform_matrix`` (default :data:`C2W`)."""
    return {"file_path": file_path, "transform_matrix": C2W if matrix is None else matrix, **keys}


def blender(root: Path, frames: Sequence[dict[str, Any]], *, angle: Any = 0.7, images: Sequence[str] = ("r_0", "r_1"),
            raw: str | None = None) -> Path:
    """``root/transforms_train.json`` (``raw`` text, or ``camera_angle_x`` + ``frames``) and
    ``root/train/<images>.png``."""
    for name in images:
        png(root / "train" / f"{name}.png")
    text = raw if raw is not None else json.dumps({"camera_angle_x": angle, "frames": list(frames)})
    (root / "transforms_train.json").write_text(text)
    return root


def instant_ngp(root: Path, frames: Sequence[dict[str, Any]], *, images: Sequence[str] = ("a", "b"),
                raw: str | None = None, **meta: Any) -> Path:
    """``root/transforms.json`` (``raw`` text, or ``meta`` + ``frames``; default intrinsics
    ``fl_x = fl_y = 10``) and ``root/images/<images>.png``."""
    for name in images:
        png(root / "images" / f"{name}.png")
    top = {"fl_x": 10.0, "fl_y": 10.0, **meta, "frames": list(frames)}
    (root / "transforms.json").write_text(raw if raw is not None else json.dumps(top))
    return root
