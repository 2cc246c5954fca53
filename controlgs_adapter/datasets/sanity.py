"""Up-front checks for the dataset mistakes that otherwise render silently wrong: camera axes flipped
(OpenGL vs OpenCV: the scene lands behind every camera and training sees only background), image
files whose size does not match their camera, and an empty split."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import torch

from ..checks import check_tensor
from ..errors import FileFormatError, InputValueError
from .base import Frame, SceneData
from .guards import warn_user
from .images import image_size

__all__ = ["check_scene"]

#: at most this many points are projected per camera (an even stride through the given ones)
_MAX_POINTS = 20_000
#: how many offending cameras / files a message names
_NAMED = 5

_AXES_HINT = {
    "blender": "NeRF-synthetic transform_matrix must be camera to world in OpenGL axes (x right, y up, z backward)",
    "instant_ngp": "instant-ngp transform_matrix must be camera to world in OpenGL axes (x right, y up, z backward)",
    "colmap": "COLMAP's images file must hold world to camera (QW QX QY QZ TX TY TZ) in OpenCV axes "
              "(x right, y down, z forward), not camera to world",
}


def check_scene(data: SceneData, points: torch.Tensor | None = None, *, min_in_front: float = 0.05,
                required: Sequence[str] = ("train",)) -> dict[str, Any]:
    """Check a parsed dataset before training; raise with a clear message on what would fail silently.

    Args:
        data: the parsed dataset.
        points: ``[P, 3]`` world points the cameras should see (e.g. the model's anchor positions);
            default ``data.points`` (SfM points). Without either the visibility check is skipped.
        min_in_front: a camera sees the scene when at least this fraction of the points has positive
            depth and projects inside its image.
        required: splits that must not be empty.

    Raises:
        InputValueError: a required split is empty; or more than half of the cameras see the scene
            (almost) not at all, the signature of flipped camera axes (the message names the format's
            convention). When fewer cameras are blind a ``RuntimeWarning`` names them.
        FileFormatError: image files whose header size differs from their camera (names them).

    Returns:
        ``{"source", "format", "splits": {split: n}, "images_checked": n, "points": P used,
        "in_front": {frame name: fraction} (empty without points), "blind": [frame names]}``.
    """
    if isinstance(min_in_front, bool) or not isinstance(min_in_front, (int, float)) or not 0.0 <= min_in_front < 1.0:
        raise InputValueError(f"min_in_front must be a fraction in [0, 1), got {min_in_front!r}")
    where = data.source or "dataset"
    for split in required:
        if not data.splits.get(split):
            raise InputValueError(f"{where}: the {split!r} split is empty "
                                  f"(splits: {', '.join(f'{s}={len(f)}' for s, f in data.splits.items()) or 'none'})")
    frames = [f for split in data.splits.values() for f in split]
    _check_sizes(frames)
    report: dict[str, Any] = {"source": data.source, "format": data.format,
                              "splits": {s: len(f) for s, f in data.splits.items()},
                              "images_checked": len(frames), "points": 0, "in_front": {}, "blind": []}
    pts = data.points if points is None else points
    if pts is None or not frames:
        return report
    check_tensor("points", pts, ["P", 3], finite=True)
    if pts.shape[0] == 0:
        return report
    pts = pts.detach().float().cpu()[:: max(1, -(-pts.shape[0] // _MAX_POINTS))]
    behind = 0.0
    for f in frames:
        cam = f.camera
        uv, z = cam.project(pts)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        report["in_front"][f.name] = float(inside.float().mean())
        behind += float((z <= 0).float().mean()) / len(frames)
    report["points"] = int(pts.shape[0])
    blind = [n for n, v in report["in_front"].items() if v < min_in_front]
    report["blind"] = blind
    if not blind:
        return report
    named = ", ".join(blind[:_NAMED]) + (", ..." if len(blind) > _NAMED else "")
    if 2 * len(blind) > len(frames):
        hint = _AXES_HINT.get(data.format, "cameras must be world to camera in OpenCV axes "
                                           "(x right, y down, z forward)")
        raise InputValueError(
            f"{where}: {len(blind)} of {len(frames)} cameras see none of the scene in front of them (fewer than "
            f"{min_in_front:.0%} of {pts.shape[0]} points have positive depth inside the image; on average "
            f"{behind:.0%} lie behind the cameras): the camera axes are probably flipped (OpenGL vs OpenCV). "
            f"{data.format or 'this dataset'}: {hint}. (Or the points are in another world frame.)")
    warn_user(f"{where}: {len(blind)} of {len(frames)} cameras see almost none of the {pts.shape[0]} points "
              f"(< {min_in_front:.0%} in front, inside the image): {named}")
    return report


def _check_sizes(frames: list[Frame]) -> None:
    """Every image's size (file header, or tensor shape) equals its camera's; raise naming the
    mismatched files."""
    bad = []
    for f in frames:
        if isinstance(f.source, Path):
            w, h = image_size(f.source)
        else:
            h, w = int(f.source.shape[-2]), int(f.source.shape[-1])
        if (w, h) != (f.camera.width, f.camera.height):
            bad.append(f"{f.source if isinstance(f.source, Path) else f.name} is {w}x{h}, "
                       f"its camera {f.camera.width}x{f.camera.height}")
    if bad:
        raise FileFormatError(f"{len(bad)} of {len(frames)} images do not match their camera's size: "
                              + "; ".join(bad[:_NAMED]) + ("; ..." if len(bad) > _NAMED else ""))
