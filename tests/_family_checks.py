"""Checks shared by the family-backend tests (tests/test_backend_*.py): wrap a model, verify
identity at init, that one anchor's condition reaches exactly its rows, and the adapter round trip."""

from __future__ import annotations

from argparse import Namespace
from pathlib import Path

import torch

from controlgs_adapter import RuntimeState
from controlgs_adapter.backend import get_attr_path
from controlgs_adapter.controlgs import ControlGS

STATE = RuntimeState(downsample=1, power_saving=0.4)  # display strength 0.5 for every anchor


def write_cfg_args(path: Path, **kw) -> None:
    """cfg_args as the families' train.py writes it: ``str(Namespace(**vars(args)))``."""
    path.write_text(str(Namespace(**kw)))


def outputs(model, inputs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    with torch.no_grad():
        return {p: get_attr_path(model, p)(x) for p, x in inputs.items()}


def check_wrap_identity_and_rows(model, inputs: dict[str, torch.Tensor], ids: torch.Tensor, backend: str,
                                 rows_per_anchor: int, tmp_path: Path, reload) -> None:
    """``inputs``: decoder path -> input rows for anchors ``ids`` (``rows_per_anchor`` rows each).
    ``reload()`` returns a fresh copy of the same backbone (to load the saved adapter onto)."""
    before = outputs(model, inputs)
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=4)
    assert cgs.backend.name == backend
    assert {t.decoder for t in cgs.targets} == set(inputs)
    # identity at init: zero conditions -> bit-identical outputs, inside and outside the block
    with cgs.conditioned(STATE, anchor_ids=ids):
        inside = outputs(model, inputs)
    for p in inputs:
        assert torch.equal(inside[p], before[p]), p
    # one anchor's condition reaches exactly its rows
    pos = len(ids) // 2
    anchor = int(ids[pos])
    with torch.no_grad():
        cgs.injector.conditions["display"][anchor] = torch.linspace(-2.0, 2.0, 4)
    with cgs.conditioned(STATE, anchor_ids=ids):
        after = outputs(model, inputs)
    for p in inputs:
        changed = (after[p] != before[p]).any(dim=1).nonzero().squeeze(1)
        want = torch.arange(pos * rows_per_anchor, (pos + 1) * rows_per_anchor)
        assert torch.equal(changed, want), (p, changed, want)
    # outside the block: the backbone again
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, before[p])
    # save / load onto a fresh copy of the backbone
    path = cgs.save(tmp_path / "adapter.safetensors")
    other = reload()
    cgs2 = ControlGS.load(path, other)
    assert torch.equal(cgs2.injector.conditions["display"], cgs.injector.conditions["display"])
    with cgs2.conditioned(STATE, anchor_ids=ids):
        again = outputs(other, inputs)
    for p in inputs:
        assert torch.equal(again[p], after[p]), p
    cgs.unwrap()
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, before[p])
