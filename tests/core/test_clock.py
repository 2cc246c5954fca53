"""The training step's phase clock: laps add up per name between calls, ``clock_stage`` laps around a
stage and removes its hooks; a clocked training step computes exactly what an unclocked one does."""

from __future__ import annotations

import pytest
import torch
from torch import nn

import controlgs_adapter.clock as clock_mod
from controlgs_adapter.clock import STEP_PHASES, PhaseClock, clock_stage


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
