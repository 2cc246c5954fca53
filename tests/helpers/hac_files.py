"""HAC++ / HAC test data (feat_dim 50, n_offsets 10): decoded or raw anchor arrays, decoders, and the output
folder written in their layout."""

from __future__ import annotations

import numpy as np
import torch
from helpers.family_checks import write_cfg_args
from torch import nn

from controlgs_adapter.formats.backbone import write_ply

A, K, F, VOXEL = 16, 10, 50, 0.01  # HAC++ defaults: feat_dim 50, n_offsets 10


def _decoders(seed: int) -> dict[str, nn.Sequential]:
    torch.manual_seed(seed)
    return {  # HAC++: every decoder takes [feat, view, dist] = F + 4 -> F
        "mlp_opacity": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
        "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
        "mlp_color": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid()),
    }


def _arrays(seed: int, *, decoded: bool, mask_cols: int, n: int = A, invalid=()) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    if decoded:
        mask = (rng.random((n, mask_cols)) < 0.6).astype(np.float32)
        if mask_cols == K + 1:
            mask[:, K] = 0.0
        mask[:, 0] = 1.0
        scale = rng.uniform(0.01, 0.2, (n, 6)).astype(np.float32)  # linear
        anchor = (np.round(rng.normal(size=(n, 3)) / VOXEL) * VOXEL).astype(np.float32)
    else:
        mask = rng.normal(0, 3, (n, mask_cols)).astype(np.float32)  # logits
        scale = rng.normal(-3, 0.5, (n, 6)).astype(np.float32)  # log
        anchor = rng.normal(size=(n, 3)).astype(np.float32)
    for i in invalid:
        mask[i, :K] = 0.0 if decoded else -20.0
    return {"anchor": anchor, "offset": rng.normal(size=(n, K, 3)).astype(np.float32), "mask": mask,
            "feat": rng.normal(size=(n, F)).astype(np.float32), "scale": scale}


def _write_dir(root, arr, decs, *, voxel_size=VOXEL):
    """HAC++'s layout: cfg_args, point_cloud/iteration_N/{point_cloud.ply, checkpoint.pth}."""
    root.mkdir(parents=True)
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=voxel_size, use_feat_bank=False,
                   lmbda=0.004, model_path=str(root))
    it = root / "point_cloud" / "iteration_30000"
    it.mkdir(parents=True)
    n = arr["anchor"].shape[0]
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2]}
    fields.update({f"n{c}": np.zeros(n, np.float32) for c in "xyz"})
    flat = arr["offset"].transpose(0, 2, 1).reshape(n, 3 * K)  # f_offset_{c*K + k}
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_mask_{i}": arr["mask"][:, i] for i in range(arr["mask"].shape[1])})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields["opacity"] = np.zeros(n, np.float32)
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(n, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    grid = nn.Sequential(nn.Linear(8, 2 * F), nn.ReLU(), nn.Linear(2 * F, 4))
    torch.save({"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
                "color_mlp": decs["mlp_color"].state_dict(), "encoding_xyz": {"params": torch.zeros(32)},
                "grid_mlp": grid.state_dict(), "deform_mlp": {"w": torch.zeros(3)}}, it / "checkpoint.pth")
    return root
