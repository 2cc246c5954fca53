"""Checks the dataparsers share: paths a dataset names stay inside its folder, numbers a file gives
are numbers that fit float32, and warnings point at the caller's line rather than the library's."""

from __future__ import annotations

import math
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any, Sequence, TypeGuard

import numpy as np
import torch

from ..errors import FileFormatError, InputValueError, warn_user
from ..state import Camera

__all__ = ["inside", "is_number", "float32_finite", "dataset_camera", "warn_user"]

#: largest finite float32
_F32_MAX = float(np.finfo(np.float32).max)


def inside(root: Path, rel: str, where: str, what: str = "path", base: Path | None = None) -> Path:
    """``base / rel`` (``base`` defaults to ``root``) if it lies inside ``root`` once resolved (``..``
    and symlinks followed); :class:`FileFormatError` ``"{where}: {what} ... outside ..."`` for an
    absolute path or one that leads out of ``root``. Only the path is resolved: nothing is opened."""
    if not rel or "\0" in rel:
        raise FileFormatError(f"{where}: {what} {rel!r} is not a usable path")
    if PurePosixPath(rel).is_absolute() or PureWindowsPath(rel).is_absolute():
        raise FileFormatError(f"{where}: {what} {rel!r} is absolute; it must be relative to the dataset folder {root}")
    path = (root if base is None else base) / rel
    try:
        top, target = root.resolve(), path.resolve()
    except (OSError, RuntimeError) as e:  # RuntimeError: a symlink loop
        raise FileFormatError(f"{where}: {what} {rel!r} cannot be resolved ({e})") from None
    if target != top and top not in target.parents:
        raise FileFormatError(f"{where}: {what} {rel!r} leads outside the dataset folder {root} (to {target}); "
                              "paths (and symlinks) must stay inside it")
    return path


def is_number(x: Any) -> TypeGuard[float]:
    """Whether ``x`` is a JSON number (not a bool or string) that is finite as a float."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(float(x))
    except OverflowError:  # an integer beyond float64
        return False


def float32_finite(values: Sequence[float] | np.ndarray | torch.Tensor) -> bool:
    """Whether every value stays finite in float32 (finite float64 values up to ~3.4e38)."""
    a = np.asarray(values.detach().cpu().double() if isinstance(values, torch.Tensor) else values, dtype=np.float64)
    return bool(np.isfinite(a).all() and (np.abs(a) <= _F32_MAX).all())


def dataset_camera(where: str, world_to_camera: torch.Tensor, intrinsics: torch.Tensor | Sequence[Sequence[float]],
                   width: int, height: int) -> Camera:
    """A :class:`Camera` built from a dataset entry, every refusal a :class:`FileFormatError` that starts
    with ``where`` (the file and frame/line). ``intrinsics`` may be float64; values beyond float32 are refused."""
    k64 = torch.as_tensor(intrinsics, dtype=torch.float64)
    if not float32_finite(k64):
        raise FileFormatError(f"{where}: intrinsics {k64[:2].tolist()} do not fit float32 (|value| > 3.4e38 or "
                              "not finite)")
    if not float32_finite(world_to_camera):
        raise FileFormatError(f"{where}: the pose does not fit float32 (|value| > 3.4e38 or not finite)")
    try:
        return Camera(world_to_camera.float(), k64.float(), width, height)
    except InputValueError as e:
        raise FileFormatError(f"{where}: {e}") from None
