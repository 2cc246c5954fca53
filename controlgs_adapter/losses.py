"""The training image loss of the paper (Eq. 14): ``a L1 + b (1 - SSIM) + c MSE (+ d LPIPS)``.

LPIPS needs ImageNet-trained AlexNet/VGG weights that no installable package ships and that
this library never downloads (see docs/reference/training-evaluation.md); its weight must therefore stay 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .checks import check_number
from .errors import InputValueError
from .metrics import check_image_pair, ssim

__all__ = ["LossWeights", "image_loss", "ImageLoss"]

LPIPS_UNAVAILABLE = (
    "LPIPS is not available offline: its AlexNet/VGG backbone weights ship with no package and "
    "controlgs-adapter never downloads; set the LPIPS loss weight to 0 (the default)"
)


@dataclass(frozen=True)
class LossWeights:
    """Weights (alpha, beta, gamma, delta) of Eq. 14. Defaults: the paper's real-scene setting without LPIPS."""

    l1: float = 0.8
    ssim: float = 0.2
    mse: float = 10.0
    lpips: float = 0.0

    def __post_init__(self) -> None:
        for name in ("l1", "ssim", "mse", "lpips"):
            object.__setattr__(self, name, check_number(f"loss weight {name}", getattr(self, name), low=0.0))
        if self.lpips > 0.0:
            raise InputValueError(LPIPS_UNAVAILABLE + f" (got lpips={self.lpips!r})")


def image_loss(pred: torch.Tensor, target: torch.Tensor, weights: LossWeights = LossWeights()) -> torch.Tensor:
    """Scalar loss between sRGB images ``pred, target`` ``[..., 3, H, W]`` (averaged over the batch)."""
    check_image_pair(pred, target, names=("pred", "target"))
    diff = pred - target
    loss = weights.l1 * diff.abs().mean() + weights.mse * diff.square().mean()
    if weights.ssim:
        loss = loss + weights.ssim * (1.0 - ssim(pred, target, data_range=1.0).mean())
    return loss


class ImageLoss(nn.Module):
    """Module form of :func:`image_loss`."""

    def __init__(self, weights: LossWeights = LossWeights()) -> None:
        super().__init__()
        self.weights = weights

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:  # noqa: D102
        return image_loss(pred, target, self.weights)
