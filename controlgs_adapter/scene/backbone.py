"""The built-in scene's backbone: a reference neural-Gaussian model trained on the diorama and
baked into the package in Scaffold-GS's on-disk format (``controlgs_adapter/data/builtin_scene/<variant>``),
so that the demo loads it and never retrains it."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import torch

from ..errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import atomic_write
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
    it with :func:`save_scaffold_dir` to ``out`` (always given: never the installed package; the shipped
    backbones are ``controlgs_adapter/data/builtin_scene/<variant>`` of a checkout), with a
    ``build.json`` that records the arguments, time and the test-view PSNR of the bare backbone."""
    from ..backends.scaffold_io import save_scaffold_dir
    from controlgs_adapter.backends.models.train_backbone import train_reference_model
    from ..metrics import psnr, ssim

    scene = load_builtin_scene(variant, resolution, cache=True)
    xyz, rgb = scene.points(point_spacing)
    t0 = time.perf_counter()
    model = train_reference_model(scene.train_images, scene.train_cameras, xyz, rgb, iterations=iterations,
                                  feat_dim=feat_dim, n_offsets=n_offsets, max_anchors=max_anchors,
                                  background=scene.background, seed=seed, progress=progress)
    seconds = time.perf_counter() - t0
    with torch.no_grad():
        renders = [model.render(c, None, scene.background).color.clamp(0, 1) for c in scene.test_cameras]
        p = [float(psnr(r, g)) for r, g in zip(renders, scene.test_images)]
        s = [float(ssim(r, g)) for r, g in zip(renders, scene.test_images)]
    target = Path(out)
    save_scaffold_dir(model, target, iteration=iterations)
    info = {"variant": variant, "resolution": resolution, "iterations": iterations, "max_anchors": max_anchors,
            "n_offsets": n_offsets, "feat_dim": feat_dim, "point_spacing": point_spacing, "seed": seed,
            "anchors": model.num_anchors, "train_seconds": round(seconds, 1), "threads": torch.get_num_threads(),
            "test_psnr": p, "test_ssim": s, "test_psnr_mean": sum(p) / len(p), "test_ssim_mean": sum(s) / len(s)}
    atomic_write(target / "build.json", lambda tmp: Path(tmp).write_text(json.dumps(info, indent=1)))
    return target
