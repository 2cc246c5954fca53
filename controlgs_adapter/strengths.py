"""Injection strengths: the schedules of the wrapped condition modules (from the registry, with their
endpoints) and their values for a run-time state, per anchor where a schedule is per anchor."""

from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import torch

from . import plugins
from .downstream.placement import Placement, to_display
from .errors import InputValueError
from .lens_frame import LensFrame
from .schedules import LensSchedule, StrengthSchedule
from .state import Camera, RuntimeState

__all__ = ["check_modules", "module_strengths", "lens_strength"]


def check_modules(modules: Sequence[str], cond_dim: int,
                  endpoints: Mapping[str, Sequence[float] | Mapping[str, Any]] | None) -> dict[str, StrengthSchedule]:
    """The schedules of ``modules``: the registered ones, with ``endpoints[m]`` (``(lo, hi)`` or a
    header's ``{"lo", "hi", ...}``) where given."""
    if isinstance(modules, str) or not isinstance(modules, Sequence):
        raise InputValueError(f"modules must be a sequence of module names, got {modules!r}")
    registered = {name: info.obj for name, info in plugins.schedules().items()}
    if not modules:
        raise InputValueError(f"modules must name at least one condition module; registered: {sorted(registered)}")
    dupes = sorted({m for m in modules if list(modules).count(m) > 1})
    if dupes:
        raise InputValueError(f"modules lists {dupes} more than once")
    unknown = [m for m in modules if m not in registered]
    if unknown:
        raise InputValueError(f"unknown condition module(s) {unknown}; registered schedules: {sorted(registered)}")
    if isinstance(cond_dim, bool) or not isinstance(cond_dim, int) or cond_dim <= 0:
        raise InputValueError(f"cond_dim must be a positive int, got {cond_dim!r}")
    endpoints = dict(endpoints or {})
    stray = sorted(set(endpoints) - set(modules))
    if stray:
        raise InputValueError(f"endpoints given for {stray}, which are not among modules {list(modules)}")
    schedules = {}
    for m in modules:
        lo_hi = endpoints.get(m)
        if lo_hi is None:
            schedules[m] = registered[m]
            continue
        pair = (lo_hi.get("lo"), lo_hi.get("hi")) if isinstance(lo_hi, Mapping) else lo_hi
        if len(pair) != 2:
            raise InputValueError(f"endpoints[{m!r}] must be (lo, hi), got {lo_hi!r}")
        schedules[m] = registered[m].with_endpoints(*pair)
    return schedules


def module_strengths(schedules: Mapping[str, StrengthSchedule], state: RuntimeState, camera: Camera | None,
                     ids: torch.Tensor, modules: Sequence[str], *, state_blind: bool,
                     anchor_positions: Callable[[], torch.Tensor], placement: Placement, dtype: torch.dtype,
                     skip_zero: bool, lens_frame: LensFrame | None = None) -> dict[str, torch.Tensor | float]:
    """Strength of each of ``modules`` for the anchors ``ids`` (``LongTensor[R]``) at ``state``: a float
    for a global schedule (left out where 0 and ``skip_zero``), ``[R]`` for a per-anchor one (their
    display positions: ``anchor_positions()`` ``[A, 3]`` seen by ``camera``, placed by ``placement``),
    ``[R, 2]`` for the lens in a ``"xy"`` ``lens_frame`` (:func:`lens_strength`); 1.0 for every module
    when ``state_blind``."""
    if not isinstance(state, RuntimeState):
        raise InputValueError(f"state must be a RuntimeState, got {type(state).__name__}")
    if state_blind:
        return {m: 1.0 for m in modules}
    screen = None
    out: dict[str, torch.Tensor | float] = {}
    for m in modules:
        schedule = schedules[m]
        if not schedule.per_anchor:
            lam = schedule.scalar_strength(float(schedule.control(state, None)))
            if lam != 0.0 or not skip_zero:
                out[m] = lam
            continue
        if screen is None:
            if not isinstance(camera, Camera):
                raise InputValueError(
                    f"module {m!r} needs each anchor's screen position: pass camera=Camera(...) "
                    f"(Camera.from_scaffold converts a Scaffold-GS camera), got {type(camera).__name__}"
                )
            positions = anchor_positions().detach()
            # the image placed on the display as the optics places it (p_v of the lens and foveation schedules)
            screen = to_display(camera.normalized_screen(positions.index_select(0, ids.to(positions.device))),
                                camera.height, camera.width, placement)
        # per-anchor strengths stay even where all zero (they add exact zeros): testing would sync the device
        if isinstance(schedule, LensSchedule) and lens_frame is not None:
            out[m] = lens_strength(schedule, lens_frame, state, screen, dtype, ids.device)
        else:
            out[m] = schedule.strength(state, screen, dtype=dtype, device=ids.device)
    return out


def lens_strength(schedule: LensSchedule, frame: LensFrame, state: RuntimeState, screen: torch.Tensor,
                  dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """The lens strength of display positions ``screen`` ``[R, 2]`` in ``frame``: ``[R]`` from the radius
    ``||p - axis||`` (``||p||`` itself for a centred lens), or ``[R, 2]`` ``(lambda_x, lambda_y)`` from the
    position in the lens's frame (``"xy"``: :meth:`LensFrame.lens_coords`, :meth:`LensSchedule.xy_strength`)."""
    if frame.mode == "xy":
        return schedule.xy_strength(frame.lens_coords(screen).to(dtype=dtype, device=device))
    if frame.axis != (0.0, 0.0):  # python scalars: no host-to-device copy
        screen = torch.stack([screen[:, 0] - frame.axis[0], screen[:, 1] - frame.axis[1]], -1)
    return schedule.strength(state, screen, dtype=dtype, device=device)

