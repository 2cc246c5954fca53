"""Helpers for the adapter-file tests: a wrapped model with non-trivial parameters, and rewriting a saved file."""

from __future__ import annotations

import torch
from helpers.rawfiles import write_raw

from controlgs_adapter import ControlGS
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND
from controlgs_adapter.formats.safetensors import load_tensors


def trained(model, seed: int = 7, **kw) -> ControlGS:
    """``ControlGS.wrap(model, **kw)`` with every adapter parameter drawn from N(0, 1) (seeded)."""
    cgs = ControlGS.wrap(model, **kw)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in cgs.trainable_parameters():
            p.copy_(torch.randn(p.shape, generator=g))
    return cgs


def rewrite(path, header_changes=None, tensor_changes=None, drop=()) -> dict[str, torch.Tensor]:
    """Rewrite the adapter file at ``path`` with header fields / tensors changed or dropped (damage
    allowed); returns the tensors written."""
    tensors, header = load_tensors(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    header = {k: v for k, v in header.items() if k not in ("kind", "format_version", "library_version")}
    header.update(header_changes or {})
    tensors.update(tensor_changes or {})
    for k in drop:
        tensors.pop(k)
    write_raw(path, tensors, header, kind=ADAPTER_KIND, format_version=ADAPTER_FORMAT_VERSION)
    return tensors


def saved_adapter(folder, seed: int = 7, file: str = "a.safetensors", **kw):
    """An adapter of ``ScaffoldStandIn(30, seed=0)`` with random parameters (``trained(model, seed, **kw)``)
    saved to ``folder / file``; the model is unwrapped again. Returns the path."""
    from helpers.scaffold_standin import ScaffoldStandIn

    cgs = trained(ScaffoldStandIn(30, seed=0), seed, **kw)
    path = cgs.save(folder / file)
    cgs.unwrap()
    return path
