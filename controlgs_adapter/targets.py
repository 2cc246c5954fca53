"""The targets of an injection: the decoders whose first layer (FC1) gets the hook, resolved and
checked before :meth:`ControlGS.wrap <controlgs_adapter.controlgs.ControlGS.wrap>` changes the model."""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import nn

from .backend import Backend, get_attr_path
from .errors import LifecycleError, TargetError
from .formats.torchscript_live import eager_from_script

__all__ = ["Target", "TargetPlan", "inspect_target", "check_shared_layers", "ATTACHED"]

#: FC1 modules that carry a live injector hook -> the wrapper (ControlGS) that owns it (wrapping twice is an error)
ATTACHED: "weakref.WeakKeyDictionary[nn.Module, Any]" = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class Target:
    """One decoder that receives the injection.

    Attributes:
        decoder: dotted path of the decoder on the model (``"mlp_opacity"``).
        fc1: dotted path of its first Linear (``"mlp_opacity.0"``).
        in_features, out_features: FC1's widths (``out_features`` = D1).
        from_torchscript: the decoder was a TorchScript module, rebuilt as an eager one.
    """

    decoder: str
    fc1: str
    in_features: int
    out_features: int
    from_torchscript: bool

    def as_header(self) -> dict[str, Any]:
        return {"decoder": self.decoder, "fc1": self.fc1, "in_features": self.in_features, "out_features": self.out_features}


@dataclass
class TargetPlan:
    """A target as resolved before the model changes."""


    target: Target
    eager: nn.Module | None  # the eager rebuild of a TorchScript decoder (dry run), else None
    layer: nn.Module | None = None  # the model's own FC1 object (eager decoders): two targets must not share it


def inspect_target(model: Any, backend: Backend, path: str) -> TargetPlan:
    """Resolve one target without changing the model; raise TargetError saying what is wrong."""
    try:
        decoder = get_attr_path(model, path)
    except (AttributeError, IndexError, KeyError, TypeError):
        raise TargetError(
            f"{backend.name}: the model has no decoder {path!r}; its decoders: {backend.decoder_paths(model)}"
        ) from None
    fc1_path = backend.first_linear_path(model, path)
    eager = None
    if isinstance(decoder, torch.jit.ScriptModule):
        eager = eager_from_script(decoder, name=path)
    fc1 = backend.check_decoder(model, path, eager)  # one check for eager and TorchScript decoders
    if not isinstance(fc1, nn.Linear):
        raise TargetError(f"{backend.name}: first layer {fc1_path!r} of {path!r} must be an eager nn.Linear, got {type(fc1).__name__}")
    if fc1 in ATTACHED:
        raise LifecycleError(f"{fc1_path!r} already carries an injector ({ATTACHED[fc1]!r}): unwrap it first, "
                          "e.g. ControlGS.attached(model).unwrap()")
    target = Target(path, fc1_path, fc1.in_features, fc1.out_features, eager is not None)
    return TargetPlan(target, eager, fc1 if eager is None else None)


def check_shared_layers(backend: Backend, plans: Sequence[TargetPlan]) -> None:
    """Raise TargetError when two targets' first layers are one module object (``mlp_cov[0] is
    mlp_opacity[0]``, or one decoder under two names): a hook per target would inject into it twice."""
    seen: dict[int, Target] = {}
    for plan in plans:
        if plan.layer is None:  # a TorchScript decoder: each target gets its own eager rebuild
            continue
        first = seen.setdefault(id(plan.layer), plan.target)
        if first is not plan.target:
            raise TargetError(
                f"{backend.name}: targets {first.decoder!r} and {plan.target.decoder!r} share one first layer "
                f"({first.fc1!r} is {plan.target.fc1!r}): its output would get the injection twice; wrap one of "
                f"them (targets=[{first.decoder!r}, ...] without {plan.target.decoder!r}) or give each decoder its own layer")
