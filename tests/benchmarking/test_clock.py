"""Tests of ``controlgs_adapter.benchmarking.clock``: the rasterizer that laps the phase clock around the splat and
renders like the rasterizer it wraps."""

from __future__ import annotations

import math
import os

import pytest
import torch

from controlgs_adapter.benchmarking import ClockedRasterizer, PhaseClock
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV
from controlgs_adapter.rendering.splatter import RasterOutput
from controlgs_adapter.state import Camera


def _gaussian_scene() -> tuple[tuple[torch.Tensor, ...], Camera]:
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), k, 8, 8)
    g = (torch.tensor([[0.0, 0.0, 2.0]]), torch.full((1, 3), 0.2), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
         torch.tensor([0.8]), torch.tensor([[1.0, 0.5, 0.25]]))
    return g, cam


def test_clocked_rasterizer_laps_and_renders_like_its_inner(monkeypatch: pytest.MonkeyPatch) -> None:
    from controlgs_adapter.rendering.splatter import rasterize

    g, cam = _gaussian_scene()
    clock = PhaseClock()
    clock.start()
    r = ClockedRasterizer(clock, "torch")
    assert r.name == "clocked" and r.inner == "torch"
    out = r(*g, cam, torch.tensor([0.0, 0.0, 1.0]))
    assert isinstance(out, RasterOutput) and list(clock.laps) == ["decode", "splat"]
    want = rasterize(*g, cam, torch.tensor([0.0, 0.0, 1.0]))
    assert torch.equal(out.color, want.color)  # the background is passed on
    # unavailable is the inner one's; None inner: $CONTROLGS_RASTERIZER, else auto
    assert r.unavailable(torch.device("cpu"), torch.float32) is None
    assert r.unavailable(torch.device("cpu"), torch.float16) == (
        "rasterizer 'torch' cannot render torch.float16 on cpu: needs float32 or float64, got torch.float16")
    monkeypatch.setenv(RASTERIZER_ENV, "nope")
    assert "rasterizer 'nope' is not registered" in str(ClockedRasterizer(clock).unavailable(torch.device("cpu"),
                                                                                            torch.float32))
    with pytest.raises(InputValueError, match="rasterizer 'nope' is not registered"):
        ClockedRasterizer(clock)(*g, cam)
    assert ClockedRasterizer(clock, "torch").unavailable(torch.device("cpu"), torch.float32) is None  # given: env ignored
    monkeypatch.setenv(RASTERIZER_ENV, "")
    assert ClockedRasterizer(clock).unavailable(torch.device("cpu"), torch.float32) is None  # empty: auto
    monkeypatch.delenv(RASTERIZER_ENV)
    assert ClockedRasterizer(clock).unavailable(torch.device("cpu"), torch.float32) is None
    assert math.isfinite(clock.total) and os.environ.get(RASTERIZER_ENV) is None
