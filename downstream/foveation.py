"""Foveation (stub stage).

Foveated rendering conditions each anchor on its eccentricity from the gaze point
(``RuntimeState.gaze``, normalised screen coordinates). That condition path lives in the core:
the ``"foveation"`` strength schedule (registered by :mod:`controlgs_adapter.schedules`) turns an
anchor's eccentricity into the injection strength ``lambda = eccentricity / e_max`` whenever
``ControlGS.wrap(..., modules=(..., "foveation"))`` is used, and it works end to end without any
image operation here.

The image side of foveation (e.g. a gaze-contingent blur or a foveated display's varying pixel
density) is not modelled yet: this stage is registered so that a scene configuration can name
the effect and a plug-in can replace it (a stage named ``"foveation"`` from a plug-in overrides
this one), but it is the identity at every state and is therefore always skipped (zero cost).
It sits before the lens pre-warp (order 5), where a compositor would apply a foveated pass.
"""

from __future__ import annotations

import torch

from controlgs_adapter.state import RuntimeState

from .stage import Stage, StageContext

__all__ = ["foveation", "Foveation"]


def foveation(image: torch.Tensor, gaze: tuple[float, float] | None) -> torch.Tensor:
    """Functional twin of :class:`Foveation`: the identity (no image-side foveation yet).

    Args:
        image: ``[..., 3, H, W]``.
        gaze: gaze point in normalised screen coordinates, or None.
    Returns:
        ``image`` unchanged.
    """
    return image


class Foveation(Stage):
    """Foveation placeholder; the identity at every state (see the module docstring)."""

    name = "foveation"
    domain = "linear"
    order = 5.0

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:  # noqa: D102
        return True

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        return foveation(image, state.gaze)
