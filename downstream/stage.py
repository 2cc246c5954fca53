"""The stage interface of the downstream pipeline (paper Eq. 8).

A stage is a differentiable ``nn.Module`` with a functional twin. Images are ``[..., 3, H, W]``
float32/float64 tensors; a stage declares the colour domain it works in (``"srgb"``: encoded,
values in [0, 1]; ``"linear"``: linear light) and whether it changes the resolution; the pipeline
converts domains between stages and skips a stage whose :meth:`Stage.is_identity` is true.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import torch
from torch import nn

from controlgs_adapter.state import RuntimeState

__all__ = ["Stage", "StageContext"]

Domain = Literal["srgb", "linear"]
Resolution = Literal["keep", "reduce", "restore"]


@dataclass
class StageContext:
    """What a stage may need besides the image and the state.

    Attributes:
        reference: ground-truth image ``[..., 3, S_h, S_w]`` (sRGB) at native resolution S, e.g.
            for the display's reference power P_ref; None at pure inference.
        native_size: ``(H, W)`` of the native (simulation) resolution S.
        record: if a dict, stages may store named intermediates/diagnostics in it (for plots).
    """

    native_size: tuple[int, int]
    reference: torch.Tensor | None = None
    record: dict[str, Any] | None = None
    extras: dict[str, Any] = field(default_factory=dict)


class Stage(nn.Module):
    """Base class of downstream stages.

    Class attributes:
        name: unique name (``"lens"``, ``"resample"``, ``"display"``, ``"oled"``, ``"optics"``,
            ``"foveation"``).
        domain: colour domain of input and output.
        resolution: ``"keep"`` (same size), ``"reduce"`` (S -> S/d) or ``"restore"`` (back to S).
        order: default position in the pipeline (lower runs first).
        after / before: optional name of a stage this one must follow / precede (third-party insertion).
    """

    name: ClassVar[str] = ""
    domain: ClassVar[Domain] = "linear"
    resolution: ClassVar[Resolution] = "keep"
    order: ClassVar[float] = 100.0
    after: ClassVar[str | None] = None
    before: ClassVar[str | None] = None

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        """True if the stage does nothing at ``state`` given ``ctx`` (the pipeline then skips it at
        no cost); ``ctx`` None asks about the state alone."""
        return False

    def forward(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        raise NotImplementedError
