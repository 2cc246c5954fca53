"""render_view refuses an image on another device or of another dtype than the model's, naming the renderer."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.protocol import FunctionRenderer, render_view
from controlgs_adapter.state import Camera

CAM = Camera(torch.eye(4), torch.tensor([[4.0, 0.0, 2.5], [0.0, 4.0, 1.0], [0.0, 0.0, 1.0]]), 5, 2)


def _returns(image: torch.Tensor) -> FunctionRenderer:
    def my_render(model: Any, camera: Camera, visible: Any, background: Any) -> torch.Tensor:
        return image

    return FunctionRenderer(my_render)


class _PlainModel:
    """A plain Python model (Scaffold-GS's GaussianModel style): tensors as attributes, an int one first."""

    def __init__(self, dtype: torch.dtype) -> None:
        self.counts = torch.zeros(3, dtype=torch.long)
        self._xyz = torch.zeros(4, 3, dtype=dtype)


def test_an_image_on_another_device_is_refused_naming_the_renderer() -> None:
    model = nn.Linear(2, 2)
    with pytest.raises(InputValueError, match=r"renderer FunctionRenderer\(.*my_render\) returned an image on meta; "
                                              r"the model is on cpu"):
        render_view(None, model, CAM, None, renderer=_returns(torch.zeros(3, 2, 5, device="meta")))
    on_meta = nn.Linear(2, 2, device="meta")
    with pytest.raises(InputValueError, match="returned an image on cpu; the model is on meta"):
        render_view(None, on_meta, CAM, None, renderer=_returns(torch.zeros(3, 2, 5)))


@pytest.mark.parametrize("model, image_dtype, wanted", [
    (nn.Linear(2, 2), torch.float64, "torch.float32"),
    (nn.Linear(2, 2), torch.float16, "torch.float32"),
    (nn.Linear(2, 2), torch.uint8, "torch.float32"),
    (nn.Linear(2, 2).double(), torch.float32, "torch.float64"),
    (_PlainModel(torch.float64), torch.float32, "torch.float64"),
    (None, torch.float16, "torch.float32 or torch.float64"),
    (None, torch.int64, "torch.float32 or torch.float64"),
])
def test_an_image_of_another_dtype_is_refused_naming_the_renderer(model: Any, image_dtype: torch.dtype,
                                                                  wanted: str) -> None:
    with pytest.raises(InputValueError, match=rf"renderer FunctionRenderer\(.*my_render\) returned a {image_dtype} image; "
                                              rf"expected {wanted}"):
        render_view(None, model, CAM, None, renderer=_returns(torch.zeros(3, 2, 5, dtype=image_dtype)))


@pytest.mark.parametrize("model, image_dtype", [(nn.Linear(2, 2), torch.float32), (nn.Linear(2, 2).double(), torch.float64),
                                                (_PlainModel(torch.float64), torch.float64), (None, torch.float32),
                                                (None, torch.float64)])
def test_an_image_on_the_model_device_and_dtype_is_returned(model: Any, image_dtype: torch.dtype) -> None:
    image = torch.rand(3, 2, 5, dtype=image_dtype)
    assert render_view(None, model, CAM, None, renderer=_returns(image)) is image
