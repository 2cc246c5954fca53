"""An exclusive lock on a run folder, so that two runs cannot write into the same ``--out``.

``with run_lock(folder):`` takes a non-blocking ``flock`` on ``<folder>/.lock`` and records the
holder (pid, host, start time, command line) in it; a second holder gets :class:`RunLockedError`
naming the first. The kernel drops the lock when its process dies (even on SIGKILL), so a stale
``.lock`` file never blocks a later run. A folder the lock created is removed again when the block
fails having written nothing else there (a refused run leaves nothing). POSIX only; elsewhere the
lock is not taken.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import sys
import time
from pathlib import Path
from typing import Any, Iterator

from .errors import FileWriteError, RunLockedError
from controlgs_adapter.formats.safetensors import as_path, file_mode

__all__ = ["run_lock", "lock_holder", "LOCK_NAME"]

LOCK_NAME = ".lock"


def lock_holder(folder: str | os.PathLike) -> dict[str, Any] | None:
    """What the lock file of ``folder`` says about its (last) holder, or None."""
    try:
        return json.loads((Path(folder) / LOCK_NAME).read_text() or "null")
    except (OSError, ValueError):
        return None


def _describe(holder: dict[str, Any] | None) -> str:
    if not isinstance(holder, dict):
        return "another process (its lock file is unreadable)"
    when = holder.get("time")
    started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(when)) if isinstance(when, (int, float)) else "?"
    return f"pid {holder.get('pid')} on {holder.get('host')} since {started} ({holder.get('command', '?')})"


@contextlib.contextmanager
def run_lock(folder: str | os.PathLike) -> Iterator[Path]:
    """Hold the exclusive lock of run folder ``folder`` (created if missing) inside the block.

    Raises:
        RunLockedError: another process holds it (the message names it: pid, host, start, command).
        FileWriteError: the folder or its lock file cannot be created.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield Path(folder) / LOCK_NAME
        return
    folder = as_path(folder, "run folder")
    path = folder / LOCK_NAME
    created = _missing_folders(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, file_mode())
    except OSError as e:
        raise FileWriteError(f"{folder}: cannot create the run folder's lock file: {e.strerror or e}") from e
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise RunLockedError(f"{folder}: this run folder is in use by {_describe(lock_holder(folder))}; "
                                 "wait for that run to end or choose another folder") from None
        me = {"pid": os.getpid(), "host": socket.gethostname(), "time": time.time(), "command": " ".join(sys.argv)[:200]}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(me).encode(), 0)
        try:
            yield path
        except BaseException:
            _remove_if_unused(created, path)
            raise
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the flock


def _missing_folders(folder: Path) -> list[Path]:
    """The folders, innermost first, that creating ``folder`` would create."""
    missing = []
    try:
        while not folder.exists() and folder != folder.parent:
            missing.append(folder)
            folder = folder.parent
    except OSError:
        return []
    return missing


def _remove_if_unused(created: list[Path], lock: Path) -> None:
    """Remove ``lock`` and the ``created`` folders (innermost first) while they hold nothing else."""
    if not created:
        return
    with contextlib.suppress(OSError):
        if [p.name for p in created[0].iterdir()] == [lock.name]:
            lock.unlink()
        for f in created:
            f.rmdir()  # fails (and stops) at the first folder something else was written into
