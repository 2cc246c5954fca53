"""Image-quality metrics in plain torch (differentiable): PSNR and SSIM.

SSIM follows Wang et al. 2004 as 3DGS and pytorch-msssim use it: an 11-tap Gaussian window with
sigma 1.5 (separable, normalised), constants ``C1 = (0.01 L)^2``, ``C2 = (0.03 L)^2``, population
(co)variances, per-channel maps averaged over the valid window positions (no padding) and the
channels. ``data_range`` L is always explicit. Optional perceptual metrics (FLIP, ColorVideoVDP)
are in :func:`optional_metrics` and run only when their packages are installed.
"""

from __future__ import annotations

from typing import Callable

import torch
import torch.nn.functional as F

from .checks import check_image
from .errors import InputValueError, ShapeError

__all__ = ["psnr", "ssim", "gaussian_window", "check_image_pair", "optional_metrics"]


def check_image_pair(x: torch.Tensor, y: torch.Tensor) -> None:
    check_image("x", x)
    check_image("y", y)
    if x.shape != y.shape:
        raise ShapeError(f"x and y must have the same shape, got {list(x.shape)} and {list(y.shape)}")


def psnr(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB of each image: ``x, y`` ``[..., 3, H, W]`` -> ``[...]``
    (``+inf`` for identical images)."""
    check_image_pair(x, y)
    mse = (x - y).square().mean(dim=(-3, -2, -1))
    return 10.0 * torch.log10(data_range**2 / mse)


def gaussian_window(size: int = 11, sigma: float = 1.5, *, dtype: torch.dtype = torch.float32,
                    device: torch.device | str | None = None) -> torch.Tensor:
    """Normalised 1-D Gaussian ``[size]`` sampled at integer offsets about the centre."""
    if size < 1 or size % 2 == 0:
        raise InputValueError(f"window size must be odd and >= 1, got {size!r}")
    r = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(r**2) / (2.0 * sigma**2))
    return g / g.sum()


def ssim(x: torch.Tensor, y: torch.Tensor, *, data_range: float = 1.0, window_size: int = 11,
         sigma: float = 1.5) -> torch.Tensor:
    """Structural similarity of each image: ``x, y`` ``[..., 3, H, W]`` -> ``[...]``.

    Needs ``H, W >= window_size`` (valid window positions only)."""
    check_image_pair(x, y)
    h, w = x.shape[-2:]
    if h < window_size or w < window_size:
        raise ShapeError(f"ssim needs images of at least {window_size}x{window_size} pixels (window size), got {h}x{w}")
    lead, c = x.shape[:-3], x.shape[-3]
    g = gaussian_window(window_size, sigma, dtype=x.dtype, device=x.device)
    gh = g.view(1, 1, 1, -1).expand(c, 1, 1, window_size)
    gv = g.view(1, 1, -1, 1).expand(c, 1, window_size, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(t, gh, groups=c), gv, groups=c)

    xs = x.reshape(-1, c, h, w)
    ys = y.reshape(-1, c, h, w)
    mu_x, mu_y = blur(xs), blur(ys)
    sxx = blur(xs * xs) - mu_x**2
    syy = blur(ys * ys) - mu_y**2
    sxy = blur(xs * ys) - mu_x * mu_y
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    smap = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return smap.mean(dim=(-3, -2, -1)).reshape(lead)


def optional_metrics() -> dict[str, Callable[[torch.Tensor, torch.Tensor], float]]:
    """Perceptual metrics whose packages are installed, as ``{name: f(eye, gt) -> float}`` on one
    sRGB image pair ``[3, H, W]`` in [0, 1]: ``"flip"`` (LDR-FLIP, lower is better; package
    ``flip-evaluator``) and ``"cvvdp"`` (ColorVideoVDP JOD, higher is better; package ``cvvdp``,
    installed with ``--no-deps`` so that it keeps the CPU torch, see docs/demo.md). Empty when
    neither is installed: nothing is ever downloaded."""
    found: dict[str, Callable[[torch.Tensor, torch.Tensor], float]] = {}
    try:
        import flip_evaluator  # type: ignore[import-not-found]
    except ImportError:
        pass
    else:
        def flip(eye: torch.Tensor, gt: torch.Tensor) -> float:
            check_image_pair(eye, gt)
            a = gt.detach().clamp(0, 1).permute(1, 2, 0).double().cpu().numpy().copy()
            b = eye.detach().clamp(0, 1).permute(1, 2, 0).double().cpu().numpy().copy()
            return float(flip_evaluator.evaluate(a, b, "LDR")[1])

        found["flip"] = flip
    try:
        import pycvvdp  # type: ignore[import-not-found]
    except ImportError:
        pass
    else:
        metric = pycvvdp.cvvdp(display_name="standard_4k", device=torch.device("cpu"), quiet=True)

        def cvvdp(eye: torch.Tensor, gt: torch.Tensor) -> float:
            check_image_pair(eye, gt)
            jod, _ = metric.predict(eye.detach().clamp(0, 1).permute(1, 2, 0).float().cpu(),
                                    gt.detach().clamp(0, 1).permute(1, 2, 0).float().cpu(), dim_order="HWC")
            return float(jod)

        found["cvvdp"] = cvvdp
    return found
