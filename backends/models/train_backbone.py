"""A small trainer for the reference neural-Gaussian model (the backbone of the built-in demo scene).

It follows Scaffold-GS's recipe, cut down to what a CPU can do in minutes:

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
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import torch
from tqdm.auto import tqdm

from controlgs_adapter.checks import check_image, check_tensor
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.metrics import ssim
from controlgs_adapter.seeding import seeded
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, median_spacing
from controlgs_adapter.rendering.splatter import rasterize

__all__ = ["train_reference_model", "grid_points", "camera_target"]


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


def train_reference_model(
    images: torch.Tensor,
    cameras: Sequence[Camera],
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
    **model_options: Any,
) -> NeuralGaussianModel:
    """Fit a :class:`NeuralGaussianModel` to posed images.

    Args:
        images: ``[V, 3, H, W]`` sRGB in [0, 1], view ``i`` seen by ``cameras[i]`` (``H x W`` each).
        cameras: ``V`` cameras.
        points: ``[P, 3]`` world points to put anchors on (e.g. an SfM cloud or the scene's surface
            samples); None = a regular grid of ``max_anchors`` points in ``bounds``.
        colors: ``[P, 3]`` colours of ``points`` in [0, 1] (sRGB), to warm-start the features.
        iterations: optimisation steps (one random training view each).
        feat_dim, n_offsets: F and K of the model.
        voxel_size: anchor voxel; None = the smallest spacing that keeps at most ``max_anchors``.
        bounds: ``[2, 3]`` box for the grid when ``points`` is None; None = a box of half-size
            0.5 x the median camera distance around :func:`camera_target`.
        background: ``[3]`` colour behind the scene (default black), as in the images.
        lr_scale: multiplies every learning rate.
        seed: seeds anchor jitter, initialisation and the view order (default 0; training is
            deterministic for a given seed and thread count).
        progress: show a tqdm bar with the running loss.
        model_options: passed to the model (``use_feat_bank``, ``appearance_dim``, ``add_*_dist``).

    Returns:
        The trained model in eval mode (decoders included), on the images' device.
    """
    dims = check_image("images", images)
    if images.dim() != 4:
        raise InputValueError(f"images must be [V, 3, H, W], got {list(images.shape)}")
    if len(cameras) != images.shape[0] or images.shape[0] < 1:
        raise InputValueError(f"need one camera per image: {images.shape[0]} images, {len(cameras)} cameras")
    for i, cam in enumerate(cameras):
        if (cam.height, cam.width) != (dims["H"], dims["W"]):
            raise InputValueError(f"cameras[{i}] is {cam.width}x{cam.height}, images are {dims['W']}x{dims['H']}")
    if iterations < 0 or max_anchors < 1:
        raise InputValueError(f"need iterations >= 0 and max_anchors >= 1, got {iterations}, {max_anchors}")
    device = images.device
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
    bg = torch.zeros(3, device=device) if background is None else background.to(device, images.dtype)
    model.train()
    order = torch.randperm(len(cameras), generator=gen)
    bar = tqdm(range(iterations), desc="training backbone", disable=not progress, leave=False)
    for step in bar:
        t = step / max(iterations - 1, 1)
        for group, (_, _, lr0, lr1) in zip(opt.param_groups, groups):
            group["lr"] = _lr_at(lr0, lr1, t) * lr_scale
        if step % len(cameras) == 0 and step:
            order = torch.randperm(len(cameras), generator=gen)
        view = int(order[step % len(cameras)])
        cam = cameras[view]
        cam = Camera(cam.world_to_camera, cam.intrinsics, cam.width, cam.height, {**cam.extra, "uid": view})
        g = model.decode(cam, model.visible_anchors(cam))
        out = rasterize(g.means, g.scales, g.rotations, g.opacities, g.colors, cam, bg)
        target = images[view]
        loss = 0.8 * (out.color - target).abs().mean() + 0.2 * (1.0 - ssim(out.color, target))
        if g.scales.shape[0]:
            loss = loss + 0.01 * g.scales.prod(dim=1).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 10 == 0:
            bar.set_postfix(loss=f"{loss.item():.4f}", gaussians=int(g.means.shape[0]))
    return model.eval()
