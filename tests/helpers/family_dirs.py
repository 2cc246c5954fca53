"""Tiny trained output folders of every supported family, written in each family's on-disk layout,
and the file that holds each folder's decoder weights (for tests that corrupt them)."""

from __future__ import annotations

import warnings
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch
from torch import nn

from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.formats.backbone import write_ply

A, K, F = 8, 2, 8
ITERATION = 100
FAMILIES = ("scaffold_gs", "scaffold_gs_split", "octree_gs", "hac", "contextgs", "compgs")


def write_cfg_args(path: Path, **kw: object) -> None:
    """cfg_args as the families' train.py writes it: ``str(Namespace(**vars(args)))``."""
    path.write_text(str(Namespace(**kw)))


def _mlps(width: int, seed: int) -> dict[str, nn.Sequential]:
    torch.manual_seed(seed)
    return {"mlp_opacity": nn.Sequential(nn.Linear(width, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(width, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(width, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}


def _state_dicts(mlps: dict[str, nn.Sequential]) -> dict[str, dict[str, torch.Tensor]]:
    return {"opacity_mlp": mlps["mlp_opacity"].state_dict(), "cov_mlp": mlps["mlp_cov"].state_dict(),
            "color_mlp": mlps["mlp_color"].state_dict()}


def _anchor_fields(rng: np.random.Generator, *, mask: bool = False) -> dict[str, np.ndarray]:
    anchor = rng.normal(size=(A, 3)).astype(np.float32)
    fields = {"x": anchor[:, 0], "y": anchor[:, 1], "z": anchor[:, 2]}
    fields.update({f"n{c}": np.zeros(A, np.float32) for c in "xyz"})
    fields.update({f"f_offset_{i}": rng.normal(size=A).astype(np.float32) for i in range(3 * K)})
    if mask:
        fields.update({f"f_mask_{i}": np.ones(A, np.float32) for i in range(K)})
    fields.update({f"f_anchor_feat_{i}": rng.normal(size=A).astype(np.float32) for i in range(F)})
    fields["opacity"] = np.zeros(A, np.float32)
    fields.update({f"scale_{i}": rng.uniform(0.01, 0.1, A).astype(np.float32) for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    return fields


def write_family_dir(family: str, root: Path, **cfg: object) -> Path:
    """Write a loadable folder of ``family`` (one of :data:`FAMILIES`; ``scaffold_gs_split``: Scaffold-GS
    with TorchScript decoders) under ``root``; ``cfg`` overrides cfg_args entries. Returns the file
    holding the decoder weights (a TorchScript file for the split layout)."""
    rng = np.random.default_rng(0)
    it = root / "point_cloud" / f"iteration_{ITERATION}"
    it.mkdir(parents=True)
    if family in ("scaffold_gs", "scaffold_gs_split"):
        write_cfg_args(root / "cfg_args", **{"feat_dim": F, "n_offsets": K, "voxel_size": 0.01, "use_feat_bank": False,
                                             "appearance_dim": 0, "add_opacity_dist": False, "add_cov_dist": False,
                                             "add_color_dist": False, **cfg})
        write_ply(it / "point_cloud.ply", _anchor_fields(rng))
        mlps = _mlps(F + 3, 1)
        if family == "scaffold_gs":
            torch.save(_state_dicts(mlps), it / "checkpoints.pth")
            return it / "checkpoints.pth"
        with warnings.catch_warnings():  # torch >= 2.10 deprecates TorchScript; checkpoints still use it
            warnings.simplefilter("ignore", DeprecationWarning)
            for attr, name in (("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")):
                torch.jit.trace(mlps[attr], torch.rand(1, F + 3)).save(str(it / name))
        return it / "opacity_mlp.pt"
    if family == "octree_gs":
        write_cfg_args(root / "cfg_args", **{"feat_dim": F, "n_offsets": K, "fork": 2, "use_feat_bank": False,
                                             "appearance_dim": 0, "add_opacity_dist": False, "add_cov_dist": False,
                                             "add_color_dist": False, "add_level": False, "dist2level": "round",
                                             "voxel_size": 0.0, **cfg})
        fields = _anchor_fields(rng)
        info = np.zeros(A, np.float32)
        info[0], info[1] = 0.1, 3.0
        fields.update({"level": np.zeros(A, np.float32), "extra_level": np.zeros(A, np.float32), "info": info})
        write_ply(it / "point_cloud.ply", fields)
        torch.save(_state_dicts(_mlps(F + 3, 2)), it / "checkpoints.pth")
        return it / "checkpoints.pth"
    if family in ("hac", "contextgs"):
        write_cfg_args(root / "cfg_args", **{"feat_dim": F, "n_offsets": K, "voxel_size": 0.01, "use_feat_bank": False,
                                             **cfg})
        fields = _anchor_fields(rng, mask=True)
        ckpt: dict[str, object] = dict(_state_dicts(_mlps(F + 4, 3)))
        if family == "contextgs":
            fields.update({f"f_hyper_latent_{i}": rng.normal(size=A).astype(np.float32) for i in range(F // 4)})
            ckpt["bound"] = [torch.full((1, 3), -3.0), torch.full((1, 3), 3.0)]
        write_ply(it / "point_cloud.ply", fields)
        torch.save(ckpt, it / "checkpoint.pth")
        return it / "checkpoint.pth"
    if family == "compgs":
        c, g, k = 8, 2, 3
        ref, res = rng.normal(size=(A, c)).astype(np.float32), rng.normal(size=(A, k * g)).astype(np.float32)
        means, scales = rng.normal(size=(A, 3)).astype(np.float32), rng.normal(-3, 0.4, (A, 6)).astype(np.float32)
        fields = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
        fields.update({f"f_res_feat_{i}": res[:, i] for i in range(k * g)})
        fields.update({f"f_ref_feat_{i}": ref[:, i] for i in range(c)})
        fields.update({f"scale_{i}": scales[:, i] for i in range(6)})
        write_ply(it / "point_cloud.ply", fields)
        torch.manual_seed(4)
        model = CompGSModel(means=torch.from_numpy(means), scales_before_exp=torch.from_numpy(scales),
                            ref_feats=torch.from_numpy(ref), res_feats=torch.from_numpy(res.reshape(A, k, g)))
        torch.save({f"prediction_net.{key}": v for key, v in model.network.prediction_net.state_dict().items()},
                   it / "weights.pth")
        return it / "weights.pth"
    raise ValueError(f"unknown family {family!r}")


def poison_first_weight(weights: Path) -> str:
    """Write NaN into the first floating-point weight of a ``torch.save`` file of state dicts; returns
    that tensor's dotted name (e.g. ``'opacity_mlp.0.weight'``)."""
    blob = torch.load(weights, weights_only=True)
    for key, value in blob.items():
        items = value.items() if isinstance(value, dict) else [("", value)]
        for sub, t in items:
            if isinstance(t, torch.Tensor) and t.is_floating_point():
                t.view(-1)[0] = float("nan")
                torch.save(blob, weights)
                return f"{key}.{sub}" if sub else key
    raise AssertionError(f"{weights}: no floating-point tensor")


def rewrite_ply(ply: Path, **changes: object) -> None:
    """Rewrite a PLY with fields replaced (a value: set to it, as float32) or dropped (None)."""
    from controlgs_adapter.formats.backbone import read_ply

    fields, _ = read_ply(ply)
    for name, value in changes.items():
        if value is None:
            fields.pop(name)
        else:
            fields[name] = np.asarray(value, np.float32)
    write_ply(ply, fields)
