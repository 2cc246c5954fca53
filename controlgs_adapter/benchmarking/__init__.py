"""Benchmark machinery: the training step's phase clock (:mod:`.clock`), the measurements of
``controlgs bench`` (:mod:`.accuracy_time`) and their Markdown report (:mod:`.report`)."""

from .clock import STEP_PHASES, ClockedRasterizer, PhaseClock, clock_stage

__all__ = ["PhaseClock", "ClockedRasterizer", "clock_stage", "STEP_PHASES"]
