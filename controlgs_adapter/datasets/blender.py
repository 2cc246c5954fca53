"""NeRF-synthetic ("Blender") datasets: ``transforms_train.json`` and ``transforms_test.json``.

Each file holds ``camera_angle_x`` (horizontal field of view, radians) and ``frames``, each with a
``file_path`` relative to the dataset folder (often without its extension: ``.png`` is appended, as
3DGS does) and a ``transform_matrix``: camera to world in OpenGL axes (x right, y up, z backward).
``transforms_val.json`` is ignored, as by the Scaffold-GS family. The helpers here are shared with
the instant-ngp reader, which uses the same axes and the same checks: every path resolves inside the
dataset folder (symlinks followed), numbers are JSON numbers (not strings or bools) that fit float32,
a 4x4 pose ends in ``[0, 0, 0, 1]``, and an image is listed once.
"""

from __future__ import annotations

import json
import math
import numbers
import posixpath
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..checks import check_tensor
from ..errors import FileFormatError, InputValueError
from .base import Frame, SceneData
from .guards import dataset_camera, float32_finite, inside, is_number
from .images import image_size

__all__ = ["read_blender", "opengl_c2w_to_w2c"]

#: OpenGL -> OpenCV camera axes: y and z change sign
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def opengl_c2w_to_w2c(c2w: Sequence[Sequence[float]] | np.ndarray) -> torch.Tensor:
    """Camera-to-world ``[4, 4]`` (or ``[3, 4]``) in OpenGL camera axes (x right, y up, z backward)
    -> world-to-camera ``[4, 4]`` float32 in OpenCV axes (x right, y down, z forward).

    The y and z columns of the rotation change sign, then the rigid transform is inverted
    (``R^T``, ``-R^T t``, in float64). Raises :class:`InputValueError` unless every entry is a
    number (not a string or bool), the rotation is orthonormal to 1e-3 (a scaled or sheared matrix is
    not a camera pose), a 4x4 matrix's last row is ``[0, 0, 0, 1]`` and the pose fits float32.
    """
    if isinstance(c2w, torch.Tensor):
        c2w = c2w.detach().cpu().double().numpy()
    if not isinstance(c2w, np.ndarray):
        if not isinstance(c2w, (list, tuple)) or not all(isinstance(row, (list, tuple, np.ndarray)) for row in c2w):
            raise InputValueError(f"transform_matrix must be a 4x4 (or 3x4) list of rows, got {c2w!r:.60}")
        odd = [v for row in c2w for v in row if isinstance(v, bool) or not isinstance(v, numbers.Real)]
        if odd:
            raise InputValueError(f"transform_matrix must hold numbers only, got {odd[0]!r}")
    elif not np.issubdtype(c2w.dtype, np.integer) and not np.issubdtype(c2w.dtype, np.floating):
        raise InputValueError(f"transform_matrix must hold numbers only, got dtype {c2w.dtype}")
    try:
        m = np.asarray(c2w, dtype=np.float64)
    except (ValueError, TypeError, OverflowError):
        raise InputValueError(f"transform_matrix must be a finite 4x4 (or 3x4) matrix, got {c2w!r:.60}") from None
    if m.shape not in ((4, 4), (3, 4)) or not np.isfinite(m).all():
        raise InputValueError(f"transform_matrix must be a finite 4x4 (or 3x4) matrix, got shape {list(m.shape)}")
    if m.shape == (4, 4) and np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-6:
        raise InputValueError(f"transform_matrix: its last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    r = m[:3, :3] @ _GL_TO_CV
    t = m[:3, 3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0:
        raise InputValueError("transform_matrix: its 3x3 part is not a rotation (scaled, sheared or mirrored)")
    w2c = np.eye(4)
    w2c[:3, :3] = r.T
    w2c[:3, 3] = -r.T @ t
    if not float32_finite(w2c):
        raise InputValueError(f"transform_matrix: the translation {t.tolist()} does not fit float32 (|value| > 3.4e38)")
    return torch.from_numpy(w2c).float()


def read_blender(root: str | Path, *, background: torch.Tensor | None = None,
                 white_background: bool = False) -> SceneData:
    """Read a NeRF-synthetic dataset folder into ``{"train", "test"}`` frames (no SfM points).

    Args:
        root: folder holding ``transforms_train.json`` (required) and ``transforms_test.json``
            (optional: without it the test split is empty).
        background: ``[3]`` sRGB colour in [0, 1] the RGBA images are composited over; overrides
            ``white_background``.
        white_background: composite over white instead of black (3DGS ``--white_background``).

    Intrinsics: fx = fy = 0.5 W / tan(camera_angle_x / 2), principal point at the image centre
    (W/2, H/2), W x H from each image's header. Raises :class:`FileFormatError` naming the file and
    frame for a missing folder, JSON file or image, a malformed or duplicated entry, or a path that
    leads outside ``root`` (``..``, absolute, or a symlink out of it).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileFormatError(f"{root}: dataset folder not found")
    bg = resolve_background(background, white_background)
    train_json = inside(root, "transforms_train.json", str(root), "the file")
    if not train_json.is_file():
        raise FileFormatError(f"{root}: no transforms_train.json (a NeRF-synthetic dataset needs "
                              "transforms_train.json and transforms_test.json)")
    splits = {"train": _read_split(root, train_json), "test": []}
    test_json = inside(root, "transforms_test.json", str(root), "the file")
    if test_json.is_file():
        splits["test"] = _read_split(root, test_json)
    both = {f.name for f in splits["train"]} & {f.name for f in splits["test"]}
    if both:
        raise FileFormatError(f"{test_json}: lists training images too ({', '.join(sorted(both)[:5])})")
    return SceneData(splits=splits, points=None, background=bg, source=str(root), format="blender")


def _read_split(root: Path, path: Path) -> list[Frame]:
    """Frames of one ``transforms_<split>.json`` of the dataset folder ``root``."""
    meta = read_json(path)
    angle = meta.get("camera_angle_x")
    if not is_number(angle) or not 0.0 < float(angle) < math.pi:
        raise FileFormatError(f"{path}: camera_angle_x must be a number in (0, pi) radians, got {angle!r}")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise FileFormatError(f"{path}: 'frames' must be a list, got {type(frames).__name__}")
    tan_half = math.tan(float(angle) / 2.0)
    out: list[Frame] = []
    first: dict[str, int] = {}
    for i, entry in enumerate(frames):
        name, image = frame_image_path(root, path, i, entry)
        where = f"{path}: frames[{i}] ({entry['file_path']!r})"
        if name in first:
            raise FileFormatError(f"{where}: an image is listed twice ({name!r}), also in frames[{first[name]}]")
        first[name] = i
        if not image.is_file():
            raise FileFormatError(f"{path}: frames[{i}] image {entry['file_path']!r} not found (looked for {image}"
                                  f"{'' if image.suffix == '.png' else ' and with .png appended'})")
        pose = frame_pose(path, i, entry)
        w, h = image_size(image)
        f = 0.5 * w / tan_half
        k = [[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]]
        out.append(Frame(name=name, camera=dataset_camera(where, pose, k, w, h), source=image))
    return out


def read_json(path: Path) -> dict[str, Any]:
    """Parse a JSON object; :class:`FileFormatError` naming the file otherwise (also for nesting
    too deep to parse)."""
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as e:  # ValueError: JSON syntax, integers too long
        raise FileFormatError(f"{path}: cannot read it as JSON ({e})") from None
    except RecursionError:
        raise FileFormatError(f"{path}: cannot read it as JSON (nested too deeply)") from None
    if not isinstance(meta, dict):
        raise FileFormatError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    return meta


def frame_image_path(root: Path, path: Path, i: int, entry: Any) -> tuple[str, Path]:
    """``(name, image path)`` of ``frames[i]`` of the JSON file ``path`` in the dataset folder ``root``.
    The image is relative to ``root``, ``.png`` appended unless ``file_path`` as written names an
    existing file; the name is that relative path, normalised (``./train/r_0`` -> ``train/r_0.png``).
    A path that is absolute or leads outside ``root`` (``..``, symlinks) is a :class:`FileFormatError`,
    refused before anything is opened."""
    if not isinstance(entry, dict) or not isinstance(entry.get("file_path"), str) or not entry["file_path"]:
        raise FileFormatError(f"{path}: frames[{i}] needs a 'file_path' string")
    rel = entry["file_path"].replace("\\", "/")
    where = f"{path}: frames[{i}]"
    image = inside(root, rel, where, "file_path")
    if not image.is_file():
        png = inside(root, rel + ".png", where, "file_path (with .png appended)")
        if png.is_file():
            rel, image = rel + ".png", png
    return posixpath.normpath(rel), image


def frame_pose(path: Path, i: int, entry: dict[str, Any]) -> torch.Tensor:
    """World-to-camera ``[4, 4]`` (OpenCV axes) of ``frames[i]`` of ``path`` from its OpenGL
    ``transform_matrix`` (numbers only, last row ``[0, 0, 0, 1]``, fitting float32);
    :class:`FileFormatError` naming the file and frame otherwise."""
    matrix = entry.get("transform_matrix")
    if matrix is None:
        raise FileFormatError(f"{path}: frames[{i}] ({entry.get('file_path')!r}): no 'transform_matrix'")
    try:
        return opengl_c2w_to_w2c(matrix)
    except (InputValueError, ValueError, TypeError) as e:
        raise FileFormatError(f"{path}: frames[{i}] ({entry.get('file_path')!r}): {e}") from None


def resolve_background(background: torch.Tensor | None, white: bool = False) -> torch.Tensor:
    """The ``[3]`` float32 background: ``background`` if given (checked: finite, in [0, 1]), else
    white or black."""
    if background is None:
        return torch.ones(3) if white else torch.zeros(3)
    check_tensor("background", background, [3], finite=True)
    bg = background.detach().float().cpu()
    if bg.min() < 0 or bg.max() > 1:
        raise InputValueError(f"background must be an sRGB colour in [0, 1], got {bg.tolist()}")
    return bg

