"""Reading a frame's image: decode (Pillow), check its size against the camera, composite RGBA over
the background, undistort to the pinhole camera."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..errors import FileFormatError, InputValueError
from .base import Frame

__all__ = ["read_image", "image_size", "load_frame_image"]


def read_image(path: str | Path) -> torch.Tensor:
    """Decode an image file to float32 ``[C, H, W]`` in [0, 1] (C = 3, or 4 with alpha; 8- and
    16-bit PNG, JPEG, ...). Raises :class:`FileFormatError` naming the file."""
    from PIL import Image, UnidentifiedImageError

    p = Path(path)
    if not p.is_file():
        raise FileFormatError(f"{p}: image file not found")
    try:
        with Image.open(p) as im:
            mode = im.mode
            if mode in ("I;16", "I;16B", "I;16L", "I"):
                arr = np.asarray(im, dtype=np.float32) / 65535.0
                arr = arr[..., None].repeat(3, axis=-1)
            else:
                im = im.convert("RGBA" if ("A" in mode or "transparency" in im.info) else "RGB")
                arr = np.asarray(im, dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise FileFormatError(f"{p}: cannot decode the image ({e})") from None
    return torch.from_numpy(np.ascontiguousarray(arr.transpose(2, 0, 1)))


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file from its header (no decoding)."""
    from PIL import Image, UnidentifiedImageError

    p = Path(path)
    if not p.is_file():
        raise FileFormatError(f"{p}: image file not found")
    try:
        with Image.open(p) as im:
            return int(im.width), int(im.height)
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise FileFormatError(f"{p}: cannot read the image header ({e})") from None


def load_frame_image(frame: Frame, background: torch.Tensor) -> torch.Tensor:
    """sRGB ``[3, H, W]`` float32 of ``frame`` at its camera's full size: RGBA composited over
    ``background`` ``[3]`` (``rgb * a + bg * (1 - a)``)."""
    img = read_image(frame.source) if isinstance(frame.source, Path) else frame.source.float()
    cam = frame.camera
    if img.dim() != 3 or img.shape[0] not in (3, 4):
        raise InputValueError(f"{frame.name}: image must be [3 | 4, H, W], got {list(img.shape)}")
    if tuple(img.shape[-2:]) != (cam.height, cam.width):
        raise FileFormatError(f"{frame.source if isinstance(frame.source, Path) else frame.name}: image is "
                              f"{img.shape[-1]}x{img.shape[-2]}, its camera is {cam.width}x{cam.height}")
    if img.shape[0] == 4:
        a = img[3:]
        img = img[:3] * a + background.to(img).view(3, 1, 1) * (1.0 - a)
    return img
