# mypy: disable-error-code="empty-body"
# (a hook specification is a signature only: pluggy never calls its body)
"""Hook specifications. Built-ins implement them exactly as third-party plug-ins do
(``@hookimpl(trylast=True)``), so a plug-in can add to or override any of them.

A plug-in is a module or object with functions marked ``@controlgs_adapter.hookimpl``; install it
through the entry-point group ``controlgs_adapter`` or call
``controlgs_adapter.plugins.register_plugin(obj)`` at run time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import pluggy

if TYPE_CHECKING:  # pragma: no cover
    from .backend import Backend
    from controlgs_adapter.rendering.rasterizer import Rasterizer
    from .schedules import StrengthSchedule
    from controlgs_adapter.downstream.stage import Stage

PROJECT = "controlgs_adapter"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)


@hookspec
def controlgs_register_backends() -> "list[Backend]":
    """Return backend instances that recognise and adapt model families.

    ``ControlGS.wrap`` asks backends in call order (third-party plug-ins before built-ins) and takes
    the first whose ``matches(model)`` is true.

    :return: a list of :class:`controlgs_adapter.backend.Backend` instances.
    """


@hookspec
def controlgs_register_stages() -> "list[type[Stage]]":
    """Return downstream stage classes (subclasses of
    :class:`controlgs_adapter.downstream.stage.Stage`). A stage's ``name`` must be unique; a
    plug-in stage with the name of a built-in replaces it (with a warning).

    :return: a list of Stage subclasses.
    """


@hookspec
def controlgs_register_schedules() -> "list[StrengthSchedule]":
    """Return strength schedules (one per condition module name: ``lens``, ``resample``, ...).

    :return: a list of :class:`controlgs_adapter.schedules.StrengthSchedule` instances.
    """


@hookspec
def controlgs_register_rasterizers() -> "list[Rasterizer]":
    """Return rasterizers: what splats decoded Gaussians into an image (names unique; a plug-in's
    rasterizer with a built-in's name replaces it, with a warning).

    ``rasterize_gaussians`` takes the first (plug-ins before built-ins) whose
    ``unavailable(device, dtype)`` is None, unless one is named (``use_rasterizer``,
    ``CONTROLGS_RASTERIZER``).

    :return: a list of :class:`controlgs_adapter.rendering.rasterizer.Rasterizer` instances.
    """
