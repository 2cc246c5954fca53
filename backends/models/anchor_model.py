"""The one base of the reference model and the family stand-ins: an anchor model decodes the
Gaussians of the anchors a view sees and splats them (prefilter -> decode -> splat), with the
pieces every Scaffold-family decode shares: visibility mask -> anchor ids, the feature-bank
re-weighting, Gaussians from decoder outputs, and the anchor prefilter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from controlgs_adapter.backend import anchor_ids_from_mask
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.rasterizers import rasterize_gaussians
from controlgs_adapter.state import Camera

from controlgs_adapter.rendering.splatter import NEAR_PLANE, RasterOutput, project_gaussians

__all__ = ["AnchorModel", "NeuralGaussians", "anchor_ids_from_mask", "anchor_visibility", "assemble_gaussians",
           "feature_bank", "as_param"]


@dataclass
class NeuralGaussians:
    """Gaussians decoded for one camera (``G`` = number kept by the opacity > 0 mask).

    Attributes:
        means: ``[G, 3]`` world positions.
        scales: ``[G, 3]`` linear standard deviations (world units).
        rotations: ``[G, 4]`` unit quaternions (w, x, y, z).
        opacities: ``[G]`` neural opacities in (0, 1].
        colors: ``[G, 3]`` colours in [0, 1] (sRGB-encoded, as the backbone was trained).
        anchor_of: ``[G]`` (long) the anchor each Gaussian came from.
        offset_of: ``[G]`` (long) which of the anchor's K offsets it is.
        visible_ids: ``[R]`` (long) the anchors that were decoded; row ``i`` of every decoder input.
        neural_opacity: ``[R * K]`` every decoded opacity before the mask (anchor-major).
    """

    means: torch.Tensor
    scales: torch.Tensor
    rotations: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    anchor_of: torch.Tensor
    offset_of: torch.Tensor
    visible_ids: torch.Tensor
    neural_opacity: torch.Tensor


def as_param(x: np.ndarray | torch.Tensor, requires_grad: bool = False) -> nn.Parameter:
    """A float32 frozen parameter from an array."""
    t = torch.as_tensor(np.ascontiguousarray(x) if isinstance(x, np.ndarray) else x, dtype=torch.float32)
    return nn.Parameter(t.clone(), requires_grad=requires_grad)


def feature_bank(feat: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's multi-resolution feature re-weighting: ``feat [R, F]`` (F divisible by 4) with
    the bank decoder's softmax ``weight [R, 3]`` -> ``[R, F]`` = every 4th channel repeated 4 times,
    every 2nd repeated twice and all channels, mixed by the three weights."""
    return (feat[:, ::4].repeat(1, 4) * weight[:, :1] + feat[:, ::2].repeat(1, 2) * weight[:, 1:2]
            + feat * weight[:, 2:])


@torch.no_grad()
def anchor_visibility(camera: Camera, means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """``[A]`` bool: anchors whose footprint can touch the image (the Scaffold family's ``prefilter_voxel``).

    Each anchor is a Gaussian (``means [A, 3]``, linear ``scales [A, 3+]`` of which the first 3
    are used, ``rotations [A, 4]``) projected as the 3DGS rasteriser does
    (:func:`~controlgs_adapter.rendering.splatter.project_gaussians`: EWA 2D covariance plus the
    0.3 px^2 low-pass), with radius ``ceil(3 * sqrt(largest eigenvalue))`` px (eigenvalue gap
    floored at 0.1 as in 3DGS). An anchor is visible iff its camera-space depth is ``>
    NEAR_PLANE`` (0.2, 3DGS's ``in_frustum``) and the square of half-width ``radius`` about its
    projected centre overlaps the image rectangle ``[0, W] x [0, H]``.

    Difference from Scaffold-GS: its CUDA ``visible_filter`` tests that overlap in 16 px tile
    units, so it may also keep anchors whose square ends up to one tile beyond the right/bottom
    edge; the set kept here is contained in that one, and both keep every anchor whose footprint
    touches the image. Which anchors are decoded only changes which Gaussians reach the splatter,
    never their attributes (decoding is per anchor).
    """
    means = means.detach()
    w2c = camera.world_to_camera.to(means)
    pc = camera.to_camera(means)  # [A, 3]
    visible = pc[:, 2] > NEAR_PLANE
    front = visible.nonzero().squeeze(1)
    uv, cov2d, _ = project_gaussians(pc[front], scales.detach()[front, :3], rotations.detach()[front],
                                     w2c, camera.intrinsics.to(means), camera.width, camera.height)
    a, b, c = cov2d.unbind(-1)
    mid = 0.5 * (a + c)
    radius = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt((mid * mid - (a * c - b * b)).clamp_min(0.1))))
    u, v = uv.unbind(-1)
    inside = (u + radius > 0) & (u - radius < camera.width) & (v + radius > 0) & (v - radius < camera.height)
    visible[front] = inside & (a * c - b * b > 0)
    return visible


def assemble_gaussians(ids: torch.Tensor, k: int, anchor: torch.Tensor, offsets: torch.Tensor, scaling: torch.Tensor,
                       neural_opacity: torch.Tensor, color: torch.Tensor, scale_rot: torch.Tensor,
                       keep: torch.Tensor) -> NeuralGaussians:
    """Scaffold-family Gaussians from decoder outputs (R anchors, K per anchor, anchor-major rows).

    Args:
        ids: ``[R]`` anchor ids; anchor ``[R, 3]``; scaling ``[R, 6]`` linear (offset scale, base scale).
        offsets: ``[R*K, 3]`` offsets in units of ``scaling[:, :3]`` (CompGS: the means decoder's output).
        neural_opacity ``[R*K]``, color ``[R*K, 3]``, scale_rot ``[R*K, 7]``, keep ``[R*K]`` bool.
    Mean = anchor + offset * scaling[:, :3]; scale = scaling[:, 3:] * sigmoid(scale_rot[:, :3]);
    rotation = normalize(scale_rot[:, 3:7]). A scaling that overflowed to +inf (``exp`` of a log-scale
    over 88 in float32) counts as the largest finite one: the scales stay finite, and so do the
    gradients through ``sigmoid(scale_rot)`` (the splatter saturates such axes).
    """
    flat = keep.nonzero().squeeze(1)  # [G]
    row = flat // k
    s = scaling[row].clamp(max=torch.finfo(scaling.dtype).max)
    return NeuralGaussians(
        means=anchor[row] + offsets[flat] * s[:, :3], scales=s[:, 3:] * torch.sigmoid(scale_rot[flat, :3]),
        rotations=F.normalize(scale_rot[flat, 3:7], dim=-1), opacities=neural_opacity[flat],
        colors=color[flat], anchor_of=ids[row], offset_of=flat % k, visible_ids=ids, neural_opacity=neural_opacity)


class AnchorModel(nn.Module):
    """Base of the reference model and every family stand-in: subclasses implement
    :meth:`visible_anchors` (the family's prefilter) and :meth:`decode`; :meth:`render` is the one
    prefilter -> decode -> splat path, :meth:`decoded_ids` the one visibility mask -> anchor ids."""

    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        """``[A]`` bool: the anchors the family's prefilter keeps for ``camera``."""
        raise NotImplementedError

    def decode(self, camera: Camera, visible_mask: torch.Tensor | None = None, **options: Any) -> NeuralGaussians:
        """The Gaussians of the anchors in ``visible_mask`` (``[A]`` bool; None = all) for ``camera``;
        ``options`` are the family's own (Octree-GS: ``appearance_id``)."""
        raise NotImplementedError

    def refuse_options(self, options: dict[str, Any]) -> None:
        """Raise :class:`InputValueError` naming the :meth:`decode` options left over after the
        family took its own (``options`` non-empty)."""
        if options:
            raise InputValueError(f"{type(self).__name__}.decode got unknown option(s) {sorted(options)}")

    @staticmethod
    def decoded_ids(visible_mask: torch.Tensor | None, anchors: torch.Tensor) -> torch.Tensor:
        """``[R]`` ascending ids of the anchors to decode: those in ``visible_mask`` (``[A]`` bool,
        checked against ``anchors [A, ...]``), or all of them when it is None. Row ``i`` of every
        decoder input is anchor ``ids[i]``."""
        if visible_mask is None:
            return torch.arange(anchors.shape[0], device=anchors.device)
        return anchor_ids_from_mask(visible_mask, anchors.shape[0])

    def render(self, camera: Camera, visible_mask: torch.Tensor | None = None, background: torch.Tensor | None = None,
               **options: Any) -> RasterOutput:
        """Prefilter (``visible_mask=None`` -> :meth:`visible_anchors`), :meth:`decode` (``options``
        go to it) and splat with the rasterizer chosen for the model's device
        (:func:`controlgs_adapter.rendering.rasterizers.rasterize_gaussians`: the pure-torch splatter, gsplat on
        CUDA when installed). Returns its ``RasterOutput``."""
        if visible_mask is None:
            visible_mask = self.visible_anchors(camera)
        g = self.decode(camera, visible_mask, **options)
        return rasterize_gaussians(g.means, g.scales, g.rotations, g.opacities, g.colors, camera, background)
