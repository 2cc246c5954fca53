"""A display pre-warp table with a known closed form, for the tests of display LUT maps."""

from __future__ import annotations

import torch

from controlgs_adapter.downstream.warp import pixel_grid


def display_tables(hd: int = 5, wd: int = 4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A display table whose displacement is ``M_c q + t_c`` at display point ``q`` (exact under bilinear
    interpolation; ``M_c`` diagonal) and gain ``1 + 0.1 c``: ``(displacement [3, hd, wd, 2], gain [3, hd, wd],
    [diag(M_c), t_c] [3, 4])``, float64."""
    m = torch.tensor([[0.10, -0.05], [0.02, 0.08], [-0.06, 0.04]], dtype=torch.float64)
    t = torch.tensor([[0.01, 0.02], [-0.03, 0.0], [0.0, -0.01]], dtype=torch.float64)
    q = pixel_grid((hd, wd), torch.float64)
    disp = m[:, None, None, :] * q + t[:, None, None, :]
    gain = (1.0 + 0.1 * torch.arange(3, dtype=torch.float64))[:, None, None].expand(3, hd, wd).clone()
    return disp, gain, torch.cat([m, t], 1)
