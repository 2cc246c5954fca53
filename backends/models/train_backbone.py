"""A small trainer for the reference neural-Gaussian model (the backbone of the built-in demo scene).

It follows Scaffold-GS's recipe, cut down to what a CPU can do in minutes:

* the training views are a dataset (``load_dataset(...).views("train", resolution=...)``, the
  :class:`~controlgs_adapter.training.Views` protocol :class:`~controlgs_adapter.training.Trainer`
  takes; images read lazily), or a stacked ``[V, 3, H, W]`` tensor and its cameras;
* anchors from a point set (voxel-snapped, :meth:`NeuralGaussianModel.from_points`, features
  warm-started from the points' colours when given) or, without points, on a regular voxel grid
  filling ``bounds`` (default: a box around the point the cameras look at);
* one training view per step; Adam on offsets, features, log-scales and the decoders jointly, with
  Scaffold-GS's learning rates and exponential decay of the offset/MLP rates (anchor positions stay
  fixed, as Scaffold-GS's ``position_lr_init = 0``);
* loss ``0.8 L1 + 0.2 (1 - SSIM)`` + ``0.01 * mean(prod(scale))`` (Scaffold-GS's volume regulariser);
* no densification (anchor growing) and no pruning: the anchor set is the initial voxel grid. An
  anchor that is not useful learns to emit only Gaussians of non-positive opacity, which decoding
  drops, so it costs decoder rows but no splatting.

:func:`build_backbone` trains, scores the model on test views (PSNR, SSIM) and writes it as a
Scaffold-GS output folder with a ``build.json``, atomically: what ``controlgs backbone train`` and
``controlgs scene build-backbone`` run.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import torch
from tqdm.auto import tqdm

from controlgs_adapter.checks import check_image, check_tensor
from controlgs_adapter.datasets.memory import posed_images
from controlgs_adapter.errors import FileWriteError, InputValueError, ShapeError
from controlgs_adapter.formats.safetensors import atomic_write, folder_mode
from controlgs_adapter.metrics import ssim
from controlgs_adapter.seeding import seeded
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, median_spacing
from controlgs_adapter.rendering.splatter import rasterize

__all__ = ["train_reference_model", "build_backbone", "BackboneBuild", "grid_points", "camera_target"]


#: the SSIM window of the loss: every training view must be at least this large on each side
_SSIM_WINDOW = 11


def camera_target(cameras: Sequence[Camera]) -> torch.Tensor:
    """``[3]`` the point closest (least squares) to every camera's optical axis."""
    a = torch.zeros(3, 3, dtype=torch.float64)
    b = torch.zeros(3, dtype=torch.float64)
    for cam in cameras:
        d = cam.world_to_camera[2, :3].double()  # optical axis (camera z) in world coordinates
        proj = torch.eye(3, dtype=torch.float64) - torch.outer(d, d) / d.dot(d)
        a += proj
        b += proj @ cam.center.double()
    if len(cameras) < 2 or torch.linalg.matrix_rank(a) < 3:  # parallel axes: a point in front of the first
        cam = cameras[0]
        return (cam.center.double() + cam.world_to_camera[2, :3].double()).float()
    return torch.linalg.solve(a, b).float()


def grid_points(bounds: torch.Tensor, count: int) -> torch.Tensor:
    """About ``count`` points ``[P, 3]`` on a regular grid (equal spacing on every axis) filling the
    box ``bounds [2, 3]`` (min, max corner)."""
    check_tensor("bounds", bounds, [2, 3], finite=True)
    size = (bounds[1] - bounds[0]).double()
    if bool((size <= 0).any()) or count < 1:
        raise InputValueError(f"bounds must have max > min on every axis and count >= 1, got {bounds.tolist()}, {count}")
    spacing = float((size.prod() / count) ** (1.0 / 3.0))
    n = [max(1, round(float(s) / spacing)) for s in size]
    axes = [bounds[0, i].double() + (torch.arange(n[i], dtype=torch.float64) + 0.5) * size[i] / n[i] for i in range(3)]
    return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3).float()


def _anchor_voxel(points: torch.Tensor, max_anchors: int) -> float:
    """The smallest voxel size (median nearest-neighbour spacing, grown by 1.2x steps) that gives at
    most ``max_anchors`` anchors."""
    voxel = median_spacing(points)
    while torch.unique(torch.round(points.double() / voxel), dim=0).shape[0] > max_anchors:
        voxel *= 1.2
    return voxel


def _lr_at(init: float, final: float, t: float) -> float:
    """Log-linear interpolation from ``init`` (t = 0) to ``final`` (t = 1), as Scaffold-GS's schedules."""
    return math.exp((1.0 - t) * math.log(init) + t * math.log(final)) if final > 0 else init * (1.0 - t)


def _param_groups(model: NeuralGaussianModel, extent: float) -> list[tuple[str, list[torch.nn.Parameter], float, float]]:
    """``(name, parameters, initial lr, final lr)`` of each optimiser group: Scaffold-GS's
    ``OptimizationParams`` (the offsets' rates scaled by the scene ``extent``, world units)."""
    groups: list[tuple[str, list[torch.nn.Parameter], float, float]] = [
        ("offset", [model._offset], 0.01 * extent, 0.0001 * extent),
        ("feature", [model._anchor_feat], 0.0075, 0.0075),
        ("scaling", [model._scaling], 0.007, 0.007),
        ("mlp_opacity", list(model.mlp_opacity.parameters()), 0.002, 0.00002),
        ("mlp_cov", list(model.mlp_cov.parameters()), 0.004, 0.004),
        ("mlp_color", list(model.mlp_color.parameters()), 0.008, 0.00005),
    ]
    if model.mlp_feature_bank is not None:
        groups.append(("mlp_featurebank", list(model.mlp_feature_bank.parameters()), 0.01, 0.00001))
    if model.embedding_appearance is not None:
        groups.append(("appearance", list(model.embedding_appearance.parameters()), 0.05, 0.0005))
    return groups


def _as_views(views: Any, cameras: Sequence[Camera] | None, background: torch.Tensor | None) -> Any:
    """The training views as a dataset: ``views`` itself, or a stacked ``[V, 3, H, W]`` tensor with
    its ``cameras`` (checked: one camera per image, every camera the images' size) in memory."""
    if not isinstance(views, torch.Tensor):
        if cameras is not None:
            raise InputValueError("cameras are given with an images tensor; a views dataset brings its own cameras")
        if not hasattr(views, "__getitem__") or not hasattr(views, "__len__") or isinstance(views, (str, bytes)):
            raise InputValueError("views must be a dataset of (camera, image) (e.g. load_dataset(path).views('train')) "
                                  f"or a [V, 3, H, W] images tensor with its cameras, got {type(views).__name__}")
        if len(views) < 1:
            raise InputValueError("views is empty: need at least one training view")
        return views
    images = views
    dims = check_image("images", images)
    if images.dim() != 4:
        raise InputValueError(f"images must be [V, 3, H, W], got {list(images.shape)}")
    cams = [] if cameras is None else list(cameras)
    if len(cams) != images.shape[0] or images.shape[0] < 1:
        raise InputValueError(f"need one camera per image: {images.shape[0]} images, {len(cams)} cameras")
    for i, cam in enumerate(cams):
        if (cam.height, cam.width) != (dims["H"], dims["W"]):
            raise InputValueError(f"cameras[{i}] is {cam.width}x{cam.height}, images are {dims['W']}x{dims['H']}")
    return posed_images(images, cams, background=background)


def _view_cameras(views: Any) -> list[Camera]:
    cams = getattr(views, "cameras", None)
    return list(cams) if cams is not None else [views[i][0] for i in range(len(views))]


def train_reference_model(
    views: Any,
    cameras: Sequence[Camera] | None = None,
    points: torch.Tensor | None = None,
    colors: torch.Tensor | None = None,
    *,
    iterations: int = 1500,
    feat_dim: int = 32,
    n_offsets: int = 5,
    voxel_size: float | None = None,
    max_anchors: int = 3000,
    bounds: torch.Tensor | None = None,
    background: torch.Tensor | None = None,
    lr_scale: float = 1.0,
    seed: int = 0,
    progress: bool = True,
    device: torch.device | str | None = None,
    **model_options: Any,
) -> NeuralGaussianModel:
    """Fit a :class:`NeuralGaussianModel` to posed images.

    Args:
        views: the training views, the dataset :class:`~controlgs_adapter.training.Trainer` takes:
            ``views[i]`` is ``(camera, image [3, H, W])`` sRGB in [0, 1] (sizes may differ between
            views), ``len(views)`` views, ``views.background`` the colour behind the scene (e.g.
            ``load_dataset(path).views("train", resolution=256)``; images are read when a step
            needs them). Or, as before, a stacked ``[V, 3, H, W]`` images tensor with ``cameras``.
        cameras: ``V`` cameras of an images tensor (view ``i`` seen by ``cameras[i]``, ``H x W`` each);
            None with a views dataset.
        points: ``[P, 3]`` world points to put anchors on (e.g. an SfM cloud or the scene's surface
            samples); None (or no point) = a regular grid of ``max_anchors`` points in ``bounds``.
        colors: ``[P, 3]`` colours of ``points`` in [0, 1] (sRGB), to warm-start the features.
        iterations: optimisation steps (one random training view each).
        feat_dim, n_offsets: F and K of the model.
        voxel_size: anchor voxel; None = the smallest spacing that keeps at most ``max_anchors``.
        bounds: ``[2, 3]`` box for the grid when ``points`` is None; None = a box of half-size
            0.5 x the median camera distance around :func:`camera_target`.
        background: ``[3]`` colour behind the scene, as in the images (default: the views'
            ``background``, else black).
        lr_scale: multiplies every learning rate.
        seed: seeds anchor jitter, initialisation and the view order (default 0; training is
            deterministic for a given seed and thread count).
        progress: show a tqdm bar with the running loss.
        device: where the model trains (default: an images tensor's device, else the CPU).
        model_options: passed to the model (``use_feat_bank``, ``appearance_dim``, ``add_*_dist``).

    Returns:
        The trained model in eval mode (decoders included), on ``device``.
    """
    if device is None:
        device = views.device if isinstance(views, torch.Tensor) else torch.device("cpu")
    device = torch.device(device)
    views = _as_views(views, cameras, background)
    cameras = _view_cameras(views)
    if iterations < 0 or max_anchors < 1:
        raise InputValueError(f"need iterations >= 0 and max_anchors >= 1, got {iterations}, {max_anchors}")
    small = next((i for i, c in enumerate(cameras) if min(c.width, c.height) < _SSIM_WINDOW), None)
    if small is not None and iterations:
        c = cameras[small]
        raise InputValueError(f"view {small} is {c.width}x{c.height} pixels; the loss's SSIM needs at least "
                              f"{_SSIM_WINDOW} on each side: train at a higher resolution")
    if isinstance(points, torch.Tensor) and points.dim() == 2 and points.shape[0] == 0:
        points, colors = None, None  # a dataset with an empty point file: the grid, as without one
    if points is None:
        if bounds is None:
            target = camera_target(cameras)
            half = 0.5 * float(torch.stack([(c.center - target).norm() for c in cameras]).median())
            bounds = torch.stack([target - half, target + half])
        points = grid_points(bounds.float(), max_anchors)
        colors = None
    check_tensor("points", points, ["P", 3], dtypes=(torch.float32, torch.float64), finite=True)
    if voxel_size is None:
        voxel_size = _anchor_voxel(points, max_anchors)
    with seeded(seed):  # the decoders' initialisation (on the CPU) follows the seed; the caller's generators are untouched
        model = NeuralGaussianModel.from_points(points.cpu(), None if colors is None else colors.cpu(), feat_dim=feat_dim,
                                                n_offsets=n_offsets, voxel_size=voxel_size, seed=seed,
                                                num_cameras=len(cameras), **model_options).to(device)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():  # spread the K Gaussians of an anchor over its voxel (Scaffold-GS starts them at 0)
        model._offset.copy_((torch.rand(model._offset.shape, generator=gen) - 0.5).to(device))
    centers = torch.stack([c.center for c in cameras])
    extent = 1.1 * float((centers - centers.mean(0)).norm(dim=1).max().clamp_min(1e-6))  # 3DGS's nerf++ radius
    groups = _param_groups(model, extent)
    opt = torch.optim.Adam([{"params": p, "lr": i * lr_scale, "name": n} for n, p, i, _ in groups], eps=1e-15)
    if background is None:
        background = getattr(views, "background", None)
    bg = torch.zeros(3, device=device) if background is None else background.to(device, torch.float32)
    model.train()
    order = torch.randperm(len(cameras), generator=gen)
    checked: set[int] = set()
    bar = tqdm(range(iterations), desc="training backbone", disable=not progress, leave=False, dynamic_ncols=True)
    for step in bar:
        t = step / max(iterations - 1, 1)
        for group, (_, _, lr0, lr1) in zip(opt.param_groups, groups):
            group["lr"] = _lr_at(lr0, lr1, t) * lr_scale
        if step % len(cameras) == 0 and step:
            order = torch.randperm(len(cameras), generator=gen)
        view = int(order[step % len(cameras)])
        cam, target = views[view]
        if view not in checked:  # the first time a view's image is read: its size and values
            if not isinstance(target, torch.Tensor) or tuple(target.shape) != (3, cam.height, cam.width):
                shape = list(target.shape) if isinstance(target, torch.Tensor) else type(target).__name__
                raise ShapeError(f"view {view}: image must be [3, {cam.height}, {cam.width}] (its camera's size), got {shape}")
            check_image(f"view {view}: image", target)
            checked.add(view)
        cam = Camera(cam.world_to_camera, cam.intrinsics, cam.width, cam.height, {**cam.extra, "uid": view})
        target = target.to(device)
        g = model.decode(cam, model.visible_anchors(cam))
        out = rasterize(g.means, g.scales, g.rotations, g.opacities, g.colors, cam, bg)
        loss = 0.8 * (out.color - target).abs().mean() + 0.2 * (1.0 - ssim(out.color, target))
        if g.scales.shape[0]:
            loss = loss + 0.01 * g.scales.prod(dim=1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 10 == 0:
            bar.set_postfix(loss=f"{loss.item():.4f}", gaussians=int(g.means.shape[0]))
    return model.eval()


@dataclass
class BackboneBuild:
    """What :func:`build_backbone` made: the folder, the trained model and the ``build.json`` record."""

    path: Path
    model: NeuralGaussianModel
    info: dict[str, Any]


@torch.no_grad()
def score_backbone(model: NeuralGaussianModel, views: Any) -> tuple[list[float], list[float]]:
    """PSNR and SSIM of ``model``'s render of every view of ``views`` against its image (background:
    the views')."""
    from controlgs_adapter.metrics import psnr

    bg = getattr(views, "background", None)
    device = model._anchor.device
    bg = None if bg is None else bg.to(device)
    p, s = [], []
    for i in range(len(views)):
        cam, gt = views[i]
        gt = gt.to(device, torch.float32)
        render = model.render(cam, None, bg).color.clamp(0, 1)
        p.append(float(psnr(render, gt)))
        s.append(float(ssim(render, gt)))
    return p, s


#: what a folder written by :func:`build_backbone` holds (the only folder ``replace`` swaps)
_BACKBONE_ENTRIES = frozenset({"build.json", "cfg_args", "point_cloud"})


def _empty_or_missing(path: Path) -> bool:
    return not path.exists() or (path.is_dir() and not any(path.iterdir()))


def build_backbone(views: Any, out: str | Path, *, test_views: Any = None, points: torch.Tensor | None = None,
                   colors: torch.Tensor | None = None, iterations: int = 1500, max_anchors: int = 3000,
                   replace: bool = False,
                   record: dict[str, Any] | None = None, progress: bool = True, **options: Any) -> BackboneBuild:
    """Train the reference model on ``views`` (:func:`train_reference_model`, which ``points``,
    ``colors``, ``iterations``, ``max_anchors`` and ``options`` go to), score it on ``test_views`` (PSNR, SSIM per
    view; None: not scored) and write it to ``out`` as a Scaffold-GS output folder
    (``point_cloud/iteration_<iterations>``, ``cfg_args``) with ``build.json``: ``record`` (what
    the caller wants kept: the data, its format, ...), the training settings, the number of anchors,
    where they came from (``"points"`` or ``"grid"``), the time, the thread count and the scores.

    The folder is assembled next to ``out`` and renamed into place at the end, so an interrupted
    build leaves nothing at ``out``. ``out`` must not exist or be an empty folder; with ``replace``
    an existing backbone folder (holding only ``build.json``, ``cfg_args``, ``point_cloud``) is
    replaced as a whole (the built-in scene's baked backbone); a folder holding anything else is refused.

    Raises:
        InputValueError: ``out`` holds files (without ``replace``; with it, files a backbone folder does
            not hold) or is a file; a bad argument.
        FileWriteError: ``out``'s folder cannot be written.
    """
    from controlgs_adapter.backends.scaffold_io import save_scaffold_dir

    target = Path(out)
    if target.exists() and not target.is_dir():
        raise InputValueError(f"{target}: is a file; expected a folder to write the backbone into")
    if not replace and not _empty_or_missing(target):
        raise InputValueError(f"{target}: the folder is not empty; a backbone is written into a new or empty folder")
    if replace and target.is_dir():
        foreign = sorted(p.name for p in target.iterdir() if p.name not in _BACKBONE_ENTRIES)
        if foreign:
            raise InputValueError(f"{target}: holds {', '.join(foreign[:3])}{', ...' if len(foreign) > 3 else ''}, which is "
                                  "not part of a backbone folder; only a backbone folder is replaced")
    has_points = points is not None and points.shape[0] > 0
    t0 = time.perf_counter()
    model = train_reference_model(views, None, points if has_points else None, colors if has_points else None,
                                  iterations=iterations, max_anchors=max_anchors, progress=progress, **options)
    seconds = time.perf_counter() - t0
    info: dict[str, Any] = dict(record or {})
    info.update({"iterations": iterations, "max_anchors": max_anchors,
                 "n_offsets": model.n_offsets, "feat_dim": model.feat_dim, "seed": options.get("seed", 0),
                 "anchors": model.num_anchors, "anchors_from": "points" if has_points else "grid",
                 "train_views": len(views), "train_seconds": round(seconds, 1), "threads": torch.get_num_threads()})
    if test_views is not None and len(test_views):
        p, s = score_backbone(model, test_views)
        info.update({"test_views": len(p), "test_psnr": p, "test_ssim": s, "test_psnr_mean": sum(p) / len(p),
                     "test_ssim_mean": sum(s) / len(s)})
    parent = target.resolve().parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=parent))
    except OSError as e:
        raise FileWriteError(f"{target}: cannot write the backbone there ({e.strerror or e})") from None
    old = None
    try:
        os.chmod(tmp, folder_mode())  # mkdtemp makes it 0700; the model folder gets the umask's mode
        save_scaffold_dir(model, tmp, iteration=iterations)
        atomic_write(tmp / "build.json", lambda f: Path(f).write_text(json.dumps(info, indent=1)))
        if target.exists():
            if any(target.iterdir()):  # replace: the old folder goes aside until the new one is in place
                old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=parent))
                os.replace(target, old / target.name)
            else:
                target.rmdir()
        os.replace(tmp, target)
    except OSError as e:
        if old is not None and not target.exists():
            os.replace(old / target.name, target)
        raise FileWriteError(f"{target}: cannot write the backbone there ({e.strerror or e})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    return BackboneBuild(target, model, info)
