"""The output-folder layout the neural-Gaussian families share: ``<root>/point_cloud/iteration_<N>/``."""

from __future__ import annotations

import re
from pathlib import Path

from controlgs_adapter.errors import FileFormatError

__all__ = ["iteration_dirs", "iteration_dir", "bitstreams_only"]


def iteration_dirs(root: str | Path) -> dict[int, Path]:
    """``{N: <root>/point_cloud/iteration_<N>}`` of the folders present (empty when there are none)."""
    pc = Path(root) / "point_cloud"
    if not pc.is_dir():
        return {}
    return {int(m.group(1)): p for p in pc.iterdir() if p.is_dir() and (m := re.fullmatch(r"iteration_(\d+)", p.name))}


def bitstreams_only(root: str | Path) -> str:
    """A sentence for a folder that holds the compressed ``bitstreams/`` but no decoded point cloud
    (empty when it holds no ``bitstreams/``)."""
    if not (Path(root) / "bitstreams").is_dir():
        return ""
    return ("; bitstreams/ was found, but it cannot be decoded here (it needs the family's arithmetic coders, and "
            "G-PCC for HAC++ positions): keep the point_cloud/iteration_<N> folder training writes next to it "
            "(with run_codec=True it holds the decoded model)")


def iteration_dir(root: str | Path, iteration: int | None, *, family: str) -> Path:
    """``<root>/point_cloud/iteration_<it>``: the given iteration or the highest one present."""
    pc = Path(root) / "point_cloud"
    if not pc.is_dir():
        raise FileFormatError(f"{Path(root)}: not a {family} output directory (no 'point_cloud/iteration_<N>' folder)"
                              + bitstreams_only(root))
    found = iteration_dirs(root)
    if iteration is None:
        if not found:
            raise FileFormatError(f"{pc}: no 'iteration_<N>' folder (not a {family} output directory)"
                                  + bitstreams_only(root))
        return found[max(found)]
    if iteration not in found:
        raise FileFormatError(f"{pc}: no 'iteration_{iteration}' folder (present: {sorted(found)})")
    return found[iteration]
