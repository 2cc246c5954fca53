"""Backend and loader for Octree-GS (city-super/Octree-GS).

Octree-GS is Scaffold-GS with all level-of-detail anchors in **one flat tensor**: ``_anchor [A, 3]``
with ``_level [A, 1]`` (int) and ``_extra_level [A]`` (float). Per view, ``set_anchor_mask``
keeps the anchors whose level is at most the level predicted from their distance
(``_anchor_mask [A]``), and ``prefilter_voxel`` returns a full-length mask ``LOD ∧ frustum``; the
renderer slices every decoder input with it, so decoder row i is anchor ``mask.nonzero()[i]``
(:func:`lod_anchor_ids`). The decoders are Scaffold-GS's with an optional level scalar after
``[feat, view, (dist)]`` (``add_level``) and the appearance code last (colour only); FC1 is
``mlp_x[0]`` with width ``feat_dim``. Anchor positions are the raw ``_anchor`` (the LOD distance
uses the voxel centre, but the decoder's view/distance inputs use the raw anchor).

On disk (``Scene.save``): ``point_cloud/iteration_<it>/point_cloud.ply`` with properties
``x,y,z, level, extra_level, info, f_offset_*, f_anchor_feat_*, opacity, scale_0..5, rot_0..3``
(``info[0]`` = voxel size, ``info[1]`` = standard distance), the decoders as TorchScript
``opacity_mlp.pt, cov_mlp.pt, color_mlp.pt [, feature_bank_mlp.pt, embedding_appearance.pt]`` or
one ``checkpoints.pth`` ('unite' mode), and ``<model>/cfg_args``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from torch import nn

from controlgs_adapter.backend import has_attrs
from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.anchor_model import AnchorModel, NeuralGaussians, anchor_visibility, as_param, assemble_gaussians, feature_bank
from controlgs_adapter.formats.decoders import Decoders, check_first_width
from controlgs_adapter.formats.backbone import (CFG_KEYS, cfg_value, ply_columns, ply_offsets, ply_xyz, read_cfg_args, read_ply,
                                                 read_yaml_scalars, require_fields)
from controlgs_adapter.formats.layout import iteration_dir
from .scaffold_gs import ScaffoldGSBackend

__all__ = ["OctreeGSBackend", "OctreeGSModel", "lod_anchor_ids", "load_octree_gs_dir"]

#: Attribute names only Octree-GS (and Octree-AnyGS) models carry, on top of Scaffold-GS's.
OCTREE_MARKERS: tuple[str, ...] = ("_level", "_extra_level", "set_anchor_mask")

#: ModelParams defaults of Octree-GS (arguments/__init__.py) for the keys the loader reads, used where
#: cfg_args lacks them (the feature bank and the appearance code are told by the decoder files).
CFG_DEFAULTS: dict[str, Any] = {
    "feat_dim": 32, "n_offsets": 10, "fork": 2, "add_opacity_dist": False, "add_cov_dist": False,
    "add_color_dist": False, "add_level": False, "dist2level": "round",
}


def lod_anchor_ids(anchor_mask: torch.Tensor, frustum_mask: torch.Tensor) -> torch.Tensor:
    """Anchor ids of the decoder rows of one Octree-GS view, ascending.

    Args:
        anchor_mask: ``[A]`` bool, the LOD mask (``model._anchor_mask`` after ``set_anchor_mask``).
        frustum_mask: either ``[A]`` bool (what ``prefilter_voxel`` returns: already LOD ∧ frustum,
            it is and-ed with ``anchor_mask`` again) or ``[A_lod]`` bool over the LOD anchors only
            (``radii > 0`` of the visibility filter run on ``anchor[anchor_mask]``).

    Returns:
        ``[R]`` long: row i of every decoder input is anchor ``ids[i]``.
    """
    check_tensor("anchor_mask", anchor_mask, ["A"], dtypes=(torch.bool,))
    check_tensor("frustum_mask", frustum_mask, ["R"], dtypes=(torch.bool,))
    a, n_lod = anchor_mask.shape[0], int(anchor_mask.sum())
    if frustum_mask.shape[0] == a:
        full = anchor_mask & frustum_mask.to(anchor_mask.device)
    elif frustum_mask.shape[0] == n_lod:
        full = anchor_mask.clone()
        full[anchor_mask] = frustum_mask.to(anchor_mask.device)
    else:
        raise ShapeError(
            f"frustum_mask must have A={a} entries (full-length mask) or {n_lod} (one per LOD-selected anchor), "
            f"got {frustum_mask.shape[0]}"
        )
    return full.nonzero().squeeze(1)


class OctreeGSBackend(ScaffoldGSBackend):
    """Octree-GS / Octree-AnyGS: Scaffold-GS decoders (optionally with the level input) over one
    flat anchor list selected per view by LOD ∧ frustum (see :func:`lod_anchor_ids`)."""

    name = "octree_gs"

    def matches(self, model: Any) -> bool:
        return super().matches(model) and has_attrs(model, OCTREE_MARKERS)

    def anchor_ids(self, model: Any, mask: torch.Tensor) -> torch.Tensor:
        """Decoder-row anchor ids for a view: the visibility ``mask`` as :func:`lod_anchor_ids` takes
        its ``frustum_mask``, and-ed with the model's current ``_anchor_mask`` (call ``set_anchor_mask`` first)."""
        anchor_mask = getattr(model, "_anchor_mask", None)
        if anchor_mask is None:
            raise InputValueError("model has no _anchor_mask: call model.set_anchor_mask(cam_center, iteration, resolution_scale) first")
        return lod_anchor_ids(anchor_mask, mask)

    rows_for = anchor_ids

    def extra_inputs(self, model: Any) -> list[tuple[str, int]]:
        """The level scalar after ``[feat, view, (dist)]`` when the model has ``add_level``."""
        return [("level", 1)] if getattr(model, "add_level", False) else []


class OctreeGSModel(AnchorModel):
    """A light stand-in for Octree-GS's ``GaussianModel`` (evaluation only) with its attribute names.

    Shapes: ``_anchor [A, 3]``, ``_offset [A, K, 3]``, ``_anchor_feat [A, F]``, ``_scaling [A, 6]``
    (log), ``_rotation [A, 4]``, ``_opacity [A, 1]``, ``_level [A, 1]`` int, ``_extra_level [A]``.
    Decoders ``mlp_opacity``, ``mlp_cov``, ``mlp_color`` (eager ``nn.Sequential``), optional
    ``mlp_feature_bank`` and ``embedding_appearance`` (``nn.Embedding``). ``voxel_centre=False``
    gives Octree-AnyGS's LOD distance (raw anchor instead of the voxel centre).
    """

    # buffers (registered in __init__; nn.Module's attribute lookup does not type them)
    _level: torch.Tensor
    _extra_level: torch.Tensor
    _anchor_mask: torch.Tensor

    def __init__(self, *, anchor: torch.Tensor, offset: torch.Tensor, anchor_feat: torch.Tensor, scaling: torch.Tensor,
                 level: torch.Tensor, extra_level: torch.Tensor, mlp_opacity: nn.Module, mlp_cov: nn.Module,
                 mlp_color: nn.Module, voxel_size: float, standard_dist: float, fork: int = 2, levels: int | None = None,
                 dist2level: str = "round", add_level: bool = False, add_opacity_dist: bool = False,
                 add_cov_dist: bool = False, add_color_dist: bool = False, mlp_feature_bank: nn.Module | None = None,
                 embedding_appearance: nn.Embedding | None = None, rotation: torch.Tensor | None = None,
                 opacity: torch.Tensor | None = None, voxel_centre: bool = True) -> None:
        super().__init__()
        dims = check_tensor("anchor", anchor, ["A", 3])
        check_tensor("offset", offset, ["A", "K", 3], dims=dims)
        dims = check_tensor("anchor_feat", anchor_feat, ["A", "F"], dims=dims)
        check_tensor("scaling", scaling, ["A", 6], dims=dims)
        check_tensor("level", level, ["A", 1], dims=dims)
        check_tensor("extra_level", extra_level, ["A"], dims=dims)
        if dist2level not in ("round", "floor", "ceil", "progressive"):
            raise InputValueError(f"dist2level must be 'round', 'floor', 'ceil' or 'progressive', got {dist2level!r}")
        n = anchor.shape[0]
        self._anchor, self._offset, self._anchor_feat = as_param(anchor), as_param(offset), as_param(anchor_feat)
        self._scaling = as_param(scaling)
        self._rotation = as_param(rotation if rotation is not None else torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1))
        self._opacity = as_param(opacity if opacity is not None else torch.zeros(n, 1))
        self.register_buffer("_level", level.to(torch.int32).clone())
        self.register_buffer("_extra_level", extra_level.to(torch.float32).clone())
        self.register_buffer("_anchor_mask", torch.ones(n, dtype=torch.bool))
        self.mlp_opacity, self.mlp_cov, self.mlp_color = mlp_opacity, mlp_cov, mlp_color
        self.mlp_feature_bank = mlp_feature_bank
        self.embedding_appearance = embedding_appearance
        self.feat_dim, self.n_offsets = anchor_feat.shape[1], offset.shape[1]
        self.appearance_dim = 0 if embedding_appearance is None else embedding_appearance.embedding_dim
        self.use_feat_bank = mlp_feature_bank is not None
        self.voxel_size, self.standard_dist, self.fork = float(voxel_size), float(standard_dist), int(fork)
        self.levels = int(levels) if levels is not None else int(level.max() - level.min() + 1) if n else 1
        self.dist2level, self.add_level, self.progressive = dist2level, bool(add_level), False
        self.add_opacity_dist, self.add_cov_dist, self.add_color_dist = bool(add_opacity_dist), bool(add_cov_dist), bool(add_color_dist)
        self.voxel_centre = bool(voxel_centre)
        self._prog_ratio: torch.Tensor | None = None
        self.transition_mask: torch.Tensor | None = None
        self.requires_grad_(False)
        self.eval()

    @property
    def get_anchor(self) -> torch.Tensor:
        return self._anchor

    @property
    def get_scaling(self) -> torch.Tensor:
        return torch.exp(self._scaling)

    @property
    def get_level(self) -> torch.Tensor:
        return self._level

    def map_to_int_level(self, pred_level: torch.Tensor, cur_level: int) -> torch.Tensor:
        """Continuous predicted level ``[A]`` -> integer level ``[A]`` (Octree-GS's ``dist2level``)."""
        if self.dist2level == "progressive":
            pred = torch.clamp(pred_level + 1.0, min=0.9999, max=cur_level + 0.9999)
            self._prog_ratio = torch.frac(pred).unsqueeze(1)
            level = torch.floor(pred).int()
            self.transition_mask = self._level.squeeze(1) == level
            return level
        rnd = {"round": torch.round, "floor": torch.floor, "ceil": torch.ceil}[self.dist2level]
        return torch.clamp(rnd(pred_level).int(), min=0, max=cur_level)

    def set_anchor_mask(self, cam_center: torch.Tensor, iteration: int = -1, resolution_scale: float = 1.0) -> None:
        """Evaluation-time LOD selection: ``_anchor_mask = _level <= level(dist)`` where
        ``level(dist) = log2(standard_dist / dist) / log2(fork) + _extra_level`` (rounded per
        ``dist2level``, clamped to ``[0, levels - 1]``); ``dist`` is measured from the voxel centre."""
        check_tensor("cam_center", cam_center, [3])
        pos: torch.Tensor = self._anchor
        if self.voxel_centre:
            pos = pos + (self.voxel_size / 2) / (float(self.fork) ** self._level)
        dist = torch.linalg.vector_norm(pos - cam_center.to(pos), dim=1) * resolution_scale
        pred = torch.log2(self.standard_dist / dist) / math.log2(self.fork) + self._extra_level
        self._anchor_mask = self._level.squeeze(1) <= self.map_to_int_level(pred, self.levels - 1)

    def decoder_inputs(self, cam_center: torch.Tensor, anchor_ids: torch.Tensor,
                       appearance_id: int | None = None) -> dict[str, torch.Tensor]:
        """The input of each decoder for the anchors ``anchor_ids`` (rows in that order), exactly as
        Octree-GS's ``generate_neural_gaussians`` builds them: ``[feat, view, (dist), (level)]``
        (+ appearance for colour). ``appearance_id`` picks a training camera's code (``ape_code``)."""
        anchor = self.get_anchor[anchor_ids]  # [R, 3]
        feat = self._anchor_feat[anchor_ids]  # [R, F]
        level = self._level[anchor_ids].to(anchor.dtype)  # [R, 1]
        view = anchor - cam_center.to(anchor)
        dist = torch.linalg.vector_norm(view, dim=1, keepdim=True)
        view = view / dist
        if self.mlp_feature_bank is not None:
            bank_in = torch.cat([view, level], dim=1) if self.add_level else view
            feat = feature_bank(feat, self.mlp_feature_bank(bank_in))
        extra = [level] if self.add_level else []
        with_dist = torch.cat([feat, view, dist, *extra], dim=1)
        without = torch.cat([feat, view, *extra], dim=1)
        out = {"mlp_opacity": with_dist if self.add_opacity_dist else without,
               "mlp_cov": with_dist if self.add_cov_dist else without,
               "mlp_color": with_dist if self.add_color_dist else without}
        if self.embedding_appearance is not None:
            if appearance_id is None:
                raise InputValueError("appearance_id is required: the model has an appearance embedding (appearance_dim > 0)")
            code = self.embedding_appearance(torch.full((len(anchor_ids),), int(appearance_id), dtype=torch.long,
                                                        device=anchor.device))
            out["mlp_color"] = torch.cat([out["mlp_color"], code], dim=1)
        return out

    @torch.no_grad()
    def visible_anchors(self, camera: Camera, resolution_scale: float = 1.0) -> torch.Tensor:
        """``[A]`` bool: LOD ∧ frustum for ``camera`` (``set_anchor_mask`` then the prefilter on
        the LOD anchors, as Octree-GS's ``prefilter_voxel``)."""
        self.set_anchor_mask(camera.center, -1, resolution_scale)
        lod = self._anchor_mask
        frustum = anchor_visibility(camera, self._anchor[lod], self.get_scaling[lod], self._rotation[lod])
        full = lod.clone()
        full[lod] = frustum
        return full  # the same set as lod_anchor_ids(lod, frustum)

    def decode(self, camera: Camera, visible_mask: torch.Tensor | None = None,
               appearance_id: int | None = None, **options: Any) -> NeuralGaussians:
        """Decode the Gaussians of the anchors in ``visible_mask`` (``[A]`` bool; None = all) as
        Octree-GS's ``generate_neural_gaussians`` at evaluation (progressive opacity ratio included).
        ``appearance_id`` defaults to ``camera.extra["uid"]`` (0 if absent); no other option is taken."""
        self.refuse_options(options)
        ids = self.decoded_ids(visible_mask, self._anchor)
        if appearance_id is None and self.embedding_appearance is not None:
            appearance_id = int(camera.extra.get("uid", 0))
        x = self.decoder_inputs(camera.center, ids, appearance_id)
        opacity = self.mlp_opacity(x["mlp_opacity"])  # [R, K]
        if self.dist2level == "progressive" and self._prog_ratio is not None and self.transition_mask is not None:
            prog = torch.where(self.transition_mask[ids].unsqueeze(1), self._prog_ratio[ids], torch.ones_like(self._prog_ratio[ids]))
            opacity = opacity * prog
        opacity = opacity.reshape(-1)  # [R*K]
        color = self.mlp_color(x["mlp_color"]).reshape(-1, 3)
        scale_rot = self.mlp_cov(x["mlp_cov"]).reshape(-1, 7)
        return assemble_gaussians(ids, self.n_offsets, self.get_anchor[ids], self._offset[ids].reshape(-1, 3),
                                  self.get_scaling[ids], opacity, color, scale_rot, opacity > 0)


def load_octree_gs_dir(path: str | Path, iteration: int | None = None, *, trust_code: bool = False) -> OctreeGSModel:
    """Load an Octree-GS output directory (``cfg_args``) or an Octree-AnyGS one with the Scaffold-GS
    base model (``config.yaml``; LOD metadata in the PLY's ``obj_info`` lines, LOD distance from the
    raw anchor) into an :class:`OctreeGSModel`. ``iteration=None`` takes the highest iteration.
    TorchScript decoders are read as data and never run; ``trust_code=True`` reads them with
    ``torch.jit.load`` instead (which can run code stored in them: only for folders you trust).

    Raises:
        FileFormatError: naming the file and what is missing or inconsistent, or a TorchScript
            decoder outside the supported subset (see ``docs/reference/backends.md``).
    """
    root = Path(path)
    if (root / "cfg_args").is_file():
        return _load_octree_gs(root, iteration, trust_code)
    if (root / "config.yaml").is_file():
        return _load_octree_anygs(root, iteration, trust_code)
    raise FileFormatError(f"{root}: neither 'cfg_args' (Octree-GS) nor 'config.yaml' (Octree-AnyGS): not an Octree-GS output directory")


def _read_anchor_ply(ply: Path, feat_dim: int, n_offsets: int, config: str) -> tuple[dict[str, Any], list[str]]:
    fields, comments = read_ply(ply)
    src = str(ply)
    require_fields(fields, ["x", "y", "z", "level", "extra_level", *(f"scale_{i}" for i in range(6))], source=src)
    feat = ply_columns(fields, "f_anchor_feat_", source=src)
    if feat.shape[1] != feat_dim:
        raise FileFormatError(f"{src}: {feat.shape[1]} f_anchor_feat_* fields, {config} says feat_dim={feat_dim}")
    t = {
        "anchor": torch.from_numpy(ply_xyz(fields)),
        "offset": torch.from_numpy(ply_offsets(fields, n_offsets, source=src)), "anchor_feat": torch.from_numpy(feat),
        "scaling": torch.from_numpy(ply_columns(fields, "scale_", count=6, source=src)),
        "level": torch.from_numpy(fields["level"].astype(np.int32)[:, None]),
        "extra_level": torch.from_numpy(fields["extra_level"].astype(np.float32)),
    }
    if "rot_0" in fields:
        t["rotation"] = torch.from_numpy(ply_columns(fields, "rot_", count=4, source=src))
    if "opacity" in fields:
        t["opacity"] = torch.from_numpy(fields["opacity"].astype(np.float32)[:, None])
    return {**t, "_fields": fields}, comments


def _build(tensors: dict[str, Any], folder: Path, trust_code: bool, source: str, **settings: Any) -> OctreeGSModel:
    """An :class:`OctreeGSModel` from the anchor ``tensors`` of :func:`_read_anchor_ply`, the decoders
    of ``folder`` and the LOD ``settings``, its decoder widths checked against its configuration."""
    mods = Decoders(folder, trust_code).modules()
    model = OctreeGSModel(**tensors, **settings, mlp_opacity=mods["mlp_opacity"], mlp_cov=mods["mlp_cov"],
                          mlp_color=mods["mlp_color"], mlp_feature_bank=mods.get("mlp_feature_bank"),
                          # Decoders.modules() builds the appearance code as an nn.Embedding (embedding_from_state)
                          embedding_appearance=cast("nn.Embedding | None", mods.get("embedding_appearance")))
    backend = OctreeGSBackend()
    for dec in ("mlp_opacity", "mlp_cov", "mlp_color"):
        layout = backend.input_layout(model, dec) or []
        check_first_width(getattr(model, dec), sum(w for _, w in layout), name=dec, source=source,
                          layout=", ".join(f"{n} {w}" for n, w in layout))
    return model


def _load_octree_gs(root: Path, iteration: int | None, trust_code: bool) -> OctreeGSModel:
    cfg_path = root / "cfg_args"
    cfg = {**CFG_DEFAULTS, **read_cfg_args(cfg_path)}
    folder = iteration_dir(root, iteration, family="Octree-GS")
    ply = folder / "point_cloud.ply"
    t, _ = _read_anchor_ply(ply, int(cfg["feat_dim"]), int(cfg["n_offsets"]), str(cfg_path))
    fields = t.pop("_fields")
    require_fields(fields, ["info"], source=str(ply))
    info = fields["info"]
    if info.shape[0] < 2:
        raise FileFormatError(f"{ply}: the 'info' column holds voxel_size and standard_dist in rows 0 and 1; the file has {info.shape[0]} anchors")
    return _build(t, folder, trust_code, f"{folder} + {cfg_path}", voxel_size=float(info[0]),
                  standard_dist=float(info[1]), fork=int(cfg["fork"]), dist2level=str(cfg["dist2level"]),
                  add_level=bool(cfg["add_level"]), add_opacity_dist=bool(cfg["add_opacity_dist"]),
                  add_cov_dist=bool(cfg["add_cov_dist"]), add_color_dist=bool(cfg["add_color_dist"]))


def _load_octree_anygs(root: Path, iteration: int | None, trust_code: bool) -> OctreeGSModel:
    yaml_path = root / "config.yaml"
    raw = read_yaml_scalars(yaml_path)

    def get(key: str, default: Any) -> Any:
        values = raw.get(key) or [default]
        if len({repr(v) for v in values}) > 1:
            raise FileFormatError(f"{yaml_path}: key {key!r} has several values {values}; cannot tell which is the model's")
        if key not in CFG_KEYS:
            return values[0]
        kind, low = CFG_KEYS[key]
        return cfg_value(values[0], kind, key=key, source=str(yaml_path), low=low)

    base = get("base_model", "scaffoldgs")
    if base != "scaffoldgs":
        raise FileFormatError(f"{yaml_path}: base_model {base!r}: only Octree-AnyGS's Scaffold-GS base model ('scaffoldgs') "
                              f"has neural decoders for ControlGS to condition")
    folder = iteration_dir(root, iteration, family="Octree-AnyGS")
    ply = folder / "point_cloud.ply"
    t, comments = _read_anchor_ply(ply, int(get("feat_dim", 32)), int(get("n_offsets", 10)), str(yaml_path))
    t.pop("_fields")
    meta = dict(c.split(None, 1) for c in comments if len(c.split()) == 2)
    try:
        standard_dist, levels = float(meta["standard_dist"]), int(float(meta["levels"]))
    except (KeyError, ValueError) as e:
        raise FileFormatError(f"{ply}: the header must carry 'obj_info standard_dist <v>' and 'obj_info levels <v>' "
                              f"(Octree-AnyGS's LOD metadata); got {comments}") from e
    return _build(t, folder, trust_code, f"{folder} + {yaml_path}", voxel_size=0.0, standard_dist=standard_dist,
                  levels=levels, fork=int(get("fork", 2)), dist2level=str(get("dist2level", "round")), voxel_centre=False)
