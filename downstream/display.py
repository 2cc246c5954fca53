"""Display mapping P_disp: uniform dimming to a power target (paper Eq. 4, Supp. "Display Mapping").

Power model (paper Eq. 7 / S2, dynamic OLED power, no static term), on linear RGB:
``P(I) = mean_{x,y}(alpha R + beta G + gamma B)`` with panel coefficients
``(alpha, beta, gamma) = (228.52, 205.66, 567.64)``. The paper writes a sum over pixels; the mean
is used here so that the power of the rendered image at the display resolution S/d and of the
reference at S are comparable (a sum would scale with the pixel count). Negative values emit no
light and count as 0. :func:`display_power_watts` gives watts as ``3/1000 * P`` (the scale used by
the same group's PowerGS: full white = 3.0055 W).

Uniform dimming: with ``P_ref = P(reference)`` (the ground-truth image; in the pipeline, the
ground truth as the display would show it, :class:`DisplayMapping`) and
``P_target = (1 - rho) P_ref``, the image is scaled by ``P_target / P(image)`` so that its power
equals the target (the paper's equal-power comparison; this brightens an image darker than the
target unless ``brighten=False``), then clipped to the display range [0, 1]. The power after
dimming equals the target exactly unless clipping happens (the clipped fraction is reported).
Gradients flow through ``P(image)``; the reference is a constant. Conventions:
- with a reference, ``rho == 0`` still maps the image to ``P_ref`` (the paper's equal-power
  operator is continuous in rho; treating rho = 0 as "off" would make a jump just above 0).
- no reference: ``P_ref = P(image)``, i.e. the image is scaled by ``1 - rho``; at ``rho == 0`` it
  is returned unchanged (not clipped) and the stage costs nothing.
- ``P(image) == 0`` (a black image): there is nothing to scale; the scale is 1 (no NaN, zero
  gradient through the power).

Domain: linear light. Shapes: ``[..., 3, H, W]``; power ``[...]`` (one value per image).
"""

from __future__ import annotations

import math
import weakref
from typing import Literal, Sequence

import torch

from controlgs_adapter.checks import check_image, check_same_device, value_checks_enabled
from controlgs_adapter.errors import InputValueError, StateRangeError
from controlgs_adapter.state import RuntimeState

from .color import srgb_to_linear
from .stage import Stage, StageContext

__all__ = [
    "PANEL_COEFFICIENTS", "WATTS_PER_UNIT", "display_power", "display_power_watts", "display_mapping", "display_mapping_with_stats",
    "DisplayMapping",
]

#: OLED power coefficients (alpha, beta, gamma) for linear (R, G, B), paper Supp. Eq. S2.
PANEL_COEFFICIENTS: tuple[float, float, float] = (228.52, 205.66, 567.64)
#: Watts per unit of :func:`display_power` (PowerGS' scale 3 / 1000).
WATTS_PER_UNIT: float = 3.0 / 1000.0

_TINY_POWER = 1e-12  # below this an image is black: no scaling


def _check_coefficients(coefficients: Sequence[float]) -> tuple[float, float, float]:
    c = tuple(float(v) for v in coefficients)
    if len(c) != 3 or not all(math.isfinite(v) and v >= 0 for v in c) or sum(c) <= 0:
        raise InputValueError(f"coefficients must be 3 finite non-negative numbers, not all 0, got {coefficients!r}")
    return c  # type: ignore[return-value]


def _power(linear: torch.Tensor, c: tuple[float, float, float]) -> torch.Tensor:
    emitted = linear.clamp(min=0.0)
    per_channel = emitted.mean(dim=(-2, -1))  # [..., 3]
    weights = torch.tensor(c, dtype=linear.dtype, device=linear.device)
    return (per_channel * weights).sum(-1)  # [...]


def display_power(
    image: torch.Tensor, coefficients: Sequence[float] = PANEL_COEFFICIENTS, *, encoding: str = "linear"
) -> torch.Tensor:
    """Dynamic display power ``mean(alpha R + beta G + gamma B)`` of ``image``.

    Args:
        image: ``[..., 3, H, W]``; ``encoding`` says whether it is linear light or sRGB-encoded.
        coefficients: panel coefficients (alpha, beta, gamma).
        encoding: ``"linear"`` or ``"srgb"``.
    Returns:
        ``[...]`` power in panel units (full white = alpha + beta + gamma).
    """
    check_image("image", image, finite=False)
    if encoding not in ("linear", "srgb"):
        raise InputValueError(f"encoding must be 'linear' or 'srgb', got {encoding!r}")
    linear = srgb_to_linear(image) if encoding == "srgb" else image
    return _power(linear, _check_coefficients(coefficients))


def display_power_watts(
    image: torch.Tensor, coefficients: Sequence[float] = PANEL_COEFFICIENTS, *, encoding: str = "linear"
) -> torch.Tensor:
    """:func:`display_power` in watts (``3/1000`` of it; full white with the default panel = 3.0055 W)."""
    return display_power(image, coefficients, encoding=encoding) * WATTS_PER_UNIT


def _check_rho(rho: object) -> float:
    try:
        value = float(rho)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise StateRangeError(f"rho (power saving) must be a real number in [0, 1), got {rho!r}") from None
    if not math.isfinite(value) or not 0.0 <= value < 1.0:
        raise StateRangeError(f"rho (power saving) must be a finite number in [0, 1), got {rho!r}")
    return value


def display_mapping(
    image: torch.Tensor,
    rho: float,
    reference: torch.Tensor | None = None,
    *,
    reference_power: torch.Tensor | float | None = None,
    coefficients: Sequence[float] = PANEL_COEFFICIENTS,
    brighten: bool = True,
) -> torch.Tensor:
    """Uniformly dim ``image`` to ``(1 - rho) P_ref`` and clip to the display range [0, 1].

    Args:
        image: ``[..., 3, H, W]`` linear light (the rendered, resampled image).
        rho: power saving in [0, 1); 0 without a reference returns ``image`` unchanged.
        reference: ``[..., 3, H_r, W_r]`` linear light (the ground truth, any resolution,
            broadcastable leading dims) giving ``P_ref``; None: ``P_ref = P(image)``.
        reference_power: ``P_ref`` itself (``[...]`` or a number, panel units), instead of
            ``reference``.
        coefficients: panel coefficients (alpha, beta, gamma).
        brighten: if False, never scale up (``scale = min(1, P_target / P(image))``).
    Returns:
        ``[..., 3, H, W]`` dimmed and clipped image (:func:`display_mapping_with_stats` also
        returns what it did).
    """
    return _display_mapping(image, rho, reference, reference_power, coefficients, brighten, False)[0]


def display_mapping_with_stats(
    image: torch.Tensor,
    rho: float,
    reference: torch.Tensor | None = None,
    *,
    reference_power: torch.Tensor | float | None = None,
    coefficients: Sequence[float] = PANEL_COEFFICIENTS,
    brighten: bool = True,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`display_mapping` and ``{"scale", "power_target", "power", "clipped_fraction"}``
    (each ``[...]``, detached; ``power`` is that of the clipped output)."""
    out, stats = _display_mapping(image, rho, reference, reference_power, coefficients, brighten, True)
    assert stats is not None
    return out, stats


def _display_mapping(image: torch.Tensor, rho: float, reference: torch.Tensor | None,
                     reference_power: torch.Tensor | float | None, coefficients: Sequence[float], brighten: bool,
                     return_stats: bool) -> tuple[torch.Tensor, dict[str, torch.Tensor] | None]:
    check_image("image", image, finite=False)
    rho = _check_rho(rho)
    c = _check_coefficients(coefficients)
    power = _power(image, c)  # [...]
    if rho == 0.0 and reference is None and reference_power is None:  # scale 1: nothing to do
        if not return_stats:
            return image, None
        p = power.detach()
        return image, {"scale": torch.ones_like(p), "power_target": p, "power": p, "clipped_fraction": torch.zeros_like(p)}
    if reference is not None and reference_power is not None:
        raise InputValueError("give reference or reference_power, not both")
    if reference is not None:
        check_image("reference", reference, finite=False)
        check_same_device(image=image, reference=reference)
        power_ref = _power(reference.detach().to(image.dtype), c)
    elif reference_power is not None:
        power_ref = torch.as_tensor(reference_power, dtype=image.dtype, device=image.device).detach()
        if value_checks_enabled() and (not bool(torch.isfinite(power_ref).all()) or bool((power_ref < 0).any())):
            raise InputValueError(f"reference_power must be finite and >= 0, got {reference_power!r}")
    else:
        power_ref = power.detach()
    target = (1.0 - rho) * power_ref
    black = power <= _TINY_POWER
    safe_power = torch.where(black, torch.ones_like(power), power)
    scale = torch.where(black, torch.ones_like(power), target / safe_power)
    if not brighten:
        scale = scale.clamp(max=1.0)
    dimmed = image * scale[..., None, None, None]
    out = dimmed.clamp(0.0, 1.0)
    if not return_stats:
        return out, None
    with torch.no_grad():
        clipped = ((dimmed < 0.0) | (dimmed > 1.0)).to(image.dtype).mean(dim=(-3, -2, -1))
        stats = {"scale": scale.detach(), "power_target": target.detach(), "power": _power(out.detach(), c),
                 "clipped_fraction": clipped}
    return out, stats


class DisplayMapping(Stage):
    """P_disp: uniform dimming to ``(1 - state.power_saving) * P_ref``, then clipping.

    ``P_ref`` is the power the display consumes showing the ground truth (paper Supp. "Display
    Mapping"): with ``p_ref="displayed"`` (default) that of the ground truth *as displayed*, i.e.
    ``ctx.reference`` through the same post-processing stages that ran before this one (pre-warp
    with its black corners, resampling), which the pipeline puts in
    ``ctx.displayed_reference``, so a perfect render gets scale 1 at every rho;
    ``p_ref="ground_truth"``: that of the sRGB ground truth at S as given (cached while the same,
    unmodified tensor comes back; it ignores the pre-warp's black corners). Without a reference the image's own power is
    the reference. Records ``display.scale``, ``display.power_ref``, ``display.power_target``,
    ``display.power`` and ``display.clipped_fraction`` into ``ctx.record``.

    Args:
        coefficients: panel coefficients (alpha, beta, gamma) of the power model.
        brighten: see :func:`display_mapping`.
        p_ref: ``"displayed"`` or ``"ground_truth"`` (above).
    """

    name = "display"
    domain = "linear"
    order = 30.0

    def __init__(self, coefficients: Sequence[float] = PANEL_COEFFICIENTS, brighten: bool = True,
                 p_ref: Literal["displayed", "ground_truth"] = "displayed") -> None:
        super().__init__()
        if p_ref not in ("displayed", "ground_truth"):
            raise InputValueError(f"p_ref must be 'displayed' or 'ground_truth', got {p_ref!r}")
        self.coefficients = _check_coefficients(coefficients)
        self.brighten = bool(brighten)
        self.p_ref = p_ref
        self._reference_power: tuple[weakref.ref, int, torch.dtype, torch.Tensor] | None = None

    @property
    def wants_displayed_reference(self) -> bool:
        """True if the pipeline should pass the ground truth as displayed (``p_ref="displayed"``)."""
        return self.p_ref == "displayed"

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        """Identity only at rho = 0 without a reference: with one, rho = 0 still maps the image to
        ``P_ref`` (the equal-power operator is continuous in rho)."""
        return state.power_saving == 0.0 and (ctx is None or ctx.reference is None)

    def reference_power(self, reference: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """``P_ref`` ``[...]`` of an sRGB ``reference``; reused while the same tensor object comes
        back unmodified (a weak reference: a new tensor at a recycled address never matches)."""
        cached = self._reference_power
        if cached is not None and cached[0]() is reference and cached[1] == reference._version and cached[2] == dtype:
            return cached[3]
        power = display_power(reference.detach().to(dtype), self.coefficients, encoding="srgb")
        self._reference_power = (weakref.ref(reference), reference._version, dtype, power)
        return power

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:  # noqa: D102
        shown = ctx.displayed_reference if self.wants_displayed_reference else None
        power_ref: torch.Tensor | None
        if shown is not None:
            power_ref = _power(shown.detach().to(image.dtype), self.coefficients)
        else:
            power_ref = None if ctx.reference is None else self.reference_power(ctx.reference, image.dtype)
        out, stats = display_mapping_with_stats(image, state.power_saving, reference_power=power_ref,
                                                coefficients=self.coefficients, brighten=self.brighten)
        if power_ref is not None:
            stats["power_ref"] = power_ref.detach()
        if ctx.record is not None:
            ctx.record.update({f"display.{k}": v for k, v in stats.items()})
        return out
