"""Injection-strength schedules (paper Eqs. 10-11).

Each condition module ``m`` turns the run-time state into a control value ``alpha = f_m(s)`` and
maps it linearly between two endpoints to a strength

    lambda = clamp((alpha - lo) / (hi - lo), 0, 1)

(``lo`` gives no injection, ``hi`` full injection; states outside the range clamp). The
built-in modules:

============  ============================================  ==========  ============
module        control value f_m                             per anchor  endpoints
============  ============================================  ==========  ============
lens          ||p||_2, p = anchor's display position        yes         0 .. sqrt(2)
resample      log2(d), d = S / display sampling rate        no          0 .. 3
display       rho = 1 - P_target / P_ref                    no          0 .. 0.8
foveation     angle(dir(p), gaze) in degrees (0: no gaze)    yes         0 .. 30
============  ============================================  ==========  ============

``p`` (and the gaze) are display-normalised positions: ``ControlGS`` places the image on the
headset display as the optics does (``controlgs_adapter.downstream.placement``, default ``"fit"``:
square pixels, the longer image axis spans [-1, 1], the shorter one ``short / long`` of it), so a
strength follows the radial distance on the display; for a square image they are the normalised
screen positions. For a lens that is not rotationally symmetric and centred, ``ControlGS`` conditions
the lens module on the anchor's position in the lens's own frame instead: a signed pair
(:meth:`LensSchedule.xy_strength`, :mod:`controlgs_adapter.lens_frame`).

The foveation control is an angle: ``dir(p)`` is the direction (degrees from the lens axis) in which
the display position ``p`` is seen through the lens (:mod:`controlgs_adapter.downstream.optics.visual_angles`),
the gaze is ``RuntimeState.gaze`` in degrees. The endpoints are configuration
(``ControlGS.wrap(endpoints={"lens": (0.0, 1.2)})``); the foveation default 0 .. 30 degrees is this
library's choice, the paper does not give one. A plug-in adds a schedule by subclassing
:class:`StrengthSchedule` and returning an instance from ``controlgs_register_schedules``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar

import torch

from .checks import check_tensor
from .errors import InputValueError
from .state import RuntimeState

if TYPE_CHECKING:
    from .downstream.optics.visual_angles import VisualAngles

__all__ = [
    "StrengthSchedule", "LensSchedule", "ResampleSchedule", "DisplaySchedule", "FoveationSchedule",
    "BUILTIN_SCHEDULES",
]


class StrengthSchedule:
    """Maps a run-time state to the injection strength of one condition module.

    Subclasses set :attr:`name`, :attr:`per_anchor`, the default endpoints and implement
    :meth:`control`.

    Args:
        lo: control value with no injection (default :attr:`default_lo`).
        hi: control value with full injection (default :attr:`default_hi`); ``hi != lo`` (``hi <
            lo`` inverts the schedule).
    """

    name: ClassVar[str] = ""
    #: True if the control value depends on the anchor's screen position (needs ``screen_xy``).
    per_anchor: ClassVar[bool] = False
    default_lo: ClassVar[float] = 0.0
    default_hi: ClassVar[float] = 1.0
    #: what the control value is, for ``repr`` and the docs
    control_doc: ClassVar[str] = ""

    def __init__(self, lo: float | None = None, hi: float | None = None) -> None:
        lo = self.default_lo if lo is None else lo
        hi = self.default_hi if hi is None else hi
        if not (isinstance(lo, (int, float)) and isinstance(hi, (int, float))) or not (math.isfinite(lo) and math.isfinite(hi)):
            raise InputValueError(f"schedule {self.name!r}: endpoints must be finite numbers, got lo={lo!r}, hi={hi!r}")
        if lo == hi:
            raise InputValueError(f"schedule {self.name!r}: endpoints must differ, got lo = hi = {lo!r}")
        self.lo, self.hi = float(lo), float(hi)

    def with_endpoints(self, lo: float | None = None, hi: float | None = None) -> "StrengthSchedule":
        """A copy with other endpoints (None keeps this one's)."""
        return type(self)(self.lo if lo is None else lo, self.hi if hi is None else hi)

    def control(self, state: RuntimeState, screen_xy: torch.Tensor | None) -> torch.Tensor | float:
        """Control value alpha: ``[R]`` for per-anchor schedules (``screen_xy`` is ``[R, 2]``
        display-normalised positions, +inf for anchors behind the camera), a float otherwise."""
        raise NotImplementedError

    def strength(self, state: RuntimeState, screen_xy: torch.Tensor | None = None, *, rows: int | None = None,
                 dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        """Injection strength ``lambda`` in [0, 1], ``[R]``.

        Args:
            state: the run-time state.
            screen_xy: ``[R, 2]`` display-normalised positions of the rows' anchors (needed if
                :attr:`per_anchor`; otherwise only its length is used).
            rows: R when ``screen_xy`` is None (global schedules only).
        """
        if screen_xy is not None:
            check_tensor("screen_xy", screen_xy, ["R", 2])
            rows, device = screen_xy.shape[0], screen_xy.device if device is None else device
        elif self.per_anchor:
            raise self._missing_screen_xy()
        if rows is None:
            raise InputValueError("strength() needs screen_xy or rows")
        alpha = self.control(state, screen_xy)
        if isinstance(alpha, torch.Tensor):
            return self._normalise(alpha.to(dtype=dtype, device=device))
        return torch.full((rows,), self.scalar_strength(alpha), dtype=dtype, device=device)

    def _missing_screen_xy(self) -> InputValueError:
        return InputValueError(f"schedule {self.name!r} is per anchor and needs screen_xy [R, 2], got None")

    def scalar_strength(self, alpha: float) -> float:
        """``clamp((alpha - lo) / (hi - lo), 0, 1)`` for one control value."""
        return min(max((alpha - self.lo) / (self.hi - self.lo), 0.0), 1.0)

    def _normalise(self, alpha: torch.Tensor) -> torch.Tensor:
        return ((alpha - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0)

    def endpoints(self) -> dict[str, float]:
        return {"lo": self.lo, "hi": self.hi}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.control_doc}: {self.lo:g} -> 0, {self.hi:g} -> 1)"


class LensSchedule(StrengthSchedule):
    """Lens correction: radius of the anchor's display position about the optical centre.

    For a lens that is not rotationally symmetric and centred, the adapter conditions on the
    anchor's position ``q`` in the lens's own frame instead (:mod:`controlgs_adapter.lens_frame`):
    :meth:`xy_strength` gives a signed pair per anchor.
    """

    name = "lens"
    per_anchor = True
    default_lo, default_hi = 0.0, math.sqrt(2.0)
    control_doc = "||p||_2"

    def control(self, state: RuntimeState, screen_xy: torch.Tensor | None) -> torch.Tensor:
        if screen_xy is None:
            raise self._missing_screen_xy()
        return torch.linalg.vector_norm(screen_xy, dim=-1)

    def xy_strength(self, q: torch.Tensor) -> torch.Tensor:
        """``[R, 2]`` signed strengths ``(lambda_x, lambda_y) = clamp(q / hi, -1, 1)`` of positions
        ``q`` ``[R, 2]`` in the lens's frame (``lo`` is not used: ``q = 0`` on the axis gives 0)."""
        check_tensor("q", q, ["R", 2])
        return (q / self.hi).clamp(-1.0, 1.0)


class ResampleSchedule(StrengthSchedule):
    """Anti-aliasing resampling: log2 of the downsampling factor d (1 -> none, 8 -> full)."""

    name = "resample"
    default_lo, default_hi = 0.0, 3.0
    control_doc = "log2(d)"

    def control(self, state: RuntimeState, screen_xy: torch.Tensor | None) -> float:
        return math.log2(state.downsample)


class DisplaySchedule(StrengthSchedule):
    """Display mapping: the power-saving ratio rho = 1 - P_target / P_ref."""

    name = "display"
    default_lo, default_hi = 0.0, 0.8
    control_doc = "rho"

    def control(self, state: RuntimeState, screen_xy: torch.Tensor | None) -> float:
        return state.power_saving


class FoveationSchedule(StrengthSchedule):
    """Foveation: each anchor's eccentricity in degrees, the angle between the direction its display
    position is seen in through the lens and the gaze (``RuntimeState.gaze``, degrees); no gaze -> 0.

    Args:
        lo, hi: endpoints in degrees (default 0 .. 30).
        angles: the lens's :class:`~controlgs_adapter.downstream.optics.visual_angles.VisualAngles`;
            None: the shipped Cardboard lens's (built on first use).

    Attributes:
        lens_angles: ``angles`` as given (None: the Cardboard lens's); an adapter file records it.
    """

    name = "foveation"
    per_anchor = True
    default_lo, default_hi = 0.0, 30.0
    control_doc = "eccentricity from the gaze [deg]"

    def __init__(self, lo: float | None = None, hi: float | None = None, angles: VisualAngles | None = None) -> None:
        super().__init__(lo, hi)
        self.lens_angles = angles
        self._angles = angles

    @property
    def angles(self) -> VisualAngles:
        """The visual-angle map anchors are measured in (:attr:`lens_angles`, None there: the Cardboard lens's)."""
        if self._angles is None:
            from .downstream.optics.bank import PSFBank  # the shipped bank's file is read only when needed
            from .downstream.optics.visual_angles import VisualAngles
            self._angles = VisualAngles.of_bank(PSFBank.default())
        return self._angles

    def with_endpoints(self, lo: float | None = None, hi: float | None = None) -> "FoveationSchedule":
        return FoveationSchedule(self.lo if lo is None else lo, self.hi if hi is None else hi, self.lens_angles)

    def for_lens(self, angles: VisualAngles) -> "FoveationSchedule":
        """A copy measuring eccentricities through the lens of ``angles``."""
        return FoveationSchedule(self.lo, self.hi, angles)

    def control(self, state: RuntimeState, screen_xy: torch.Tensor | None) -> torch.Tensor:
        if screen_xy is None:
            raise self._missing_screen_xy()
        if state.gaze is None:
            return torch.zeros(screen_xy.shape[:-1], dtype=screen_xy.dtype, device=screen_xy.device)
        from .downstream.optics.visual_angles import eccentricity  # loads the optics only where a gaze is given

        self.angles.check_gaze(state.gaze)
        finite = torch.isfinite(screen_xy).all(-1, keepdim=True)
        directions = self.angles.directions(torch.where(finite, screen_xy, torch.zeros_like(screen_xy)))
        ecc = eccentricity(directions, state.gaze)
        return torch.where(finite[..., 0], ecc, torch.full_like(ecc, math.inf))  # behind the camera: far out


#: the built-in schedules, registered (one instance each) by :mod:`controlgs_adapter.builtin`
BUILTIN_SCHEDULES: tuple[type[StrengthSchedule], ...] = (LensSchedule, ResampleSchedule, DisplaySchedule, FoveationSchedule)
