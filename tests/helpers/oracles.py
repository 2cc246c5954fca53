"""Brute-force reference implementations written from the published definitions, for tests to compare
the library's vectorised code against."""

from __future__ import annotations

import math
from typing import Any

import torch


def ssim_brute_force(x: Any, y: Any, *, data_range: float = 1.0, size: int = 11, sigma: float = 1.5) -> float:
    """SSIM of two ``[C, H, W]`` images (tensors or arrays) in float64, by Wang et al.'s definition: at
    every valid ``size`` x ``size`` window position, Gaussian weights g(u) g(v) with
    g(r) = exp(-r^2 / 2 sigma^2) normalised, local means, variances and covariance, c1 = (0.01 L)^2 and
    c2 = (0.03 L)^2 with L = ``data_range``; the mean over channels and positions."""
    x, y = torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(y, dtype=torch.float64)
    r = [i - (size - 1) / 2 for i in range(size)]
    g = [math.exp(-t * t / (2 * sigma * sigma)) for t in r]
    w = torch.tensor([[a * b for b in g] for a in g], dtype=torch.float64) / sum(g) ** 2
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    values = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - size + 1):
            for j in range(x.shape[2] - size + 1):
                a, b = x[c, i:i + size, j:j + size], y[c, i:i + size, j:j + size]
                ma, mb = float((w * a).sum()), float((w * b).sum())
                va, vb = float((w * (a - ma) ** 2).sum()), float((w * (b - mb) ** 2).sum())
                cov = float((w * (a - ma) * (b - mb)).sum())
                values.append((2 * ma * mb + c1) * (2 * cov + c2) / ((ma * ma + mb * mb + c1) * (va + vb + c2)))
    return sum(values) / len(values)
