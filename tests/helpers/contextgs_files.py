"""ContextGS test data (feat_dim 50, n_offsets 10, a bound): decoded (zero-padded) or raw anchor arrays,
decoders, a model holding them, and its output folder written in ContextGS's layout."""

from __future__ import annotations

import numpy as np
import torch
from helpers.family_checks import write_cfg_args
from torch import nn

from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.formats.backbone import write_ply

A, K, F, PAD = 14, 10, 50, 4


H = F // 4  # hyper_divisor 4


LO, HI = torch.tensor([[-2.4, -2.0, -3.0]]), torch.tensor([[2.0, 2.6, 1.5]])


def _decoders(seed: int) -> dict[str, nn.Sequential]:
    torch.manual_seed(seed)
    return {"mlp_opacity": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}


def _arrays(seed: int, *, decoded: bool) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    arr = {"anchor": rng.uniform(-1.8, 1.4, (A, 3)).astype(np.float32), "offset": rng.normal(size=(A, K, 3)).astype(np.float32),
           "feat": rng.normal(size=(A, F)).astype(np.float32), "hyper": rng.normal(size=(A, H)).astype(np.float32)}
    if decoded:
        arr["mask"] = (rng.random((A, K)) < 0.5).astype(np.float32)
        arr["mask"][:, 1] = 1.0
        arr["scale"] = rng.uniform(0.01, 0.3, (A, 6)).astype(np.float32)
        for v in arr.values():  # decoded arrays are zero-padded from the valid count to the full count
            v[A - PAD:] = 0.0
    else:
        arr["mask"] = rng.normal(0, 3, (A, K)).astype(np.float32)
        arr["scale"] = rng.normal(-3, 0.5, (A, 6)).astype(np.float32)
    return arr


def _model(arr, decs, *, decoded: bool) -> ContextGSModel:
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    return ContextGSModel(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                          scaling=t["scale"], hyper_latent=t["hyper"], x_bound_min=LO, x_bound_max=HI,
                          decoded_version=decoded, **decs)


def _write_dir(root, arr, decs, *, bound=True):
    root.mkdir(parents=True)
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, hyper_divisor=4, use_feat_bank=False, voxel_size=0.01)
    it = root / "point_cloud" / "iteration_30000"
    it.mkdir(parents=True)
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2]}
    fields.update({f"n{c}": np.zeros(A, np.float32) for c in "xyz"})
    flat = arr["offset"].transpose(0, 2, 1).reshape(A, 3 * K)
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_mask_{i}": arr["mask"][:, i] for i in range(K)})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields.update({f"f_hyper_latent_{i}": arr["hyper"][:, i] for i in range(H)})
    fields["opacity"] = np.zeros(A, np.float32)
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    ckpt = {"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
            "color_mlp": decs["mlp_color"].state_dict(), "latent_codec": {"quantiles": torch.zeros(H, 1, 3)},
            "grid_mlp": {"0.0.weight": torch.zeros(4, 4)}, "level_scale": torch.ones(3)}
    if bound:
        ckpt["bound"] = [LO, HI]
    torch.save(ckpt, it / "checkpoint.pth")
    return root
