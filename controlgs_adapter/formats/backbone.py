"""Readers and writers for the on-disk formats of the neural-Gaussian codebases: binary PLY point
clouds, ``cfg_args`` (a printed ``argparse.Namespace``), ``torch.save`` state dicts and TorchScript
MLPs. Nothing here unpickles arbitrary objects and nothing evaluates code; every error names the
file and the field.
"""

from __future__ import annotations

import ast
import math
import os
import re
import warnings
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np
import torch

from controlgs_adapter.errors import FileFormatError, TargetError
from controlgs_adapter.formats.safetensors import atomic_write
from controlgs_adapter.formats.torchscript import eager_from_archive, eager_from_script, tensors_from_archive

__all__ = ["read_ply", "ply_field_names", "write_ply", "parse_cfg_args", "read_cfg_args", "load_state_dict_file", "load_torchscript",
           "load_torchscript_tensors", "require_fields",
           "ply_columns", "ply_offsets", "ply_xyz", "read_yaml_scalars", "CFG_KEYS", "cfg_value",
           "check_finite_weights"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}


_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_PLY_MAX_HEADER = 1 << 20  # bytes; real headers are a few hundred


def _ply_header(f: Any, path: Path) -> tuple[str, int, list[tuple[str, str]], list[str]]:
    """Parse a PLY header up to ``end_header``: ``(format, vertex count, vertex properties, comments)``.
    Every malformed line raises :class:`FileFormatError` naming the file and the line number."""
    if f.readline(16).strip() != b"ply":
        raise FileFormatError(f"{path}: not a PLY file (first line is not 'ply')")
    fmt: str | None = None
    count: int | None = None
    props: list[tuple[str, str]] = []
    comments: list[str] = []
    in_vertex = seen_vertex = False
    lineno = 1
    while True:
        line = f.readline(_PLY_MAX_HEADER)
        lineno += 1
        if not line:
            raise FileFormatError(f"{path}: PLY header ends before 'end_header' (truncated file, {lineno - 1} lines)")
        if f.tell() > _PLY_MAX_HEADER:
            raise FileFormatError(f"{path}: PLY header longer than {_PLY_MAX_HEADER} bytes without 'end_header'")
        words = line.decode("ascii", "replace").strip().split()
        where = f"{path}: PLY header line {lineno} {' '.join(words)[:80]!r}"
        if not words:
            continue
        key = words[0]
        if key == "end_header":
            break
        if key in ("comment", "obj_info"):
            comments.append(" ".join(words[1:]))
        elif key == "format":
            if len(words) != 3 or words[1] not in _PLY_FORMATS:
                raise FileFormatError(f"{where}: expected 'format <{'|'.join(_PLY_FORMATS)}> 1.0'")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise FileFormatError(f"{where}: expected 'element <name> <count>' with a non-negative integer count")
            in_vertex = words[1] == "vertex"
            if in_vertex:
                if seen_vertex:
                    raise FileFormatError(f"{where}: a second 'vertex' element")
                count, seen_vertex = int(words[2]), True
            elif not seen_vertex:
                raise FileFormatError(f"{where}: element {words[1]!r} precedes 'vertex'; only vertex-first files are read")
        elif key == "property":
            if not seen_vertex:
                raise FileFormatError(f"{where}: 'property' before any 'element vertex' line")
            if len(words) >= 2 and words[1] == "list":
                if in_vertex:
                    raise FileFormatError(f"{where}: list property {words[-1]!r} in 'vertex' is not supported")
                continue
            if len(words) != 3:
                raise FileFormatError(f"{where}: expected 'property <type> <name>'")
            if words[1] not in _PLY_TYPES:
                raise FileFormatError(f"{where}: property {words[2]!r} has unknown type {words[1]!r} "
                                      f"(known: {', '.join(_PLY_TYPES)})")
            if in_vertex:
                if any(n == words[2] for n, _ in props):
                    raise FileFormatError(f"{where}: property {words[2]!r} declared twice")
                props.append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise FileFormatError(f"{where}: unknown header keyword {key!r}")
    if fmt is None:
        raise FileFormatError(f"{path}: no 'format' line in the PLY header")
    if count is None:
        raise FileFormatError(f"{path}: no 'vertex' element in the PLY header")
    if not props and count:
        raise FileFormatError(f"{path}: the 'vertex' element declares {count} vertices but no properties")
    return fmt, count, props, comments


def ply_field_names(path: str | os.PathLike) -> list[str]:
    """Vertex property names from a PLY header (the data is not read)."""
    with open(path, "rb") as f:
        _, _, props, _ = _ply_header(f, Path(path))
    return [name for name, _ in props]


def read_ply(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """Read the ``vertex`` element of a PLY file (binary little/big endian or ASCII).

    Returns ``(fields, comments)``: one ``[V]`` array per property, in file order, and the header's
    ``comment``/``obj_info`` lines (without the keyword). Elements after ``vertex`` are ignored.
    The declared vertex count is checked against the file's size before anything is read, so a
    small file cannot make this allocate or loop for long.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    size = path.stat().st_size
    with open(path, "rb") as f:
        fmt, count, props, comments = _ply_header(f, path)
        remaining = size - f.tell()
        if fmt == "ascii":
            # each vertex needs len(props) numbers of >= 1 character, separated by one byte
            if count * (2 * len(props) - 1) > remaining:
                raise FileFormatError(
                    f"{path}: header declares {count} vertices of {len(props)} values, but only {remaining} bytes "
                    "follow the header (truncated file or a wrong count)")
            rows = []
            for i in range(count):
                words = f.readline().split()
                if len(words) < len(props):
                    raise FileFormatError(f"{path}: truncated ASCII PLY: vertex {i} has {len(words)} of {len(props)} "
                                          f"values (expected {count} vertices)")
                rows.append(words[:len(props)])
            try:
                table = np.asarray(rows, dtype=np.float64).reshape(count, len(props))
            except ValueError as e:
                raise FileFormatError(f"{path}: ASCII PLY vertex data holds a value that is not a number: {e}") from e
            return {n: table[:, i].astype(t) for i, (n, t) in enumerate(props)}, comments
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        need = count * dtype.itemsize
        if need > remaining:
            raise FileFormatError(
                f"{path}: truncated PLY: header declares {count} vertices x {dtype.itemsize} bytes = {need} bytes, "
                f"file holds {remaining} bytes of vertex data")
        data = f.read(need)
    arr = np.frombuffer(data, dtype=dtype, count=count)
    return {n: np.ascontiguousarray(arr[n]).astype(dtype[n].newbyteorder("=")) for n, _ in props}, comments


def write_ply(path: str | os.PathLike, fields: Mapping[str, np.ndarray], comments: Iterable[str] = (),
              *, comment_keyword: str = "comment") -> Path:
    """Write ``fields`` (name -> ``[V]`` array, all the same length) as a binary little-endian PLY
    ``vertex`` element, atomically. Float arrays are stored as float32 unless already float64."""
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


CFG_MAX_BYTES = 1 << 20  # a real cfg_args is a few kB
CFG_MAX_DEPTH = 32  # nesting of a value (lists of lists ...)
CFG_MAX_NODES = 100_000
_CFG_FLOATS = {"inf": math.inf, "-inf": -math.inf, "nan": math.nan}  # how repr() prints these floats


#: the ``cfg_args`` keys the loaders read: their type and smallest value (checked when the file is parsed)
CFG_KEYS: dict[str, tuple[type, float | None]] = {
    "feat_dim": (int, 1), "n_offsets": (int, 1), "appearance_dim": (int, 0), "fork": (int, 1),
    "voxel_size": (float, None), "use_feat_bank": (bool, None), "add_opacity_dist": (bool, None),
    "add_cov_dist": (bool, None), "add_color_dist": (bool, None), "add_level": (bool, None), "dist2level": (str, None),
}
_BOOL_WORDS = {"true": True, "false": False, "1": True, "0": False}


def cfg_value(value: Any, kind: type, *, key: str, source: str, low: float | None = None) -> Any:
    """``value`` of configuration ``key`` as ``kind``: ``int`` a whole number (``32``, ``32.0``,
    ``'32'``), ``float`` a finite number, ``bool`` ``True``/``False`` (or 0/1, ``'true'``/``'false'``),
    ``str`` a string; at least ``low`` where given.

    Raises:
        FileFormatError: naming ``source`` and ``key`` (e.g. ``voxel_size='abc'``).
    """
    def refuse(what: str) -> FileFormatError:
        return FileFormatError(f"{source}: {key}={value!r} must be {what}")

    if kind is bool:
        if isinstance(value, bool):
            return value
        word = str(value).strip().lower() if isinstance(value, (int, str)) else None
        if word not in _BOOL_WORDS:
            raise refuse("True or False")
        return _BOOL_WORDS[word]
    if kind is str:
        if not isinstance(value, str):
            raise refuse("a string")
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise refuse("a number")
    try:
        number = float(value)
    except ValueError:
        raise refuse("a number") from None
    if not math.isfinite(number):
        raise refuse("a finite number")
    if kind is int:
        if not number.is_integer():
            raise refuse("a whole number")
        number = int(number)
    if low is not None and number < low:
        raise refuse(f"at least {low:g}")
    return number


def _check_cfg_tree(node: ast.AST, source: str) -> None:
    """Refuse a parse tree deeper than :data:`CFG_MAX_DEPTH` or larger than :data:`CFG_MAX_NODES`
    (iteratively: no recursion on hostile input)."""
    stack, seen = [(node, 0)], 0
    while stack:
        n, depth = stack.pop()
        seen += 1
        if depth > CFG_MAX_DEPTH + 2 or seen > CFG_MAX_NODES:
            raise FileFormatError(f"{source}: nested deeper than {CFG_MAX_DEPTH} levels or longer than "
                                  f"{CFG_MAX_NODES} terms; not a printed argparse Namespace")
        stack.extend((c, depth + 1) for c in ast.iter_child_nodes(n))


def parse_cfg_args(text: str, *, source: str = "cfg_args") -> dict[str, Any]:
    """Parse a printed ``Namespace(a=1, b='x', ...)`` without evaluating code.

    Values must be Python literals (``inf``/``nan`` as ``repr`` prints them included); anything
    else, text over :data:`CFG_MAX_BYTES`, or nesting deeper than :data:`CFG_MAX_DEPTH` raises
    :class:`FileFormatError` naming ``source`` (and the key). The keys the loaders read
    (:data:`CFG_KEYS`) come back as their type (:func:`cfg_value`), or the same error names the key."""
    if len(text) > CFG_MAX_BYTES:
        raise FileFormatError(f"{source}: {len(text)} characters, more than a cfg_args holds (<= {CFG_MAX_BYTES})")
    try:
        node = ast.parse(text.strip(), mode="eval").body
    except (SyntaxError, ValueError, RecursionError, MemoryError) as e:
        raise FileFormatError(f"{source}: not a printed argparse Namespace: {type(e).__name__}: {e}") from None
    _check_cfg_tree(node, source)
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "Namespace"):
        raise FileFormatError(f"{source}: expected 'Namespace(...)', got {text.strip()[:60]!r}")
    if node.args:
        raise FileFormatError(f"{source}: 'Namespace(...)' has positional arguments; expected only key=value pairs")
    out: dict[str, Any] = {}
    for kw in node.keywords:
        if kw.arg is None:
            raise FileFormatError(f"{source}: '**' in 'Namespace(...)'; expected only key=value pairs")
        code = ast.unparse(kw.value)
        if code in _CFG_FLOATS:
            out[kw.arg] = _CFG_FLOATS[code]
            continue
        try:
            out[kw.arg] = ast.literal_eval(kw.value)
        except (ValueError, TypeError, SyntaxError, RecursionError, MemoryError):
            raise FileFormatError(f"{source}: value of {kw.arg!r} must be a Python literal (number, string, bool, "
                                  f"None, list, tuple, dict), got {code[:60]!r}") from None
    for key, (kind, low) in CFG_KEYS.items():
        if key in out:
            out[key] = cfg_value(out[key], kind, key=key, source=source, low=low)
    return out


def read_cfg_args(path: str | os.PathLike) -> dict[str, Any]:
    """Read and parse a ``cfg_args`` file (at most :data:`CFG_MAX_BYTES`)."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    if path.stat().st_size > CFG_MAX_BYTES:
        raise FileFormatError(f"{path}: {path.stat().st_size} bytes, more than a cfg_args holds (<= {CFG_MAX_BYTES})")
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


def check_finite_weights(tensors: Mapping[str, Any], *, source: str, prefix: str = "") -> None:
    """Refuse NaN/Inf in the floating-point tensors of ``tensors`` (a state dict, nested dicts and
    lists walked): :class:`FileFormatError` naming ``source`` and the first such tensor
    (``prefix`` + its key, e.g. ``'opacity_mlp.0.weight'``)."""
    stack: list[tuple[str, Any]] = [(prefix.rstrip("."), tensors)]
    while stack:
        name, value = stack.pop(0)
        if isinstance(value, torch.Tensor):
            if (value.is_floating_point() or value.is_complex()) and not bool(torch.isfinite(value).all()):
                bad = int((~torch.isfinite(value)).sum())
                raise FileFormatError(f"{source}: tensor {name!r} holds {bad} NaN/Inf value(s) of {value.numel()}")
        elif isinstance(value, Mapping):
            stack.extend((f"{name}.{k}" if name else str(k), v) for k, v in value.items())
        elif isinstance(value, (list, tuple)):
            stack.extend((f"{name}.{i}" if name else str(i), v) for i, v in enumerate(value))


def load_torchscript(path: str | os.PathLike, *, trust_code: bool = False) -> torch.nn.Module:
    """A TorchScript decoder file (``opacity_mlp.pt``, ...) as an eager module on CPU.

    By default the archive is read as data and nothing in it runs
    (:func:`controlgs_adapter.formats.torchscript.eager_from_archive`): it must be a traced or scripted
    ``nn.Sequential`` of the supported layers, else it is refused with a FileFormatError naming the
    file and what was found. ``trust_code=True`` is an explicit opt-in for archives you trust
    outside that subset: ``torch.jit.load`` (which can run code stored in the archive) and a rebuild
    checked by running the module on a probe batch.
    """
    path = Path(path)
    if not trust_code:
        return eager_from_archive(path)
    script = _jit_load_trusted(path)
    try:
        return eager_from_script(script, name=str(path))
    except TargetError as e:
        raise FileFormatError(f"{path}: TorchScript decoder cannot be rebuilt as an eager module: {e}") from e


def load_torchscript_tensors(path: str | os.PathLike, *, trust_code: bool = False) -> dict[str, torch.Tensor]:
    """The tensors of a TorchScript archive (e.g. ``embedding_appearance.pt``) by state-dict name, on CPU.

    By default read as data, nothing in the archive runs
    (:func:`controlgs_adapter.formats.torchscript.tensors_from_archive`); ``trust_code=True`` uses
    ``torch.jit.load`` (which can run code stored in the archive).
    """
    if not trust_code:
        return tensors_from_archive(path)
    # state_dict() (keep_vars=False) already gives detached tensors; the clone owns its storage
    return {k: v.clone() for k, v in _jit_load_trusted(Path(path)).state_dict().items()}


def _jit_load_trusted(path: Path) -> torch.jit.ScriptModule:
    """``torch.jit.load`` on CPU: only for archives the caller trusts (``trust_code=True``)."""
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


_YAML_SCALAR = re.compile(r"^\s*([A-Za-z_]\w*)\s*:\s*([^{}\[\]]*?)\s*,?\s*$")


def _yaml_value(text: str) -> object:
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("null", "none", "~"):
        return None
    for cast in (int, float):
        try:
            return cast(text)  # int("40_000") works as in YAML 1.1
        except ValueError:
            pass
    return text


YAML_MAX_BYTES = 1 << 20


def read_yaml_scalars(path: str | Path) -> dict[str, list[object]]:
    """The ``key: scalar`` entries of a YAML file, block or flow style (Octree-AnyGS's
    ``config.yaml``), without a YAML dependency: ``{key: [value, ...]}`` in file order (a key may
    occur in several sections). Nested structure, lists and multi-line scalars are not read."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    if path.stat().st_size > YAML_MAX_BYTES:
        raise FileFormatError(f"{path}: {path.stat().st_size} bytes, more than a config file holds (<= {YAML_MAX_BYTES})")
    out: dict[str, list[object]] = {}
    for line in path.read_text(errors="replace").splitlines():
        line = line.split(" #", 1)[0] if not line.lstrip().startswith("#") else ""
        m = _YAML_SCALAR.match(line)
        if m and m.group(2):
            out.setdefault(m.group(1), []).append(_yaml_value(m.group(2)))
    return out


def ply_columns(fields: Mapping[str, np.ndarray], prefix: str, *, source: str, count: int | None = None) -> np.ndarray:
    """Stack ``<prefix>0 .. <prefix>{n-1}`` into ``[V, n]`` float32: n = ``count``, or every
    ``<prefix><i>`` column present, which must then be numbered 0..n-1 (as the families write them)."""
    if count is None:
        idx = sorted(int(n[len(prefix):]) for n in fields if n.startswith(prefix) and n[len(prefix):].isdigit())
        if idx != list(range(len(idx))):
            gaps = sorted(set(range(idx[-1] + 1)) - set(idx))
            what = f"missing {prefix}{gaps[0]}" if gaps else "a number used twice"
            raise FileFormatError(f"{source}: PLY fields {prefix}* are not numbered 0..n-1 ({what})")
        count = len(idx)
    names = [f"{prefix}{i}" for i in range(count)]
    missing = [k for k in names if k not in fields]
    if missing or count == 0:
        raise FileFormatError(f"{source}: missing PLY field(s) {missing or [prefix + '0']}")
    return np.stack([fields[k].astype(np.float32) for k in names], axis=1)


def ply_xyz(fields: Mapping[str, np.ndarray]) -> np.ndarray:
    """The ``x, y, z`` columns as ``[V, 3]`` float32 (check them with :func:`require_fields` first)."""
    return np.stack([fields["x"], fields["y"], fields["z"]], axis=1).astype(np.float32)


def ply_offsets(fields: Mapping[str, np.ndarray], n_offsets: int, *, source: str) -> np.ndarray:
    """Scaffold-family offsets: ``f_offset_{c*K + k}`` is coordinate c of offset k. -> ``[V, K, 3]``."""
    flat = ply_columns(fields, "f_offset_", source=source)
    if flat.shape[1] != 3 * n_offsets:
        raise FileFormatError(f"{source}: expected {3 * n_offsets} f_offset_* fields (3 x n_offsets={n_offsets}), got {flat.shape[1]}")
    return np.ascontiguousarray(flat.reshape(-1, 3, n_offsets).transpose(0, 2, 1))
