"""The render's lap points for the step clock: :class:`ClockedRasterizer` splits a render into
decoding and splatting. The clock itself (:class:`PhaseClock`, :func:`clock_stage`,
:data:`STEP_PHASES`) lives in :mod:`controlgs_adapter.clock`, below the trainer that laps it; it is
re-exported here.
"""

from __future__ import annotations

import os
from typing import Any

import torch

from controlgs_adapter.clock import STEP_PHASES, PhaseClock, clock_stage
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV, Rasterizer, select_rasterizer
from controlgs_adapter.state import Camera

__all__ = ["PhaseClock", "ClockedRasterizer", "clock_stage", "STEP_PHASES"]


class ClockedRasterizer(Rasterizer):
    """A rasterizer that laps ``clock`` around another: ``decode`` when the Gaussians arrive
    (everything of the render before rasterization: prefilter, decoding), ``splat`` when the
    image is out. Use with :func:`~controlgs_adapter.rendering.rasterizers.use_rasterizer`.

    Args:
        clock: the :class:`PhaseClock` to lap.
        inner: the rasterizer that renders: a registered name, ``"auto"``, an instance, or None
            (``$CONTROLGS_RASTERIZER``, else ``"auto"``).
    """

    name = "clocked"

    def __init__(self, clock: PhaseClock, inner: str | Rasterizer | None = None) -> None:
        self.clock, self.inner = clock, inner

    def _inner(self, device: torch.device, dtype: torch.dtype) -> Rasterizer:
        inner = self.inner if self.inner is not None else os.environ.get(RASTERIZER_ENV, "") or "auto"
        return select_rasterizer(device, dtype, inner)

    def unavailable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        """None if the inner rasterizer can render these tensors, else why not (its selection's refusal)."""
        try:
            self._inner(device, dtype)  # selects only a rasterizer that can run them
        except InputValueError as e:
            return str(e)
        return None

    def __call__(self, means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor, opacities: torch.Tensor,
                 colors: torch.Tensor, camera: Camera, background: torch.Tensor | None = None) -> Any:
        inner = self._inner(means.device, means.dtype)
        self.clock.lap("decode")
        out = inner(means, scales, rotations, opacities, colors, camera, background)
        self.clock.lap("splat")
        return out

