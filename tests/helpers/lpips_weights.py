"""Random LPIPS (AlexNet + linear head) weights of the shapes :class:`~controlgs_adapter.perceptual.LPIPS`
expects, for tests that need a working network without the real weight files."""

from __future__ import annotations

import torch

from controlgs_adapter.perceptual import _expected


def random_lpips_weights(seed: int = 0, scale: float = 0.1) -> dict[str, torch.Tensor]:
    """Uniform in [-0.3, 0.7) x ``scale``, the head weights made >= 0 (as LPIPS' are)."""
    g = torch.Generator().manual_seed(seed)
    w = {k: (torch.rand(s, generator=g) - 0.3) * scale for k, s in _expected().items()}
    for i in range(5):
        w[f"lin{i}"] = w[f"lin{i}"].abs()
    return w
