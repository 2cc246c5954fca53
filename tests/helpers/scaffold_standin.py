"""A tiny stand-in with Scaffold-GS's structure, for tests: a PLAIN object (Scaffold-GS's
``GaussianModel`` is not an ``nn.Module``) with its attribute names and decoder widths
(``Linear(feat_dim + 3, feat_dim)`` first layers; K = n_offsets outputs per anchor)."""

from __future__ import annotations

import io
import warnings

import torch
from torch import nn

from controlgs_adapter import Camera


class ScaffoldStandIn:
    def __init__(self, num_anchors: int = 40, feat_dim: int = 32, n_offsets: int = 10, *, use_feat_bank: bool = False,
                 seed: int = 0, dtype: torch.dtype = torch.float32) -> None:
        g = torch.Generator().manual_seed(seed)
        torch.manual_seed(seed)
        self.feat_dim, self.n_offsets, self.use_feat_bank = feat_dim, n_offsets, use_feat_bank
        f, k = feat_dim, n_offsets
        self._anchor = nn.Parameter((torch.rand(num_anchors, 3, generator=g) * 2 - 1).to(dtype))
        self._anchor_feat = nn.Parameter(torch.randn(num_anchors, f, generator=g).to(dtype))
        self._offset = nn.Parameter(torch.randn(num_anchors, k, 3, generator=g).to(dtype) * 0.1)
        self.mlp_opacity = nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(True), nn.Linear(f, k), nn.Tanh()).to(dtype)
        self.mlp_cov = nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(True), nn.Linear(f, 7 * k)).to(dtype)
        self.mlp_color = nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(True), nn.Linear(f, 3 * k), nn.Sigmoid()).to(dtype)
        if use_feat_bank:
            self.mlp_feature_bank = nn.Sequential(nn.Linear(4, f), nn.ReLU(True), nn.Linear(f, 3), nn.Softmax(dim=1)).to(dtype)

    @property
    def get_anchor(self) -> torch.Tensor:
        return self._anchor

    def decoder_input(self, camera_center: torch.Tensor, visible_mask: torch.Tensor | None = None) -> torch.Tensor:
        """``[R, F + 3]`` = [feature, view direction] of the visible anchors (Scaffold-GS's layout)."""
        mask = torch.ones(self._anchor.shape[0], dtype=torch.bool) if visible_mask is None else visible_mask
        anchor, feat = self._anchor[mask], self._anchor_feat[mask]
        view = anchor - camera_center.to(anchor)
        view = view / view.norm(dim=1, keepdim=True)
        return torch.cat([feat, view], dim=1)

    def decode(self, x: torch.Tensor) -> dict[str, torch.Tensor]:
        """Outputs of the three attribute decoders for decoder input ``x``."""
        return {"opacity": self.mlp_opacity(x), "cov": self.mlp_cov(x), "color": self.mlp_color(x)}


def script_decoders(model: ScaffoldStandIn) -> ScaffoldStandIn:
    """Replace the decoders by TorchScript traces, saved and reloaded with ``torch.jit.load``, as in a
    Scaffold-GS checkpoint (``opacity_mlp.pt``, ...). Returns the model."""
    names = ["mlp_opacity", "mlp_cov", "mlp_color"] + (["mlp_feature_bank"] if model.use_feat_bank else [])
    for name in names:
        mlp = getattr(model, name)
        example = torch.randn(5, mlp[0].in_features, dtype=mlp[0].weight.dtype)
        buf = io.BytesIO()
        with warnings.catch_warnings():  # torch >= 2.10 deprecates TorchScript; checkpoints still use it
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.jit.save(torch.jit.trace(mlp, example), buf)
            buf.seek(0)
            setattr(model, name, torch.jit.load(buf))
    return model


def make_camera(width: int = 64, height: int = 48, distance: float = 3.0, dtype: torch.dtype = torch.float32) -> Camera:
    """A camera at z = -distance looking down +z at the unit cube (anchors are in [-1, 1]^3)."""
    w2c = torch.eye(4, dtype=dtype)
    w2c[2, 3] = distance
    k = torch.tensor([[1.2 * width, 0.0, width / 2], [0.0, 1.2 * width, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)
    return Camera(w2c, k, width, height)
