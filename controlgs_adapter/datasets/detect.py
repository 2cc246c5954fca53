"""Pick the dataparser for a dataset folder from what it contains."""

from __future__ import annotations

from pathlib import Path

import torch

from ..errors import FileFormatError, InputValueError
from .base import SceneData
from .blender import read_blender, resolve_background
from .instant_ngp import read_instant_ngp

__all__ = ["load_dataset", "detect_format", "FORMATS"]

#: the formats and what a folder needs to be recognised as each (checked in this order)
FORMATS = {
    "colmap": "sparse/0/ (or sparse/) with cameras.bin|txt, images.bin|txt",
    "blender": "transforms_train.json (and transforms_test.json)",
    "instant_ngp": "transforms.json",
}


def detect_format(root: str | Path) -> str:
    """The format of the dataset folder ``root`` (a key of :data:`FORMATS`): COLMAP if
    ``sparse/0`` or ``sparse`` holds ``cameras.bin`` or ``cameras.txt``, else Blender if
    ``transforms_train.json`` exists, else instant-ngp if ``transforms.json`` exists.
    Raises :class:`FileFormatError` for a missing folder or one in no known format."""
    root = Path(root)
    if not root.is_dir():
        raise FileFormatError(f"{root}: dataset folder not found")
    if any((root / sub / f"cameras.{ext}").is_file() for sub in ("sparse/0", "sparse") for ext in ("bin", "txt")):
        return "colmap"
    if (root / "transforms_train.json").is_file():
        return "blender"
    if (root / "transforms.json").is_file():
        return "instant_ngp"
    listing = sorted(p.name + ("/" if p.is_dir() else "") for p in root.iterdir())
    needs = "; ".join(f"{name}: {need}" for name, need in FORMATS.items())
    raise FileFormatError(f"{root}: not a dataset folder in a known format (it holds: "
                          f"{', '.join(listing[:10]) + (', ...' if len(listing) > 10 else '') or 'nothing'}). "
                          f"Each format needs: {needs}")


def load_dataset(path: str | Path, *, format: str | None = None, images: str | None = None,
                 resolution: int | None = None, holdout: int = 8, background: torch.Tensor | None = None,
                 white_background: bool = False) -> SceneData:
    """Read the dataset folder ``path`` with the dataparser its contents call for (:func:`detect_format`)
    or the one ``format`` names (``"colmap"``, ``"blender"``, ``"instant_ngp"``).

    Args:
        images, resolution: COLMAP only (passed to ``read_colmap``): ``images`` for a format that has
            no image folder of that name is an error; ``resolution`` is ignored by the others, whose
            frames stay full size until ``SceneData.views(resolution=...)`` brings them to a working size.
        holdout: every ``holdout``-th frame by name is a test view (COLMAP, instant-ngp; 0: none).
            Blender datasets carry their own split.
        background: ``[3]`` sRGB colour RGBA images are composited over; overrides ``white_background``
            (white instead of black, 3DGS ``--white_background``).
    """
    fmt = detect_format(path) if format is None else _format_name(format)
    root = Path(path)
    if fmt != "colmap" and images is not None:
        raise InputValueError(f"images={images!r} applies to COLMAP datasets only; {root} is read as {fmt}")
    bg = resolve_background(background, white_background)
    if fmt == "colmap":
        from .colmap import read_colmap  # imported on use

        return read_colmap(root, images=images, resolution=resolution, holdout=holdout, background=bg)
    if fmt == "blender":
        return read_blender(root, background=bg)
    return read_instant_ngp(root, holdout=holdout, background=bg)


def _format_name(format: str) -> str:
    """``format`` checked and normalised (``instant-ngp`` -> ``instant_ngp``)."""
    name = format.strip().lower().replace("-", "_") if isinstance(format, str) else format
    if name not in FORMATS:
        raise InputValueError(f"format must be one of {', '.join(FORMATS)} (or None to detect it), got {format!r}")
    return name
