"""Decoders of the shapes the families save as TorchScript (Scaffold-GS, Octree-GS, HAC: feature + view
[+ distance] [+ appearance] inputs), plus one with every supported layer kind, nested."""

from __future__ import annotations

from torch import nn

F, K = 32, 10

DECODERS = {
    "opacity": lambda: nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(True), nn.Linear(F, K), nn.Tanh()),
    "opacity_dist": lambda: nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(True), nn.Linear(F, K), nn.Tanh()),
    "cov": lambda: nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(True), nn.Linear(F, 7 * K)),
    "color_appearance": lambda: nn.Sequential(nn.Linear(F + 3 + 32, F), nn.ReLU(True), nn.Linear(F, 3 * K), nn.Sigmoid()),
    "feature_bank": lambda: nn.Sequential(nn.Linear(4, F), nn.ReLU(True), nn.Linear(F, 3), nn.Softmax(dim=1)),
    "hac_opacity": lambda: nn.Sequential(nn.Linear(54, 50), nn.ReLU(True), nn.Linear(50, K), nn.Tanh()),
    "nested": lambda: nn.Sequential(nn.Linear(6, 8), nn.LeakyReLU(0.1), nn.Sequential(nn.Linear(8, 8, bias=False),
                                    nn.SiLU()), nn.Linear(8, 5), nn.Softplus(beta=2.0, threshold=10.0),
                                    nn.Identity(), nn.Softmax(-1)),
}
