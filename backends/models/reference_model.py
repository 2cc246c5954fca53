"""A neural-Gaussian model with Scaffold-GS's structure, attribute names and decoding, as an ``nn.Module``.

Anchors ``v`` (position ``x_v``, feature ``f_v``, 6 log-scales, ``K`` learned offsets) emit ``K``
Gaussians each whose attributes three MLPs decode from ``[f_v, view direction (, distance)]`` at
render time (paper Eqs. 9-10). The decoding reproduces Scaffold-GS's ``generate_neural_gaussians``
exactly (``gaussian_renderer/__init__.py``; see ``docs/reference/reference-model.md``):

* rows of every decoder input are the visible anchors in ascending index order
  (``visible_mask.nonzero()``), so row ``i`` is anchor ``visible_mask.nonzero()[i]``;
* ``ob_view = (anchor - camera centre) / |.|``, ``ob_dist = |anchor - camera centre|``;
* decoder outputs are reshaped anchor-major (row ``i * K + k`` is offset ``k`` of row ``i``);
* only Gaussians with neural opacity ``> 0`` are kept;
* mean = anchor + offset * exp(_scaling)[:, :3]; scale = exp(_scaling)[:, 3:6] * sigmoid(cov[:, :3]);
  rotation = normalize(cov[:, 3:7]) (quaternion w, x, y, z); colour = colour MLP output (sigmoid).

Besides the tensors, the model carries Scaffold-GS's accessor names (``get_anchor``,
``get_scaling``, ``get_opacity_mlp``, ...), so Scaffold-GS's own renderer code runs on it too.
"""

from __future__ import annotations

import math
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.anchor_model import AnchorModel, NeuralGaussians, anchor_visibility, assemble_gaussians, feature_bank

__all__ = ["NeuralGaussianModel", "NeuralGaussians", "AppearanceEmbedding", "median_spacing"]


class AppearanceEmbedding(nn.Module):
    """Per-training-camera appearance code (Scaffold-GS's ``Embedding``: state-dict key ``embedding.weight``)."""

    def __init__(self, num_cameras: int, dim: int) -> None:
        super().__init__()
        self.embedding = nn.Embedding(num_cameras, dim)

    def forward(self, ids: torch.Tensor) -> torch.Tensor:  # [R] long -> [R, dim]
        return self.embedding(ids)


def _mlp(d_in: int, d_hidden: int, d_out: int, out_act: nn.Module | None) -> nn.Sequential:
    layers: list[nn.Module] = [nn.Linear(d_in, d_hidden), nn.ReLU(True), nn.Linear(d_hidden, d_out)]
    return nn.Sequential(*layers, *([out_act] if out_act is not None else []))


class NeuralGaussianModel(AnchorModel):
    """Scaffold-GS's anchor model (``scene/gaussian_model.py``) as an ``nn.Module``.

    Args:
        num_anchors: A, number of anchors (tensors start at zero; see :meth:`from_points`).
        feat_dim: F, anchor feature width (= first hidden width D1 of every decoder).
        n_offsets: K, Gaussians per anchor.
        voxel_size: anchor grid spacing (world units; kept for the file format and growth).
        use_feat_bank: multi-resolution feature re-weighting by ``mlp_feature_bank([view, dist])``.
        appearance_dim: width of the per-camera appearance code appended last to the colour input
            (0 = none, as every shipped Scaffold-GS script uses). The camera's id is read from
            ``camera.extra["uid"]`` (default 0).
        num_cameras: rows of the appearance embedding (number of training cameras).
        add_opacity_dist, add_cov_dist, add_color_dist: feed the distance ``|anchor - camera|``
            to that decoder.

    Parameters (Scaffold-GS names): ``_anchor [A, 3]``, ``_offset [A, K, 3]`` (in units of
    ``get_scaling[:, :3]``), ``_anchor_feat [A, F]``, ``_scaling [A, 6]`` (log), ``_rotation
    [A, 4]`` and ``_opacity [A, 1]`` (anchor-level; only the prefilter and the file format use them).
    """

    def __init__(self, num_anchors: int = 0, *, feat_dim: int = 32, n_offsets: int = 10, voxel_size: float = 0.01,
                 use_feat_bank: bool = False, appearance_dim: int = 0, num_cameras: int = 1,
                 add_opacity_dist: bool = False, add_cov_dist: bool = False, add_color_dist: bool = False) -> None:
        super().__init__()
        if num_anchors < 0 or feat_dim < 1 or n_offsets < 1 or appearance_dim < 0 or num_cameras < 1:
            raise InputValueError(
                f"need num_anchors >= 0, feat_dim >= 1, n_offsets >= 1, appearance_dim >= 0, num_cameras >= 1; got "
                f"{num_anchors}, {feat_dim}, {n_offsets}, {appearance_dim}, {num_cameras}")
        if use_feat_bank and feat_dim % 4:
            raise InputValueError(f"use_feat_bank needs feat_dim divisible by 4, got {feat_dim}")
        if not (math.isfinite(voxel_size) and voxel_size > 0):
            raise InputValueError(f"voxel_size must be a finite number > 0, got {voxel_size!r}")
        self.feat_dim, self.n_offsets, self.voxel_size = int(feat_dim), int(n_offsets), float(voxel_size)
        self.use_feat_bank, self.appearance_dim = bool(use_feat_bank), int(appearance_dim)
        self.add_opacity_dist, self.add_cov_dist, self.add_color_dist = (
            bool(add_opacity_dist), bool(add_cov_dist), bool(add_color_dist))
        self.opacity_dist_dim, self.cov_dist_dim, self.color_dist_dim = (
            int(add_opacity_dist), int(add_cov_dist), int(add_color_dist))
        a, f, k = int(num_anchors), self.feat_dim, self.n_offsets
        self._anchor = nn.Parameter(torch.zeros(a, 3))
        self._offset = nn.Parameter(torch.zeros(a, k, 3))
        self._anchor_feat = nn.Parameter(torch.zeros(a, f))
        self._scaling = nn.Parameter(torch.zeros(a, 6))
        rot = torch.zeros(a, 4)
        rot[:, 0] = 1.0
        self._rotation = nn.Parameter(rot)
        self._opacity = nn.Parameter(torch.full((a, 1), math.log(0.1 / 0.9)))
        self.mlp_feature_bank = _mlp(3 + 1, f, 3, nn.Softmax(dim=1)) if use_feat_bank else None
        self.mlp_opacity = _mlp(f + 3 + self.opacity_dist_dim, f, k, nn.Tanh())
        self.mlp_cov = _mlp(f + 3 + self.cov_dist_dim, f, 7 * k, None)
        self.mlp_color = _mlp(f + 3 + self.color_dist_dim + self.appearance_dim, f, 3 * k, nn.Sigmoid())
        self.embedding_appearance = AppearanceEmbedding(num_cameras, appearance_dim) if appearance_dim else None

    # ----------------------------------------------------------------- Scaffold-GS accessors
    @property
    def get_anchor(self) -> torch.Tensor:  # [A, 3]
        return self._anchor

    @property
    def get_scaling(self) -> torch.Tensor:  # [A, 6], linear
        return torch.exp(self._scaling)

    @property
    def get_rotation(self) -> torch.Tensor:  # [A, 4], unit quaternions
        return F.normalize(self._rotation, dim=-1)

    @property
    def get_opacity(self) -> torch.Tensor:  # [A, 1] anchor-level opacity (unused by decoding)
        return torch.sigmoid(self._opacity)

    @property
    def get_opacity_mlp(self) -> nn.Module:
        return self.mlp_opacity

    @property
    def get_cov_mlp(self) -> nn.Module:
        return self.mlp_cov

    @property
    def get_color_mlp(self) -> nn.Module:
        return self.mlp_color

    @property
    def get_featurebank_mlp(self) -> nn.Module | None:
        return self.mlp_feature_bank

    @property
    def get_appearance(self) -> nn.Module | None:
        return self.embedding_appearance

    @staticmethod
    def rotation_activation(q: torch.Tensor) -> torch.Tensor:
        return F.normalize(q, dim=-1)

    @property
    def num_anchors(self) -> int:
        return int(self._anchor.shape[0])

    # ----------------------------------------------------------------- construction
    @classmethod
    @torch.no_grad()
    def from_points(cls, points: torch.Tensor, colors: torch.Tensor | None = None, *, feat_dim: int = 32,
                    n_offsets: int = 10, voxel_size: float | None = None, seed: int = 0,
                    color_fit_steps: int = 200, **options: Any) -> "NeuralGaussianModel":
        """Anchors on a voxel grid from a point set (Scaffold-GS's ``create_from_pcd``).

        Points are snapped to ``round(p / voxel_size) * voxel_size`` and de-duplicated (ascending
        lexicographic order, as ``np.unique``); ``voxel_size=None`` uses the median distance of a
        point to its nearest neighbour. Log-scales (all 6) start at ``log(sqrt(mean squared
        distance to the 3 nearest anchors))`` and offsets at zero, as in Scaffold-GS. Without
        ``colors`` the features start at zero (Scaffold-GS); with ``colors [P, 3]`` in [0, 1] the
        features start small and random and are fitted (``color_fit_steps`` Adam steps, colour
        MLP included, random view directions) so that every anchor's K colours match the mean
        colour of its points: a warm start for training. ``options`` go to the constructor.
        """
        check_tensor("points", points, ["P", 3], dtypes=(torch.float32, torch.float64), finite=True)
        if points.shape[0] < 1:
            raise ShapeError("points must hold at least one point, got shape [0, 3]")
        if colors is not None:
            check_tensor("colors", colors, [points.shape[0], 3], dtypes=(torch.float32, torch.float64), finite=True)
        pts = points.detach().to(torch.float64)
        if voxel_size is None:
            voxel_size = median_spacing(pts)
        if not (math.isfinite(voxel_size) and voxel_size > 0):
            raise InputValueError(f"voxel_size must be a finite number > 0, got {voxel_size!r}")
        cells, inverse = torch.unique(torch.round(pts / voxel_size), dim=0, return_inverse=True)
        anchors = (cells * voxel_size).to(torch.float32)  # [A, 3]
        model = cls(anchors.shape[0], feat_dim=feat_dim, n_offsets=n_offsets, voxel_size=voxel_size, **options)
        model._anchor.copy_(anchors)
        d2 = _knn_sq_dists(anchors.double(), 3).mean(1).clamp_min(1e-7)  # k is capped at A - 1 inside
        if anchors.shape[0] == 1:
            d2 = torch.full_like(d2, voxel_size ** 2)
        model._scaling.copy_(torch.log(torch.sqrt(d2)).float()[:, None].expand(-1, 6))
        if colors is not None:
            sums = torch.zeros(anchors.shape[0], 3, dtype=torch.float64).index_add_(0, inverse, colors.double())
            counts = torch.bincount(inverse, minlength=anchors.shape[0]).clamp_min(1).double()
            with torch.enable_grad():
                model._fit_colors((sums / counts[:, None]).float().clamp(0, 1), color_fit_steps, seed)
        return model

    def _fit_colors(self, target: torch.Tensor, steps: int, seed: int) -> None:
        """Fit ``_anchor_feat`` and ``mlp_color`` so that every colour output of anchor ``a`` is ``target[a]``."""
        gen = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            self._anchor_feat.copy_(0.1 * torch.randn(self._anchor_feat.shape, generator=gen))
        opt = torch.optim.Adam([self._anchor_feat, *self.mlp_color.parameters()], lr=1e-2)
        a, k = self.num_anchors, self.n_offsets
        for _ in range(steps):
            view = F.normalize(torch.randn(a, 3, generator=gen), dim=1)
            x = [self._anchor_feat, view]
            if self.add_color_dist:
                x.append(torch.ones(a, 1))
            if self.embedding_appearance is not None:
                x.append(self.embedding_appearance(torch.zeros(a, dtype=torch.long)))
            pred = self.mlp_color(torch.cat(x, dim=1)).reshape(a, k, 3)
            loss = (pred - target[:, None]).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()

    # ----------------------------------------------------------------- visibility (prefilter)
    @torch.no_grad()
    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        """``BoolTensor[A]``: anchors whose footprint can touch the image (Scaffold-GS's
        ``prefilter_voxel``): each anchor as a Gaussian with mean ``get_anchor``, scales
        ``get_scaling[:, :3]`` and rotation ``_rotation``, kept by the rule of
        :func:`~controlgs_adapter.backends.models.anchor_model.anchor_visibility`."""
        return anchor_visibility(camera, self.get_anchor, self.get_scaling, self._rotation)

    # ----------------------------------------------------------------- decoding
    def decode(self, camera: Camera, visible_mask: torch.Tensor | None = None, **options: Any) -> NeuralGaussians:
        """Decode the Gaussians of the anchors in ``visible_mask`` (``BoolTensor[A]``; None = all)
        for ``camera``: exactly Scaffold-GS's ``generate_neural_gaussians`` (module docstring). No option is taken."""
        self.refuse_options(options)
        anchor_all = self.get_anchor
        ids = self.decoded_ids(visible_mask, anchor_all)  # [R] ascending
        feat = self._anchor_feat[ids]  # [R, F]
        anchor = anchor_all[ids]  # [R, 3]
        ob_view = anchor - camera.center.to(anchor)
        ob_dist = ob_view.norm(dim=1, keepdim=True)  # [R, 1]
        ob_view = ob_view / ob_dist  # [R, 3]
        if self.mlp_feature_bank is not None:
            feat = feature_bank(feat, self.mlp_feature_bank(torch.cat([ob_view, ob_dist], dim=1)))
        with_dist = torch.cat([feat, ob_view, ob_dist], dim=1)  # [R, F+4]
        without_dist = torch.cat([feat, ob_view], dim=1)  # [R, F+3]
        neural_opacity = self.mlp_opacity(with_dist if self.add_opacity_dist else without_dist).reshape(-1)  # [R*K]
        color_in = with_dist if self.add_color_dist else without_dist
        if self.embedding_appearance is not None:
            uid = int(camera.extra.get("uid", 0))
            appearance = self.embedding_appearance(torch.full((ids.shape[0],), uid, dtype=torch.long, device=ids.device))
            color_in = torch.cat([color_in, appearance], dim=1)
        color = self.mlp_color(color_in).reshape(-1, 3)  # [R*K, 3]
        scale_rot = self.mlp_cov(with_dist if self.add_cov_dist else without_dist).reshape(-1, 7)  # [R*K, 7]
        return assemble_gaussians(ids, self.n_offsets, anchor, self._offset[ids].reshape(-1, 3), self.get_scaling[ids],
                                  neural_opacity, color, scale_rot, neural_opacity > 0.0)

    def extra_repr(self) -> str:
        return (f"anchors={self.num_anchors}, feat_dim={self.feat_dim}, n_offsets={self.n_offsets}, "
                f"voxel_size={self.voxel_size:g}, use_feat_bank={self.use_feat_bank}, "
                f"appearance_dim={self.appearance_dim}, dist=(opacity={self.add_opacity_dist}, "
                f"cov={self.add_cov_dist}, color={self.add_color_dist})")


def _knn_sq_dists(points: torch.Tensor, k: int, rows: torch.Tensor | None = None) -> torch.Tensor:
    """``[R, k]`` squared distances of the points ``rows`` (default: all) to their ``k`` nearest
    other points (brute force, chunked to about 2^24 distances at a time)."""
    n = points.shape[0]
    rows = torch.arange(n) if rows is None else rows
    if n < 2:
        return torch.zeros(rows.shape[0], k, dtype=points.dtype)
    k = min(k, n - 1)
    chunk = max(1, (1 << 24) // n)
    out = []
    for s in range(0, rows.shape[0], chunk):
        idx = rows[s:s + chunk]
        d2 = torch.cdist(points[idx], points).pow(2)
        d2[torch.arange(idx.shape[0]), idx] = float("inf")
        out.append(d2.topk(k, dim=1, largest=False).values)
    return torch.cat(out)


def median_spacing(points: torch.Tensor, samples: int = 4096) -> float:
    """Median distance of a point to its nearest neighbour (over at most ``samples`` evenly strided
    points, each against all points); 1.0 when all points coincide."""
    rows = torch.arange(0, points.shape[0], max(1, points.shape[0] // samples))
    d = _knn_sq_dists(points.double(), 1, rows)[:, 0].sqrt()
    d = d[d > 0]
    return float(d.median()) if d.numel() else 1.0
