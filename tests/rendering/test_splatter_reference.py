"""Tests of ``controlgs_adapter.rendering.splatter_reference``: the float64 brute-force oracle the splatter is tested
against (its agreement with the splatter is in test_splatter.py)."""

from __future__ import annotations

import torch

from controlgs_adapter.rendering.splatter_reference import rasterize_reference
from controlgs_adapter.state import Camera

D = torch.float64


def test_reference_splatter_returns_float64_for_an_empty_scene():
    """``rasterize_reference`` returns float64 tensors, also with no Gaussian at all (no splat promotes an
    accumulator): colour the background, alpha and depth zero."""
    cam = Camera(torch.eye(4, dtype=D), torch.tensor([[8.0, 0, 2], [0, 8.0, 1.5], [0, 0, 1]], dtype=D), 4, 3)
    empty = [torch.zeros(0, *s) for s in ((3,), (3,), (4,), (), (3,))]
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = rasterize_reference(*empty, cam, bg)
    assert (out.color.dtype, out.alpha.dtype, out.depth.dtype) == (D, D, D)
    assert torch.equal(out.color, bg.to(D)[:, None, None].expand(3, 3, 4))
    assert torch.equal(out.alpha, torch.zeros(1, 3, 4, dtype=D)) and torch.equal(out.depth, torch.zeros(1, 3, 4, dtype=D))
    assert out.visible.shape == (0,)
