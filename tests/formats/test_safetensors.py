"""The library's safetensors files (``formats.safetensors``): the header (kind, format version), what
refuses to be saved, atomic writes that leave no partial file, the removal of a dead writer's partial
file, and file modes that follow the umask."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.scaffold_standin import ScaffoldStandIn
from safetensors import safe_open
from safetensors.torch import save_file

from controlgs_adapter._version import __version__
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import FileFormatError, FileWriteError, InputValueError, NonFiniteError
from controlgs_adapter.formats import safetensors as st

ROOT = Path(__file__).resolve().parents[2]


def _dead_pid() -> int:
    """The id of a process that has exited."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _raw(path, header: object | None) -> None:
    meta = {} if header is None else {st.HEADER_KEY: header if isinstance(header, str) else json.dumps(header)}
    save_file({"t": torch.zeros(2)}, str(path), metadata=meta)


# -------------------------------------------------------------------------------------------- header
def test_save_tensors_header_and_data_read_back_by_safetensors_itself(tmp_path):
    a = torch.arange(6.0).view(2, 3).t()  # non-contiguous
    st.save_tensors(tmp_path / "s.safetensors", {"a": a, "b": a[0]}, {"extra": 5}, kind="k1", format_version=4)
    with safe_open(str(tmp_path / "s.safetensors"), framework="pt") as f:
        meta = f.metadata()
        assert torch.equal(f.get_tensor("a"), a) and torch.equal(f.get_tensor("b"), a[0])
    h = json.loads(meta[st.HEADER_KEY])
    assert h == {"kind": "k1", "format_version": 4, "library_version": __version__, "extra": 5}
    assert meta["format"] == "pt"
    assert oct((tmp_path / "s.safetensors").stat().st_mode & 0o777) == oct(st.file_mode())


def test_read_header_accepts_versions_up_to_max_and_load_tensors_reads_data(tmp_path):
    for v in (1, 2):
        _raw(tmp_path / "f.safetensors", {"kind": "adapter", "format_version": v, "x": [1]})
        assert st.read_header(tmp_path / "f.safetensors", kind="adapter", max_version=2)["x"] == [1]
    tensors, header = st.load_tensors(tmp_path / "f.safetensors", kind="adapter", max_version=2)
    assert list(tensors) == ["t"] and tensors["t"].tolist() == [0.0, 0.0] and header["format_version"] == 2
    tensors, header = st.load_tensors(tmp_path / "f.safetensors", kind="adapter", max_version=2, device="cpu")
    assert tensors["t"].device == torch.device("cpu")


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
def test_read_header_refusals_name_the_file(tmp_path, header, words):
    _raw(tmp_path / "f.safetensors", header)
    with pytest.raises(FileFormatError, match="f.safetensors: ") as e:
        st.read_header(tmp_path / "f.safetensors", kind="adapter", max_version=2)
    assert words in str(e.value)


def test_missing_unreadable_or_undecodable_files_are_named(tmp_path):
    with pytest.raises(FileFormatError, match="nope.safetensors: no such file"):
        st.read_header(tmp_path / "nope.safetensors", kind="adapter", max_version=2)
    (tmp_path / "junk.safetensors").write_bytes(b"\x08\0\0\0\0\0\0\0{}")
    with pytest.raises(FileFormatError, match="junk.safetensors: not a readable safetensors file"):
        st.read_header(tmp_path / "junk.safetensors", kind="adapter", max_version=2)
    p = st.save_tensors(tmp_path / "x.safetensors", {"a": torch.ones(2)}, {}, kind="k", format_version=1)
    with pytest.raises(FileFormatError, match=r"x\.safetensors: tensor data unreadable"):
        st.load_tensors(p, kind="k", max_version=1, device="nope")


# ---------------------------------------------------------------------------------------- refusals
def test_save_tensors_refusals_name_the_file_and_write_nothing(tmp_path):
    p = tmp_path / "s.safetensors"
    with pytest.raises(NonFiniteError, match=r"s.safetensors: .*'w'.* 2 NaN/Inf"):
        st.save_tensors(p, {"w": torch.tensor([1.0, math.nan, math.inf])}, {}, kind="k", format_version=1)
    for big in (1e5, 1e6):  # beyond float16's 65504: overflowed to inf
        with pytest.raises(NonFiniteError, match=r"s.safetensors: .*'h'.*float16.*65504 overflowed"):
            st.save_tensors(p, {"h": torch.tensor([big]).half()}, {}, kind="k", format_version=1)
    with pytest.raises(NonFiniteError, match="s.safetensors: .*header with a NaN/Inf"):
        st.save_tensors(p, {}, {"x": math.nan}, kind="k", format_version=1)
    for bad in (np.zeros(2), [1.0, 2.0]):
        with pytest.raises(InputValueError, match=rf"s.safetensors: tensor 'n' must be a torch.Tensor, got {type(bad).__name__}"):
            st.save_tensors(p, {"n": bad}, {}, kind="k", format_version=1)  # type: ignore[dict-item]
    assert list(tmp_path.iterdir()) == []
    st.save_tensors(p, {"i": torch.tensor([2**31 - 1], dtype=torch.int32)}, {}, kind="k", format_version=1)  # ints pass
    assert p.is_file()


@pytest.mark.parametrize("path", [None, 3.5, "", 5], ids=["None", "float", "empty", "int"])
def test_a_path_that_is_not_a_file_path_is_refused_naming_the_argument(path):
    for call in (lambda: st.save_tensors(path, {}, {}, kind="k", format_version=1),
                 lambda: st.read_header(path, kind="k", max_version=1), lambda: st.as_path(path)):
        with pytest.raises(InputValueError, match=rf"^path must be a file path .*got {path!r}$"):
            call()
    with pytest.raises(InputValueError, match=rf"^out must be a file path .*got {path!r}$"):
        st.as_path(path, "out")


# ---------------------------------------------------------------------------------- atomic writes
def test_atomic_write_leaves_no_partial_file_on_failure_and_refuses_folders(tmp_path):
    def full_disk(tmp: str) -> None:
        open(tmp, "wb").write(b"half")
        raise OSError(28, "No space left on device")

    with pytest.raises(FileWriteError, match="x.bin: write failed: No space left on device"):
        st.atomic_write(tmp_path / "x.bin", full_disk)
    assert list(tmp_path.iterdir()) == []
    for error in (RuntimeError("killed"), KeyError("k")):  # any other error passes through, cleaned up after

        def fail(tmp: str, error=error) -> None:
            Path(tmp).write_bytes(b"half")
            raise error

        with pytest.raises(type(error)):
            st.atomic_write(tmp_path / "x.bin", fail)
        assert list(tmp_path.iterdir()) == []
    (tmp_path / "d").mkdir()
    with pytest.raises(InputValueError, match=f"{tmp_path / 'd'}: is a folder"):
        st.atomic_write(tmp_path / "d", full_disk)
    (tmp_path / "file").write_bytes(b"")
    with pytest.raises(FileWriteError, match="cannot write here"):
        st.atomic_write(tmp_path / "file" / "sub" / "x.bin", full_disk)
    out = st.atomic_write(str(tmp_path / "new" / "y.bin"), lambda tmp: open(tmp, "wb").write(b"ok"))
    assert out == tmp_path / "new" / "y.bin" and out.read_bytes() == b"ok"
    assert st.as_path(os.fsencode(str(out))) == out


def test_partial_files_of_dead_writers_are_removed_by_the_next_write(tmp_path):
    """A partial file ``.<name>.<pid>.<tag>.tmp`` of a writer that has exited is removed before the next
    write of the same target; those of running writers (this one, its parent, a live child), of another
    target, or not named by a pid are left alone."""
    dead = _dead_pid()
    assert st._pid_alive(os.getpid()) and not st._pid_alive(dead)
    target = tmp_path / "a.safetensors"
    stale = tmp_path / f".a.safetensors.{dead}.xyz.tmp"
    mine = tmp_path / f".a.safetensors.{os.getpid()}.abc.tmp"
    parent = tmp_path / f".a.safetensors.{os.getppid()}.def.tmp"
    other = tmp_path / f".b.safetensors.{dead}.xyz.tmp"
    odd = tmp_path / ".a.safetensors.notapid.tmp"
    for p in (stale, mine, parent, other, odd):
        p.write_bytes(b"x")
    assert st.remove_stale_tmp(target) == [stale]
    stale.write_bytes(b"half")
    live_child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        live = tmp_path / f".a.safetensors.{live_child.pid}.abc.tmp"
        live.write_bytes(b"in progress")
        st.save_tensors(target, {"w": torch.zeros(2)}, {}, kind="k", format_version=1)
        assert not stale.exists() and live.exists()
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in (target, mine, parent, other, odd, live))
    finally:
        live_child.kill()
        live_child.wait()


def test_a_killed_writer_leaves_a_partial_file_that_the_next_write_removes(tmp_path):
    script = ("import os, sys, signal\nfrom pathlib import Path\nfrom controlgs_adapter.formats.safetensors import atomic_write\n"
              "def w(t):\n    Path(t).write_bytes(b'half')\n    os.kill(os.getpid(), signal.SIGKILL)\n"
              "atomic_write(sys.argv[1], w)\n")
    r = subprocess.run([sys.executable, "-c", script, str(tmp_path / "x.bin")], cwd=ROOT, timeout=120)
    assert r.returncode == -signal.SIGKILL
    assert len(list(tmp_path.glob(".x.bin.*.tmp"))) == 1
    st.atomic_write(tmp_path / "x.bin", lambda t: Path(t).write_bytes(b"whole"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.bin"]


# ------------------------------------------------------------------------------------------ modes
@pytest.mark.parametrize("mask, file_bits, folder_bits", [(0o022, 0o644, 0o755), (0o077, 0o600, 0o700), (0o027, 0o640, 0o750)])
def test_modes_follow_the_umask(tmp_path, mask, file_bits, folder_bits):
    """Written files and the folders made for them get the modes a plain ``open`` / ``mkdir`` would under
    the umask, an adapter file included."""
    old = os.umask(mask)
    cgs = ControlGS.wrap(ScaffoldStandIn(30, seed=0))
    try:
        assert st.file_mode() == file_bits and st.folder_mode() == folder_bits
        out = st.atomic_write(tmp_path / "new" / "f.bin", lambda tmp: open(tmp, "wb").write(b"x"))
        assert out.stat().st_mode & 0o777 == file_bits
        assert (tmp_path / "new").stat().st_mode & 0o777 == folder_bits
        adapter = cgs.save(tmp_path / "sub" / "a.safetensors")
        assert adapter.stat().st_mode & 0o777 == file_bits
        assert (tmp_path / "sub").stat().st_mode & 0o777 == folder_bits
    finally:
        cgs.unwrap()
        os.umask(old)
