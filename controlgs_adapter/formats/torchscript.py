"""Rebuild TorchScript decoders as eager modules (forward hooks do not work on ScriptModules).

This module reads archive files; the live rebuild is :mod:`.torchscript_live` and the supported
layers are one table, :data:`~controlgs_adapter.formats.torchscript_layers.SUPPORTED_LAYERS` (both
re-exported here).

Scaffold-GS and its family save their decoders as ``torch.jit.trace`` archives
(``opacity_mlp.pt``, ...). Two ways in:

* :func:`eager_from_archive` reads an archive **file** as data and never executes anything in it:
  the zip's ``data.pkl`` goes through a restricted unpickler (TorchScript module classes become
  inert records, tensors are rebuilt from the zip's storage records, any other global is refused),
  the code files are parsed as text (``ast``, never compiled or run) and checked to be a plain
  chain of supported layers, and the eager ``nn.Sequential`` is built from that structure.
  :func:`tensors_from_archive` reads only the tensors (e.g. ``embedding_appearance.pt``).
* :func:`eager_from_script` rebuilds a ``ScriptModule`` that is already in memory (the user's live
  model): its children keep their eager class name in ``original_name``; the rebuild is checked on
  a probe batch against the script module's own output (this runs its code: use it on trusted
  modules only).
"""

from __future__ import annotations

import ast
import collections
import io
import math
import os
import pickle
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.torchscript_layers import SUPPORTED_LAYERS
from controlgs_adapter.formats.torchscript_live import eager_from_script

__all__ = ["eager_from_script", "eager_from_archive", "tensors_from_archive", "SUPPORTED_LAYERS"]

# --------------------------------------------------------------------------------------------------
# Reading an archive file without executing it
# --------------------------------------------------------------------------------------------------

_MAX_ENTRIES = 4096  # a decoder archive holds a few dozen entries
_MAX_TOTAL_BYTES = 1 << 30  # declared uncompressed size of everything that is read
_MAX_PICKLE_BYTES = 16 << 20
_MAX_CODE_BYTES = 4 << 20  # all code files together
_MAX_DEPTH = 32  # module nesting
_MAX_DIMS = 8

_FLOAT_STORAGES = {"FloatStorage": torch.float32, "DoubleStorage": torch.float64, "HalfStorage": torch.float16,
                   "BFloat16Storage": torch.bfloat16}
_OTHER_STORAGES = {"LongStorage": torch.int64, "IntStorage": torch.int32, "ShortStorage": torch.int16,
                   "CharStorage": torch.int8, "ByteStorage": torch.uint8, "BoolStorage": torch.bool,
                   "ComplexFloatStorage": torch.complex64, "ComplexDoubleStorage": torch.complex128}

# ``torch.<name>`` the archive's code may mention at all (the layer ops and what the scripted
# ``torch.nn.functional`` helpers of those layers use); anything else is refused.
_SAFE_TORCH = frozenset(op for kind in SUPPORTED_LAYERS.values() for op in kind.ops) | {
    "__is__", "__isnot__", "warn", "format", "eq", "ne", "dim"}
_SAFE_CALLS = frozenset({"getattr", "unchecked_cast", "int", "float", "bool", "str", "isinstance"})
_QUALNAME = re.compile(r"__torch__\.torch\.nn\.modules\.[a-z_]+(?:\.___torch_mangle_\d+)?\.([A-Za-z]\w*)")


class _Refused(Exception):
    """Internal: what was found; turned into a FileFormatError naming the file."""


class _ScriptObject:
    """Inert stand-in for a pickled TorchScript object: its class name and its state, nothing runs."""

    qualname = ""

    def __new__(cls, *args: Any) -> "_ScriptObject":
        if args:
            raise _Refused(f"object of class {cls.qualname} built with arguments")
        return super().__new__(cls)

    def __setstate__(self, state: Any) -> None:
        self.state = state


@dataclass(frozen=True)
class _StorageType:
    name: str
    dtype: torch.dtype

    def __setstate__(self, state: Any) -> None:  # pickle's BUILD writes __dict__ directly, past frozen=True
        raise _Refused("a pickled BUILD on a storage type")


@dataclass(frozen=True)
class _Storage:
    dtype: torch.dtype
    key: str
    numel: int

    def __setstate__(self, state: Any) -> None:
        raise _Refused("a pickled BUILD on a storage record")


class _TensorRecord:
    """A tensor read from the archive (a plain holder, so no pickle opcode can touch a real tensor)."""

    __slots__ = ("tensor", "requires_grad")

    def __init__(self, tensor: torch.Tensor, requires_grad: bool) -> None:
        self.tensor, self.requires_grad = tensor, requires_grad

    def __setstate__(self, state: Any) -> None:
        raise _Refused("a pickled BUILD on a tensor")


class _ArchiveUnpickler(pickle.Unpickler):
    """Unpickles ``data.pkl``/``constants.pkl`` allowing only what a TorchScript module tree holds."""

    def __init__(self, data: bytes, archive: "_Archive") -> None:
        super().__init__(io.BytesIO(data))
        self._archive = archive
        self._classes: dict[str, type] = {}

    def find_class(self, module: str, name: str) -> Any:
        qual = f"{module}.{name}"
        if (module == "__torch__" or module.startswith("__torch__.")) and all(
                part.isidentifier() for part in qual.split(".")):
            if qual not in self._classes:
                self._classes[qual] = type(name, (_ScriptObject,), {"qualname": qual})
            return self._classes[qual]
        if qual == "torch._utils._rebuild_tensor_v2":
            return self._archive.rebuild_tensor
        if qual == "collections.OrderedDict":
            return collections.OrderedDict
        if module == "torch" and name in _FLOAT_STORAGES:
            return _StorageType(name, _FLOAT_STORAGES[name])
        if module == "torch" and name in _OTHER_STORAGES:
            return _StorageType(name, _OTHER_STORAGES[name])
        raise _Refused(f"a pickled reference to the global {qual!r}, which a decoder never holds")

    def persistent_load(self, pid: Any) -> _Storage:
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage" and isinstance(pid[1], _StorageType)
                and isinstance(pid[2], str) and pid[2].isdigit() and isinstance(pid[3], str)
                and type(pid[4]) is int and pid[4] >= 0):
            raise _Refused(f"an unexpected persistent id {str(pid)[:80]!r}")
        if pid[1].name not in _FLOAT_STORAGES:
            raise _Refused(f"a non-float tensor ({pid[1].dtype}); decoders hold floating-point weights only")
        return _Storage(pid[1].dtype, pid[2], pid[4])


class _Archive:
    """The entries of a TorchScript zip, read with bounds; tensors rebuilt from its storage records."""

    def __init__(self, zf: zipfile.ZipFile) -> None:
        infos = zf.infolist()
        if len(infos) > _MAX_ENTRIES:
            raise _Refused(f"{len(infos)} zip entries (at most {_MAX_ENTRIES}; not a decoder archive)")
        if sum(i.file_size for i in infos) > _MAX_TOTAL_BYTES:
            raise _Refused(f"an uncompressed size over {_MAX_TOTAL_BYTES} bytes (not a decoder archive)")
        pkls = [i.filename for i in infos if i.filename.endswith("/data.pkl") and i.filename.count("/") == 1]
        if len(pkls) != 1:
            raise _Refused("no <name>/data.pkl (not a TorchScript or torch.save zip archive)"
                           if not pkls else f"several module trees {pkls}")
        self.zf = zf
        self.prefix = pkls[0][: -len("data.pkl")]
        self.entries = {i.filename: i for i in infos}
        self.storages: dict[str, torch.Tensor] = {}

    def read(self, name: str, limit: int) -> bytes:
        info = self.entries.get(self.prefix + name)
        if info is None:
            raise _Refused(f"no entry {self.prefix + name!r}")
        if info.file_size > limit:
            raise _Refused(f"entry {info.filename!r} of {info.file_size} bytes (at most {limit})")
        with self.zf.open(info) as f:
            data = f.read(limit + 1)
        if len(data) > limit:
            raise _Refused(f"entry {info.filename!r} is larger than its header says")
        return data

    def storage(self, st: _Storage) -> torch.Tensor:
        if st.key not in self.storages:
            itemsize = torch.empty((), dtype=st.dtype).element_size()
            raw = self.read(f"data/{st.key}", _MAX_TOTAL_BYTES)
            if len(raw) < st.numel * itemsize:
                raise _Refused(f"storage data/{st.key} holds {len(raw)} bytes, its record needs {st.numel * itemsize}")
            raw = raw[: st.numel * itemsize]
            flat = torch.frombuffer(bytearray(raw), dtype=st.dtype) if raw else torch.empty(0, dtype=st.dtype)
            self.storages[st.key] = flat
        flat = self.storages[st.key]
        if flat.dtype != st.dtype or flat.numel() != st.numel:
            raise _Refused(f"storage data/{st.key} is referenced with two dtypes or sizes")
        return flat

    def rebuild_tensor(self, storage: Any, offset: Any, size: Any, stride: Any, requires_grad: Any,
                       hooks: Any, metadata: Any = None) -> _TensorRecord:
        """``torch._utils._rebuild_tensor_v2`` over the storages read from the zip, every index checked."""
        ints = lambda t: isinstance(t, tuple) and len(t) <= _MAX_DIMS and all(  # noqa: E731
            type(v) is int and v >= 0 for v in t)
        if not (isinstance(storage, _Storage) and type(offset) is int and offset >= 0 and ints(size) and ints(stride)
                and len(size) == len(stride) and isinstance(requires_grad, bool)
                and isinstance(hooks, collections.OrderedDict) and not hooks and not metadata):
            raise _Refused("a malformed tensor record")
        flat = self.storage(storage)
        if math.prod(size) > flat.numel():  # decoder weights never alias: no tensor bigger than its storage
            raise _Refused(f"a tensor of shape {list(size)} larger than its storage data/{storage.key}")
        if math.prod(size) and offset + sum((n - 1) * s for n, s in zip(size, stride)) >= flat.numel():
            raise _Refused(f"a tensor of shape {list(size)} that reaches past its storage data/{storage.key}")
        return _TensorRecord(torch.as_strided(flat, size, stride, offset).clone(), requires_grad)

    def unpickle(self, name: str) -> Any:
        return _ArchiveUnpickler(self.read(name, _MAX_PICKLE_BYTES), self).load()

    def code(self) -> dict[str, ast.Module]:
        """``code/**.py`` parsed as text, keyed by module qualname (``__torch__.torch.nn.modules.linear``)."""
        out, total = {}, 0
        for full in self.entries:
            if not (full.startswith(self.prefix + "code/") and full.endswith(".py")):
                continue
            rel = full[len(self.prefix + "code/"): -len(".py")]
            text = self.read(f"code/{rel}.py", _MAX_CODE_BYTES)
            total += len(text)
            if total > _MAX_CODE_BYTES:
                raise _Refused(f"over {_MAX_CODE_BYTES} bytes of code")
            try:
                out[rel.replace("/", ".")] = ast.parse(text.decode("utf-8"), filename=full)
            except (SyntaxError, ValueError, RecursionError, MemoryError) as e:
                raise _Refused(f"code file {full!r} that is not TorchScript source ({type(e).__name__})") from None
        if not out:
            raise _Refused("no code/ folder (not a TorchScript archive; a torch.save file?)")
        return out


@dataclass
class _Node:
    """One module of the pickled tree."""

    qualname: str
    attrs: dict[str, Any] = field(default_factory=dict)
    tensors: dict[str, _TensorRecord] = field(default_factory=dict)
    children: dict[str, "_Node"] = field(default_factory=dict)


def _tree(obj: Any, where: str, depth: int = 0) -> _Node:
    if depth > _MAX_DEPTH:
        raise _Refused(f"modules nested deeper than {_MAX_DEPTH} (or a cycle) at {where}")
    if not isinstance(obj, _ScriptObject):
        raise _Refused(f"{where} is a pickled {type(obj).__name__}, not a TorchScript module")
    state = getattr(obj, "state", None)
    if not isinstance(state, dict) or not all(isinstance(k, str) for k in state):
        raise _Refused(f"module {where} ({obj.qualname}) whose state is not a plain dict of attributes "
                       f"(a custom __getstate__/__setstate__?)")
    node = _Node(obj.qualname)
    for key, value in state.items():
        if isinstance(value, _ScriptObject):
            node.children[key] = _tree(value, f"{where}.{key}" if where else key, depth + 1)
        elif isinstance(value, _TensorRecord):
            node.tensors[key] = value
        elif value is None or isinstance(value, (bool, int, float, str)):
            node.attrs[key] = value
        else:
            raise _Refused(f"attribute {where}.{key} holding a {type(value).__name__}")
    return node


class _Code:
    """The archive's code as parsed text: classes and functions by qualname."""

    def __init__(self, modules: dict[str, ast.Module]) -> None:
        self.classes: dict[str, ast.ClassDef] = {}
        self.functions: dict[str, ast.FunctionDef] = {}
        for mod, tree in modules.items():
            for stmt in tree.body:
                if isinstance(stmt, ast.ClassDef):
                    self.classes[f"{mod}.{stmt.name}"] = stmt
                elif isinstance(stmt, ast.FunctionDef):
                    self.functions[f"{mod}.{stmt.name}"] = stmt
        self.modules = modules

    def methods(self, qualname: str) -> dict[str, ast.FunctionDef | ast.AsyncFunctionDef]:
        cls = self.classes.get(qualname)
        if cls is None:
            raise _Refused(f"no code for the class {qualname}")
        return {s.name: s for s in cls.body if isinstance(s, (ast.FunctionDef, ast.AsyncFunctionDef))}

    def check_methods(self) -> None:
        """Every class defines ``forward`` (and ``__len__``) only: no ``__setstate__``, no exported methods."""
        for qual in self.classes:
            extra = sorted(set(self.methods(qual)) - {"forward", "__len__"})
            if extra:
                raise _Refused(f"class {qual} defines {', '.join(extra)} (code that torch.jit.load or a caller "
                               f"would run; a decoder has forward only)")

    def check_names(self) -> None:
        """Every ``torch.*`` the code mentions is a harmless layer op, every ``__torch__.*`` is defined here,
        every called bare name is local or a TorchScript builtin."""
        defined = set(self.classes) | set(self.functions)
        for mod, tree in self.modules.items():
            nodes = list(ast.walk(tree))
            local = {n.id for n in nodes if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
            local |= {a.arg for n in nodes if isinstance(n, ast.arguments) for a in (*n.posonlyargs, *n.args, *n.kwonlyargs)}
            inner = {id(n.value) for n in nodes if isinstance(n, ast.Attribute)}
            for n in nodes:
                if isinstance(n, ast.Attribute) and id(n) not in inner:  # the whole ``a.b.c`` chain
                    dotted = _dotted(n)
                    root = dotted.split(".")[0]
                    if root.startswith("<"):  # ``(expr).attr``: expr is checked on its own
                        continue
                    if root == "torch" and dotted[len("torch."):] not in _SAFE_TORCH:
                        raise _Refused(f"code ({mod}) that calls {dotted}")
                    if root == "__torch__" and dotted not in defined:
                        raise _Refused(f"code ({mod}) that uses {dotted}, which the archive does not define")
                    if root not in {"torch", "__torch__", "self"} and root not in local:
                        raise _Refused(f"code ({mod}) that uses {dotted}")
                elif (isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id not in local
                      and n.func.id not in _SAFE_CALLS):
                    raise _Refused(f"code ({mod}) that calls {n.func.id}")


def _dotted(node: ast.AST) -> str:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    parts.append(node.id if isinstance(node, ast.Name) else f"<{type(node).__name__}>")
    return ".".join(reversed(parts))


def _symbolic_forward(fn: ast.FunctionDef, where: str) -> tuple[Any, bool]:
    """Read ``forward`` as a dataflow expression over ``input``, ``self.<attr>`` and submodule calls.

    Returns ``(expression, takes_input)``. Only assignments to names and one final ``return`` of
    names, constants, ``getattr(self, "k")``, ``(sub).forward(...)`` and calls of ``torch.*`` /
    ``__torch__.*`` functions are accepted; any other statement (loops, branches, ...) is refused.
    """
    a = fn.args
    params = [p.arg for p in (*a.posonlyargs, *a.args)]
    if a.vararg or a.kwarg or a.kwonlyargs or a.defaults or not params or params[0] != "self" or len(params) > 2:
        raise _Refused(f"{where}.forward with the signature ({', '.join(params)}); expected (self, input)")
    env: dict[str, Any] = {"self": ("self",)}
    if len(params) == 2:
        env[params[1]] = ("input",)

    def ev(n: ast.AST) -> Any:
        if isinstance(n, ast.Name):
            if n.id in env:
                return env[n.id]
            if n.id == "getattr":
                return ("builtin", "getattr")
        elif isinstance(n, ast.Constant) and (n.value is None or type(n.value) in (bool, int, float, str)):
            return ("const", n.value)
        elif isinstance(n, ast.UnaryOp) and isinstance(n.op, ast.USub) and isinstance(n.operand, ast.Constant) \
                and isinstance(n.operand.value, (int, float)) and not isinstance(n.operand.value, bool):
            return ("const", -n.operand.value)
        elif isinstance(n, ast.Attribute):
            dotted = _dotted(n)
            if dotted.startswith(("torch.", "__torch__.")):
                return ("fn", dotted)
            if isinstance(n.value, ast.Name) and n.value.id == "self":
                return ("attr", n.attr)
        elif isinstance(n, ast.Call) and not n.keywords:
            if isinstance(n.func, ast.Attribute) and n.func.attr == "forward":
                sub = ev(n.func.value)
                if sub[0] == "sub":
                    return ("apply", sub[1], tuple(ev(x) for x in n.args))
            else:
                f = ev(n.func)
                if f == ("builtin", "getattr") and len(n.args) == 2 and isinstance(n.args[1], ast.Constant) \
                        and isinstance(n.args[1].value, str) and ev(n.args[0]) == ("self",):
                    return ("sub", n.args[1].value)
                if f[0] == "fn":
                    return ("call", f[1], tuple(ev(x) for x in n.args))
        raise _Refused(f"{where}.forward with the expression {ast.unparse(n)[:80]!r} (not a plain chain of layers)")

    for stmt in fn.body[:-1]:
        if not (isinstance(stmt, ast.Assign) and len(stmt.targets) == 1 and isinstance(stmt.targets[0], ast.Name)):
            raise _Refused(f"{where}.forward with the statement {ast.unparse(stmt).splitlines()[0][:80]!r} "
                           f"(not a plain chain of layers)")
        env[stmt.targets[0].id] = ev(stmt.value)
    last = fn.body[-1] if fn.body else None
    if not isinstance(last, ast.Return) or last.value is None:
        raise _Refused(f"{where}.forward that does not end in a return of its result")
    return ev(last.value), len(params) == 2


def _finite(t: _TensorRecord, where: str) -> torch.Tensor:
    if not t.tensor.is_floating_point():
        raise _Refused(f"a non-float tensor {where} ({t.tensor.dtype})")
    if not torch.isfinite(t.tensor).all():
        bad = "NaN" if torch.isnan(t.tensor).any() else "inf"
        raise _Refused(f"non-finite weights ({bad}) in {where}")
    return t.tensor


def _build(node: _Node, code: _Code, where: str) -> nn.Module:
    """The eager module of one node (in the node's train/eval mode), its children included."""
    module = _layer(node, code, where)
    module.training = bool(node.attrs.get("training", False))
    return module


def _layer(node: _Node, code: _Code, where: str) -> nn.Module:
    """The eager module of one node, after checking its state and its forward's code against its kind."""
    m = _QUALNAME.fullmatch(node.qualname)
    kind = m.group(1) if m else None
    label = where or "the root module"
    if kind not in SUPPORTED_LAYERS:
        raise _Refused(f"{label} of type {node.qualname} (supported: Sequential of "
                       f"{', '.join(k for k in SUPPORTED_LAYERS if k != 'Sequential')})")
    extra_attrs = {k for k, v in node.attrs.items()
                   if k != "training" and not (k.startswith("_") and (v is None or isinstance(v, bool)))}
    extra_attrs -= {"bias"} if kind == "Linear" and node.attrs.get("bias", 0) is None else set()
    if extra_attrs:
        raise _Refused(f"{label} ({kind}) with unexpected attributes {sorted(extra_attrs)}")
    forward = code.methods(node.qualname).get("forward")
    if forward is None:
        raise _Refused(f"{label} ({kind}) without a forward method")
    if not isinstance(forward, ast.FunctionDef):
        raise _Refused(f"{label} ({kind}) with an 'async def forward' (TorchScript has no async code)")
    expr, takes_input = _symbolic_forward(forward, label)
    if kind == "Sequential":
        return _build_sequential(node, code, where, expr)
    if node.children:
        raise _Refused(f"{label} ({kind}) with submodules {sorted(node.children)}")
    if kind == "Linear":
        return _build_linear(node, label, expr)
    if node.tensors:
        raise _Refused(f"{label} ({kind}) with tensors {sorted(node.tensors)}")
    if kind == "Identity":
        if expr != (("input",) if takes_input else ("const", None)):
            raise _Refused(f"{label} (Identity) whose forward does not return its input")
        return nn.Identity()
    if not (isinstance(expr, tuple) and expr[0] == "call" and expr[2][:1] == (("input",),)
            and all(a[0] == "const" for a in expr[2][1:])):
        raise _Refused(f"{label} ({kind}) whose forward is not one call of {sorted(SUPPORTED_LAYERS[kind].ops)} on its input")
    fn, consts = expr[1], [a[1] for a in expr[2][1:]]
    op = fn.rsplit(".", 1)[-1]
    if fn not in {f"torch.{op}", f"__torch__.torch.nn.functional.{op}"} or op not in SUPPORTED_LAYERS[kind].ops:
        raise _Refused(f"{label} ({kind}) whose forward calls {fn}")
    return _activation(kind, op, consts, label)


def _activation(kind: str, op: str, consts: list[Any], label: str) -> nn.Module:
    """The eager activation; its settings are the constants of the forward call (as TorchScript inlines them)."""
    spec = SUPPORTED_LAYERS[kind]
    why = spec.refuse_constants(consts, op)
    if why is not None:
        raise _Refused(f"{label} ({kind}) {why}")
    values = []
    for i, (name, types) in enumerate(spec.settings):
        if i >= len(consts) or type(consts[i]) not in types:
            raise _Refused(f"{label} ({kind}) whose forward does not give {name} as a constant "
                           f"(call arguments {consts})")
        values.append(consts[i])
    return spec.build(values)


def _build_linear(node: _Node, label: str, expr: Any) -> nn.Linear:
    names = set(node.tensors)
    if not ({"weight"} <= names <= {"weight", "bias"}) or node.children:
        raise _Refused(f"{label} (Linear) holding {sorted(names | set(node.children))}; expected weight[, bias]")
    weight = _finite(node.tensors["weight"], f"{label}.weight")
    bias = _finite(node.tensors["bias"], f"{label}.bias") if "bias" in node.tensors else None
    if weight.dim() != 2 or (bias is not None and (bias.dim() != 1 or bias.shape[0] != weight.shape[0])):
        raise _Refused(f"{label} (Linear) with weight {list(weight.shape)} and bias "
                       f"{None if bias is None else list(bias.shape)}; expected [out, in] and [out]")
    if bias is not None and bias.dtype != weight.dtype:
        raise _Refused(f"{label} (Linear) with weight {weight.dtype} and bias {bias.dtype}")
    args = (("input",), ("attr", "weight"), ("attr", "bias")) if "bias" in node.attrs or bias is not None \
        else (("input",), ("attr", "weight"))
    if expr not in {("call", "torch.linear", args), ("call", "torch.linear", args[:2] + (("const", None),))}:
        raise _Refused(f"{label} (Linear) whose forward is not torch.linear(input, self.weight, self.bias)")
    layer = nn.Linear(weight.shape[1], weight.shape[0], bias=bias is not None, dtype=weight.dtype)
    with torch.no_grad():
        layer.weight.copy_(weight)
        if bias is not None:
            layer.bias.copy_(bias)
    layer.weight.requires_grad_(node.tensors["weight"].requires_grad)
    if bias is not None:
        layer.bias.requires_grad_(node.tensors["bias"].requires_grad)
    return layer


def _build_sequential(node: _Node, code: _Code, where: str, expr: Any) -> nn.Sequential:
    label = where or "the root Sequential"
    keys = list(node.children)
    if not keys or keys != [str(i) for i in range(len(keys))] or node.tensors:
        raise _Refused(f"{label} (Sequential) holding {keys + sorted(node.tensors)}; expected submodules '0'..'n-1'")
    layers = {k: _build(child, code, f"{where}.{k}" if where else k) for k, child in node.children.items()}
    chain = []
    while isinstance(expr, tuple) and expr[0] == "apply" and len(expr[2]) == 1:
        chain.append(expr[1])
        expr = expr[2][0]
    chain.reverse()
    # A traced Identity drops out of the chain (its forward takes no input): it may be absent from it.
    wanted = [k for k in keys if k in chain or not isinstance(layers[k], nn.Identity)]
    if expr != ("input",) or chain != wanted:
        raise _Refused(f"{label} (Sequential) whose forward is not the chain of its submodules {keys} in order")
    return nn.Sequential(*layers.values())


def _open_archive(path: str | Path) -> tuple[_Archive, Any, _Code, zipfile.ZipFile]:
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    try:
        zf = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise FileFormatError(f"{path}: not a TorchScript archive (not a zip file: {e})") from None
    try:
        archive = _Archive(zf)
        code = _Code(archive.code())
        code.check_methods()  # before unpickling: a __setstate__ is refused without looking further
        byteorder = archive.prefix + "byteorder"
        if byteorder in archive.entries and archive.read("byteorder", 16).strip() != b"little":
            raise _Refused("big-endian tensor data")
        root = archive.unpickle("data.pkl")
    except BaseException:
        zf.close()
        raise
    return archive, root, code, zf


def _refuse(path: Path, e: Exception) -> FileFormatError:
    if isinstance(e, _Refused):
        return FileFormatError(f"{path}: TorchScript archive refused (nothing in it was run): {e}")
    return FileFormatError(f"{path}: unreadable TorchScript archive (truncated or damaged?): "
                           f"{type(e).__name__}: {str(e)[:200]}")


def eager_from_archive(path: str | Path) -> nn.Module:
    """Read a TorchScript decoder file as data and rebuild it as an eager module; nothing in it runs.

    The archive must hold a traced or scripted ``nn.Sequential`` (possibly nested) of the layers in
    :data:`SUPPORTED_LAYERS` (or one such layer), with floating-point, finite weights and code that
    only chains those layers. The result is in eval/train mode as stored, on CPU, in the stored dtype.

    Raises:
        FileFormatError: naming the file and what was found: not a zip / not TorchScript, a global
            other than module classes, tensors and OrderedDict in the pickle, a class with methods
            besides ``forward`` (e.g. ``__setstate__``), code calling anything but the layer ops,
            unsupported layers, a forward that is not a plain chain, non-float or NaN/inf weights,
            inconsistent shapes, or an archive too large to be a decoder.
    """
    path = Path(path)
    try:
        archive, root, code, zf = _open_archive(path)
        with zf:
            module = _build(_tree(root, ""), code, "")
            code.check_names()
            if archive.prefix + "constants.pkl" in archive.entries and archive.unpickle("constants.pkl") != ():
                raise _Refused("tensor constants used by its code (a decoder has none)")
            return module
    except FileFormatError:
        raise
    except Exception as e:  # noqa: BLE001 - every failure of a foreign file is a format error naming it
        raise _refuse(path, e) from None


def tensors_from_archive(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """The floating-point tensors of a TorchScript archive by state-dict name (``embedding.weight``),
    read as data; nothing in the archive runs and its code is not interpreted (any module class).

    Raises:
        FileFormatError: naming the file: not TorchScript, a global other than module classes,
            tensors and OrderedDict, a class with methods besides ``forward`` (e.g. ``__setstate__``),
            non-float or non-finite tensors, or an archive too large to be a decoder.
    """
    path = Path(path)
    try:
        _, root, _, zf = _open_archive(path)
        with zf:
            out: dict[str, torch.Tensor] = {}

            def collect(node: _Node, prefix: str) -> None:
                for k, t in node.tensors.items():
                    out[prefix + k] = _finite(t, prefix + k)
                for k, c in node.children.items():
                    collect(c, f"{prefix}{k}.")

            collect(_tree(root, ""), "")
            return out
    except FileFormatError:
        raise
    except Exception as e:  # noqa: BLE001
        raise _refuse(path, e) from None
