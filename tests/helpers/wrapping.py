"""Shared code of the wrapper's tests (``ControlGS`` and its parts): the Scaffold-GS stand-in in its
eager and TorchScript forms, decoder outputs with and without the injection, and a record of
everything wrapping may change on a model (module objects, hooks, tensors and their flags)."""

from __future__ import annotations

import functools
from typing import Any

import torch
from helpers.scaffold_standin import ScaffoldStandIn, script_decoders
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState

#: the stand-in's default targets
DECODERS = ("mlp_opacity", "mlp_cov", "mlp_color")

#: every shared strength at its top (d = 8, rho just below 0.8)
FULL = RuntimeState(downsample=8.0, power_saving=0.8 - 1e-9)


def stand_in(kind: str = "eager", **kw: Any) -> ScaffoldStandIn:
    """``ScaffoldStandIn(**kw)``; ``kind="script"``: its decoders as TorchScript modules (a Scaffold-GS checkpoint)."""
    model = ScaffoldStandIn(**kw)
    return script_decoders(model) if kind == "script" else model


@functools.lru_cache(maxsize=None)
def refusing_stand_in(kind: str) -> ScaffoldStandIn:
    """One default stand-in per kind, shared by the tests of refusals: they must leave it unchanged
    (the TorchScript one is built once)."""
    return stand_in(kind)


def decode(model: Any, x: torch.Tensor) -> dict[str, torch.Tensor]:
    """The stand-in's three decoder outputs for input ``x``, without autograd."""
    with torch.no_grad():
        return model.decode(x)


def conditioned_decode(cgs: ControlGS, model: Any, x: torch.Tensor, state: RuntimeState, **block: Any
                       ) -> dict[str, torch.Tensor]:
    """:func:`decode` inside ``cgs.conditioned(state, **block)``."""
    with torch.no_grad(), cgs.conditioned(state, **block):
        return model.decode(x)


def assert_same_outputs(want: dict[str, torch.Tensor], got: dict[str, torch.Tensor]) -> None:
    """Bit-identical decoder outputs."""
    assert want.keys() == got.keys()
    for k in want:
        assert torch.equal(want[k], got[k]), k


def _modules(model: Any) -> list[tuple[str, nn.Module]]:
    if isinstance(model, nn.Module):
        return list(model.named_modules(remove_duplicate=False))
    return [(f"{k}.{n}".rstrip("."), m) for k, v in vars(model).items() if isinstance(v, nn.Module)
            for n, m in v.named_modules(remove_duplicate=False)]


def _tensors(model: Any) -> list[tuple[str, torch.Tensor]]:
    if isinstance(model, nn.Module):
        return list(model.state_dict(keep_vars=True).items())
    out = []
    for k, v in vars(model).items():
        if isinstance(v, nn.Module):
            out += [(f"{k}.{n}", t) for n, t in v.state_dict(keep_vars=True).items()]
        elif isinstance(v, torch.Tensor):
            out.append((k, v))
    return out


def model_record(model: Any) -> dict[str, Any]:
    """Everything wrapping may change on ``model`` (an ``nn.Module`` or a plain object holding modules
    and tensors): the module object at each path, its hooks, and each tensor's ``requires_grad`` and value."""
    modules = _modules(model)
    return {"modules": [(p, id(m)) for p, m in modules],
            "hooks": [(p, len(m._forward_hooks), len(m._forward_pre_hooks)) for p, m in modules],
            "tensors": [(p, t.requires_grad, t.detach().clone()) for p, t in _tensors(model)]}


def assert_unchanged(before: dict[str, Any], model: Any) -> None:
    """``model`` is as :func:`model_record` saw it."""
    after = model_record(model)
    assert after["modules"] == before["modules"]
    assert after["hooks"] == before["hooks"]
    assert [(p, g) for p, g, _ in after["tensors"]] == [(p, g) for p, g, _ in before["tensors"]]
    assert all(torch.equal(a, b) for (_, _, a), (_, _, b) in zip(after["tensors"], before["tensors"]))
