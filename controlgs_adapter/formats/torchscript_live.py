"""Rebuild a live TorchScript module (one already in memory, e.g. the user's model) as an eager one.

Its children keep their eager class name in ``original_name``; the kinds and settings come from
:data:`~controlgs_adapter.formats.torchscript_layers.SUPPORTED_LAYERS`. The rebuild is checked on a
probe batch against the script module's own output, which runs its code: use it on trusted modules
only (files are read as data by :func:`~controlgs_adapter.formats.torchscript.eager_from_archive`).
"""

from __future__ import annotations

import re
from typing import cast

import torch
from torch import nn

from controlgs_adapter.errors import TargetError
from controlgs_adapter.formats.torchscript_layers import SUPPORTED_LAYERS

__all__ = ["eager_from_script"]

_NUM = r"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?"


def _setting(sm: torch.jit.ScriptModule, attr: str, fn: str, index: int, name: str) -> float:
    """A layer setting: the attribute a scripted module keeps (``dim``, ``negative_slope``), else the
    ``index``-th number after the input in the traced code ``torch.<fn>(x, a0, a1, ...)``."""
    try:
        return float(getattr(sm, attr))
    except (AttributeError, RuntimeError):
        pass
    m = re.search(rf"\b{fn}\(\s*[\w.]+\s*((?:,\s*{_NUM}\s*)+)", sm.code)
    args = re.findall(_NUM, m.group(1)) if m else []
    if index >= len(args):
        raise TargetError(f"{name}: cannot read {sm.original_name}.{attr} from its TorchScript code:\n{sm.code}")
    return float(args[index])


def _linear(sm: torch.jit.ScriptModule, name: str) -> nn.Linear:
    weight = sm.weight  # [out, in]
    bias = getattr(sm, "bias", None)
    layer = nn.Linear(weight.shape[1], weight.shape[0], bias=bias is not None, device=weight.device, dtype=weight.dtype)
    with torch.no_grad():
        layer.weight.copy_(weight)
        if bias is not None:
            layer.bias.copy_(bias)
    layer.weight.requires_grad_(weight.requires_grad)
    if bias is not None:
        layer.bias.requires_grad_(bias.requires_grad)
    return layer


def _rebuild(sm: torch.jit.ScriptModule, name: str) -> nn.Module:
    kind = getattr(sm, "original_name", type(sm).__name__)
    if kind == "Sequential":
        # a ScriptModule's children are ScriptModules; torch's stubs type named_children() as Module
        return nn.Sequential(*(_rebuild(cast(torch.jit.ScriptModule, child), f"{name}.{key}")
                               for key, child in sm.named_children()))
    if kind not in SUPPORTED_LAYERS:
        raise TargetError(
            f"decoder {name!r}: TorchScript layer of type {kind!r} cannot be rebuilt as an eager module "
            f"(supported: Sequential of {', '.join(sorted(k for k in SUPPORTED_LAYERS if k != 'Sequential'))})"
        )
    if kind == "Linear":
        return _linear(sm, name)
    spec = SUPPORTED_LAYERS[kind]
    return spec.build([_setting(sm, attr, spec.ops[0], i, name) for i, (attr, _) in enumerate(spec.settings)])


def _first_linear(module: nn.Module) -> nn.Linear | None:
    return next((m for m in module.modules() if isinstance(m, nn.Linear)), None)


def eager_from_script(script_module: torch.jit.ScriptModule, name: str = "decoder") -> nn.Module:
    """Rebuild a traced or scripted ``Sequential`` (or single layer) as an eager module.

    Args:
        script_module: e.g. ``torch.jit.load("opacity_mlp.pt")``.
        name: the decoder's name, used in error messages (e.g. ``"mlp_opacity"``).

    Returns:
        An ``nn.Sequential`` (or layer) on the same device and dtype, in the same train/eval mode,
        whose outputs equal the script module's (checked on a random probe batch of 4 rows).

    Raises:
        TargetError: a layer type is not supported, a setting cannot be read, or the rebuilt
            module's output differs from the script module's (e.g. a custom ``forward``).
    """
    if not isinstance(script_module, torch.jit.ScriptModule):
        raise TargetError(f"decoder {name!r}: expected a TorchScript module, got {type(script_module).__name__}")
    eager = _rebuild(script_module, name)
    eager.train(script_module.training)
    fc1 = _first_linear(eager)
    if fc1 is None:
        raise TargetError(f"decoder {name!r}: the TorchScript module holds no Linear layer")
    gen = torch.Generator()  # fresh CPU generator: a fixed initial seed, the same probe every call (any probe does)
    probe = torch.randn(4, fc1.in_features, generator=gen, dtype=fc1.weight.dtype).to(fc1.weight.device)
    with torch.no_grad():
        try:
            want = script_module(probe)
        except RuntimeError as e:
            raise TargetError(f"decoder {name!r}: the TorchScript module does not take a [rows, {fc1.in_features}] input: {e}") from e
        got = eager(probe)
    if not isinstance(want, torch.Tensor) or want.shape != got.shape or not torch.equal(want, got):
        raise TargetError(
            f"decoder {name!r}: the eager rebuild of the TorchScript module does not reproduce its output "
            f"(its forward is not a plain chain of its layers?):\n{script_module.code}"
        )
    return eager
