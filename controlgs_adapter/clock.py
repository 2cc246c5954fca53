"""A phase clock for one training step: wall-clock laps of named phases.

:meth:`Trainer.step(clock=...) <controlgs_adapter.training.Trainer.step>` calls :meth:`PhaseClock.start`
and then :meth:`PhaseClock.lap` at the end of each of its phases; without a clock it makes no
such calls (no timing, no device synchronisation). More lap points plug in from outside:
:func:`clock_stage` times a pipeline stage by forward hooks, and
:class:`~controlgs_adapter.benchmarking.clock.ClockedRasterizer` splits a render into decoding and
splatting. Laps of the same name add up (a batch of several views).
"""

from __future__ import annotations

import contextlib
import time
from typing import Iterator

import torch
from torch import nn

__all__ = ["PhaseClock", "clock_stage", "STEP_PHASES"]

#: the laps of :meth:`Trainer.step`, in order: view and state sampling (and reading the view),
#: the render (prefilter, decode, rasterize), the downstream pipeline, the loss, its backward, and
#: the update (gradient exchange, Adam step, parameter check)
STEP_PHASES: tuple[str, ...] = ("sample", "render", "pipeline", "loss", "backward", "optimizer")


class PhaseClock:
    """Seconds per named phase of one step.

    Args:
        device: the device whose queued work a lap waits for (``torch.cuda.synchronize``) so that
            a lap times the work of its phase, not its launch; None or a CPU device: no waiting.

    Attributes: ``laps`` (``{phase: seconds}`` since the last :meth:`start`, in first-lap order).
    """

    def __init__(self, device: torch.device | str | None = None) -> None:
        self.device = None if device is None else torch.device(device)
        self.laps: dict[str, float] = {}
        self._last = time.perf_counter()

    def _sync(self) -> None:
        if self.device is not None and self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def start(self) -> None:
        """Forget the laps and start timing (after the device's queued work)."""
        self._sync()
        self.laps = {}
        self._last = time.perf_counter()

    def lap(self, name: str) -> None:
        """Add the seconds since the previous lap (or :meth:`start`) to phase ``name``."""
        self._sync()
        now = time.perf_counter()
        self.laps[name] = self.laps.get(name, 0.0) + now - self._last
        self._last = now

    @property
    def total(self) -> float:
        """Seconds from :meth:`start` to the last lap."""
        return sum(self.laps.values())


@contextlib.contextmanager
def clock_stage(clock: PhaseClock, stage: nn.Module, name: str, before: str) -> Iterator[None]:
    """Inside the block, lap ``clock`` as ``before`` when ``stage``'s forward starts and as ``name``
    when it ends (forward hooks, removed on exit)."""
    hooks = [stage.register_forward_pre_hook(lambda *_: clock.lap(before)),
             stage.register_forward_hook(lambda *_: clock.lap(name))]
    try:
        yield
    finally:
        for h in hooks:
            h.remove()
