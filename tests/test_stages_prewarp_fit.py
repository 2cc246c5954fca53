"""Fitting the learned lens pre-warp through the optics (paper Supp. B.1)."""

from __future__ import annotations

import pytest
import torch

from controlgs_adapter import plugins
from controlgs_adapter.downstream.lens import LensPrewarp, LUTMap
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.prewarp_fit import fit_prewarp
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.losses import image_loss
from controlgs_adapter.state import RuntimeState



def _smooth_images(n: int) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, n), torch.linspace(-1, 1, n), indexing="ij")
    a = torch.stack([torch.cos(4 * xx + yy), torch.sin(3 * yy - xx), xx * yy]) * 0.3 + 0.45
    return torch.stack([a, a.flip(-1)])


@pytest.mark.skipif("optics" not in plugins.stages(), reason="optics stage not registered")
def test_fit_reduces_the_eye_loss_and_bakes():
    torch.manual_seed(0)
    images = _smooth_images(32)
    pipe = Pipeline.from_config({"lens": LensPrewarp.learned(hidden=32, layers=2, frequencies=2),
                                 "optics": {"mode": "distortion"}})

    def eye_loss() -> float:
        with torch.no_grad():
            return sum(float(image_loss(pipe(img, RuntimeState(), reference=img), img)) for img in images) / 2

    before = eye_loss()
    losses = fit_prewarp(pipe, images, steps=60, lr=1e-2, generator=torch.Generator().manual_seed(0))
    assert len(losses) == 60 and pipe.training  # the pipeline's mode is restored
    after = eye_loss()
    assert after < 0.8 * before
    baked = pipe["lens"].bake((32, 32))
    assert isinstance(baked.map, LUTMap)
    pipe.stages[pipe.names.index("lens")] = baked
    assert abs(eye_loss() - after) < 1e-3


def test_fit_rejects_what_it_cannot_fit():
    images = torch.rand(2, 3, 16, 16)
    with pytest.raises(InputValueError, match="no 'lens'"):
        fit_prewarp(Pipeline.from_config(["resample"]), images, steps=1)
    with pytest.raises(InputValueError, match="trainable"):
        fit_prewarp(Pipeline.from_config(["lens"]), images, steps=1)
    pipe = Pipeline([LensPrewarp.learned(hidden=4, layers=1)])
    with pytest.raises(ShapeError, match="targets"):
        fit_prewarp(pipe, images, torch.rand(3, 3, 16, 16), steps=1)
    with pytest.raises(InputValueError, match="steps"):
        fit_prewarp(pipe, images, steps=0)
