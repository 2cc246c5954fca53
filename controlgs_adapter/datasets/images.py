"""Reading a frame's image: decode (Pillow), check its size against the camera, composite RGBA over
the background, undistort to the pinhole camera.

Distortion is OpenCV's radial-tangential model on normalised image coordinates ``(x, y)``, with
``r^2 = x^2 + y^2``: ``x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)`` and
``y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y`` (COLMAP's SIMPLE_RADIAL,
RADIAL and OPENCV models are special cases)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import FileFormatError, InputValueError
from ..state import Camera

if TYPE_CHECKING:  # pragma: no cover - base imports this module; a frame is only read here
    from .base import Frame

__all__ = ["read_image", "image_size", "load_frame_image", "distort_normalized", "undistort", "undistort_points"]


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
    ``background`` ``[3]`` (``rgb * a + bg * (1 - a)``), then undistorted to the pinhole camera if the
    frame has ``distortion`` (:func:`undistort`)."""
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
    if frame.distortion is not None:
        img = undistort(img, cam, frame.distortion)
    return img


def _coefficients(distortion: Sequence[float]) -> tuple[float, float, float, float, float]:
    """``distortion`` checked: 4 or 5 finite OpenCV coefficients ``(k1, k2, p1, p2[, k3])``."""
    try:
        d = [float(v) for v in distortion]
    except (TypeError, ValueError):
        raise InputValueError(f"distortion must be (k1, k2, p1, p2[, k3]), got {distortion!r}") from None
    if len(d) not in (4, 5) or not all(math.isfinite(v) for v in d):
        raise InputValueError(f"distortion must be 4 or 5 finite values (k1, k2, p1, p2[, k3]), got {distortion!r}")
    k1, k2, p1, p2, k3 = d + [0.0] * (5 - len(d))
    return k1, k2, p1, p2, k3


def distort_normalized(xy: torch.Tensor, distortion: Sequence[float]) -> torch.Tensor:
    """Apply OpenCV's radial-tangential model to normalised coordinates ``[..., 2]`` (same shape out)."""
    k1, k2, p1, p2, k3 = _coefficients(distortion)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def undistort(image: torch.Tensor, camera: Camera, distortion: Sequence[float]) -> torch.Tensor:
    """Resample a distorted capture ``[C, H, W]`` to the pinhole ``camera`` (same K and size).

    Each output pixel centre ``(j + 0.5, i + 0.5)`` is normalised with K, distorted
    (:func:`distort_normalized`), mapped back to pixels with the same K and sampled bilinearly
    (``grid_sample``, ``align_corners=False``: pixel centres at ``i + 0.5``). Samples that fall
    outside the capture are 0, as OpenCV's ``cv2.undistort``. Returns a floating ``[C, H, W]``.
    """
    if image.dim() != 3 or not image.is_floating_point():
        raise InputValueError(f"image must be a floating [C, H, W] tensor, got {image.dtype} {list(image.shape)}")
    h, w = image.shape[-2:]
    if (w, h) != (camera.width, camera.height):
        raise InputValueError(f"image is {w}x{h}, its camera is {camera.width}x{camera.height}")
    k = camera.intrinsics.to(device=image.device, dtype=torch.float64)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    ys = (torch.arange(h, dtype=torch.float64, device=image.device) + 0.5 - cy) / fy
    xs = (torch.arange(w, dtype=torch.float64, device=image.device) + 0.5 - cx) / fx
    xy = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=-1)  # [H, W, 2]
    d = distort_normalized(xy, distortion)
    grid = torch.stack([(fx * d[..., 0] + cx) * (2.0 / w) - 1.0, (fy * d[..., 1] + cy) * (2.0 / h) - 1.0], dim=-1)
    return F.grid_sample(image[None], grid[None].to(image.dtype), mode="bilinear", padding_mode="zeros",
                         align_corners=False)[0]


def undistort_points(uv: torch.Tensor, intrinsics: torch.Tensor, distortion: Sequence[float],
                     iterations: int = 20) -> torch.Tensor:
    """Pixel positions ``[N, 2]`` in a distorted capture -> their positions ``[N, 2]`` in the pinhole
    image with the same ``intrinsics`` ``[3, 3]`` (inverse of the model by Newton's method, float64
    inside; converges wherever the model is monotonic, i.e. inside any sensible field of view)."""
    if uv.dim() != 2 or uv.shape[-1] != 2:
        raise InputValueError(f"uv must be [N, 2], got {list(uv.shape)}")
    k1, k2, p1, p2, k3 = _coefficients(distortion)
    k = intrinsics.to(device=uv.device, dtype=torch.float64)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    target = torch.stack([(uv[:, 0].double() - cx) / fx, (uv[:, 1].double() - cy) / fy], dim=-1)
    xy = target.clone()
    for _ in range(iterations):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        d_radial = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d radial / d r^2
        res = distort_normalized(xy, (k1, k2, p1, p2, k3)) - target
        j00 = radial + 2.0 * x * x * d_radial + 2.0 * p1 * y + 6.0 * p2 * x
        j01 = 2.0 * x * y * d_radial + 2.0 * p1 * x + 2.0 * p2 * y
        j11 = radial + 2.0 * y * y * d_radial + 6.0 * p1 * y + 2.0 * p2 * x
        det = j00 * j11 - j01 * j01  # the Jacobian is symmetric
        step = torch.stack([j11 * res[:, 0] - j01 * res[:, 1], j00 * res[:, 1] - j01 * res[:, 0]], dim=-1)
        xy = xy - step / det[:, None]
    return torch.stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy], dim=-1).to(uv.dtype)
