"""The training step's phase clock: laps add up per name between calls, ``clock_stage`` laps around a
stage and removes its hooks; a clocked training step computes exactly what an unclocked one does."""

from __future__ import annotations

import copy
import time

import pytest
import torch
from torch import nn

import controlgs_adapter.clock as clock_mod
from controlgs_adapter.benchmarking import ClockedRasterizer
from controlgs_adapter.clock import STEP_PHASES, PhaseClock, clock_stage
from controlgs_adapter.rendering.rasterizers import use_rasterizer
from controlgs_adapter.training import TrainConfig, Trainer

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


def test_phase_clock_laps_add_up_the_time_between_calls_per_name(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [10.0]
    monkeypatch.setattr(clock_mod.time, "perf_counter", lambda: now[0])
    clock = PhaseClock()
    assert clock.device is None and clock.laps == {}
    now[0] = 11.0
    clock.start()  # the time before start() does not count
    now[0] = 11.5
    clock.lap("a")
    now[0] = 13.5
    clock.lap("b")
    now[0] = 13.75
    clock.lap("a")
    assert clock.laps == {"a": 0.75, "b": 2.0} and list(clock.laps) == ["a", "b"] and clock.total == 2.75
    clock.start()  # starts over
    assert clock.laps == {} and clock.total == 0
    assert PhaseClock("cpu").device == torch.device("cpu")
    assert STEP_PHASES == ("sample", "render", "pipeline", "loss", "backward", "optimizer")


def test_clock_stage_laps_around_the_stage_and_removes_its_hooks() -> None:
    clock = PhaseClock()
    stage = nn.Identity()
    clock.start()
    with clock_stage(clock, stage, "psf", before="stages"):
        stage(torch.zeros(1))
    assert list(clock.laps) == ["stages", "psf"]
    assert not stage._forward_hooks and not stage._forward_pre_hooks
    clock.start()
    stage(torch.zeros(1))
    assert clock.laps == {}
    with pytest.raises(ZeroDivisionError), clock_stage(clock, stage, "x", before="y"):
        1 / 0  # noqa: B018 - an error inside the block still removes the hooks
    assert not stage._forward_hooks and not stage._forward_pre_hooks
