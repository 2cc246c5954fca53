"""The built-in scene: a diorama of photographs on planes at different depths and angles.

Two variants, after the paper's two dataset kinds (Sec. 4.1):
- ``"ar"``: object-centric, on black (like NeRF Synthetic);
- ``"vr"``: immersive, the same objects in front of a brick wall on a gravel floor, no background
  visible (like Mip-NeRF 360).
Everything is deterministic: the same arguments give bit-identical images.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import torch

from ..datasets.base import PosedImages, SceneData
from ..datasets.memory import tensor_frames
from ..errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors
from ..state import Camera
from .cameras import arc_cameras
from .planes import TexturedPlane, plane_points, render_planes

__all__ = ["VARIANTS", "SCENE_VERSION", "BuiltinScene", "diorama_planes", "load_builtin_scene", "default_cache_dir"]

VARIANTS = ("ar", "vr")
#: bump when the geometry, cameras or ground-truth rendering change (invalidates caches)
SCENE_VERSION = 1
_CACHE_KIND = "controlgs_builtin_scene_images"


def diorama_planes(variant: str) -> list[TexturedPlane]:
    """The planes of ``variant`` (``"ar"`` or ``"vr"``), world y up, viewed from +z."""
    if variant not in VARIANTS:
        raise InputValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    P = TexturedPlane.make
    planes = [
        P("rocket", "rocket", (-1.15, 1.0, -1.0), 1.8, 1.2, yaw_deg=20.0),
        P("coffee", "coffee", (1.15, 0.9, -1.15), 1.8, 1.2, yaw_deg=-18.0),
        P("brick-panel", "brick", (0.0, 0.45, -0.35), 0.8, 1.5, yaw_deg=6.0),
        P("astronaut", "astronaut", (-0.8, 0.25, 0.45), 1.1, 1.1, yaw_deg=28.0),
        P("chelsea", "chelsea", (0.85, 0.05, 0.6), 1.35, 0.9, yaw_deg=-32.0, pitch_deg=-12.0),
        P("gravel-ramp", "gravel", (-0.1, -0.3, 1.1), 1.0, 0.6, pitch_deg=-60.0),
        P("grass-patch", "grass", (0.0, -0.55, -0.1), 3.4, 2.8, pitch_deg=-90.0),
    ]
    if variant == "vr":
        planes += [
            P("wall", "brick", (0.0, 3.0, -3.2), 26.0, 12.0, repeat=(6, 3)),
            P("floor", "gravel", (0.0, -0.62, 1.0), 26.0, 20.0, pitch_deg=-90.0, repeat=(8, 6)),
        ]
    return planes


@dataclass
class BuiltinScene:
    """Ground-truth views of the diorama with a train/test split.

    Attributes:
        variant: ``"ar"`` or ``"vr"``.
        resolution: native (simulation) resolution S; images are ``S x S``.
        planes: the scene geometry.
        train_cameras / test_cameras: cameras at S.
        train_images / test_images: sRGB ``[N, 3, S, S]`` float32 in [0, 1].
        background: ``[3]`` colour where no plane is hit.

    As a dataset like any other: :attr:`data` (a :class:`SceneData` of in-memory frames, format
    ``"builtin"``) and :meth:`views` (its splits as :class:`PosedImages`).
    """

    variant: str
    resolution: int
    planes: list[TexturedPlane]
    train_cameras: list[Camera]
    test_cameras: list[Camera]
    train_images: torch.Tensor
    test_images: torch.Tensor
    background: torch.Tensor

    @property
    def name(self) -> str:
        return f"builtin-{self.variant}"

    @cached_property
    def data(self) -> SceneData:
        """The scene as a parsed dataset: splits ``train`` / ``test`` of in-memory frames at S."""
        return SceneData({"train": tensor_frames(self.train_images, self.train_cameras, prefix=f"{self.name}/train"),
                          "test": tensor_frames(self.test_images, self.test_cameras, prefix=f"{self.name}/test")},
                         background=self.background, source=self.name, format="builtin")

    def views(self, split: str) -> PosedImages:
        """Cameras and images of ``split`` (``"train"`` or ``"test"``) at S."""
        return self.data.views(split)

    def points(self, spacing: float = 0.05) -> tuple[torch.Tensor, torch.Tensor]:
        """Points on every plane on a ``spacing`` grid with their texture colour, to initialise
        anchors: ``(xyz [P, 3], rgb [P, 3])`` float32."""
        xyz, rgb = zip(*(plane_points(p, spacing) for p in self.planes))
        return torch.cat(xyz).float(), torch.cat(rgb).float()


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/controlgs-adapter/scene`` (``~/.cache/...`` by default)."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "controlgs-adapter" / "scene"


def load_builtin_scene(variant: str = "ar", resolution: int = 128, *, views: int = 32, test_every: int = 8,
                       samples: int = 4, fov_deg: float = 50.0, cache: str | os.PathLike | bool | None = None) -> BuiltinScene:
    """Build the scene and render its ground truth at ``resolution`` with ``samples x samples``
    anti-aliasing. Views ``i`` with ``i % test_every == 0`` are the test split (3DGS's convention).

    ``cache``: a folder (or True for :func:`default_cache_dir`) where the rendered ground truth is
    kept as a safetensors file keyed by every argument and :data:`SCENE_VERSION`, so that the next
    call reads it instead of ray casting again; None/False renders every time."""
    if int(resolution) < 16:
        raise InputValueError(f"resolution must be >= 16 pixels, got {resolution!r}")
    if int(test_every) < 2 or int(views) < int(test_every):
        raise InputValueError(f"need views >= test_every >= 2, got views={views!r}, test_every={test_every!r}")
    planes = diorama_planes(variant)
    background = (0.0, 0.0, 0.0)
    cams = arc_cameras(int(views), size=int(resolution), fov_deg=fov_deg)
    key = {"variant": variant, "resolution": int(resolution), "views": int(views), "samples": int(samples),
           "fov_deg": float(fov_deg), "scene_version": SCENE_VERSION}
    path = None
    if cache:
        folder = default_cache_dir() if cache is True else Path(cache)
        path = folder / ("builtin-" + "-".join(f"{k}{v}" for k, v in key.items()) + ".safetensors")
    images = None
    if path is not None and path.is_file():
        try:
            tensors, header = load_tensors(path, kind=_CACHE_KIND, max_version=1)
            if header.get("key") == key and tuple(tensors["images"].shape) == (len(cams), 3, int(resolution), int(resolution)):
                images = tensors["images"]
        except FileFormatError:
            images = None
    if images is None:
        images = torch.stack([render_planes(planes, c, samples=samples, background=background)[0] for c in cams]).float()
        if path is not None:
            save_tensors(path, {"images": images}, {"key": key}, kind=_CACHE_KIND, format_version=1)
    test = [i for i in range(len(cams)) if i % test_every == 0]
    train = [i for i in range(len(cams)) if i % test_every != 0]
    return BuiltinScene(
        variant=variant,
        resolution=int(resolution),
        planes=planes,
        train_cameras=[cams[i] for i in train],
        test_cameras=[cams[i] for i in test],
        train_images=images[train],
        test_images=images[test],
        background=torch.tensor(background, dtype=torch.float32),
    )
