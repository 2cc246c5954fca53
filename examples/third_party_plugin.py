"""A third-party plug-in: a backend for a custom neural-Gaussian family and a downstream stage.

A plug-in is a module with functions marked ``@controlgs_adapter.hookimpl``. Ship it in your own
package and declare it in your ``pyproject.toml``::

    [project.entry-points.controlgs_adapter]
    tiny_ng = "my_package.third_party_plugin"

or register it at run time: ``controlgs_adapter.plugins.register_plugin(module)``. Run this file
to see both in ``controlgs plugins`` and in use::

    python examples/third_party_plugin.py
"""

from __future__ import annotations

import torch
from torch import nn

import controlgs_adapter
from controlgs_adapter.backend import Backend
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.state import RuntimeState


class TinyNeuralGaussians:
    """A toy family: anchors ``centers [A, 3]`` with features, decoded by one MLP ``head``."""

    def __init__(self, num_anchors: int = 64, feat_dim: int = 16, seed: int = 0) -> None:
        g = torch.Generator().manual_seed(seed)
        self.centers = torch.rand(num_anchors, 3, generator=g) * 2 - 1  # [A, 3]
        self.features = torch.randn(num_anchors, feat_dim, generator=g)  # [A, F]
        self.head = nn.Sequential(nn.Linear(feat_dim, 24), nn.ReLU(), nn.Linear(24, 8))


# --- the backend: how to recognise the family and where to inject ----------------------------
class TinyBackend(Backend):
    """TinyNeuralGaussians: a ``head`` decoder (nn.Sequential) and anchors ``centers``."""

    name = "tiny_ng"

    def matches(self, model):
        return isinstance(getattr(model, "head", None), nn.Sequential) and hasattr(model, "centers")

    def decoder_paths(self, model):
        return ["head"]  # FC1 = head.0 (the default first_linear_path)

    def anchor_positions(self, model):
        return model.centers


# --- the stage: a radial vignette in linear light, after the lens pre-warp -------------------
class VignetteStage(Stage):
    """Darkens the image towards the corners: ``I * (1 - strength * r^2 / 2)``, r in [0, sqrt 2]."""

    name = "vignette"
    domain = "linear"
    order = 15.0  # between lens (10) and resample (20)

    def __init__(self, strength: float = 0.3) -> None:
        super().__init__()
        self.strength = float(strength)

    def is_identity(self, state: RuntimeState, ctx: StageContext | None = None) -> bool:
        return self.strength == 0.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        h, w = image.shape[-2:]
        y = (torch.arange(h, dtype=image.dtype, device=image.device) + 0.5) * 2 / h - 1
        x = (torch.arange(w, dtype=image.dtype, device=image.device) + 0.5) * 2 / w - 1
        r2 = y[:, None] ** 2 + x[None, :] ** 2  # [H, W]
        return image * (1.0 - self.strength * r2 / 2.0)


# --- the hooks -----------------------------------------------------------------------------
@controlgs_adapter.hookimpl
def controlgs_register_backends():
    return [TinyBackend()]


@controlgs_adapter.hookimpl
def controlgs_register_stages():
    return [VignetteStage]


if __name__ == "__main__":
    import sys

    from controlgs_adapter import ControlGS, cli, plugins
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.state import Camera

    plugins.register_plugin(sys.modules[__name__], name="tiny_ng_example")
    cli.main(["plugins"])

    model = TinyNeuralGaussians()
    cgs = ControlGS.wrap(model, modules=("resample", "display"))
    print(cgs.summary())
    cam = Camera(torch.eye(4), torch.tensor([[64.0, 0, 32], [0, 64.0, 32], [0, 0, 1]]), 64, 64)
    with cgs.conditioned(RuntimeState(downsample=4.0, power_saving=0.4), camera=cam):
        attributes = model.head(model.features)  # the decoder now sees the injection
    print("decoded", tuple(attributes.shape))

    pipeline = Pipeline.from_config({"vignette": {"strength": 0.5}, "oled": False})
    eye = pipeline(torch.full((3, 32, 32), 0.5), RuntimeState())
    print("vignette: centre", round(float(eye[0, 16, 16]), 3), "corner", round(float(eye[0, 0, 0]), 3))
