"""The built-in scene's backbone: a reference neural-Gaussian model trained on the diorama and
baked into the package in Scaffold-GS's on-disk format (``controlgs_adapter/data/builtin_scene/<variant>``),
so that the demo loads it and never retrains it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import FileFormatError, InputValueError
from .diorama import VARIANTS, load_builtin_scene

__all__ = ["builtin_backbone_dir", "load_builtin_backbone", "build_builtin_backbone"]

_DATA = Path(__file__).resolve().parent.parent / "data" / "builtin_scene"


def builtin_backbone_dir(variant: str = "ar") -> Path:
    """Folder of the baked backbone of ``variant`` (a Scaffold-GS model directory)."""
    if variant not in VARIANTS:
        raise InputValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    return _DATA / variant


def load_builtin_backbone(variant: str = "ar") -> Any:
    """The baked backbone of ``variant`` as a :class:`NeuralGaussianModel` in eval mode."""
    from ..backends.scaffold_io import load_scaffold_dir

    path = builtin_backbone_dir(variant)
    if not (path / "point_cloud").is_dir():
        raise FileFormatError(
            f"{path}: the built-in {variant!r} backbone is not baked into this installation; "
            f"bake it in a checkout with `controlgs scene build-backbone --variant {variant} --out {path}`"
        )
    return load_scaffold_dir(path).eval()


def build_builtin_backbone(variant: str = "ar", *, out: str | Path, resolution: int = 128, iterations: int = 1500,
                           max_anchors: int = 3000, n_offsets: int = 5, feat_dim: int = 32, point_spacing: float = 0.04,
                           seed: int = 0, progress: bool = True) -> Path:
    """Train the reference model on the built-in scene's training views at ``resolution`` and save
    it to ``out`` (always given: never the installed package; the shipped backbones are
    ``controlgs_adapter/data/builtin_scene/<variant>`` of a checkout, replaced as a whole) with
    :func:`~controlgs_adapter.backends.models.train_backbone.build_backbone`: a Scaffold-GS folder
    and a ``build.json`` that records the arguments, time and the test-view PSNR/SSIM of the bare
    backbone."""
    from controlgs_adapter.backends.models.train_backbone import build_backbone

    scene = load_builtin_scene(variant, resolution, cache=True)
    xyz, rgb = scene.points(point_spacing)
    record = {"variant": variant, "resolution": resolution, "point_spacing": point_spacing}
    built = build_backbone(scene.views("train"), out, test_views=scene.views("test"), points=xyz, colors=rgb,
                           iterations=iterations, max_anchors=max_anchors, feat_dim=feat_dim, n_offsets=n_offsets,
                           seed=seed, progress=progress, replace=True, record=record)
    return built.path
