"""Octree-GS / Octree-AnyGS test data (levels, level and distance inputs): anchor arrays, decoders, a model
holding them, and output folders written in Octree-GS's and Octree-AnyGS's layouts."""

from __future__ import annotations

import numpy as np
import torch
from helpers.family_checks import write_cfg_args
from torch import nn

from controlgs_adapter.backends.octree_gs import OctreeGSModel
from controlgs_adapter.formats.backbone import write_ply

A, K, F, FORK, VOXEL, STD_DIST = 14, 4, 32, 2, 0.1, 3.0


CFG = dict(feat_dim=F, n_offsets=K, fork=FORK, use_feat_bank=False, appearance_dim=0, add_opacity_dist=True,
           add_cov_dist=False, add_color_dist=False, add_level=True, dist2level="round", progressive=False,
           voxel_size=0.0, source_path="/data/scene", model_path="/out/scene")


def _decoders(gen: torch.Generator) -> dict[str, nn.Sequential]:
    torch.manual_seed(int(torch.randint(0, 10_000, (1,), generator=gen)))
    return {  # Octree-GS widths: [feat, view, (dist), (level)] -> F
        "mlp_opacity": nn.Sequential(nn.Linear(F + 3 + 1 + 1, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
        "mlp_cov": nn.Sequential(nn.Linear(F + 3 + 1, F), nn.ReLU(), nn.Linear(F, 7 * K)),
        "mlp_color": nn.Sequential(nn.Linear(F + 3 + 1, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid()),
    }


def _arrays(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    level = rng.integers(0, 3, A)
    return {"anchor": rng.normal(size=(A, 3)).astype(np.float32), "offset": rng.normal(size=(A, K, 3)).astype(np.float32),
            "feat": rng.normal(size=(A, F)).astype(np.float32), "scale": rng.normal(-2, 0.3, size=(A, 6)).astype(np.float32),
            "level": level, "extra": rng.uniform(-0.4, 0.4, A).astype(np.float32)}


def _model(arr, decoders) -> OctreeGSModel:
    return OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                         anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                         level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                         voxel_size=VOXEL, standard_dist=STD_DIST, fork=FORK, add_level=True, add_opacity_dist=True,
                         **decoders)


def _write_dir(root, arr, decoders, *, mode="split", iteration=30000):
    """Octree-GS's on-disk layout, written independently of the loader."""
    root.mkdir(parents=True, exist_ok=True)
    write_cfg_args(root / "cfg_args", **CFG)
    it = root / "point_cloud" / f"iteration_{iteration}"
    it.mkdir(parents=True)
    info = np.zeros(A, np.float32)
    info[0], info[1] = VOXEL, STD_DIST
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2],
              "level": arr["level"].astype(np.float32), "extra_level": arr["extra"], "info": info}
    flat = arr["offset"].transpose(0, 2, 1).reshape(A, 3 * K)  # f_offset_{c*K + k}
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields["opacity"] = np.zeros(A, np.float32)
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    if mode == "split":
        for attr, fname in (("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")):
            dec = decoders[attr]
            torch.jit.trace(dec, torch.randn(5, dec[0].in_features)).save(str(it / fname))
    else:
        torch.save({"opacity_mlp": decoders["mlp_opacity"].state_dict(), "cov_mlp": decoders["mlp_cov"].state_dict(),
                    "color_mlp": decoders["mlp_color"].state_dict()}, it / "checkpoints.pth")
    return root


ANYGS_YAML = """# Model Parameters
model_params: {
    model_config: {
        name: "GaussianLoDModel",
        kwargs: {
            feat_dim: %d,
            view_dim: 3,
            appearance_dim: 0,
            n_offsets: %d,
            fork: 2,
            visible_threshold: 0.9,
            dist2level: 'round',
            progressive: True,
            use_feat_bank: False,
            levels: -1,
        }
    },
    base_model: "%s",
    resolution_scales: [1.0],
}
optim_params: {
    iterations: 40_000,
}
"""


def anygs_decoders(seed: int) -> dict[str, nn.Sequential]:
    """Octree-AnyGS's decoders on its Scaffold-GS base: every one takes [feat, view] = F + 3."""
    torch.manual_seed(seed)
    return {"mlp_opacity": nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}


def anygs_fields(arr) -> dict[str, np.ndarray]:
    """The PLY fields of Octree-AnyGS's anchors: no ``info`` or ``opacity`` column."""
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2],
              "level": arr["level"].astype(np.float32), "extra_level": arr["extra"]}
    flat = arr["offset"].transpose(0, 2, 1).reshape(A, 3 * K)
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    return fields


def write_anygs_dir(root, arr, decoders, *, base_model="scaffoldgs"):
    """Octree-AnyGS's layout (Scaffold-GS base): config.yaml, a PLY whose LOD metadata (standard_dist,
    levels) sits in obj_info lines, TorchScript decoders. Returns the iteration folder."""
    it = root / "point_cloud" / "iteration_40000"
    it.mkdir(parents=True)
    (root / "config.yaml").write_text(ANYGS_YAML % (F, K, base_model))
    write_ply(it / "point_cloud.ply", anygs_fields(arr), comments=[f"standard_dist {STD_DIST}", "levels 3"],
              comment_keyword="obj_info")
    for attr, fname in (("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")):
        torch.jit.trace(decoders[attr], torch.randn(5, F + 3)).save(str(it / fname))
    return it
