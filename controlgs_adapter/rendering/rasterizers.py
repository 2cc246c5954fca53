"""Rasterizers: the last step of a render, splatting decoded 3D Gaussians into an image. Plug-ins.

This module holds the built-in rasterizers and the choice among the registered ones; the contract
(:class:`Rasterizer`, re-exported here) is :mod:`controlgs_adapter.rendering.rasterizer`, and the
built-ins register from :mod:`controlgs_adapter.rendering.builtin`.

Every family of the library decodes its anchors into Gaussians and calls :func:`rasterize_gaussians`,
which runs the rasterizer chosen for the tensors' device and dtype (:func:`select_rasterizer`):

* ``torch`` (built-in, the default and the reference): the pure-PyTorch EWA splatter of
  :mod:`controlgs_adapter.rendering.splatter`; any device, float32 or float64.
* ``gsplat`` (built-in, optional): gsplat's CUDA ``rasterization``; chosen on CUDA devices for
  float32 when ``gsplat`` imports (``pip install --no-deps gsplat``, docs/how-to/gpu.md). It follows
  the project's conventions where gsplat lets it (near plane, low-pass, the 0.99 alpha clamp);
  what remains different is documented in docs/reference/rasterizers.md.

Third-party rasterizers register through the hook ``controlgs_register_rasterizers`` (a list of
:class:`Rasterizer` instances); the automatic choice takes the first that can run the tensors,
plug-ins before built-ins. ``use_rasterizer(name)`` or ``CONTROLGS_RASTERIZER=name`` force one.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import importlib
import os
import re
from typing import Any, Iterator

import torch

from controlgs_adapter import plugins
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.rasterizer import Rasterizer
from controlgs_adapter.rendering.splatter import ALPHA_MAX, LOW_PASS, NEAR_PLANE, RasterOutput, rasterize
from controlgs_adapter.state import Camera

__all__ = ["Rasterizer", "TorchSplatter", "GsplatRasterizer", "rasterize_gaussians", "select_rasterizer",
           "use_rasterizer", "RASTERIZER_ENV", "gsplat_alpha_max"]

#: environment variable naming the rasterizer to use (``auto``, ``torch``, ``gsplat`` or a plug-in's)
RASTERIZER_ENV = "CONTROLGS_RASTERIZER"

_CHOICE: contextvars.ContextVar["str | Rasterizer | None"] = contextvars.ContextVar("controlgs_rasterizer", default=None)


class TorchSplatter(Rasterizer):
    """The pure-PyTorch EWA splatter (any device, float32/float64): the default and the reference."""

    name = "torch"

    def unavailable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        return None if dtype in (torch.float32, torch.float64) else f"needs float32 or float64, got {dtype}"

    def __call__(self, means, scales, rotations, opacities, colors, camera, background=None):  # noqa: D102
        return rasterize(means, scales, rotations, opacities, colors, camera, background)


@functools.lru_cache(maxsize=1)
def _import_gsplat() -> Any:
    """The ``gsplat`` module, or the ImportError's text (cached: imported at most once)."""
    try:
        return importlib.import_module("gsplat")
    except Exception as e:  # noqa: BLE001 - a broken install (missing CUDA build, ABI) is "not available"
        return f"gsplat does not import ({type(e).__name__}: {e}); install it with 'pip install --no-deps gsplat'"


def gsplat_alpha_max(version: str) -> float:
    """The per-splat alpha clamp of a gsplat release: 0.999 up to 1.5.x, 0.99 from 1.6 on."""
    m = re.match(r"(\d+)\.(\d+)", version)
    return 0.99 if m and (int(m.group(1)), int(m.group(2))) >= (1, 6) else 0.999


class GsplatRasterizer(Rasterizer):
    """gsplat's CUDA ``rasterization`` (float32 on CUDA, when gsplat is installed), called with the
    project's conventions: near plane 0.2, low-pass 0.3 px^2, alpha clamped at 0.99."""

    name = "gsplat"

    def unavailable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        if torch.device(device).type != "cuda":
            return f"runs on CUDA devices only, not {device}"
        if dtype != torch.float32:
            return f"needs float32, got {dtype}"
        mod = _import_gsplat()
        return mod if isinstance(mod, str) else None

    def __call__(self, means, scales, rotations, opacities, colors, camera, background=None):  # noqa: D102
        gsplat = _import_gsplat()
        if isinstance(gsplat, str):
            raise InputValueError(f"rasterizer 'gsplat': {gsplat}")
        n, dev, h, w = means.shape[0], means.device, camera.height, camera.width
        if n == 0:  # nothing to draw: the background, kept in the autograd graph as the torch splatter's is
            # (a training view whose Gaussians are all culled back-propagates zeros instead of raising
            # "element 0 of tensors does not require grad" at loss.backward())
            tie = torch.stack([t.sum() for t in (means, scales, rotations, opacities, colors)]).sum() * 0.0
            zero = means.new_zeros(1, h, w) + tie
            color = (means.new_zeros(3, h, w) if background is None else background.view(3, 1, 1).expand(3, h, w)) + tie
            return RasterOutput(color=color, alpha=zero, depth=zero.clone(), visible=torch.zeros(0, dtype=torch.bool, device=dev))
        if gsplat_alpha_max(getattr(gsplat, "__version__", "0")) > ALPHA_MAX:
            # the kernel clamps alpha at 0.999: cap the opacity at 0.99 so no splat exceeds the
            # project's 0.99 (exact for o <= 0.99); straight-through, so the gradient is unchanged
            opacities = opacities - (opacities - opacities.clamp(max=ALPHA_MAX)).detach()
        viewmat = camera.world_to_camera.to(device=dev, dtype=torch.float32).unsqueeze(0)  # [1, 4, 4]
        k = camera.intrinsics.to(device=dev, dtype=torch.float32).unsqueeze(0)  # [1, 3, 3]
        out, alpha, meta = gsplat.rasterization(
            means.contiguous(), rotations.contiguous(), scales.contiguous(), opacities.contiguous(), colors.contiguous(),
            viewmat, k, w, h, near_plane=NEAR_PLANE, eps2d=LOW_PASS, packed=False, render_mode="RGB+D",
            backgrounds=None if background is None else background.view(1, 3), rasterize_mode="classic",
        )  # out [1, H, W, 4] (colour + accumulated depth), alpha [1, H, W, 1]
        radii = meta["radii"].reshape(n, -1)  # [N, 2] (gsplat >= 1.5) or [N, 1]
        return RasterOutput(color=out[0, :, :, :3].permute(2, 0, 1), alpha=alpha[0].permute(2, 0, 1),
                            depth=out[0, :, :, 3:4].permute(2, 0, 1), visible=(radii > 0).all(dim=-1))


@contextlib.contextmanager
def use_rasterizer(rasterizer: "str | Rasterizer | None") -> Iterator[None]:
    """Render with ``rasterizer`` (a registered name, ``"auto"``, an instance, or None = the
    default) inside the block; an unsuitable one raises at the render that needs it."""
    token = _CHOICE.set(rasterizer)
    try:
        yield
    finally:
        _CHOICE.reset(token)


def select_rasterizer(device: torch.device | str, dtype: torch.dtype = torch.float32,
                      rasterizer: "str | Rasterizer | None" = None) -> Rasterizer:
    """The rasterizer for tensors of ``dtype`` on ``device``: ``rasterizer`` if given, else the one
    set by :func:`use_rasterizer`, else ``$CONTROLGS_RASTERIZER``, else ``"auto"`` (the first
    registered one that can run them: plug-ins, then gsplat, then torch).

    Raises:
        InputValueError: the named rasterizer is not registered or cannot run these tensors (why).
    """
    device = torch.device(device)
    choice = rasterizer if rasterizer is not None else _CHOICE.get()
    if choice is None:
        choice = os.environ.get(RASTERIZER_ENV, "") or "auto"
    if isinstance(choice, Rasterizer):
        chosen = choice
    else:
        registered = {name: info.obj for name, info in plugins.rasterizers().items()}
        if choice == "auto":
            reasons = []
            for r in registered.values():
                why = r.unavailable(device, dtype)
                if why is None:
                    return r
                reasons.append(f"{r.name}: {why}")
            raise InputValueError(f"no registered rasterizer can render {dtype} on {device}: " + "; ".join(reasons))
        if choice not in registered:
            raise InputValueError(f"rasterizer {choice!r} is not registered; registered: {sorted(registered)} (or 'auto')")
        chosen = registered[choice]
    why = chosen.unavailable(device, dtype)
    if why is not None:
        raise InputValueError(f"rasterizer {chosen.name!r} cannot render {dtype} on {device}: {why}")
    return chosen


def rasterize_gaussians(means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor, opacities: torch.Tensor,
                        colors: torch.Tensor, camera: Camera, background: torch.Tensor | None = None, *,
                        rasterizer: "str | Rasterizer | None" = None) -> Any:
    """Render Gaussians (shapes as :meth:`Rasterizer.__call__`) with :func:`select_rasterizer`'s
    choice for ``means``' device and dtype. Returns a ``RasterOutput``."""
    return select_rasterizer(means.device, means.dtype, rasterizer)(means, scales, rotations, opacities, colors,
                                                                    camera, background)
