"""Photographic textures of the built-in scene: scikit-image's bundled data images.

All seven ship inside the scikit-image wheel (no download) and are public domain or CC0 (see
``docs/reference/builtin-scene.md`` and :data:`TEXTURES`). The three grey-level ones get a fixed colour tint so the
diorama has colour everywhere.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from ..errors import InputValueError

__all__ = ["TextureInfo", "TEXTURES", "load_texture", "mip_pyramid"]


@dataclass(frozen=True)
class TextureInfo:
    """Where a texture comes from and under which licence (as stated in ``skimage.data``'s docstring).

    Attributes:
        name: function name in ``skimage.data``.
        licence: licence as stated by scikit-image.
        source: original source named by scikit-image.
        tint: sRGB multiplier applied to a grey-level image (None for colour photographs).
    """

    name: str
    licence: str
    source: str
    tint: tuple[float, float, float] | None = None


TEXTURES: dict[str, TextureInfo] = {
    "astronaut": TextureInfo("astronaut", "public domain (no known copyright restrictions)", "NASA Great Images database"),
    "coffee": TextureInfo("coffee", "CC0 (photographer Rachel Michetti)", "Pikolo Espresso Bar"),
    "chelsea": TextureInfo("chelsea", "CC0 (photographer Stefan van der Walt)", "Stefan van der Walt"),
    "rocket": TextureInfo("rocket", "public domain (released by SpaceX)", "SpaceX Photos on Flickr"),
    "brick": TextureInfo("brick", "CC0", "CC0Textures (Bricks25)", tint=(0.92, 0.55, 0.42)),
    "grass": TextureInfo("grass", "CC0", "DeviantArt, linolafett (Grass 01)", tint=(0.55, 0.85, 0.35)),
    "gravel": TextureInfo("gravel", "CC0", "CC0Textures (Gravel04)", tint=(0.85, 0.80, 0.70)),
}


def load_texture(name: str) -> torch.Tensor:
    """The texture ``name`` as sRGB float64 ``[3, H, W]`` in [0, 1] (row 0 = top of the photograph)."""
    if name not in TEXTURES:
        raise InputValueError(f"texture must be one of {sorted(TEXTURES)}, got {name!r}")
    return _decoded(name).clone()


@lru_cache(maxsize=None)
def _decoded(name: str) -> torch.Tensor:
    try:
        import skimage.data
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "the built-in scene needs scikit-image for its photographs: pip install 'controlgs-adapter[demo]'"
        ) from e
    info = TEXTURES[name]
    img = np.asarray(getattr(skimage.data, name)(), dtype=np.float64) / 255.0
    if img.ndim == 2:
        img = img[..., None] * np.asarray(info.tint, dtype=np.float64)
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))


def mip_pyramid(texture: torch.Tensor) -> list[torch.Tensor]:
    """Mip levels of ``texture`` ``[3, H, W]``: level l is level l-1 resized to ``ceil(size / 2)``
    with an anti-aliased (triangle) filter over the same extent, down to 1 x 1."""
    levels = [texture]
    while max(levels[-1].shape[-2:]) > 1:
        h, w = levels[-1].shape[-2:]
        size = ((h + 1) // 2, (w + 1) // 2)
        levels.append(torch.nn.functional.interpolate(
            levels[-1].unsqueeze(0), size=size, mode="bilinear", antialias=True, align_corners=False).squeeze(0))
    return levels
