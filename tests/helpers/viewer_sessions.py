"""A viewer session on the built-in AR backbone at 16 px (its ground truth rendered from the scene's planes) with
random adapters, and decoding the PNGs the viewer sends."""

from __future__ import annotations

import base64
import io
from pathlib import Path
from typing import Any

import numpy as np
import torch
from helpers.adapters import random_adapter
from PIL import Image

from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene, render_planes
from controlgs_adapter.viewer import ViewerSession

#: the session's image size (pixels, square)
SIZE = 16


def builtin_session(folder: Path, adapters: dict[str, dict[str, Any]]) -> tuple[ViewerSession, Any]:
    """``(session, scene)``: the 16 px AR scene (4 views, the first one the test view) and one random adapter
    per entry of ``adapters`` (name -> :meth:`ControlGS.wrap` options), saved in ``folder``."""
    scene = load_builtin_scene("ar", SIZE, views=4, test_every=4, samples=1)
    model = load_builtin_backbone("ar")
    paths = {name: random_adapter(model, folder / f"{name}.controlgs.safetensors", 3, **wrap)
             for name, wrap in adapters.items()}
    session = ViewerSession(model, scene.views("test"), paths, name="tiny",
                            truth=lambda cam: render_planes(scene.planes, cam, samples=1)[0].float())
    return session, scene


def decode_png(b64: str) -> torch.Tensor:
    """base64 PNG -> float ``[H, W, C]`` in 0..255."""
    img = np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))), dtype=np.float32)
    return torch.from_numpy(img).view(img.shape[0], img.shape[1], -1)
