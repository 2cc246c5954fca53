"""Self-describing safetensors files (adapters, PSF banks, training checkpoints), written atomically.

Every file carries one JSON header under the metadata key ``"controlgs_adapter"`` with at least
``kind`` (what the file holds), ``format_version`` and ``library_version``. Nothing is ever
unpickled.
"""

from __future__ import annotations

import contextlib
import glob
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Mapping

import torch
from safetensors import SafetensorError, safe_open
from safetensors.torch import save_file

from controlgs_adapter._version import __version__
from controlgs_adapter.errors import FileFormatError, FileWriteError, InputValueError, NonFiniteError

__all__ = ["HEADER_KEY", "atomic_write", "save_tensors", "load_tensors", "read_header"]

HEADER_KEY = "controlgs_adapter"


def as_path(path: object, what: str = "path") -> Path:
    """``path`` as a :class:`Path`; :class:`InputValueError` naming ``what`` if it is not a path."""
    if isinstance(path, bytes):
        path = os.fsdecode(path)
    if not isinstance(path, (str, os.PathLike)) or not str(path):
        raise InputValueError(f"{what} must be a file path (str or os.PathLike), got {path!r}")
    return Path(path)


def _umask() -> int:
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1], 8) for line in f if line.startswith("Umask:"))
    except (OSError, StopIteration, ValueError):
        umask = os.umask(0o022)
        os.umask(umask)
        return umask


def file_mode() -> int:
    """Permission bits of a new file under the process's umask (0644 under the usual 022)."""
    return 0o666 & ~_umask()


def folder_mode() -> int:
    """Permission bits of a new folder under the process's umask (0755 under the usual 022)."""
    return 0o777 & ~_umask()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_tmp(path: Path) -> list[Path]:
    """Remove the ``.<name>.<pid>.*.tmp`` siblings of ``path`` left by writers (of this host) that
    were killed mid-write: those whose pid is no longer running. Returns what was removed."""
    removed = []
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        pid = tmp.name[len(path.name) + 2:].split(".", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid)):
            with contextlib.suppress(OSError):
                tmp.unlink()
                removed.append(tmp)
    return removed


def atomic_write(path: str | os.PathLike, write: Callable[[str], object]) -> Path:
    """Call ``write(tmp_path)`` then rename onto ``path`` so that readers never see a half file.

    The file gets the umask's mode (as ``open`` would give it); the temporary sibling is named
    ``.<name>.<pid>.<random>.tmp`` so that one left by a killed writer is removed by the next write
    to ``path``. Raises :class:`InputValueError` for a path that is not one or names a folder, and
    :class:`FileWriteError` (an ``OSError``) naming ``path`` when the write fails (a full disk, a file
    size limit, safetensors' own error from the same causes); the temporary file is removed and a
    file already at ``path`` is left as it was."""
    path = as_path(path)
    if path.is_dir():
        raise InputValueError(f"{path}: is a folder; expected the path of a file to write")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_tmp(path)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp", dir=path.parent)
        os.close(fd)
    except OSError as e:
        raise FileWriteError(f"{path}: cannot write here: {e.strerror or e}") from e
    try:
        write(tmp)
        os.chmod(tmp, file_mode())
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except (OSError, SafetensorError) as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        why = (e.strerror if isinstance(e, OSError) else None) or " ".join(str(e).split()) or type(e).__name__
        raise FileWriteError(f"{path}: write failed: {why}") from e
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def save_tensors(path: str | os.PathLike, tensors: Mapping[str, torch.Tensor], header: Mapping[str, Any], *, kind: str,
                 format_version: int) -> Path:
    """Write ``tensors`` (made contiguous, de-aliased, moved to CPU) with ``header`` atomically.

    Raises :class:`NonFiniteError` naming the tensor if a floating-point one holds NaN/Inf (a
    float16 one: its values overflowed float16's range), before anything is written."""
    path = as_path(path)
    for k, v in tensors.items():
        if not isinstance(v, torch.Tensor):
            raise InputValueError(f"{path}: tensor {k!r} must be a torch.Tensor, got {type(v).__name__}")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            why = (f" (values beyond {v.dtype}'s range {torch.finfo(v.dtype).max:g} overflowed)"
                   if v.dtype in (torch.float16, torch.bfloat16) else "")
            raise NonFiniteError(f"{path}: refusing to save tensor {k!r}: it holds "
                                 f"{int((~torch.isfinite(v)).sum())} NaN/Inf value(s){why}")
    full = {"kind": kind, "format_version": format_version, "library_version": __version__, **header}
    try:
        meta = {HEADER_KEY: json.dumps(full, sort_keys=True, allow_nan=False), "format": "pt"}
    except ValueError as e:
        raise NonFiniteError(f"{path}: refusing to save a header with a NaN/Inf number: {e}") from e
    data = {k: v.detach().to("cpu").contiguous().clone() for k, v in tensors.items()}
    return atomic_write(path, lambda tmp: save_file(data, tmp, metadata=meta))


def read_header(path: str | os.PathLike, *, kind: str, max_version: int) -> dict[str, Any]:
    """Read and check the JSON header only. Raises :class:`FileFormatError` naming the file."""
    path = as_path(path)
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
    except (ValueError, RecursionError) as e:
        raise FileFormatError(f"{path}: corrupt controlgs-adapter header: {type(e).__name__}: {e}") from None
    if not isinstance(header, dict):
        raise FileFormatError(f"{path}: controlgs-adapter header must be a JSON object, got {type(header).__name__}")
    if header.get("kind") != kind:
        raise FileFormatError(f"{path}: holds a {header.get('kind')!r}, expected a {kind!r}")
    v = header.get("format_version")
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise FileFormatError(f"{path}: format_version must be an integer >= 1, got {v!r}")
    if v > max_version:
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
