"""The stage interface of the downstream pipeline (paper Eq. 8).

A stage is a differentiable ``nn.Module`` with a functional twin of the same name in snake case
(kornia's scheme: ``LensPrewarp`` / ``lens_prewarp``, ``AreaResample`` / ``area_resample``,
``DisplayMapping`` / ``display_mapping``, ``OLEDEmission`` / ``oled_emission``, ``PSFOptics`` /
``psf_optics``, ``Foveation`` / ``foveation``). Images are ``[..., 3, H, W]`` float32/float64
tensors; a stage declares the colour domain it works in (``"srgb"``: encoded, values in [0, 1];
``"linear"``: linear light); the pipeline converts domains between stages and skips a stage whose
:meth:`Stage.is_identity` is true. A stage is also a plain module: ``stage(image)`` runs it at the
default :class:`RuntimeState` with the image's size as the native size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import torch
from torch import nn

from controlgs_adapter.state import RuntimeState

__all__ = ["Stage", "StageContext"]

Domain = Literal["srgb", "linear"]


@dataclass
class StageContext:
    """What a stage may need besides the image and the state.

    Attributes:
        reference: ground-truth image ``[..., 3, S_h, S_w]`` (sRGB) at native resolution S, e.g.
            for the display's reference power P_ref; None at pure inference.
        native_size: ``(H, W)`` of the native (simulation) resolution S.
        record: if a dict, stages may store named intermediates/diagnostics in it (for plots).
        displayed_reference: the reference through the stages that ran before this one, in this
            stage's domain (set by the pipeline for stages with ``wants_displayed_reference``).
    """

    native_size: tuple[int, int]
    reference: torch.Tensor | None = None
    record: dict[str, Any] | None = None
    displayed_reference: torch.Tensor | None = None


class Stage(nn.Module):
    """Base class of downstream stages.

    Class attributes:
        name: unique name (``"lens"``, ``"resample"``, ``"display"``, ``"oled"``, ``"optics"``,
            ``"foveation"``).
        domain: colour domain of input and output.
        order: default position in the pipeline (lower runs first).
        after / before: optional name of a stage this one must follow / precede (third-party insertion).
    """

    name: ClassVar[str] = ""
    domain: ClassVar[Domain] = "linear"
    order: ClassVar[float] = 100.0
    after: ClassVar[str | None] = None
    before: ClassVar[str | None] = None

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        """True if the stage does nothing at ``state`` given ``ctx`` (the pipeline then skips it at
        no cost); ``ctx`` None asks about the state alone."""
        return False

    def forward(self, image: torch.Tensor, state: RuntimeState | None = None,
                ctx: StageContext | None = None) -> torch.Tensor:
        """Apply the stage to ``image`` ``[..., 3, H, W]`` in :attr:`domain`. ``state`` None: the
        default :class:`RuntimeState`; ``ctx`` None: the image's size as the native size, no reference."""
        state, ctx = self.resolve(image, state, ctx)
        return self.process(image, state, ctx)

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        """The stage's work with state and context given (what subclasses implement)."""
        raise NotImplementedError

    @staticmethod
    def resolve(image: torch.Tensor, state: RuntimeState | None,
                ctx: StageContext | None) -> tuple[RuntimeState, StageContext]:
        """Defaults of :meth:`forward`: the default state and the image's size as the native size."""
        if state is None:
            state = RuntimeState()
        if ctx is None:
            ctx = StageContext(native_size=(int(image.shape[-2]), int(image.shape[-1])))
        return state, ctx
