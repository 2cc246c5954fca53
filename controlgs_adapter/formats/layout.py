"""The output-folder layout the neural-Gaussian families share: ``<root>/point_cloud/iteration_<N>/``."""

from __future__ import annotations

import numbers
import re
from pathlib import Path

from controlgs_adapter.errors import FileFormatError, InputValueError

__all__ = ["iteration_dirs", "iteration_dir", "check_iteration", "bitstreams_only"]


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


def check_iteration(iteration: object) -> int | None:
    """The ``iteration`` argument of the loaders as an int >= 0 (a whole number, also written as a
    string such as ``'30000'``); None stays None. Anything else: :class:`InputValueError` naming it."""
    if iteration is None:
        return None
    text = str(iteration).strip() if isinstance(iteration, str) else None
    if text is not None and text.isdigit():
        return int(text)
    if isinstance(iteration, bool) or not isinstance(iteration, numbers.Integral) or int(iteration) < 0:
        raise InputValueError(f"iteration must be a whole number >= 0 (the N of point_cloud/iteration_<N>) or None, "
                              f"got {iteration!r}")
    return int(iteration)


def iteration_dir(root: str | Path, iteration: int | None, *, family: str) -> Path:
    """``<root>/point_cloud/iteration_<it>``: the given iteration or the highest one present."""
    iteration = check_iteration(iteration)
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
