"""Rebuild TorchScript decoders as eager modules (forward hooks do not work on ScriptModules).

Scaffold-GS and its family save their decoders as ``torch.jit.trace`` archives
(``opacity_mlp.pt``, ...). Loaded with ``torch.jit.load`` they are ``RecursiveScriptModule`` s
whose children keep their eager class name in ``original_name``; this module rebuilds the eager
``nn.Sequential`` from those names, the weights and (for layers with a setting such as Softmax's
``dim``) the layer's TorchScript code, then checks on a probe batch that both give identical
outputs.
"""

from __future__ import annotations

import re
from typing import Callable

import torch
from torch import nn

from .errors import TargetError

__all__ = ["eager_from_script", "SUPPORTED_LAYERS"]

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


#: ``original_name`` -> builder of the eager layer.
SUPPORTED_LAYERS: dict[str, Callable[[torch.jit.ScriptModule, str], nn.Module]] = {
    "Linear": _linear,
    "ReLU": lambda sm, name: nn.ReLU(),
    "Tanh": lambda sm, name: nn.Tanh(),
    "Sigmoid": lambda sm, name: nn.Sigmoid(),
    "Identity": lambda sm, name: nn.Identity(),
    "SiLU": lambda sm, name: nn.SiLU(),
    "Softmax": lambda sm, name: nn.Softmax(dim=int(_setting(sm, "dim", "softmax", 0, name))),
    "LeakyReLU": lambda sm, name: nn.LeakyReLU(_setting(sm, "negative_slope", "leaky_relu", 0, name)),
    "Softplus": lambda sm, name: nn.Softplus(
        beta=_setting(sm, "beta", "softplus", 0, name), threshold=_setting(sm, "threshold", "softplus", 1, name)
    ),
}


def _rebuild(sm: torch.jit.ScriptModule, name: str) -> nn.Module:
    kind = getattr(sm, "original_name", type(sm).__name__)
    if kind == "Sequential":
        return nn.Sequential(*(_rebuild(child, f"{name}.{key}") for key, child in sm.named_children()))
    if kind not in SUPPORTED_LAYERS:
        raise TargetError(
            f"decoder {name!r}: TorchScript layer of type {kind!r} cannot be rebuilt as an eager module "
            f"(supported: Sequential of {', '.join(sorted(SUPPORTED_LAYERS))})"
        )
    return SUPPORTED_LAYERS[kind](sm, name)


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
    gen = torch.Generator(device="cpu").manual_seed(0)
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
