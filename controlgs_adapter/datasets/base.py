"""Posed images: what a dataparser reads (:class:`Frame`, :class:`SceneData`) and what training and
evaluation consume (:class:`PosedImages`, cameras and lazily loaded images at a working resolution).

Conventions (docs/reference/conventions.md): cameras are pinhole with OpenCV axes (x right, y down, z forward),
world-to-camera ``[4, 4]``, intrinsics in pixels with pixel centres at ``i + 0.5``. Images are sRGB
``[3, H, W]`` float32 in [0, 1]. A frame's camera holds at the full size of its image file; a
:class:`PosedImages` rescales both to the working resolution (area downscale, intrinsics scaled
exactly), so a full-resolution image is decoded only on a cache miss and never kept.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import torch
import torch.nn.functional as F

from ..checks import check_number
from ..errors import InputValueError
from ..state import Camera
from .images import load_frame_image

__all__ = ["Frame", "SceneData", "PosedImages", "DEFAULT_CACHE_BYTES", "working_size", "area_resize"]

#: default budget of the decoded-image cache of a :class:`PosedImages` (bytes)
DEFAULT_CACHE_BYTES = 1 << 30


@dataclass(frozen=True)
class Frame:
    """One posed image as a dataparser found it.

    Attributes:
        name: the image's name (relative path as the dataset lists it); unique in a scene.
        camera: pinhole camera at the full size of the image (after undistortion, if any).
        source: the image file, or an in-memory sRGB ``[3 | 4, H, W]`` float tensor at the camera's size.
        distortion: OpenCV radial-tangential coefficients ``(k1, k2, p1, p2, k3)`` of the original
            capture; the image is undistorted to ``camera`` on load. None: already pinhole.
    """

    name: str
    camera: Camera
    source: Path | torch.Tensor
    distortion: tuple[float, float, float, float, float] | None = None


@dataclass
class SceneData:
    """A parsed dataset: its frames by split, optional SfM points and the render background.

    Attributes:
        splits: ``{"train": [Frame], "test": [Frame]}``.
        points: ``[P, 3]`` float32 world points (COLMAP's ``points3D``) or None.
        background: ``[3]`` sRGB colour that RGBA images are composited over (the model's background).
        source: what was read (a path or a description), for messages and report headers.
        format: the dataparser's name (``"colmap"``, ``"blender"``, ``"instant_ngp"``, ``"builtin"``).
    """

    splits: dict[str, list[Frame]]
    points: torch.Tensor | None = None
    background: torch.Tensor = field(default_factory=lambda: torch.zeros(3))
    source: str = ""
    format: str = ""

    def views(self, split: str, *, resolution: int | None = None, factor: float | None = None,
              cache_bytes: int = DEFAULT_CACHE_BYTES, first: int | None = None) -> "PosedImages":
        """The frames of ``split`` (only its first ``first``, at least 1, when given) at a working
        resolution: ``resolution`` = longer side in pixels, or ``factor`` = downscale factor (neither:
        full size). Raises if the split is empty."""
        if split not in self.splits:
            raise InputValueError(f"{self.source or 'dataset'}: no split {split!r} (splits: {sorted(self.splits)})")
        frames = self.splits[split] if first is None else \
            self.splits[split][:max(1, int(check_number("first", first, integer=True)))]
        if not frames:
            raise InputValueError(f"{self.source or 'dataset'}: the {split!r} split is empty")
        return PosedImages(frames, resolution=resolution, factor=factor, background=self.background,
                           cache_bytes=cache_bytes, name=f"{self.source}:{split}")


def working_size(width: int, height: int, *, resolution: int | None = None, factor: float | None = None) -> tuple[int, int]:
    """``(w, h)`` of a ``width x height`` image brought to ``resolution`` (longer side, pixels) or
    divided by ``factor``; never upscaled; at least 1 pixel."""
    if resolution is not None and factor is not None:
        raise InputValueError(f"give resolution or factor, not both (got {resolution!r} and {factor!r})")
    if resolution is not None:
        if isinstance(resolution, bool) or not isinstance(resolution, int) or resolution < 2:
            raise InputValueError(f"resolution must be an int >= 2 (longer side in pixels), got {resolution!r}")
        f = max(1.0, max(width, height) / resolution)
    elif factor is not None:
        if isinstance(factor, bool) or not isinstance(factor, (int, float)) or not math.isfinite(factor) or factor < 1:
            raise InputValueError(f"factor must be a finite number >= 1, got {factor!r}")
        f = float(factor)
    else:
        f = 1.0
    return max(1, round(width / f)), max(1, round(height / f))


def area_resize(image: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Downscale ``[C, H, W]`` to ``[C, height, width]`` by area averaging (exact box filter for
    integer factors; ``antialias`` bilinear otherwise). Returns the input if the size already matches."""
    if tuple(image.shape[-2:]) == (height, width):
        return image
    h, w = image.shape[-2:]
    if h % height == 0 and w % width == 0 and h // height == w // width:
        return F.avg_pool2d(image[None], h // height)[0]
    return F.interpolate(image[None], size=(height, width), mode="bilinear", antialias=True, align_corners=False)[0]


class PosedImages(Sequence[tuple[Camera, torch.Tensor]]):
    """Cameras and sRGB images of a list of frames at one working resolution, images loaded lazily.

    ``views[i]`` is ``(camera, image [3, h, w])``; cameras are rescaled from the frame's full size
    (per frame: sizes may differ). Decoded images stay in an LRU cache of at most ``cache_bytes``;
    a frame's full-resolution decode is dropped as soon as it is downscaled.

    Args:
        frames: the frames (see :class:`Frame`).
        resolution / factor: working size (:func:`working_size`).
        background: ``[3]`` colour RGBA images are composited over.
        cache_bytes: budget of the decoded-image cache (0: no cache).
        name: for messages.
    """

    def __init__(self, frames: Sequence[Frame], *, resolution: int | None = None, factor: float | None = None,
                 background: torch.Tensor | None = None, cache_bytes: int = DEFAULT_CACHE_BYTES, name: str = "views") -> None:
        if not frames:
            raise InputValueError(f"{name}: no frames")
        if isinstance(cache_bytes, bool) or not isinstance(cache_bytes, int) or cache_bytes < 0:
            raise InputValueError(f"cache_bytes must be an int >= 0, got {cache_bytes!r}")
        self.frames = list(frames)
        self.name = name
        self.background = torch.zeros(3) if background is None else background.detach().float().cpu()
        self.cache_bytes = cache_bytes
        self._cache: OrderedDict[int, torch.Tensor] = OrderedDict()
        self._cached_bytes = 0
        self.cameras: list[Camera] = []
        for f in self.frames:
            w, h = working_size(f.camera.width, f.camera.height, resolution=resolution, factor=factor)
            self.cameras.append(f.camera if (w, h) == (f.camera.width, f.camera.height) else _resized(f.camera, w, h))

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> tuple[Camera, torch.Tensor]:  # type: ignore[override]
        return self.cameras[i], self.image(i)

    def __iter__(self) -> Iterator[tuple[Camera, torch.Tensor]]:
        for i in range(len(self)):
            yield self[i]

    def camera(self, i: int) -> Camera:
        """Camera of view ``i`` at the working resolution."""
        return self.cameras[i]

    def image(self, i: int) -> torch.Tensor:
        """sRGB ``[3, h, w]`` float32 of view ``i`` at the working resolution (cached)."""
        i = range(len(self))[i]  # IndexError for a bad index, negative indices allowed
        hit = self._cache.get(i)
        if hit is not None:
            self._cache.move_to_end(i)
            return hit
        cam = self.cameras[i]
        img = area_resize(load_frame_image(self.frames[i], self.background), cam.height, cam.width).contiguous()
        size = img.numel() * img.element_size()
        if size <= self.cache_bytes:
            while self._cached_bytes + size > self.cache_bytes:
                _, old = self._cache.popitem(last=False)
                self._cached_bytes -= old.numel() * old.element_size()
            self._cache[i] = img
            self._cached_bytes += size
        return img

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """``(h, w)`` of every view at the working resolution."""
        return [(c.height, c.width) for c in self.cameras]

    def fingerprint(self) -> str:
        """Hash of the frame names, sizes and cameras (not the pixels): identifies the data a
        checkpoint was trained on."""
        h = hashlib.sha256()
        for f, c in zip(self.frames, self.cameras):
            h.update(f.name.encode())
            h.update(f"{c.width}x{c.height}".encode())
            h.update(c.world_to_camera.double().numpy().round(6).tobytes())
            h.update(c.intrinsics.double().numpy().round(4).tobytes())
        return h.hexdigest()[:16]

    def describe(self) -> dict[str, Any]:
        """JSON-able summary: number of views and their distinct sizes."""
        return {"views": len(self), "sizes": sorted({f"{w}x{h}" for h, w in self.sizes})}


def _resized(camera: Camera, width: int, height: int) -> Camera:
    """``camera`` at ``width x height``: fx, cx scale by ``width / W``, fy, cy by ``height / H``
    (exact under the pixel-centre convention)."""
    k = camera.intrinsics.clone()
    k[0] *= width / camera.width
    k[1] *= height / camera.height
    return Camera(camera.world_to_camera, k, width, height, dict(camera.extra))
