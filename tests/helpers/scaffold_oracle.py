"""Independent test oracles for the Scaffold-GS format and decoding (no code from the library):

* ``write_scaffold_dir_by_hand``: lays a model out on disk as Scaffold-GS's ``save_ply`` /
  ``save_mlp_checkpoints`` / ``train.py`` do, with raw bytes, ``torch.jit.trace`` and ``torch.save``;
* ``decode_by_hand``: Scaffold-GS's ``generate_neural_gaussians`` anchor by anchor, offset by
  offset, in float64 from the raw weights (explicit matrix products, no ``nn`` modules).
"""

from __future__ import annotations

from argparse import Namespace
from pathlib import Path

import numpy as np
import torch
from torch import nn


class Embedding(nn.Module):  # Scaffold-GS's scene/embedding.py layout: state key "embedding.weight"
    def __init__(self, n: int, d: int) -> None:
        super().__init__()
        self.embedding = nn.Embedding(n, d)

    def forward(self, x):
        return self.embedding(x)


def make_raw_model(a: int, f: int, k: int, *, seed: int, feat_bank=False, appearance_dim=0, num_cameras=1,
                   dists=(False, False, False)) -> dict:
    """Random anchors + decoders as plain tensors/Sequentials (what a trained Scaffold-GS holds)."""
    g = torch.Generator().manual_seed(seed)
    do, dc, dcol = (int(d) for d in dists)
    raw = {
        "anchor": torch.randn(a, 3, generator=g) + torch.tensor([0.0, 0.0, 5.0]),
        "offset": torch.randn(a, k, 3, generator=g),
        "feat": torch.randn(a, f, generator=g),
        "opacity": torch.randn(a, 1, generator=g),
        "scaling": torch.randn(a, 6, generator=g) * 0.3 - 2.0,
        "rotation": torch.randn(a, 4, generator=g),
        "dists": (do, dc, dcol), "feat_bank": feat_bank, "appearance_dim": appearance_dim,
    }
    torch.manual_seed(seed)
    raw["mlp_opacity"] = nn.Sequential(nn.Linear(f + 3 + do, f), nn.ReLU(True), nn.Linear(f, k), nn.Tanh())
    raw["mlp_cov"] = nn.Sequential(nn.Linear(f + 3 + dc, f), nn.ReLU(True), nn.Linear(f, 7 * k))
    raw["mlp_color"] = nn.Sequential(nn.Linear(f + 3 + dcol + appearance_dim, f), nn.ReLU(True), nn.Linear(f, 3 * k),
                                     nn.Sigmoid())
    raw["mlp_feature_bank"] = (nn.Sequential(nn.Linear(4, f), nn.ReLU(True), nn.Linear(f, 3), nn.Softmax(dim=1))
                               if feat_bank else None)
    raw["embedding"] = Embedding(num_cameras, appearance_dim) if appearance_dim else None
    return raw


def write_ply_by_hand(path: Path, raw: dict) -> None:
    a, k, _ = raw["offset"].shape
    f = raw["feat"].shape[1]
    names = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_offset_{i}" for i in range(3 * k)]
             + [f"f_anchor_feat_{i}" for i in range(f)] + ["opacity"] + [f"scale_{i}" for i in range(6)]
             + [f"rot_{i}" for i in range(4)])
    offsets = raw["offset"].numpy().transpose(0, 2, 1).reshape(a, 3 * k)  # column c*K + k
    table = np.concatenate([raw["anchor"].numpy(), np.zeros((a, 3), np.float32), offsets, raw["feat"].numpy(),
                            raw["opacity"].numpy(), raw["scaling"].numpy(), raw["rotation"].numpy()], axis=1)
    header = "ply\nformat binary_little_endian 1.0\nelement vertex %d\n%send_header\n" % (
        a, "".join(f"property float {n}\n" for n in names))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode("ascii") + table.astype("<f4").tobytes())


def write_scaffold_dir_by_hand(root: Path, raw: dict, *, iteration: int = 30000, mode: str = "split",
                               cfg_overrides: dict | None = None) -> Path:
    folder = root / "point_cloud" / f"iteration_{iteration}"
    write_ply_by_hand(folder / "point_cloud.ply", raw)
    f = raw["feat"].shape[1]
    do, dc, dcol = raw["dists"]
    mods = {"opacity_mlp": (raw["mlp_opacity"], torch.rand(1, f + 3 + do)),
            "cov_mlp": (raw["mlp_cov"], torch.rand(1, f + 3 + dc)),
            "color_mlp": (raw["mlp_color"], torch.rand(1, f + 3 + dcol + raw["appearance_dim"]))}
    if raw["feat_bank"]:
        mods["feature_bank_mlp"] = (raw["mlp_feature_bank"], torch.rand(1, 3 + 1))
    if raw["appearance_dim"]:
        mods["appearance"] = (raw["embedding"], torch.zeros((1,), dtype=torch.long))
    if mode == "split":
        for key, (m, example) in mods.items():
            m.eval()
            name = "embedding_appearance.pt" if key == "appearance" else f"{key}.pt"
            torch.jit.trace(m, example).save(str(folder / name))
            m.train()
    else:
        torch.save({key: m.state_dict() for key, (m, _) in mods.items()}, folder / "checkpoints.pth")
    cfg = dict(sh_degree=3, feat_dim=f, n_offsets=raw["offset"].shape[1], voxel_size=0.001, update_depth=3,
               update_init_factor=16, update_hierachy_factor=4, use_feat_bank=raw["feat_bank"], source_path="/data/x",
               model_path=str(root), images="images", resolution=-1, white_background=False, data_device="cuda",
               eval=True, lod=0, appearance_dim=raw["appearance_dim"], lowpoly=False, ds=1, ratio=1,
               undistorted=False, add_opacity_dist=bool(do), add_cov_dist=bool(dc), add_color_dist=bool(dcol))
    cfg.update(cfg_overrides or {})
    (root / "cfg_args").write_text(str(Namespace(**cfg)))
    return folder


def _seq(m: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """A Linear-act-Linear(-act) Sequential on one row, from its raw weights, in float64."""
    w0, b0 = m[0].weight.detach().double(), m[0].bias.detach().double()
    w2, b2 = m[2].weight.detach().double(), m[2].bias.detach().double()
    h = torch.clamp(w0 @ x + b0, min=0.0)
    y = w2 @ h + b2
    if len(m) == 4:
        act = type(m[3]).__name__
        y = {"Tanh": torch.tanh, "Sigmoid": torch.sigmoid, "Softmax": lambda t: torch.softmax(t, 0)}[act](y)
    return y


def decode_by_hand(raw: dict, cam_center: torch.Tensor, visible: torch.Tensor, uid: int = 0) -> dict:
    """Gaussians of the visible anchors (ascending), anchor by anchor, offset by offset, float64."""
    k = raw["offset"].shape[1]
    do, dc, dcol = raw["dists"]
    out = {n: [] for n in ("means", "scales", "rotations", "opacities", "colors", "anchor_of")}
    for v in range(raw["anchor"].shape[0]):
        if not bool(visible[v]):
            continue
        x = raw["anchor"][v].double()
        feat = raw["feat"][v].double()
        d = x - cam_center.double()
        dist = d.norm()
        view = d / dist
        if raw["feat_bank"]:
            w = _seq(raw["mlp_feature_bank"], torch.cat([view, dist[None]]))
            fdim = feat.shape[0]
            feat = torch.stack([w[0] * feat[(j % (fdim // 4)) * 4] + w[1] * feat[(j % (fdim // 2)) * 2] + w[2] * feat[j]
                                for j in range(fdim)])
        inp = lambda use_d: torch.cat([feat, view] + ([dist[None]] if use_d else []))  # noqa: E731
        op = _seq(raw["mlp_opacity"], inp(do))
        col_in = inp(dcol)
        if raw["appearance_dim"]:
            col_in = torch.cat([col_in, raw["embedding"].embedding.weight[uid].detach().double()])
        col = _seq(raw["mlp_color"], col_in)
        cov = _seq(raw["mlp_cov"], inp(dc))
        s = torch.exp(raw["scaling"][v].double())
        for j in range(k):
            if op[j] <= 0:
                continue
            sr = cov[7 * j:7 * j + 7]
            out["means"].append(x + raw["offset"][v, j].double() * s[:3])
            out["scales"].append(s[3:] * torch.sigmoid(sr[:3]))
            out["rotations"].append(sr[3:7] / sr[3:7].norm())
            out["opacities"].append(op[j])
            out["colors"].append(col[3 * j:3 * j + 3])
            out["anchor_of"].append(v)
    widths = {"means": 3, "scales": 3, "rotations": 4, "colors": 3}
    res = {n: torch.stack(t) if t else torch.zeros(0, widths.get(n, 0), dtype=torch.float64).squeeze(1)
           for n, t in out.items() if n != "anchor_of"}
    res["anchor_of"] = torch.tensor(out["anchor_of"], dtype=torch.long)
    return res


def camera_looking_down_z(size: int = 32, f: float = 30.0, center=(0.0, 0.0, 0.0)):
    from controlgs_adapter.state import Camera

    w2c = torch.eye(4)
    w2c[:3, 3] = -torch.tensor(center, dtype=torch.float32)
    return Camera(w2c, torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]]), size, size)


__all__ = ["make_raw_model", "write_scaffold_dir_by_hand", "write_ply_by_hand", "decode_by_hand",
           "camera_looking_down_z", "Embedding"]
