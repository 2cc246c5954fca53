"""Tests of ``controlgs_adapter.formats.safetensors``."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pytest
import torch
from helpers.scaffold_standin import ScaffoldStandIn
from safetensors.torch import save_file

from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import ControlGSError, FileFormatError, FileWriteError, InputValueError, NonFiniteError
from controlgs_adapter.formats import safetensors as st
from controlgs_adapter.formats.safetensors import as_path, atomic_write, file_mode, read_header, save_tensors

ROOT = Path(__file__).resolve().parents[2]


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ============================================================================ API: adapter wrap / save / load
@pytest.fixture
def cgs():
    c = ControlGS.wrap(ScaffoldStandIn(30, seed=0))
    yield c
    if c._wrapped:
        c.unwrap()


# ============================================================================ API: safetensors I/O
IO_CASES = [
    ("NaN", {"w": torch.tensor([1.0, math.nan])}, NonFiniteError, "'w'"),
    ("Inf", {"w": torch.tensor([math.inf])}, NonFiniteError, "'w'"),
    ("fp16 inf", {"h": torch.tensor([1e5]).half()}, NonFiniteError, "float16"),
    ("not a tensor", {"w": [1.0, 2.0]}, InputValueError, "'w'"),
]


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


@pytest.mark.parametrize("tensors, error, name", [c[1:] for c in IO_CASES], ids=[c[0] for c in IO_CASES])
def test_save_tensors(tmp_path, tensors, error, name):
    _raises(lambda: save_tensors(tmp_path / "x.safetensors", tensors, {}, kind="k", format_version=1), error, name,
            "x.safetensors")
    assert not list(tmp_path.iterdir()), "nothing may be written"


def test_save_tensors_refuses_nan_in_the_header(tmp_path):
    _raises(lambda: save_tensors(tmp_path / "x.safetensors", {}, {"a": math.nan}, kind="k", format_version=1),
            NonFiniteError, "x.safetensors")


@pytest.mark.parametrize("path", [None, 3.5, ""], ids=["None", "float", "empty"])
def test_io_paths(path):
    _raises(lambda: save_tensors(path, {}, {}, kind="k", format_version=1), InputValueError, "path")
    _raises(lambda: read_header(path, kind="k", max_version=1), InputValueError, "path")


def test_atomic_write_onto_a_folder(tmp_path):
    _raises(lambda: atomic_write(tmp_path, lambda p: None), InputValueError, str(tmp_path))


# ============================================================================ file modes and partial files
def test_files_get_the_umask_mode(tmp_path, cgs):
    old = os.umask(0o022)
    try:
        p = cgs.save(tmp_path / "sub" / "a.safetensors")
        assert p.stat().st_mode & 0o777 == 0o644
        assert (tmp_path / "sub").stat().st_mode & 0o777 == 0o755
        os.umask(0o027)
        q = atomic_write(tmp_path / "b.txt", lambda t: Path(t).write_text("x"))
        assert q.stat().st_mode & 0o777 == 0o640 and file_mode() == 0o640
    finally:
        os.umask(old)


def test_partial_tmp_files_of_killed_writers_are_removed(tmp_path):
    target = tmp_path / "a.safetensors"
    stale = tmp_path / f".a.safetensors.{_dead_pid()}.xyz.tmp"
    stale.write_bytes(b"half")
    live_child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = tmp_path / f".a.safetensors.{live_child.pid}.abc.tmp"
        live.write_bytes(b"in progress")
        other = tmp_path / f".b.safetensors.{_dead_pid()}.q.tmp"
        other.write_bytes(b"another target's")
        save_tensors(target, {"w": torch.zeros(2)}, {}, kind="k", format_version=1)
        assert not stale.exists(), "a dead writer's partial file must be removed"
        assert live.exists(), "a running writer's file must be left alone"
        assert other.exists(), "only the target's own partial files"
    finally:
        live_child.kill()
        live_child.wait()


def test_a_failed_write_leaves_no_tmp(tmp_path):
    def boom(tmp: str) -> None:
        Path(tmp).write_bytes(b"half")
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError):
        atomic_write(tmp_path / "x.bin", boom)
    assert list(tmp_path.iterdir()) == []


def test_killed_writer_leaves_a_tmp_that_the_next_write_removes(tmp_path):
    script = ("import os, sys, signal\nfrom pathlib import Path\nfrom controlgs_adapter.formats.safetensors import atomic_write\n"
              "def w(t):\n    Path(t).write_bytes(b'half')\n    os.kill(os.getpid(), signal.SIGKILL)\n"
              "atomic_write(sys.argv[1], w)\n")
    r = subprocess.run([sys.executable, "-c", script, str(tmp_path / "x.bin")], cwd=ROOT, timeout=120)
    assert r.returncode == -9
    assert len(list(tmp_path.glob(".x.bin.*.tmp"))) == 1
    atomic_write(tmp_path / "x.bin", lambda t: Path(t).write_bytes(b"whole"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.bin"]


def _raw(path, header: object | None, extra_meta: dict | None = None) -> None:
    meta = {} if header is None else {st.HEADER_KEY: header if isinstance(header, str) else json.dumps(header)}
    save_file({"t": torch.zeros(2)}, str(path), metadata={**meta, **(extra_meta or {})})


@pytest.mark.parametrize("header, words", [
    (None, "not written by controlgs-adapter"),
    ("{not json", "corrupt controlgs-adapter header: JSONDecodeError"),
    ([1, 2], "header must be a JSON object, got list"),
    ({"kind": "psf_bank", "format_version": 1}, "holds a 'psf_bank', expected a 'adapter'"),
    ({"format_version": 1}, "holds a None, expected a 'adapter'"),
    ({"kind": "adapter", "format_version": True}, "format_version must be an integer >= 1, got True"),
    ({"kind": "adapter", "format_version": 0}, "format_version must be an integer >= 1, got 0"),
    ({"kind": "adapter", "format_version": "1"}, "format_version must be an integer >= 1, got '1'"),
    ({"kind": "adapter", "format_version": 1.0}, "format_version must be an integer >= 1, got 1.0"),
    ({"kind": "adapter", "format_version": 3, "library_version": "9.9"},
     "format_version 3 is newer than this library reads (<= 2); written by controlgs-adapter 9.9"),
])
def test_read_header_refusals(tmp_path, header, words):
    _raw(tmp_path / "f.safetensors", header)
    with pytest.raises(FileFormatError, match="f.safetensors: ") as e:
        st.read_header(tmp_path / "f.safetensors", kind="adapter", max_version=2)
    assert words in str(e.value)


def test_read_header_accepts_versions_up_to_max_and_load_tensors_reads_data(tmp_path):
    for v in (1, 2):
        _raw(tmp_path / "f.safetensors", {"kind": "adapter", "format_version": v, "x": [1]})
        assert st.read_header(tmp_path / "f.safetensors", kind="adapter", max_version=2)["x"] == [1]
    tensors, header = st.load_tensors(tmp_path / "f.safetensors", kind="adapter", max_version=2)
    assert list(tensors) == ["t"] and tensors["t"].tolist() == [0.0, 0.0] and header["format_version"] == 2
    with pytest.raises(FileFormatError, match="nope.safetensors: no such file"):
        st.read_header(tmp_path / "nope.safetensors", kind="adapter", max_version=2)
    (tmp_path / "junk.safetensors").write_bytes(b"\x08\0\0\0\0\0\0\0{}")
    with pytest.raises(FileFormatError, match="junk.safetensors: not a readable safetensors file"):
        st.read_header(tmp_path / "junk.safetensors", kind="adapter", max_version=2)


def test_save_tensors_header_and_data_read_back_by_safetensors_itself(tmp_path):
    from safetensors import safe_open

    a = torch.arange(6.0).view(2, 3).t()  # non-contiguous
    st.save_tensors(tmp_path / "s.safetensors", {"a": a, "b": a[0]}, {"extra": 5}, kind="k1", format_version=4)
    with safe_open(str(tmp_path / "s.safetensors"), framework="pt") as f:
        meta = f.metadata()
        assert torch.equal(f.get_tensor("a"), a) and torch.equal(f.get_tensor("b"), a[0])
    h = json.loads(meta[st.HEADER_KEY])
    from controlgs_adapter._version import __version__
    assert h == {"kind": "k1", "format_version": 4, "library_version": __version__, "extra": 5}
    assert meta["format"] == "pt"
    assert oct((tmp_path / "s.safetensors").stat().st_mode & 0o777) == oct(st.file_mode())


def test_save_tensors_refusals_write_nothing(tmp_path):
    p = tmp_path / "s.safetensors"
    with pytest.raises(NonFiniteError, match=r"s.safetensors: refusing to save tensor 'w': it holds 2 NaN/Inf value\(s\)$"):
        st.save_tensors(p, {"w": torch.tensor([1.0, math.nan, math.inf])}, {}, kind="k", format_version=1)
    with pytest.raises(NonFiniteError, match="overflowed"):
        st.save_tensors(p, {"h": torch.tensor([1e6]).half()}, {}, kind="k", format_version=1)
    with pytest.raises(NonFiniteError, match="s.safetensors: refusing to save a header with a NaN/Inf number"):
        st.save_tensors(p, {}, {"x": math.nan}, kind="k", format_version=1)
    with pytest.raises(InputValueError, match="s.safetensors: tensor 'n' must be a torch.Tensor, got ndarray"):
        st.save_tensors(p, {"n": np.zeros(2)}, {}, kind="k", format_version=1)  # type: ignore[dict-item]
    assert list(tmp_path.iterdir()) == []
    st.save_tensors(p, {"i": torch.tensor([2**31 - 1], dtype=torch.int32)}, {}, kind="k", format_version=1)  # ints pass
    with pytest.raises(InputValueError, match="path must be a file path"):
        st.save_tensors("", {}, {}, kind="k", format_version=1)


def test_remove_stale_tmp_only_removes_dead_writers(tmp_path):
    target = tmp_path / "a.safetensors"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True).stdout.strip()
    stale = tmp_path / f".a.safetensors.{dead}.xyz.tmp"
    mine = tmp_path / f".a.safetensors.{os.getpid()}.abc.tmp"
    alive = tmp_path / f".a.safetensors.{os.getppid()}.def.tmp"
    other = tmp_path / f".b.safetensors.{dead}.xyz.tmp"
    odd = tmp_path / ".a.safetensors.notapid.tmp"
    for p in (stale, mine, alive, other, odd):
        p.write_bytes(b"x")
    assert st.remove_stale_tmp(target) == [stale]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in (mine, alive, other, odd))


def test_atomic_write_leaves_no_tmp_on_failure_and_refuses_folders(tmp_path):

    def fail(tmp: str) -> None:
        open(tmp, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(FileWriteError, match="x.bin: write failed: No space left on device"):
        st.atomic_write(tmp_path / "x.bin", fail)
    assert list(tmp_path.iterdir()) == []

    def boom(tmp: str) -> None:
        raise KeyError("k")

    with pytest.raises(KeyError):
        st.atomic_write(tmp_path / "x.bin", boom)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "d").mkdir()
    with pytest.raises(InputValueError, match="d: is a folder"):
        st.atomic_write(tmp_path / "d", fail)
    (tmp_path / "file").write_bytes(b"")
    with pytest.raises(FileWriteError, match="cannot write here"):
        st.atomic_write(tmp_path / "file" / "sub" / "x.bin", fail)
    out = st.atomic_write(str(tmp_path / "new" / "y.bin"), lambda tmp: open(tmp, "wb").write(b"ok"))
    assert out == tmp_path / "new" / "y.bin" and out.read_bytes() == b"ok"
    assert st.as_path(os.fsencode(str(out))) == out


# --------------------------------------------------------------------------- formats
def test_as_path_default_names_path():
    with pytest.raises(InputValueError, match=r"^path must be a file path \(str or os.PathLike\), got 5$"):
        as_path(5)
    with pytest.raises(InputValueError, match=r"^out must be a file path .*got ''$"):
        as_path("", "out")


@pytest.mark.parametrize("mask, file_bits, folder_bits", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700), (0o027, 0o640, 0o750)])
def test_modes_follow_the_umask(tmp_path, mask, file_bits, folder_bits):
    old = os.umask(mask)
    try:
        assert st.file_mode() == file_bits and st.folder_mode() == folder_bits
        out = st.atomic_write(tmp_path / "f.bin", lambda tmp: open(tmp, "wb").write(b"x"))
        assert out.stat().st_mode & 0o777 == file_bits
    finally:
        os.umask(old)


def test_pid_alive():
    import subprocess
    import sys

    assert st._pid_alive(os.getpid())
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                              check=True).stdout)
    assert not st._pid_alive(dead)


def test_load_tensors_unreadable_data_names_the_file(tmp_path):
    import torch

    p = st.save_tensors(tmp_path / "x.safetensors", {"a": torch.ones(2)}, {}, kind="k", format_version=1)
    with pytest.raises(FileFormatError, match=r"x\.safetensors: tensor data unreadable"):
        st.load_tensors(p, kind="k", max_version=1, device="nope")
    tensors, header = st.load_tensors(p, kind="k", max_version=1, device="cpu")
    assert torch.equal(tensors["a"], torch.ones(2)) and header["kind"] == "k"
