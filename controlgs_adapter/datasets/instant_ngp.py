"""instant-ngp captures: one ``transforms.json`` for all frames (``colmap2nerf.py``'s output).

Poses are camera to world in OpenGL axes, as in the NeRF-synthetic files. Intrinsics come from the
top level (``fl_x, fl_y, cx, cy, w, h``, floats allowed, or ``camera_angle_x`` / ``camera_angle_y``
in radians) and OpenCV radial-tangential distortion ``k1 k2 p1 p2 [k3]``; a frame that carries its
own keys overrides them. ``aabb_scale``, ``scale`` and ``offset`` are ignored: they only place the
scene in instant-ngp's unit cube for its hash grid (a similarity transform of every camera alike),
not part of the camera model; the cameras stay in the file's world frame.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from ..errors import FileFormatError, InputValueError
from ..state import Camera
from .base import Frame, SceneData
from .blender import frame_image_path, frame_pose, read_json, resolve_background
from .guards import dataset_camera, inside, is_number, warn_user
from .images import image_size

__all__ = ["read_instant_ngp"]

#: key groups a frame overrides as a whole (its camera_angle_x replaces the file's fl_x, ...)
_GROUPS = {
    "focal": ("fl_x", "fl_y", "camera_angle_x", "camera_angle_y"),
    "centre": ("cx", "cy"),
    "size": ("w", "h"),
    "distortion": ("k1", "k2", "p1", "p2", "k3"),
}
#: keys of camera models this reader cannot represent as a pinhole plus radial-tangential distortion
_UNSUPPORTED = ("is_fisheye", "k4")
#: nerfstudio's ``camera_model`` values that are a pinhole plus radial-tangential distortion
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
#: how many missing images a warning names
_NAMED = 5
#: relative difference above which a focal length and a field of view given together disagree
_FOCAL_RTOL = 1e-3


def read_instant_ngp(root: str | Path, *, holdout: int = 8, background: torch.Tensor | None = None,
                     transforms: str = "transforms.json") -> SceneData:
    """Read an instant-ngp dataset into ``{"train", "test"}`` frames (no SfM points).

    Args:
        root: the folder holding ``transforms``; image paths are relative to it.
        holdout: frames sorted by name, every ``holdout``-th (index % holdout == 0) is a test view
            (3DGS ``--eval``); 0: all frames train.
        background: ``[3]`` sRGB colour in [0, 1] RGBA images are composited over (default black).
        transforms: the JSON file's name inside ``root``.

    Each camera's size is its image's (header); when the file's ``w, h`` differ from it by one
    uniform factor (downscaled images), the intrinsics are scaled, otherwise the file is refused.
    Frames whose image is missing are skipped with a ``RuntimeWarning`` naming how many and the first
    few; none left is a :class:`FileFormatError`. Where ``fl_x`` (``fl_y``) and ``camera_angle_x``
    (``camera_angle_y``) are both given and disagree, ``fl_x`` (``fl_y``) is used and a ``RuntimeWarning``
    names the frames. Paths that lead outside ``root`` (``..``, absolute, symlinks out), a duplicated
    image, strings where numbers belong and values beyond float32 are refused with a
    :class:`FileFormatError` naming the file and frame.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileFormatError(f"{root}: dataset folder not found")
    if isinstance(holdout, bool) or not isinstance(holdout, int) or holdout < 0 or holdout == 1:
        raise InputValueError(f"holdout must be 0 (no test split) or an int >= 2, got {holdout!r}")
    bg = resolve_background(background)
    if not isinstance(transforms, str) or not transforms:
        raise InputValueError(f"transforms must be the name of a JSON file in {root}, got {transforms!r}")
    path = inside(root, transforms, str(root), "transforms")
    if not path.is_file():
        raise FileFormatError(f"{path}: not found (an instant-ngp dataset needs {transforms})")
    meta = read_json(path)
    entries = meta.get("frames")
    if not isinstance(entries, list) or not entries:
        raise FileFormatError(f"{path}: 'frames' must be a non-empty list, got {entries!r:.60}")
    frames: list[Frame] = []
    missing: list[str] = []
    conflicts: list[str] = []
    first: dict[str, int] = {}
    for i, entry in enumerate(entries):
        name, image = frame_image_path(root, path, i, entry)
        if name in first:
            raise FileFormatError(f"{path}: frames[{i}] ({entry['file_path']!r}): an image is listed twice "
                                  f"({name!r}), also in frames[{first[name]}]")
        first[name] = i
        if not image.is_file():
            missing.append(entry["file_path"])
            continue
        camera, distortion = _camera(path, i, meta, entry, image, conflicts)
        frames.append(Frame(name=name, camera=camera, source=image, distortion=distortion))
    if conflicts:
        warn_user(f"{path}: fl_x / fl_y and camera_angle_x / camera_angle_y disagree in {len(conflicts)} "
                  f"frame(s), the focal length fl_x / fl_y is used: {'; '.join(conflicts[:_NAMED])}"
                  f"{'; ...' if len(conflicts) > _NAMED else ''}")
    if missing:
        warn_user(f"{path}: {len(missing)} of {len(entries)} frames list an image that is not there, "
                  f"skipped: {', '.join(missing[:_NAMED])}{', ...' if len(missing) > _NAMED else ''}")
    if not frames:
        raise FileFormatError(f"{path}: none of the {len(entries)} images its frames list exists "
                              f"(first: {root / entries[0]['file_path']})")
    frames.sort(key=lambda f: f.name)
    test = [f for j, f in enumerate(frames) if holdout and j % holdout == 0]
    train = [f for j, f in enumerate(frames) if not (holdout and j % holdout == 0)]
    return SceneData(splits={"train": train, "test": test}, points=None, background=bg, source=str(root),
                     format="instant_ngp")


def _camera(path: Path, i: int, meta: dict[str, Any], entry: dict[str, Any], image: Path,
            conflicts: list[str]) -> tuple[Camera, tuple[float, float, float, float, float] | None]:
    """Camera (at the image file's size) and distortion of ``frames[i]``: each key group from the
    frame if it has any key of it, else from the top level. A focal length that disagrees with the
    field of view given beside it is described in ``conflicts`` (the focal length is used)."""
    where = f"{path}: frames[{i}] ({entry['file_path']!r})"
    model = entry.get("camera_model", meta.get("camera_model", "OPENCV"))
    if model not in _PINHOLE_MODELS:
        raise FileFormatError(f"{where}: camera_model {model!r} is not supported ({', '.join(_PINHOLE_MODELS)} "
                              "only); undistort the images first")
    for key in _UNSUPPORTED:
        value = entry.get(key, meta.get(key))
        if value is not None and not (isinstance(value, bool) if key == "is_fisheye" else is_number(value)):
            raise FileFormatError(f"{where}: {key} must be a {'bool' if key == 'is_fisheye' else 'finite number'}, "
                                  f"got {value!r}")
        if value:
            raise FileFormatError(f"{where}: {key} set: fisheye cameras are not supported (pinhole with "
                                  "k1 k2 p1 p2 k3 only); undistort the images first")
    p: dict[str, float] = {}
    for keys in _GROUPS.values():
        src = entry if any(k in entry for k in keys) else meta
        for k in keys:
            if k in src:
                if not is_number(src[k]):
                    raise FileFormatError(f"{where}: {k} must be a finite number, got {src[k]!r}")
                p[k] = float(src[k])
    width, height = image_size(image)
    w, h = p.get("w", float(width)), p.get("h", float(height))
    if w <= 0 or h <= 0:
        raise FileFormatError(f"{where}: w and h must be > 0, got {w} x {h}")
    from_angle = {"x": _focal(where, p.get("camera_angle_x"), w, "x"),
                  "y": _focal(where, p.get("camera_angle_y"), h, "y")}
    for axis in "xy":
        given, derived = p.get(f"fl_{axis}"), from_angle[axis]
        if given is not None and derived is not None and abs(given - derived) > _FOCAL_RTOL * abs(derived):
            conflicts.append(f"frames[{i}] ({entry['file_path']!r}): fl_{axis} {given:g} px, camera_angle_{axis} "
                             f"gives {derived:g} px")
    fx = p["fl_x"] if "fl_x" in p else from_angle["x"]
    fy = p["fl_y"] if "fl_y" in p else from_angle["y"]
    fx, fy = fx if fx is not None else fy, fy if fy is not None else fx
    if fx is None or fy is None or fx <= 0 or fy <= 0:
        raise FileFormatError(f"{where}: no usable focal length (give fl_x / fl_y > 0 or camera_angle_x / "
                              "camera_angle_y, at the top level or per frame)")
    cx, cy = p.get("cx", w / 2.0), p.get("cy", h / 2.0)
    sx, sy = width / w, height / h
    if abs(h * sx - height) > 1.0 or abs(w * sy - width) > 1.0:
        raise FileFormatError(f"{where}: the file says {w:g} x {h:g} but the image {image} is {width} x {height} "
                              f"(not one uniform scale: x {sx:.4g}, y {sy:.4g})")
    intrinsics = [[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]]
    d = tuple(p.get(key, 0.0) for key in _GROUPS["distortion"])
    distortion = (d[0], d[1], d[2], d[3], d[4]) if any(d) else None
    return dataset_camera(where, frame_pose(path, i, entry), intrinsics, width, height), distortion


def _focal(where: str, angle: float | None, size: float, axis: str) -> float | None:
    """Focal length in pixels from a field of view in radians (None if not given)."""
    if angle is None:
        return None
    if not 0.0 < angle < math.pi:
        raise FileFormatError(f"{where}: camera_angle_{axis} must be in (0, pi) radians, got {angle}")
    return 0.5 * size / math.tan(angle / 2.0)
