"""Reference neural-Gaussian models with random parameters, for the splatter and reference-model tests."""

from __future__ import annotations

import torch

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel


def random_reference_model(a=20, f=8, k=4, seed=0, **opts) -> NeuralGaussianModel:
    """A reference model of ``a`` anchors with random parameters, in front of a camera at the origin looking down +z."""
    torch.manual_seed(seed)
    m = NeuralGaussianModel(a, feat_dim=f, n_offsets=k, **opts)
    with torch.no_grad():
        m._anchor.normal_()
        m._anchor[:, 2] += 5.0
        m._offset.normal_()
        m._anchor_feat.normal_()
        m._scaling.normal_(-2.0, 0.3)
        m._rotation.normal_()
    return m
