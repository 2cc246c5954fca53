"""The rasterizer contract: the last step of a render, splatting decoded 3D Gaussians into an image.

A rasterizer plug-in subclasses :class:`Rasterizer` and is returned (an instance) from the hook
``controlgs_register_rasterizers``; :mod:`controlgs_adapter.rendering.rasterizers` holds the
built-in ones and chooses among the registered ones. Imports no registry and registers nothing.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch

from controlgs_adapter.state import Camera

__all__ = ["Rasterizer"]


class Rasterizer:
    """Base class of rasterizer plug-ins: set :attr:`name`, implement :meth:`unavailable` and
    :meth:`__call__` with the conventions of :func:`controlgs_adapter.rendering.splatter.rasterize`
    (OpenCV camera, pixel centres at +0.5, quaternions ``(w, x, y, z)``, linear scales)."""

    name: ClassVar[str] = ""

    def unavailable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        """None if this rasterizer can render tensors of ``dtype`` on ``device``, else why not (one line)."""
        raise NotImplementedError

    def __call__(self, means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor, opacities: torch.Tensor,
                 colors: torch.Tensor, camera: Camera, background: torch.Tensor | None = None) -> Any:
        """Render ``N`` Gaussians: means ``[N, 3]`` (world), scales ``[N, 3]`` (linear std-devs),
        rotations ``[N, 4]`` ``(w, x, y, z)``, opacities ``[N]`` in [0, 1], colors ``[N, 3]``,
        background ``[3]`` or None (black). Returns a
        :class:`~controlgs_adapter.rendering.splatter.RasterOutput` (color ``[3, H, W]``, alpha and
        depth ``[1, H, W]``, visible ``[N]`` bool)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
