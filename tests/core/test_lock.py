"""The run-folder lock: it records its holder and clears the record on release, refuses a second
holder naming the first (pid, host, start time, command), removes the folders it created when the
block fails having written nothing else there, and refuses a folder it cannot create."""

from __future__ import annotations

import fcntl
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import pytest
from helpers.cli_runs import error_line

from controlgs_adapter import lock
from controlgs_adapter.cli import main
from controlgs_adapter.errors import ControlGSError, FileWriteError, RunLockedError
from controlgs_adapter.lock import LOCK_NAME, lock_holder, run_lock


def test_lock_records_this_holder_refuses_a_second_and_clears_the_record(tmp_path: Path) -> None:
    folder = tmp_path / "run" / "deep"
    assert lock_holder(folder) is None
    with run_lock(folder) as path:
        assert path == folder / LOCK_NAME == folder / ".lock"
        held = lock_holder(folder)
        assert held is not None and held["pid"] == os.getpid() and isinstance(held["time"], float) and held["command"]
        with pytest.raises(RunLockedError, match=rf"{re.escape(str(folder))}: .*pid {os.getpid()} on {held['host']} since "):
            with run_lock(folder):  # a second open file description of the same file
                pass
    assert path.read_text() == "" and lock_holder(folder) is None  # released: the record is emptied
    with run_lock(folder):  # and it can be taken again
        pass


def test_a_failing_block_removes_the_folders_the_lock_created_and_nothing_else(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError), run_lock(tmp_path / "new" / "run"):
        raise RuntimeError
    assert not (tmp_path / "new").exists()
    with pytest.raises(RuntimeError), run_lock(tmp_path / "kept"):
        (tmp_path / "kept" / "result.json").write_text("{}")  # something written: the folder stays
        raise RuntimeError
    assert sorted(p.name for p in (tmp_path / "kept").iterdir()) == [".lock", "result.json"]
    (tmp_path / "existing").mkdir()
    with pytest.raises(RuntimeError), run_lock(tmp_path / "existing"):
        raise RuntimeError
    assert (tmp_path / "existing").is_dir()  # not created by the lock


def test_a_folder_under_a_file_is_refused(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    for folder in (tmp_path / "f" / "run", tmp_path / "f"):
        with pytest.raises(FileWriteError, match=f"^{re.escape(str(folder))}: .*lock file"):
            with run_lock(folder):
                pass


def test_a_foreign_or_unreadable_holder_is_described(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    folder.mkdir()
    fd = os.open(folder / LOCK_NAME, os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, b"garbage")
        with pytest.raises(RunLockedError, match="unreadable"):
            run_lock(folder).__enter__()
        t = 86400.0 * 365
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": 4242, "host": "h", "time": t, "command": "c x"}).encode(), 0)
        started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(t))
        with pytest.raises(RunLockedError, match=rf"^{re.escape(str(folder))}: .*pid 4242 on h since {started} \(c x\)"):
            run_lock(folder).__enter__()
    finally:
        os.close(fd)
    (folder / LOCK_NAME).write_text("{not json")
    assert lock_holder(folder) is None
    assert "unreadable" in lock._describe(None)
    assert lock._describe({"pid": 5, "host": "h", "time": "x"}) == "pid 5 on h since ? (?)"


ROOT = Path(__file__).resolve().parents[2]


#: a process that holds a run folder's lock for two minutes
_HOLDER = """
import sys, time
from controlgs_adapter.lock import run_lock
with run_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


def test_run_folder_lock_refuses_a_second_process_naming_the_holder(tmp_path, capsys):
    run = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(run)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "held"
        msg = _raises(lambda: run_lock(run).__enter__(), RunLockedError, str(run), f"pid {holder.pid}")
        assert "since" in msg
        assert main(["demo", "--out", str(run)]) == 2  # the CLI too: one line naming the holder
        line = error_line(capsys, "demo")
        assert f"pid {holder.pid}" in line
        second = subprocess.run([sys.executable, "-c", _HOLDER, str(run)], capture_output=True, text=True, cwd=ROOT,
                                timeout=120)
        assert second.returncode != 0 and f"pid {holder.pid}" in second.stderr
    finally:
        holder.kill()  # SIGKILL: the kernel drops the lock, the stale .lock file does not block
        holder.wait()
    with run_lock(run):
        assert json.loads((run / ".lock").read_text())["pid"] == os.getpid()
