"""CompGS test data (its MipNeRF360 widths): random anchor arrays, a model holding them, and its training
checkpoint folder written in CompGS's layout."""

from __future__ import annotations

import numpy as np
import torch

from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.formats.backbone import write_ply

A, K, C, G = 9, 10, 32, 8  # CompGS MipNeRF360 config: derive_factor 10, ref_feats_dim 32, res_feats_dim 8


def _arrays(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(size=(A, 3)).astype(np.float32), "scales": rng.normal(-3, 0.4, (A, 6)).astype(np.float32),
            "ref": rng.normal(size=(A, C)).astype(np.float32), "res": rng.normal(size=(A, K, G)).astype(np.float32)}


def _model(arr, seed: int) -> CompGSModel:
    torch.manual_seed(seed)
    return CompGSModel(means=torch.from_numpy(arr["means"]), scales_before_exp=torch.from_numpy(arr["scales"]),
                       ref_feats=torch.from_numpy(arr["ref"]), res_feats=torch.from_numpy(arr["res"]))


def _write_checkpoint(root, arr, model, *, iteration=30000):
    """CompGS's training checkpoint: <exp>/point_cloud/iteration_N/{point_cloud.ply, weights.pth}."""
    it = root / "point_cloud" / f"iteration_{iteration}"
    it.mkdir(parents=True)
    fields = {"x": arr["means"][:, 0], "y": arr["means"][:, 1], "z": arr["means"][:, 2]}
    fields.update({f"n{c}": np.zeros(A, np.float32) for c in "xyz"})
    res = arr["res"].reshape(A, K * G)  # k-major, no transpose: f_res_feat_{k*G + g}
    fields.update({f"f_res_feat_{i}": res[:, i] for i in range(K * G)})
    fields.update({f"f_ref_feat_{i}": arr["ref"][:, i] for i in range(C)})
    fields.update({f"scale_{i}": arr["scales"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    state = {f"prediction_net.{k}": v for k, v in model.network.prediction_net.state_dict().items()}
    state["entropy_model.entropy_bottleneck.quantiles"] = torch.zeros(4, 1, 3)  # compressai parts are ignored
    torch.save(state, it / "weights.pth")
    return root
