"""Tests of ``controlgs_adapter.benchmarking.clock``: the rasterizer that laps the phase clock around the splat and
renders like the rasterizer it wraps."""

from __future__ import annotations

import copy
import math
import os
import time

import pytest
import torch

from controlgs_adapter.benchmarking import ClockedRasterizer, PhaseClock
from controlgs_adapter.clock import STEP_PHASES, clock_stage
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV, use_rasterizer
from controlgs_adapter.rendering.splatter import RasterOutput
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig, Trainer


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


EFFECTS = {"lens": True, "resample": True, "display": True, "oled": True, "optics": True}


def _trainer(scene, model):
    config = TrainConfig(iterations=4, checkpoint_every=0, psf_fraction=0.5, psf_mode="exact")
    return Trainer(copy.deepcopy(model), scene.views("train"), config, effects=EFFECTS)


def test_clocked_step_computes_the_same_and_times_every_phase(tiny):
    scene, model = tiny
    plain, timed = _trainer(scene, model), _trainer(scene, model)
    clock = PhaseClock("cpu")
    try:
        for it in range(4):  # distortion-only optics, then the exact PSF
            loss = plain.step()
            t0 = time.perf_counter()
            with use_rasterizer(ClockedRasterizer(clock)), clock_stage(clock, timed.pipeline["optics"], "psf", "stages"):
                timed_loss = timed.step(clock)
            outer = time.perf_counter() - t0
            assert timed_loss == loss  # bit-identical: the clock only reads the time
            # the render splits into decode and splat at the rasterizer, the pipeline at the optics stage
            assert list(clock.laps) == ["sample", "decode", "splat", "render", "stages", "psf", "pipeline", "loss",
                                        "backward", "optimizer"], (it, clock.laps)
            assert set(STEP_PHASES) <= set(clock.laps)
            assert all(v >= 0 for v in clock.laps.values())
            assert clock.laps["splat"] > 0 and clock.laps["psf"] > 0 and clock.laps["backward"] > 0
            assert clock.total <= outer  # the laps cover the step, nothing outside it
        for a, b in zip(plain.cgs.trainable_parameters(), timed.cgs.trainable_parameters()):
            assert torch.equal(a, b)
    finally:
        plain.cgs.unwrap()
        timed.cgs.unwrap()
