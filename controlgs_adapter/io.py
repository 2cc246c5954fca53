"""Self-describing safetensors files (adapters, PSF banks, training checkpoints), written atomically.

Every file carries one JSON header under the metadata key ``"controlgs_adapter"`` with at least
``kind`` (what the file holds), ``format_version`` and ``library_version``. Nothing is ever
unpickled.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Mapping

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from ._version import __version__
from .errors import FileFormatError

__all__ = ["HEADER_KEY", "atomic_write", "save_tensors", "load_tensors", "read_header"]

HEADER_KEY = "controlgs_adapter"


def atomic_write(path: str | os.PathLike, write: "callable[[str], None]") -> Path:  # type: ignore[valid-type]
    """Call ``write(tmp_path)`` then rename onto ``path`` so that readers never see a half file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def save_tensors(path: str | os.PathLike, tensors: Mapping[str, torch.Tensor], header: Mapping[str, Any], *, kind: str,
                 format_version: int) -> Path:
    """Write ``tensors`` (made contiguous, de-aliased, moved to CPU) with ``header`` atomically."""
    full = {"kind": kind, "format_version": format_version, "library_version": __version__, **header}
    meta = {HEADER_KEY: json.dumps(full, sort_keys=True), "format": "pt"}
    data = {k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}
    return atomic_write(path, lambda tmp: save_file(data, tmp, metadata=meta))


def read_header(path: str | os.PathLike, *, kind: str, max_version: int) -> dict[str, Any]:
    """Read and check the JSON header only. Raises :class:`FileFormatError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    try:
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
    except (SafetensorError, OSError, ValueError) as e:
        raise FileFormatError(f"{path}: not a readable safetensors file (truncated or foreign?): {e}") from e
    if HEADER_KEY not in meta:
        raise FileFormatError(f"{path}: a safetensors file, but not written by controlgs-adapter (no '{HEADER_KEY}' header)")
    try:
        header = json.loads(meta[HEADER_KEY])
    except json.JSONDecodeError as e:
        raise FileFormatError(f"{path}: corrupt controlgs-adapter header: {e}") from e
    if header.get("kind") != kind:
        raise FileFormatError(f"{path}: holds a {header.get('kind')!r}, expected a {kind!r}")
    v = header.get("format_version")
    if not isinstance(v, int) or v > max_version:
        raise FileFormatError(
            f"{path}: format_version {v!r} is newer than this library reads (<= {max_version}); "
            f"written by controlgs-adapter {header.get('library_version')}, this is {__version__}: upgrade"
        )
    return header


def load_tensors(path: str | os.PathLike, *, kind: str, max_version: int,
                 device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Read a file written by :func:`save_tensors`: ``(tensors, header)``."""
    header = read_header(path, kind=kind, max_version=max_version)
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise FileFormatError(f"{path}: tensor data unreadable (truncated?): {e}") from e
    return tensors, header
