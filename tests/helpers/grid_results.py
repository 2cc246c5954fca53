"""A small evaluation result with known numbers: a 2 x 2 run-time grid (d in {1, 2}, rho in {0, 0.5}) of
two views per cell, for the tests of :class:`~controlgs_adapter.evaluation.GridResult` and the report."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import torch

from controlgs_adapter.evaluation import IDEAL, GridResult

DOWNSAMPLE, POWER_SAVING = (1.0, 2.0), (0.0, 0.5)

#: [d, rho] grids of each method (the mean over the two views, which are the grid -/+ 1 dB)
PSNR = {"no_ss": [[20, 21], [17, 15]], "ss": [[20, 22], [18, 16]], "controlgs": [[21, 21], [19, 18]],
        IDEAL: [[25, 20], [22, 15]], "wo_lens": [[18.75] * 2] * 2, "wo_display": [[19.25] * 2] * 2}

#: [d, rho] grids of each method (the mean over the two views, which are the grid -/+ 0.01)
FLIP = {"no_ss": [[0.3] * 2] * 2, "ss": [[0.2] * 2] * 2, "controlgs": [[0.1, 0.25], [0.15, 0.1]],
        IDEAL: [[0.05] * 2] * 2, "wo_lens": [[0.18] * 2] * 2, "wo_display": [[0.22] * 2] * 2}


def two_views(grid: list[list[float]], spread: float) -> torch.Tensor:
    """``[d, rho, 2]``: the grid minus and plus ``spread`` (float64)."""
    g = torch.tensor(grid, dtype=torch.float64)
    return torch.stack([g - spread, g + spread], dim=-1)


def grid_result(methods: Iterable[str] = tuple(PSNR), offset: float = 0.0,
                info: Mapping[str, Any] | None = None) -> GridResult:
    """PSNR (``offset`` added) and FLIP of ``methods`` on the 2 x 2 grid."""
    per_view = {m: {"psnr": two_views(PSNR[m], 1.0) + offset, "flip": two_views(FLIP[m], 0.01)} for m in methods}
    return GridResult(DOWNSAMPLE, POWER_SAVING, per_view, info=dict(info or {}))
