"""The decoders of a Scaffold-family iteration folder (Scaffold-GS, Octree-GS, HAC/HAC++, ContextGS),
read one way: TorchScript traces (``'split'``: ``opacity_mlp.pt``, ...) or one file of state dicts
(``'unite'``: ``checkpoints.pth``; HAC/ContextGS: ``checkpoint.pth``), rebuilt as eager modules.
TorchScript archives are read as data (``trust_code=True`` runs ``torch.jit.load``), state dicts
through ``torch.load(weights_only=True)``; every error names the file and the entry.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path
from typing import Callable, Mapping

import torch
from torch import nn

from controlgs_adapter.errors import FileFormatError

from controlgs_adapter.formats.backbone import (check_finite_weights, load_state_dict_file, load_torchscript,
                                                 load_torchscript_tensors)

__all__ = ["MLP_FILES", "UNITE_FILE", "ATTRIBUTE_DECODERS", "DECODER_ACTIVATIONS", "Decoders", "build_mlp",
           "decoders_from_state_dicts", "mlp_from_state_dict", "check_first_width"]

#: decoder attribute -> (TorchScript file in 'split' mode, key of checkpoints.pth in 'unite' mode)
MLP_FILES: dict[str, tuple[str, str]] = {
    "mlp_opacity": ("opacity_mlp.pt", "opacity_mlp"),
    "mlp_cov": ("cov_mlp.pt", "cov_mlp"),
    "mlp_color": ("color_mlp.pt", "color_mlp"),
    "mlp_feature_bank": ("feature_bank_mlp.pt", "feature_bank_mlp"),
    "embedding_appearance": ("embedding_appearance.pt", "appearance"),
}
UNITE_FILE = "checkpoints.pth"
ATTRIBUTE_DECODERS: tuple[str, ...] = ("mlp_opacity", "mlp_cov", "mlp_color")

#: Activations of the Scaffold-family decoders between their Linears (Sequential indices).
DECODER_ACTIVATIONS: dict[str, dict[int, Callable[[], nn.Module]]] = {
    "mlp_opacity": {1: nn.ReLU, 3: nn.Tanh}, "mlp_cov": {1: nn.ReLU}, "mlp_color": {1: nn.ReLU, 3: nn.Sigmoid},
    "mlp_feature_bank": {1: nn.ReLU, 3: functools.partial(nn.Softmax, dim=1)},
}


def mlp_from_state_dict(state: Mapping[str, torch.Tensor], activations: Mapping[int, nn.Module], *, name: str,
                        source: str) -> nn.Sequential:
    """Rebuild an ``nn.Sequential`` of Linears (at the indices the keys ``<i>.weight`` name) with
    the given activation modules at the other indices, e.g. ``{1: ReLU(), 3: Tanh()}``.

    Raises :class:`FileFormatError` naming ``source``/``name`` if a Linear index collides with an
    activation or the layer widths do not chain.
    """
    if not isinstance(state, Mapping):
        raise FileFormatError(f"{source}: entry {name!r} is not a state dict (got {type(state).__name__})")
    linear_ids = sorted({int(k.split(".")[0]) for k in state if re.fullmatch(r"\d+\.weight", k)})
    if not linear_ids:
        raise FileFormatError(f"{source}: entry {name!r} holds no '<i>.weight' Linear weights (keys: {sorted(state)[:6]})")
    size = max([*linear_ids, *activations]) + 1
    layers: list[nn.Module] = []
    prev_out = None
    for i in range(size):
        if i in linear_ids:
            if i in activations:
                raise FileFormatError(f"{source}: {name!r} has a Linear at index {i} where an activation was expected")
            w = state[f"{i}.weight"]
            b = state.get(f"{i}.bias")
            if w.dim() != 2 or (prev_out is not None and w.shape[1] != prev_out):
                raise FileFormatError(f"{source}: {name!r} layer {i} weight {list(w.shape)} does not take the previous width {prev_out}")
            lin = nn.Linear(w.shape[1], w.shape[0], bias=b is not None)
            with torch.no_grad():
                lin.weight.copy_(w)
                if b is not None:
                    lin.bias.copy_(b)
            layers.append(lin)
            prev_out = w.shape[0]
        elif i in activations:
            layers.append(activations[i])
        else:
            raise FileFormatError(f"{source}: {name!r} has no layer at index {i} (keys: {sorted(state)})")
    return nn.Sequential(*layers)


def build_mlp(attr: str, state: Mapping[str, torch.Tensor], *, name: str, source: str) -> nn.Sequential:
    """The decoder ``attr`` (a key of :data:`DECODER_ACTIVATIONS`) from its state dict."""
    return mlp_from_state_dict(state, {i: make() for i, make in DECODER_ACTIVATIONS[attr].items()}, name=name,
                               source=source)


def decoders_from_state_dicts(sd: Mapping[str, object], keys: Mapping[str, str], *, source: str,
                              optional: tuple[str, ...] = ()) -> dict[str, nn.Module]:
    """Decoders ``{attr: module}`` from a file of state dicts ``sd`` whose entry ``keys[attr]`` holds
    decoder ``attr``; an absent entry is an error unless ``attr`` is in ``optional``, a NaN/Inf
    weight is an error naming ``source`` and the tensor."""
    out: dict[str, nn.Module] = {}
    for attr, key in keys.items():
        if key not in sd:
            if attr in optional:
                continue
            raise FileFormatError(f"{source}: missing entry {key!r} (has {sorted(sd)})")
        if isinstance(sd[key], Mapping):
            check_finite_weights(sd[key], source=source, prefix=key)  # type: ignore[arg-type]
        out[attr] = build_mlp(attr, sd[key], name=key, source=source)  # type: ignore[arg-type]
    return out


def embedding_from_state(state: Mapping[str, torch.Tensor], *, source: str) -> nn.Embedding:
    """The appearance embedding (one ``[num_cameras, appearance_dim]`` table) as an ``nn.Embedding``."""
    weights = [v for k, v in state.items() if k.endswith("weight")]
    if len(weights) != 1 or weights[0].dim() != 2:
        raise FileFormatError(f"{source}: expected one [num_cameras, appearance_dim] embedding table")
    return nn.Embedding.from_pretrained(weights[0].float().clone())


def check_first_width(decoder: nn.Module, want_in: int, *, name: str, source: str, layout: str) -> None:
    """Raise if the decoder's first Linear does not take ``want_in`` inputs (the family's layout)."""
    fc1 = next(m for m in decoder.modules() if isinstance(m, nn.Linear))
    if fc1.in_features != want_in:
        raise FileFormatError(f"{source}: {name} takes {fc1.in_features} inputs, the configuration gives {want_in} ({layout})")


def _describe(module: nn.Module) -> list[tuple[str, tuple[int, int] | None]]:
    return [(type(m).__name__, (m.in_features, m.out_features) if isinstance(m, nn.Linear) else None)
            for m in (module.children() if isinstance(module, nn.Sequential) else [module])]


class Decoders:
    """The decoders of one Scaffold-GS / Octree-GS iteration folder, in either mode, before any width
    check: ``state`` (attribute -> state dict), ``source`` (attribute -> file [entry]), ``layers``
    (split mode: the rebuilt layer list, ``[(type, (in, out) | None)]``) and ``mode``. A NaN/Inf
    weight is refused (:class:`FileFormatError` naming the file and the tensor)."""

    def __init__(self, folder: Path, trust_code: bool = False) -> None:
        split = {n: folder / f for n, (f, _) in MLP_FILES.items()}
        self.mode = "split" if any(p.is_file() for p in split.values()) else "unite"
        self.state: dict[str, dict[str, torch.Tensor]] = {}
        self.layers: dict[str, list] = {}
        self.source: dict[str, str] = {}
        self._eager: dict[str, nn.Module] = {}
        if self.mode == "split":
            for name, p in split.items():
                if not p.is_file():
                    continue
                self.source[name] = str(p)
                if name == "embedding_appearance":
                    self.state[name] = load_torchscript_tensors(p, trust_code=trust_code)
                    continue
                eager = load_torchscript(p, trust_code=trust_code)
                self._eager[name] = eager
                self.layers[name] = _describe(eager)
                self.state[name] = eager.state_dict()
            missing = [MLP_FILES[n][0] for n in ATTRIBUTE_DECODERS if n not in self.state]
            if missing:
                raise FileFormatError(f"{folder}: missing MLP file(s) {missing} (split mode: TorchScript traces)")
        else:
            unite = folder / UNITE_FILE
            if not unite.is_file():
                raise FileFormatError(
                    f"{folder}: missing MLPs: neither the TorchScript traces {[f for f, _ in MLP_FILES.values()][:3]} "
                    f"nor {UNITE_FILE} is there")
            blob = load_state_dict_file(unite)
            for name, (_, key) in MLP_FILES.items():
                if key in blob:
                    if not isinstance(blob[key], dict):
                        raise FileFormatError(f"{unite}: entry {key!r} is not a state dict")
                    self.state[name], self.source[name] = blob[key], f"{unite} [{key!r}]"
            missing = [MLP_FILES[n][1] for n in ATTRIBUTE_DECODERS if n not in self.state]
            if missing:
                raise FileFormatError(f"{unite}: missing MLP entr(y/ies) {missing}")
        for name, sd in self.state.items():  # either mode, trusted TorchScript included
            check_finite_weights(sd, source=self.source[name], prefix=MLP_FILES[name][1] if self.mode == "unite" else "")

    def weight(self, name: str, key: str) -> torch.Tensor:
        """Tensor ``key`` of decoder ``name``'s state dict, or an error naming the file."""
        sd = self.state[name]
        if key not in sd or not isinstance(sd[key], torch.Tensor):
            raise FileFormatError(f"{self.source[name]}: decoder {name!r} has no tensor {key!r} (keys: {sorted(sd)})")
        return sd[key]

    def modules(self) -> dict[str, nn.Module]:
        """Every decoder as an eager module (split mode: the rebuilt traces; unite mode: Sequentials
        with the family's activations) and the appearance embedding as an ``nn.Embedding``."""
        out: dict[str, nn.Module] = {}
        for name, sd in self.state.items():
            if name == "embedding_appearance":
                out[name] = embedding_from_state(sd, source=self.source[name])
            elif name in self._eager:
                out[name] = self._eager[name]
            else:
                out[name] = build_mlp(name, sd, name=MLP_FILES[name][1], source=self.source[name])
        return out
