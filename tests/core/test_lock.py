"""Tests of ``controlgs_adapter.lock``."""

from __future__ import annotations

import fcntl
import json
import os
from datetime import datetime
from pathlib import Path

import pytest

from controlgs_adapter import lock
from controlgs_adapter.errors import FileWriteError, RunLockedError
from controlgs_adapter.lock import lock_holder, run_lock


def test_run_lock_is_reentrant_after_release(tmp_path):
    with run_lock(tmp_path):
        pass
    with run_lock(tmp_path):
        pass


# ---------------------------------------------------------------- run-folder lock
def test_lock_records_this_holder_and_clears_it(tmp_path: Path) -> None:
    with run_lock(tmp_path / "run") as path:
        assert path == tmp_path / "run" / ".lock"
        holder = lock_holder(tmp_path / "run")
        assert holder is not None and holder["pid"] == os.getpid()
        with pytest.raises(RunLockedError, match=f"pid {os.getpid()} on "):  # a second open file: refused
            run_lock(tmp_path / "run").__enter__()
    assert lock_holder(tmp_path / "run") is None  # released: the record is cleared
    assert lock_holder(tmp_path / "none") is None


def test_lock_message_of_a_foreign_or_unreadable_holder(tmp_path: Path) -> None:
    folder = tmp_path / "run"
    folder.mkdir()
    fd = os.open(folder / ".lock", os.O_RDWR | os.O_CREAT)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.write(fd, b"garbage")
        with pytest.raises(RunLockedError, match="its lock file is unreadable"):
            run_lock(folder).__enter__()
        t = 86400.0 * 365
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({"pid": 4242, "host": "h", "time": t, "command": "c x"}).encode(), 0)
        with pytest.raises(RunLockedError) as e:
            run_lock(folder).__enter__()
        started = datetime.fromtimestamp(t).strftime("%Y-%m-%d %H:%M:%S")
        assert f"{folder}: this run folder is in use by pid 4242 on h since {started} (c x)" in str(e.value)
    finally:
        os.close(fd)
    (tmp_path / "f").write_text("")
    with pytest.raises(FileWriteError, match=str(tmp_path / "f")):
        run_lock(tmp_path / "f" / "run").__enter__()


def test_run_lock_records_the_holder_and_refuses_a_second_holder(tmp_path):
    import os

    folder = tmp_path / "run" / "deep"
    assert lock.lock_holder(folder) is None
    with lock.run_lock(folder) as path:
        assert path == folder / lock.LOCK_NAME == folder / ".lock"
        held = lock.lock_holder(folder)
        assert held["pid"] == os.getpid() and isinstance(held["time"], float) and held["command"]
        with pytest.raises(RunLockedError) as e:  # a second open file description of the same file
            with lock.run_lock(folder):
                pass
        assert f"pid {os.getpid()} on {held['host']} since " in str(e.value) and str(folder) in str(e.value)
    assert path.read_text() == "" and lock.lock_holder(folder) is None  # emptied on release
    with lock.run_lock(folder):  # released: it can be taken again
        pass
    (tmp_path / "f").write_text("x")
    with pytest.raises(FileWriteError, match="cannot create the run folder's lock file"):
        with lock.run_lock(tmp_path / "f"):
            pass


def test_lock_holder_descriptions(tmp_path):
    (tmp_path / ".lock").write_text("{not json")
    assert lock.lock_holder(tmp_path) is None
    assert lock._describe(None) == "another process (its lock file is unreadable)"
    assert lock._describe({"pid": 5, "host": "h", "time": "x"}) == "pid 5 on h since ? (?)"
    (tmp_path / ".lock").write_text(json.dumps({"pid": 5, "host": "h", "time": 0, "command": "c"}))
    import time as _time
    want = _time.strftime("%Y-%m-%d %H:%M:%S", _time.localtime(0))
    assert lock._describe(lock.lock_holder(tmp_path)) == f"pid 5 on h since {want} (c)"
