"""A device-placement guard that catches, on the CPU, what fails only on a GPU: a tensor the library makes
on the host (a factory call without ``device=``) meeting the model's tensors.

On a GPU machine the model is moved to ``cuda`` and a tensor created without ``device=`` is on the CPU. Here
both are on the CPU, so :class:`DeviceGuard` (a :class:`~torch.overrides.TorchFunctionMode`) labels the
tensors it sees:

- on the *model's device* (:data:`MODEL_DEVICE`, ``cpu:1``, what their ``.device`` says; their ``.is_cuda`` is
  True, so the library's CUDA-only branches run): tensors made with
  ``device=MODEL_DEVICE`` (or a ``.device`` read from such a tensor), moved there (``.to``, ``Module.to``,
  ``.cuda()``), and anything computed from them;
- on the *host* (``cpu``): every other tensor: made without ``device=`` (by the library, by torch on its
  behalf, by a test), read from a file, existing before the guard started, ``.cpu()`` copies.

The first operation given a host tensor of one or more dimensions and a tensor on the model's device raises
:class:`DevicePlacementError`, naming the operation, its caller and, for a host tensor made inside the guard,
the line that made it. As on CUDA, 0-dim host tensors (CPU scalars) mix with any device and cross-device
copies (``.to``, ``copy_``) and host index tensors in ``t[index]`` of a model tensor (CUDA copies them) are
allowed. Everything computes on real values, so host-side tables built on the CPU and moved once work as
on a GPU.

Move the model inside the guard (``model.to(MODEL_DEVICE)``): outside it nothing is labelled. Limits: only
operations called from Python are checked (torch's own Python functions count as one call); a tensor made
where the mode cannot see it (inside a C++ call) counts as on the host, which can give a false alarm but
never hides two labelled tensors meeting.
"""

from __future__ import annotations

import ast
import inspect
import os
import site
import sys
import textwrap
from collections.abc import Callable
from types import FrameType
from typing import Any

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

import controlgs_adapter

#: what ``.device`` says inside the guard: the model's device, and the host
MODEL_DEVICE, HOST_DEVICE = torch.device("cpu", 1), torch.device("cpu")

#: factory functions: without ``device=`` (and without a tensor argument) their result is on the host
FACTORIES: frozenset[Callable[..., Any]] = frozenset({
    torch.tensor, torch.as_tensor, torch.scalar_tensor, torch.zeros, torch.ones, torch.empty, torch.full,
    torch.empty_strided, torch.arange, torch.linspace, torch.logspace, torch.eye, torch.rand, torch.randn,
    torch.randint, torch.randperm, torch.tril_indices, torch.triu_indices, torch.from_numpy,
})

#: the attribute holding a tensor's label: True on the model's device, else where it was made on the host (or absent)
LABEL = "_device_guard_label"

#: calls that read what tensors are, not their values: fine across devices
_METADATA = frozenset({torch._has_compatible_shallow_copy_type, torch.Tensor.data_ptr, torch.Tensor.untyped_storage,
                       torch.Tensor.is_set_to})

_DEVICE_GET = torch.Tensor.device.__get__  # type: ignore[attr-defined]
_DATA_SET = torch.Tensor.data.__set__  # type: ignore[attr-defined]
_IS_CUDA_GET = torch.Tensor.is_cuda.__get__  # type: ignore[attr-defined]


def on_model(t: torch.Tensor) -> bool:
    """True if ``t`` is on the model's device."""
    return getattr(t, LABEL, None) is True


def made_at(t: torch.Tensor) -> str:
    """Where the host tensor ``t`` was made (``file:line``), as far as the guard saw."""
    label = getattr(t, LABEL, None)
    return label if isinstance(label, str) else "the host (before the guard or outside its view)"


def _library_roots() -> tuple[str, ...]:
    """The real paths of the library's code: the package and its symlinked subpackages."""
    pkg = os.path.dirname(os.path.abspath(controlgs_adapter.__file__))
    return tuple(sorted({os.path.join(os.path.realpath(os.path.join(pkg, sub)), "") for sub in ("", "downstream", "backends")}))


def _label(out: Any, label: bool | str) -> Any:
    """``out`` with every tensor in it labelled ``label``."""
    for t in tree_flatten(out)[0]:
        if isinstance(t, torch.Tensor):
            setattr(t, LABEL, label)
    return out


def _to_model(device: Any) -> bool:
    return torch.device(device) == MODEL_DEVICE


def _target(func: Any, args: tuple[Any, ...], kwargs: dict[str, Any]) -> bool | None:
    """For a cross-device copy (``.cpu()``, ``.cuda()``, ``.to`` given a device or a tensor): whether its
    result is on the model's device; None for any other call."""
    if func is torch.Tensor.cpu:
        return False
    if func is torch.Tensor.cuda:
        return True
    if func is not torch.Tensor.to:
        return None
    for a in args[1:]:
        if isinstance(a, torch.Tensor):
            return on_model(a)
    device = next((a for a in args[1:] if isinstance(a, (str, torch.device))), kwargs.get("device"))
    return None if device is None else _to_model(device)


class DevicePlacementError(AssertionError):
    """An operation was given a host tensor and a tensor on the model's device."""


_parameter_new = torch.nn.Parameter.__new__


def _labelled_parameter(cls: Any, data: torch.Tensor | None = None, requires_grad: bool = True) -> Any:
    """``Parameter(data)`` where ``data`` is (torch makes it without a call the mode sees)."""
    p = _parameter_new(cls, data, requires_grad)
    if data is not None and hasattr(data, LABEL):
        setattr(p, LABEL, getattr(data, LABEL))
    return p


class DeviceGuard(TorchFunctionMode):
    """The mode; ``made`` counts the host tensors (of one or more dimensions) made while it was active."""

    def __init__(self) -> None:
        super().__init__()
        self.roots = _library_roots()
        self.packages = tuple({os.path.join(os.path.realpath(p), "") for p in site.getsitepackages()}
                              | {os.path.join(os.path.dirname(os.__file__), "")})
        self.made = 0

    def _site(self, frame: FrameType | None) -> str:
        """``file:line`` of ``frame``, and of the innermost library frame outside it when it is not one."""
        where = []
        while frame is not None:
            path = os.path.realpath(frame.f_code.co_filename)
            where.append(f"{os.path.relpath(path) if path.startswith(self.roots) else os.path.basename(path)}:{frame.f_lineno}")
            if path.startswith(self.roots) or not path.startswith(self.packages):
                break
            frame = frame.f_back
        return " via ".join(where[:1] + where[-1:] if len(where) > 1 else where)

    def __torch_function__(self, func: Any, types: Any, args: tuple[Any, ...] = (), kwargs: dict[str, Any] | None = None) -> Any:
        kwargs = kwargs or {}
        if func == _DEVICE_GET:
            return MODEL_DEVICE if on_model(args[0]) else HOST_DEVICE
        if func == _IS_CUDA_GET:  # the library's CUDA-only branches run on the model's tensors
            return on_model(args[0])
        if func == _DATA_SET:  # param.data = t (Module.to): the parameter is now where t is
            func(*args, **kwargs)
            setattr(args[0], LABEL, getattr(args[1], LABEL, None))
            return None
        tensors = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        if func in FACTORIES and not tensors:
            out = func(*args, **kwargs)
            device = kwargs.get("device")
            if device is not None and _to_model(device):
                return _label(out, True)
            self.made += out.dim() > 0
            return _label(out, self._site(sys._getframe(1)))
        target = _target(func, args, kwargs)
        if target is not None:  # a cross-device copy: its result is a new tensor where it went
            out = func(*args, **kwargs)
            if out is args[0] and on_model(out) != target:
                out = out.clone()
            return _label(out, True if target else self._site(sys._getframe(1)))
        if func is torch.Tensor.copy_ or func in _METADATA:
            return func(*args, **kwargs)
        if func in (torch.Tensor.numpy, torch.Tensor.__array__) and on_model(args[0]):
            raise DevicePlacementError(f"{func.__name__}() of a tensor {list(args[0].shape)} on the model's device "
                                       f"(a CUDA tensor has no NumPy view), called from {self._site(sys._getframe(1))}")
        if func in (torch.Tensor.__getitem__, torch.Tensor.__setitem__) and on_model(args[0]):
            # host index tensors are copied to the indexed tensor's device, as CUDA does
            tensors = [t for t in tree_flatten((args[0], args[2:]))[0] if isinstance(t, torch.Tensor)]
        model = [t for t in tensors if on_model(t)]
        host = [t for t in tensors if not on_model(t) and t.dim() > 0]
        if model and host:
            raise DevicePlacementError(
                f"{getattr(func, '__qualname__', func)} was given a host tensor {list(host[0].shape)} made at "
                f"{made_at(host[0])} with a tensor {list(model[0].shape)} on the model's device, "
                f"called from {self._site(sys._getframe(1))}")
        out = func(*args, **kwargs)
        if model:
            return _label(out, True)
        if host and isinstance(getattr(host[0], LABEL, None), str):
            return _label(out, made_at(host[0]))
        return out

    def __enter__(self) -> "DeviceGuard":
        torch.nn.Parameter.__new__ = _labelled_parameter  # type: ignore[method-assign,assignment]
        return super().__enter__()  # type: ignore[no-any-return]

    def __exit__(self, *exc: Any) -> None:
        torch.nn.Parameter.__new__ = _parameter_new  # type: ignore[method-assign]
        super().__exit__(*exc)


def with_edit(func: Callable[..., Any], old: str, new: str) -> Callable[..., Any]:
    """``func`` (a module-level function or a method without ``super()``) recompiled from its source with the
    one occurrence of ``old`` replaced by ``new``, keeping its file and line numbers (so the guard and
    tracebacks name the real line)."""
    src = textwrap.dedent(inspect.getsource(func))
    if src.count(old) != 1:
        raise ValueError(f"{func.__qualname__}: {old!r} occurs {src.count(old)} times, expected once")
    tree = ast.parse(src.replace(old, new))
    ast.increment_lineno(tree, func.__code__.co_firstlineno - 1)
    namespace: dict[str, Any] = {}
    exec(compile(tree, func.__code__.co_filename, "exec"), func.__globals__, namespace)  # noqa: S102
    return namespace[func.__name__]  # type: ignore[no-any-return]


def patch_everywhere(monkeypatch: Any, func: Callable[..., Any], replacement: Callable[..., Any]) -> int:
    """Replace ``func`` by ``replacement`` in every loaded library module that holds it by name (its own
    module and those that imported it) and in its class for a method; returns how many places."""
    places = 0
    if "." in func.__qualname__:
        owner = sys.modules[func.__module__]
        for part in func.__qualname__.split(".")[:-1]:
            owner = getattr(owner, part)
        monkeypatch.setattr(owner, func.__name__, replacement)
        return 1
    for name, module in list(sys.modules.items()):
        if name.startswith("controlgs_adapter") and getattr(module, func.__name__, None) is func:
            monkeypatch.setattr(module, func.__name__, replacement)
            places += 1
    return places


__all__ = ["FACTORIES", "LABEL", "MODEL_DEVICE", "HOST_DEVICE", "DeviceGuard", "DevicePlacementError", "on_model",
           "made_at", "with_edit", "patch_everywhere"]
