"""Checks of a lens's PSF bank and its pre-warp shared by the optics tests: the inner part of an image, the
largest step between adjacent pixels beyond the local trend (seams), and where each primary of a dot
lands through a pipeline (the pre-warp accuracy)."""

from __future__ import annotations

import torch

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.color import linear_to_srgb, rgb_to_primaries, srgb_to_linear
from controlgs_adapter.downstream.pipeline import Pipeline

D = torch.float64
STATE = RuntimeState()
#: dot positions (image-normalised): the centre, the corners at 0.85 and points between
FIELD = [(0.0, 0.0), (0.85, 0.85), (-0.85, -0.85), (0.85, -0.85), (-0.85, 0.0), (0.0, 0.85), (0.5, 0.5)]
#: every point of a 0.1 grid over [-0.8, 0.8]^2, and the corners of FIELD
GRID_FIELD = [(round(0.1 * i, 1), round(0.1 * j, 1)) for j in range(-8, 9) for i in range(-8, 9)] + FIELD[1:4]


def inner(o: torch.Tensor, frac: float = 0.9) -> torch.Tensor:
    """The central ``frac`` of the last two axes."""
    H, W = o.shape[-2:]
    a, b = round(H * (1 - frac) / 2), round(W * (1 - frac) / 2)
    return o[..., a:H - a, b:W - b]


def steps(o: torch.Tensor) -> float:
    """Largest step between adjacent pixels beyond the local linear trend (first difference minus
    the mean of its two neighbours), both axes."""
    dx, dy = o[..., :, 1:] - o[..., :, :-1], o[..., 1:, :] - o[..., :-1, :]
    sx = dx[..., 1:-1] - 0.5 * (dx[..., 2:] + dx[..., :-2])
    sy = dy[..., 1:-1, :] - 0.5 * (dy[..., 2:, :] + dy[..., :-2, :])
    return max(sx.abs().max().item(), sy.abs().max().item())


def gaussian_dot_errors(pipe: Pipeline, size: tuple[int, int], field=FIELD) -> torch.Tensor:
    """``[dots, 3]`` distance (px) of each primary's eye centroid from the centre of a Gaussian dot
    (sigma 1 px) rendered at each ``field`` point, through the whole pipeline (sRGB in and out)."""
    h, w = size
    yy, xx = torch.meshgrid(torch.arange(h, dtype=D) + 0.5, torch.arange(w, dtype=D) + 0.5, indexing="ij")
    centres = [((u + 1) / 2 * w, (v + 1) / 2 * h) for u, v in field]
    dots = torch.stack([0.5 * torch.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 2).expand(3, h, w) for cx, cy in centres])
    with torch.no_grad():
        prim = torch.cat([rgb_to_primaries(srgb_to_linear(pipe(linear_to_srgb(chunk), STATE)))   # [dots, 3, H, W]
                          for chunk in dots.split(64)])
    r = max(6, min(h, w) // 8)
    errs = []
    for k, (cx, cy) in enumerate(centres):
        m = prim[k] * (((xx - cx).abs() < r) & ((yy - cy).abs() < r))
        s = m.sum((1, 2))
        errs.append(torch.hypot((m * xx).sum((1, 2)) / s - cx, (m * yy).sum((1, 2)) / s - cy))
    return torch.stack(errs)
