"""Tests of ``controlgs_adapter.downstream.stage``: the stage base class's defaults (the default state and
the image's size as the native size when called as a plain module) and its contract points. What every
stage must do is :func:`helpers.stage_contract.check_stage` (``test_stage_contract.py``)."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.state import RuntimeState


class _Probe(Stage):
    name = "probe"

    def process(self, image, state, ctx):
        self.seen = (state, ctx)
        return image * 2


def test_stage_defaults_and_resolve():
    """Called without state and context a stage gets the default state and a context with the image's size
    as the native size, no reference and no record; given ones are passed through. A stage is never the
    identity, works in linear light at order 100 with no anchor unless it says otherwise; the base class
    has no work of its own."""
    p = _Probe()
    img = torch.ones(2, 3, 4, 5, dtype=torch.float64)
    assert torch.equal(p(img), img * 2)
    state, ctx = p.seen
    assert state == RuntimeState() and ctx.native_size == (4, 5) and ctx.reference is None and ctx.record is None
    assert ctx.displayed_reference is None
    s = RuntimeState(downsample=2.0)
    c = StageContext((8, 10))
    p(img, s, c)
    assert p.seen[0] is s and p.seen[1] is c
    assert not p.is_identity(s) and not p.is_identity(s, c)
    assert (p.domain, p.order, p.after, p.before) == ("linear", 100.0, None, None)
    assert Stage.name == ""
    with pytest.raises(NotImplementedError):
        Stage().process(img, s, c)
