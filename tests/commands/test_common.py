"""The pieces the commands share for run folders: ``read_run`` (every run.json field checked, naming
the file and the field), ``apply_run_defaults`` (a run's renderer only with the user's say),
``parse_device`` (a device that can hold data) and ``check_out_path`` (creates nothing)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import pytest

from controlgs_adapter.commands.common import apply_run_defaults, check_out_path, parse_device, read_run
from controlgs_adapter.errors import ControlGSError, FileWriteError, InputValueError

#: every field ``controlgs train`` writes for a user's scene, each with a valid value
FULL = {"model": "/m", "data": "/d", "family": "scaffold_gs", "model_iteration": 30000, "allow_unquantized": False,
        "format": "colmap", "images": "images_4", "holdout": 8, "white_background": False, "resolution": 256,
        "effects": ["display", "lens"], "iterations": 1000, "seed": 0, "seeds": 2, "adapters": ["controlgs", "no_lens"],
        "rasterizer": "auto", "renderer": "/r/mine.py:render",
        "distributed": {"processes": 1, "backend": None, "exchange": "sparse"}}


def _write(folder: Path, record: Any) -> Path:
    (folder / "run.json").write_text(json.dumps(record))
    return folder / "run.json"


def test_read_run_takes_a_full_record_and_nothing(tmp_path: Path) -> None:
    assert read_run(tmp_path) is None
    _write(tmp_path, FULL)
    assert read_run(tmp_path) == FULL
    _write(tmp_path, {k: None for k in FULL} | {"future_field": [1, {"x": 2}]})  # nulls and unknown fields pass
    assert read_run(tmp_path) is not None


@pytest.mark.parametrize("field, value", [
    ("model", ""), ("model", "a\0b"), ("data", ["d"]), ("family", "gsplat"), ("model_iteration", -1),
    ("allow_unquantized", 1), ("format", 3), ("images", {}), ("holdout", 2.5), ("white_background", "false"),
    ("resolution", True), ("effects", []), ("effects", "display"), ("effects", ["display", 1]), ("iterations", -5),
    ("seed", 2**63), ("seeds", 0), ("adapters", "controlgs"), ("rasterizer", 0), ("renderer", ["x.py:r"]),
    ("distributed", {"processes": [1]}), ("variant", "xr"),
])
def test_each_field_is_checked_naming_file_and_field(tmp_path: Path, field: str, value: Any) -> None:
    path = _write(tmp_path, {**FULL, field: value})
    with pytest.raises(InputValueError) as e:
        read_run(tmp_path)
    assert str(e.value).startswith(f"{path}: field {field!r} must be ") and "got " in str(e.value)


def test_a_run_file_that_is_not_a_json_object(tmp_path: Path) -> None:
    for text in ("[]", "5", "null", "\"x\"", "{", "\xff", "[" * 50_000 + "]" * 50_000):
        (tmp_path / "run.json").write_bytes(text.encode("utf-8", "surrogateescape") if text != "\xff" else b"\xff")
        with pytest.raises(InputValueError, match=f"{tmp_path / 'run.json'}: not a controlgs run file"):
            read_run(tmp_path)
    (tmp_path / "run.json").unlink()
    (tmp_path / "run.json").mkdir()
    with pytest.raises(InputValueError, match="not a file"):
        read_run(tmp_path)


def _ns(**kw: Any) -> argparse.Namespace:
    base: dict[str, Any] = {"model": None, "data": None, "renderer": None, "rasterizer": None, "resolution": None}
    return argparse.Namespace(**(base | kw))


def test_a_run_renderer_needs_the_users_say(tmp_path: Path) -> None:
    spec = "/elsewhere/evil.py:renderer"
    _write(tmp_path, {"model": "/m", "data": "/d", "renderer": spec})
    args = _ns()
    with pytest.raises(InputValueError) as e:
        apply_run_defaults(args, tmp_path)
    assert f"--renderer {spec}" in str(e.value) and "--trust-run-renderer" in str(e.value)
    assert args.renderer is None
    args = _ns(renderer="mine:render")  # named on the command line: the user's, not the run's
    assert apply_run_defaults(args, tmp_path) is not None and args.renderer == "mine:render"
    args = _ns(trust_run_renderer=True)
    assert apply_run_defaults(args, tmp_path) is not None
    assert (args.renderer, args.model, args.data) == (spec, "/m", "/d")


@pytest.mark.parametrize("name", ["meta", "cuda:99", "nodevice", "xla"])
def test_a_device_that_cannot_hold_data(name: str) -> None:
    with pytest.raises(InputValueError, match=f"^--device '?{name}'?: "):
        parse_device(name)


def test_parse_device_cpu() -> None:
    assert str(parse_device("cpu")) == "cpu"


def test_check_out_path_creates_nothing(tmp_path: Path) -> None:
    deep = tmp_path / "a" / "b" / "c"
    assert check_out_path(deep, "--out", folder=True) == deep
    assert check_out_path(deep / "f.json", "--out", folder=False) == deep / "f.json"
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "file").write_text("")
    with pytest.raises(InputValueError, match=f"^--out {tmp_path / 'file'}: is a file"):
        check_out_path(tmp_path / "file", "--out", folder=True)
    with pytest.raises(InputValueError, match=f"^--bank {tmp_path}: is a folder"):
        check_out_path(tmp_path, "--bank", folder=False)
    with pytest.raises(ControlGSError, match=f"^--out {tmp_path / 'file' / 'x' / 'y'}: {tmp_path / 'file'} is a file"):
        check_out_path(tmp_path / "file" / "x" / "y", "--out", folder=True)


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write anywhere")
def test_check_out_path_refuses_a_read_only_folder(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        with pytest.raises(FileWriteError, match=f"^--out {locked / 'run'}: cannot write into {locked}"):
            check_out_path(locked / "run", "--out", folder=True)
    finally:
        locked.chmod(0o700)
