"""The TorchScript layers that are rebuilt as eager modules: one table for both ways in.

:func:`~controlgs_adapter.formats.torchscript_live.eager_from_script` rebuilds a live ScriptModule
(its settings are its attributes or the constants of its traced code);
:func:`~controlgs_adapter.formats.torchscript.eager_from_archive` reads an archive file as data (its
settings are the constants of its forward's one call). Both take the kinds, their eager classes,
their ops and their settings from :data:`SUPPORTED_LAYERS`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

from torch import nn

__all__ = ["LayerKind", "SUPPORTED_LAYERS"]


def _only_flags(consts: list[Any], op: str) -> str | None:
    # the functional helper's ``inplace`` flag is the only constant these calls pass
    return None if all(type(c) is bool for c in consts) else f"whose forward passes {consts} to {op}"


def _softmax_extra(consts: list[Any], op: str) -> str | None:
    # softmax(input, dim, _stacklevel, dtype): no dtype
    return None if len(consts) <= 3 and consts[2:3] in ([], [None]) else f"with a dtype argument {consts[2]!r}"


def _at_most(n: int) -> Callable[[list[Any], str], str | None]:
    return lambda consts, op: None if len(consts) <= n else f"whose forward passes {consts}"


def _exactly(n: int) -> Callable[[list[Any], str], str | None]:
    return lambda consts, op: None if len(consts) == n else f"whose forward passes {consts}"


@dataclass(frozen=True)
class LayerKind:
    """One supported layer kind (``original_name`` of a live module, class name in an archive).

    Attributes:
        eager: the eager class built for it; None for the two built from their structure
            (``Sequential`` from its children, ``Linear`` from its weights).
        ops: what its forward may call (``torch.<op>`` or ``__torch__.torch.nn.functional.<op>``);
            the first is the one traced code shows.
        settings: ``eager``'s keyword arguments in the order its forward's call passes them after
            the input, each with the constant types accepted.
        refuse_constants: ``(constants, op)`` -> why the call's constants as a whole are refused
            (the tail of the message), or None; checked before the settings.
    """

    eager: type[nn.Module] | None
    ops: tuple[str, ...] = ()
    settings: tuple[tuple[str, tuple[type, ...]], ...] = ()
    refuse_constants: Callable[[list[Any], str], str | None] = _only_flags

    def build(self, values: Sequence[Any]) -> nn.Module:
        """The eager layer with ``values`` (one per setting, in order): floats where a setting
        takes floats, ints where it takes ints only, None as is."""
        if self.eager is None:
            raise TypeError("Sequential and Linear are built from their structure")
        kwargs = {name: None if v is None else float(v) if float in types else int(v)
                  for (name, types), v in zip(self.settings, values)}
        return self.eager(**kwargs)


#: kind -> what is supported of it; the order is the one error messages list them in
SUPPORTED_LAYERS: dict[str, LayerKind] = {
    "Sequential": LayerKind(None),
    "Linear": LayerKind(None, ("linear",)),
    "Identity": LayerKind(nn.Identity),
    "ReLU": LayerKind(nn.ReLU, ("relu", "relu_")),
    "Tanh": LayerKind(nn.Tanh, ("tanh",)),
    "Sigmoid": LayerKind(nn.Sigmoid, ("sigmoid",)),
    "SiLU": LayerKind(nn.SiLU, ("silu", "silu_")),
    "Softmax": LayerKind(nn.Softmax, ("softmax",), (("dim", (int, type(None))),), _softmax_extra),
    "LeakyReLU": LayerKind(nn.LeakyReLU, ("leaky_relu", "leaky_relu_"), (("negative_slope", (int, float)),), _at_most(2)),
    "Softplus": LayerKind(nn.Softplus, ("softplus",), (("beta", (int, float)), ("threshold", (int, float))), _exactly(2)),
}
