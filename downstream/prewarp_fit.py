"""Fitting the learned lens pre-warp (paper Supp. "Lens Correction Through Pre-Warping").

The paper trains the pre-warp MLP end to end through the display-optics path with the 3DGS image
loss (10,000 iterations, learning rate 1e-3) and then bakes it into a lookup table:

    pipe = Pipeline.from_config({"lens": LensPrewarp.learned(), "optics": {"mode": "distortion"}})
    losses = fit_prewarp(pipe, images, targets)
    pipe.stages[pipe.names.index("lens")] = pipe["lens"].bake((H, W))   # or save_lut(...)

Only the lens stage's parameters are optimised; everything else in the pipeline is fixed.
"""

from __future__ import annotations

import torch

from controlgs_adapter.checks import check_image, check_tensor
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.losses import LossWeights, image_loss
from controlgs_adapter.state import RuntimeState

from .pipeline import Pipeline

__all__ = ["fit_prewarp", "PREWARP_LOSS"]

#: The 3DGS loss the paper names for the pre-warp: 0.8 L1 + 0.2 (1 - SSIM).
PREWARP_LOSS = LossWeights(l1=0.8, ssim=0.2, mse=0.0)


def fit_prewarp(
    pipeline: Pipeline,
    images: torch.Tensor,
    targets: torch.Tensor | None = None,
    *,
    state: RuntimeState = RuntimeState(),
    steps: int = 10_000,
    lr: float = 1e-3,
    weights: LossWeights = PREWARP_LOSS,
    generator: torch.Generator | None = None,
) -> list[float]:
    """Train the pipeline's ``"lens"`` stage so that the eye image matches the target.

    Args:
        pipeline: a pipeline with a trainable ``lens`` stage (e.g. ``LensPrewarp.learned()``) and
            the optics it must compensate.
        images: ``[N, 3, H, W]`` sRGB inputs at the native size (renders, or the ground truth
            itself for a pure lens calibration).
        targets: ``[N, 3, H, W]`` sRGB images the eye should see; default ``images``.
        state: run-time state during the fit.
        steps: optimiser steps, one image each (drawn with ``generator``).
        lr: Adam learning rate.
        weights: image-loss weights (default :data:`PREWARP_LOSS`).
    Returns:
        The loss of every step.
    """
    if "lens" not in pipeline:
        raise InputValueError(f"pipeline has no 'lens' stage to fit (stages: {pipeline.names})")
    params = [p for p in pipeline["lens"].parameters() if p.requires_grad]
    if not params:
        raise InputValueError("the pipeline's lens stage has no trainable parameters (use LensPrewarp.learned())")
    b = check_image("images", images)
    check_tensor("images", images, ["N", 3, "H", "W"])
    if targets is None:
        targets = images
    check_tensor("targets", targets, [images.shape[0], 3, b["H"], b["W"]], dtypes=(images.dtype,))
    if steps < 1 or not lr > 0:
        raise InputValueError(f"steps must be >= 1 and lr > 0, got steps={steps!r}, lr={lr!r}")
    optimizer = torch.optim.Adam(params, lr=lr)
    was_training = pipeline.training
    pipeline.train()
    losses: list[float] = []
    try:
        for _ in range(steps):
            i = int(torch.randint(images.shape[0], (1,), generator=generator))
            eye = pipeline(images[i], state, reference=targets[i])
            loss = image_loss(eye, targets[i], weights)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
    finally:
        pipeline.train(was_training)
    return losses
