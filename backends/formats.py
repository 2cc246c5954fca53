"""Readers and writers for the on-disk formats of the neural-Gaussian codebases: binary PLY point
clouds, ``cfg_args`` (a printed ``argparse.Namespace``), ``torch.save`` state dicts and TorchScript
MLPs. Nothing here unpickles arbitrary objects and nothing evaluates code; every error names the
file and the field.
"""

from __future__ import annotations

import ast
import os
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import torch

from controlgs_adapter.errors import FileFormatError

__all__ = ["read_ply", "write_ply", "parse_cfg_args", "read_cfg_args", "load_state_dict_file", "load_torchscript",
           "require_fields"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


def read_ply(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read the ``vertex`` element of a PLY file (binary little/big endian or ASCII).

    Returns ``(fields, comments)``: one ``[V]`` array per property, in file order, and the header's
    ``comment``/``obj_info`` lines (without the keyword). Elements after ``vertex`` are ignored.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise FileFormatError(f"{path}: not a PLY file (first line is not 'ply')")
        fmt, count, props, comments, in_vertex, seen_vertex = None, None, [], [], False, False
        while True:
            line = f.readline()
            if not line:
                raise FileFormatError(f"{path}: PLY header ends before 'end_header' (truncated file)")
            words = line.decode("ascii", "replace").strip().split()
            if not words:
                continue
            if words[0] == "end_header":
                break
            if words[0] == "format":
                fmt = words[1]
            elif words[0] in ("comment", "obj_info"):
                comments.append(" ".join(words[1:]))
            elif words[0] == "element":
                in_vertex = words[1] == "vertex"
                if in_vertex:
                    count, seen_vertex = int(words[2]), True
                elif not seen_vertex:
                    raise FileFormatError(f"{path}: element {words[1]!r} precedes 'vertex'; only vertex-first files are read")
            elif words[0] == "property" and in_vertex:
                if words[1] == "list":
                    raise FileFormatError(f"{path}: list property {words[-1]!r} in 'vertex' is not supported")
                if words[1] not in _PLY_TYPES:
                    raise FileFormatError(f"{path}: property {words[2]!r} has unknown type {words[1]!r}")
                props.append((words[2], _PLY_TYPES[words[1]]))
        if count is None:
            raise FileFormatError(f"{path}: no 'vertex' element in the PLY header")
        if fmt == "ascii":
            rows = [f.readline().split() for _ in range(count)]
            if len(rows) < count or any(len(r) < len(props) for r in rows):
                raise FileFormatError(f"{path}: truncated ASCII PLY: expected {count} vertices of {len(props)} values")
            table = np.asarray(rows, dtype=np.float64).reshape(count, len(props)) if count else np.zeros((0, len(props)))
            return {n: table[:, i].astype(t) for i, (n, t) in enumerate(props)}, comments
        if fmt not in ("binary_little_endian", "binary_big_endian"):
            raise FileFormatError(f"{path}: unsupported PLY format {fmt!r}")
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        data = f.read(count * dtype.itemsize)
    if len(data) < count * dtype.itemsize:
        raise FileFormatError(
            f"{path}: truncated PLY: header declares {count} vertices x {dtype.itemsize} bytes, "
            f"file holds {len(data)} bytes of vertex data"
        )
    arr = np.frombuffer(data, dtype=dtype, count=count)
    return {n: np.ascontiguousarray(arr[n]).astype(dtype[n].newbyteorder("=")) for n in arr.dtype.names}, comments


def write_ply(path: str | os.PathLike, fields: Mapping[str, np.ndarray], comments: Iterable[str] = (),
              *, comment_keyword: str = "comment") -> Path:
    """Write ``fields`` (name -> ``[V]`` array, all the same length) as a binary little-endian PLY
    ``vertex`` element, atomically. Float arrays are stored as float32 unless already float64."""
    from controlgs_adapter.io import atomic_write

    names = list(fields)
    cols = [np.asarray(fields[n]) for n in names]
    if not cols or len({c.shape for c in cols}) != 1 or cols[0].ndim != 1:
        raise FileFormatError(f"write_ply: fields must be 1-D arrays of one length, got { {n: c.shape for n, c in zip(names, cols)} }")
    inverse = {v: k for k, v in _PLY_TYPES.items() if k in ("char", "uchar", "short", "ushort", "int", "uint", "float", "double")}
    dtype = np.dtype([(n, "<" + ("f4" if c.dtype.kind == "f" and c.dtype != np.float64 else c.dtype.str[1:])) for n, c in zip(names, cols)])
    arr = np.empty(cols[0].shape[0], dtype=dtype)
    for n, c in zip(names, cols):
        arr[n] = c
    header = ["ply", "format binary_little_endian 1.0", *(f"{comment_keyword} {c}" for c in comments),
              f"element vertex {arr.shape[0]}", *(f"property {inverse[dtype[n].str[1:]]} {n}" for n in names), "end_header"]

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(("\n".join(header) + "\n").encode("ascii"))
            f.write(arr.tobytes())

    return atomic_write(path, write)


def parse_cfg_args(text: str, *, source: str = "cfg_args") -> dict[str, Any]:
    """Parse a printed ``Namespace(a=1, b='x', ...)`` without evaluating code. Values that are not
    Python literals are kept as their source text."""
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except SyntaxError as e:
        raise FileFormatError(f"{source}: not a printed argparse Namespace: {e}") from e
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "Namespace"):
        raise FileFormatError(f"{source}: expected 'Namespace(...)', got {text.strip()[:60]!r}")
    out: dict[str, Any] = {}
    for kw in node.keywords:
        if kw.arg is None:
            continue
        try:
            out[kw.arg] = ast.literal_eval(kw.value)
        except ValueError:
            out[kw.arg] = ast.unparse(kw.value)
    return out


def read_cfg_args(path: str | os.PathLike) -> dict[str, Any]:
    """Read and parse a ``cfg_args`` file."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    return parse_cfg_args(path.read_text(errors="replace"), source=str(path))


def load_state_dict_file(path: str | os.PathLike) -> dict[str, Any]:
    """``torch.load`` with ``weights_only=True`` on CPU: tensors, dicts, lists and numbers only."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for bad/untrusted archives
        raise FileFormatError(
            f"{path}: cannot be read as a weights-only torch file (truncated, TorchScript, or holds pickled "
            f"objects that are not loaded for safety): {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
        ) from e
    if not isinstance(obj, dict):
        raise FileFormatError(f"{path}: expected a dict of state dicts, got {type(obj).__name__}")
    return obj


def load_torchscript(path: str | os.PathLike) -> torch.jit.ScriptModule:
    """Load a TorchScript archive on CPU (no pickle of arbitrary objects)."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    try:
        with warnings.catch_warnings():  # the families' on-disk format is TorchScript: not our choice to deprecate
            warnings.filterwarnings("ignore", message=r"`torch.jit.load` is deprecated", category=DeprecationWarning)
            return torch.jit.load(str(path), map_location="cpu")
    except Exception as e:  # noqa: BLE001
        raise FileFormatError(f"{path}: not a loadable TorchScript archive (truncated?): {type(e).__name__}") from e


def require_fields(fields: Mapping[str, np.ndarray], names: Iterable[str], *, source: str) -> None:
    """Raise naming the file and every missing PLY property."""
    missing = [n for n in names if n not in fields]
    if missing:
        raise FileFormatError(f"{source}: missing PLY field(s) {missing}")
