"""Backend and loader for HAC++ (YihangChen-ee/HAC-plus) and HAC (YihangChen-ee/HAC).

Both are Scaffold-GS with entropy-coded anchors. The render decoders ``mlp_opacity``,
``mlp_cov``, ``mlp_color`` always take ``[feat, view, dist]`` (``feat_dim + 4`` = 54 -> 50 by
default; FC1 = ``mlp_x[0]``, D1 = ``feat_dim``); the compression modules (``encoding_xyz`` hash
grid, ``mlp_grid``, ``mlp_deform``, entropy models) never feed a decoder's FC1. Decoder row i is
anchor ``visible_mask.nonzero()[i]`` as in Scaffold-GS.

Anchor positions as the decoder sees them: ``get_anchor`` snaps ``_anchor`` to the voxel grid
(``round(_anchor / voxel_size) * voxel_size``) unless the model is the decoded one
(``decoded_version``), whose stored positions are already the decoded values.

Invalid anchors: ``_mask [A, K(+1), 1]`` switches offsets off; an anchor whose K offset masks are
all off produces no Gaussian at evaluation (its rows still reach the decoders, and its Gaussians
are dropped after them). :meth:`HACBackend.valid_anchors` reports them; the condition table keeps
one row per model anchor (so ids stay the model's own) and the rows of invalid anchors stay inert:
no Gaussian carries their injection, so they get no gradient and stay at their zero init.
:func:`load_hac_dir` drops them when it builds the stand-in (they contribute nothing).

On disk: ``point_cloud/iteration_<it>/point_cloud.ply`` (``x,y,z, nx,ny,nz, f_offset_*,
f_mask_0..K (HAC++: K+1 columns; HAC: K), f_anchor_feat_*, opacity, scale_0..5, rot_0..3``) and
``checkpoint.pth`` (state dicts ``opacity_mlp, cov_mlp, color_mlp, [mlp_feature_bank],
encoding_xyz, grid_mlp, deform_mlp``), ``cfg_args`` at the root. With the default ``run_codec=True``
the saved PLY is the *decoded* model: scales are linear (not log), masks binary, HAC++ anchors
Morton-sorted (not the training order), HAC anchors zero-padded at the end.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch
from torch import nn

from controlgs_adapter.backend import has_attrs
from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.anchor_model import AnchorModel, NeuralGaussians, anchor_visibility, as_param, assemble_gaussians, feature_bank
from controlgs_adapter.formats.decoders import DECODER_ACTIVATIONS, ATTRIBUTE_DECODERS, check_first_width, decoders_from_state_dicts
from controlgs_adapter.formats.backbone import load_state_dict_file, ply_columns, ply_offsets, ply_xyz, read_cfg_args, read_ply, require_fields
from controlgs_adapter.formats.layout import iteration_dir
from .scaffold_gs import ScaffoldGSBackend

__all__ = ["HACBackend", "HACModel", "MaskedAnchorModel", "load_hac_dir", "infer_decoded", "DECODER_ACTIVATIONS"]

#: Attribute names that tell a HAC/HAC++ model from plain Scaffold-GS.
HAC_MARKERS: tuple[str, ...] = ("_mask", "mlp_grid", "encoding_xyz")
#: ContextGS carries these instead of the hash grid (see backends/contextgs.py).
CONTEXTGS_MARKERS: tuple[str, ...] = ("latent_codec", "_hyper_latent")

#: Entries of ``checkpoint.pth`` that hold the decoders (HAC/HAC++ and ContextGS).
CHECKPOINT_KEYS: dict[str, str] = {"mlp_opacity": "opacity_mlp", "mlp_cov": "cov_mlp", "mlp_color": "color_mlp",
                                   "mlp_feature_bank": "mlp_feature_bank"}

_MASK_THRESHOLD = 0.01  # sigmoid(_mask) > 0.01 switches an offset on (not-decoded models)


class HACBackend(ScaffoldGSBackend):
    """HAC++ / HAC: Scaffold-GS decoders on ``[feat, view, dist]``, masked offsets, snapped anchors."""

    name = "hac"

    def matches(self, model: Any) -> bool:
        return (super().matches(model) and has_attrs(model, HAC_MARKERS)
                and not has_attrs(model, CONTEXTGS_MARKERS))

    def valid_anchors(self, model: Any) -> torch.Tensor:
        """``[A]`` bool: anchors with at least one offset switched on (the family's ``get_mask_anchor``)."""
        return _valid_from_mask(model.get_mask)

    def input_layout(self, model: Any, decoder_path: str) -> list[tuple[str, int]] | None:
        """Inputs of the attribute decoders' FC1, in order: ``[feat, view, dist]`` (None for the
        feature bank or a model without ``feat_dim``)."""
        if decoder_path not in ATTRIBUTE_DECODERS or not hasattr(model, "feat_dim"):
            return None
        return [("feat", int(model.feat_dim)), ("view", 3), ("dist", 1)]


def _valid_from_mask(mask: torch.Tensor) -> torch.Tensor:
    """``get_mask`` ``[A, K, 1]`` (0/1 or STE float) -> ``[A]`` bool: any offset on."""
    return mask.detach().reshape(mask.shape[0], -1).sum(dim=1) > 0


class MaskedAnchorModel(AnchorModel):
    """Common part of the HAC/HAC++ and ContextGS stand-ins: Scaffold-GS attribute names plus
    ``_mask`` and ``decoded_version``; decoders take ``[feat, view, dist]``.

    Shapes: ``_anchor [A, 3]``, ``_offset [A, K, 3]``, ``_mask [A, M, 1]`` (M = K, or K + 1 in
    HAC++), ``_anchor_feat [A, F]``, ``_scaling [A, 6]`` (linear if ``decoded_version`` else log).
    ``source_index [A]`` (long buffer) is each anchor's row in the file it was loaded from.
    Subclasses define :attr:`get_anchor` (the family's anchor positions as the decoders see them).
    """

    source_index: torch.Tensor  # buffer (registered in __init__; nn.Module's attribute lookup does not type it)

    def __init__(self, *, anchor: torch.Tensor, offset: torch.Tensor, mask: torch.Tensor, anchor_feat: torch.Tensor,
                 scaling: torch.Tensor, mlp_opacity: nn.Module, mlp_cov: nn.Module, mlp_color: nn.Module,
                 decoded_version: bool, mlp_feature_bank: nn.Module | None = None, rotation: torch.Tensor | None = None,
                 opacity: torch.Tensor | None = None, source_index: torch.Tensor | None = None) -> None:
        super().__init__()
        dims = check_tensor("anchor", anchor, ["A", 3])
        dims = check_tensor("offset", offset, ["A", "K", 3], dims=dims)
        check_tensor("mask", mask, ["A", "M", 1], dims=dims)
        check_tensor("anchor_feat", anchor_feat, ["A", "F"], dims=dims)
        check_tensor("scaling", scaling, ["A", 6], dims=dims)
        n = anchor.shape[0]
        self._anchor, self._offset, self._mask = as_param(anchor), as_param(offset), as_param(mask)
        self._anchor_feat, self._scaling = as_param(anchor_feat), as_param(scaling)
        self._rotation = as_param(rotation if rotation is not None else torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1))
        self._opacity = as_param(opacity if opacity is not None else torch.zeros(n, 1))
        self.register_buffer("source_index", source_index.clone() if source_index is not None else torch.arange(n))
        self.mlp_opacity, self.mlp_cov, self.mlp_color = mlp_opacity, mlp_cov, mlp_color
        self.mlp_feature_bank = mlp_feature_bank
        self.use_feat_bank = mlp_feature_bank is not None
        self.feat_dim, self.n_offsets = anchor_feat.shape[1], offset.shape[1]
        self.decoded_version = bool(decoded_version)
        self.requires_grad_(False)
        self.eval()

    @property
    def get_scaling(self) -> torch.Tensor:
        return self._scaling if self.decoded_version else torch.exp(self._scaling)

    @property
    def get_anchor(self) -> torch.Tensor:
        """``[A, 3]`` anchor positions as the decoders see them."""
        raise NotImplementedError

    @property
    def get_mask(self) -> torch.Tensor:
        """``[A, K, 1]`` offset masks in {0, 1} (forward value of the family's straight-through mask)."""
        m = self._mask[:, : self.n_offsets]
        return m if self.decoded_version else (torch.sigmoid(m) > _MASK_THRESHOLD).to(m.dtype)

    @property
    def get_mask_anchor(self) -> torch.Tensor:
        """``[A]`` bool: anchors with at least one offset on."""
        return _valid_from_mask(self.get_mask)

    def decoder_inputs(self, cam_center: torch.Tensor, anchor_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        """The common input ``[feat, view, dist]`` ``[R, F + 4]`` of the three decoders for the
        anchors ``anchor_ids`` (rows in that order), as the family's renderer builds it."""
        anchor = self.get_anchor[anchor_ids]
        feat = self._anchor_feat[anchor_ids]
        view = anchor - cam_center.to(anchor)
        dist = torch.linalg.vector_norm(view, dim=1, keepdim=True)
        view = view / dist
        if self.mlp_feature_bank is not None:
            feat = feature_bank(feat, self.mlp_feature_bank(torch.cat([view, dist], dim=1)))
        x = torch.cat([feat, view, dist], dim=1)
        return {"mlp_opacity": x, "mlp_cov": x, "mlp_color": x}

    @torch.no_grad()
    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        """``[A]`` bool: the family's ``prefilter_voxel`` (anchors as Gaussians; no mask filtering)."""
        return anchor_visibility(camera, self.get_anchor, self.get_scaling, self._rotation)  # the first 3 scales

    def decode(self, camera: Camera, visible_mask: torch.Tensor | None = None, **options: Any) -> NeuralGaussians:
        """Decode the anchors in ``visible_mask`` (``[A]`` bool; None = all) as the family's renderer at
        evaluation: Gaussians with neural opacity > 0 **and** their offset mask on are kept. No option is taken."""
        self.refuse_options(options)
        ids = self.decoded_ids(visible_mask, self._anchor)
        x = self.decoder_inputs(camera.center, ids)
        opacity = self.mlp_opacity(x["mlp_opacity"]).reshape(-1)  # [R*K]
        color = self.mlp_color(x["mlp_color"]).reshape(-1, 3)
        scale_rot = self.mlp_cov(x["mlp_cov"]).reshape(-1, 7)
        keep = (opacity > 0) & (self.get_mask[ids].reshape(-1) > 0)
        return assemble_gaussians(ids, self.n_offsets, self.get_anchor[ids], self._offset[ids].reshape(-1, 3),
                                  self.get_scaling[ids], opacity, color, scale_rot, keep)


class HACModel(MaskedAnchorModel):
    """Stand-in for HAC++'s (``variant="hac++"``, ``_mask [A, K+1, 1]``) or HAC's (``"hac"``,
    ``_mask [A, K, 1]``) ``GaussianModel`` at evaluation. The compression-only modules
    (``encoding_xyz``, ``mlp_grid``) are not loaded (None): a decoded model does not use them."""

    def __init__(self, *, voxel_size: float, variant: str = "hac++", **kw: Any) -> None:
        super().__init__(**kw)
        if variant not in ("hac++", "hac"):
            raise InputValueError(f"variant must be 'hac++' or 'hac', got {variant!r}")
        want = self.n_offsets + (1 if variant == "hac++" else 0)
        if self._mask.shape[1] != want:
            raise InputValueError(f"{variant}: mask must have {want} columns (n_offsets={self.n_offsets}), got {self._mask.shape[1]}")
        self.variant, self.voxel_size = variant, float(voxel_size)
        self.encoding_xyz = None
        self.mlp_grid = None

    @property
    def get_anchor(self) -> torch.Tensor:
        """``[A, 3]``: stored positions if decoded, else snapped to the voxel grid."""
        return self._anchor if self.decoded_version else voxel_snap(self._anchor, self.voxel_size)


def voxel_snap(anchor: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """HAC/HAC++ ``get_anchor`` of a not-decoded model: ``round(anchor / voxel_size) * voxel_size``. ``[A, 3]``."""
    return torch.round(anchor / voxel_size) * voxel_size


def infer_decoded(scales: np.ndarray, masks: np.ndarray, *, extra_mask_column: bool) -> bool | None:
    """Whether a HAC/ContextGS PLY holds the decoded model, from what their codecs write: offset masks
    exactly 0/1 (a binary arithmetic coder; HAC++'s extra column is filled with 0) and linear scales
    ``round(s / Q) * Q`` with a step Q of about 1e-3, hence >= 0 and exactly 0 where a scale is
    below Q / 2. A raw model holds mask logits and log scales. Returns True (decoded), False (raw:
    some mask is not 0/1) or None (0/1 masks with negative scales: the file does not tell).
    All-zero rows (the zero padding of decoded HAC/ContextGS models) pass both tests as they are."""
    binary = bool(np.isin(masks, (0.0, 1.0)).all())
    if extra_mask_column:
        binary = binary and bool((masks[:, -1] == 0).all())
    if not binary:
        return False
    return True if bool((scales >= 0).all()) else None


def decoders_from_checkpoint(sd: dict[str, Any], path: Path, *, feature_bank: bool) -> dict[str, nn.Module]:
    """Rebuild ``mlp_opacity``, ``mlp_cov``, ``mlp_color`` (and the feature bank) from a HAC-family
    ``checkpoint.pth`` of state dicts ``sd`` (entries :data:`CHECKPOINT_KEYS`) read from ``path``."""
    if feature_bank and "mlp_feature_bank" not in sd:
        raise FileFormatError(f"{path}: missing entry 'mlp_feature_bank' (cfg_args has use_feat_bank=True)")
    keys = CHECKPOINT_KEYS if feature_bank else {a: CHECKPOINT_KEYS[a] for a in ATTRIBUTE_DECODERS}
    return decoders_from_state_dicts(sd, keys, source=str(path))


def read_masked_anchor_ply(ply: Path, *, n_offsets: int, feat_dim: int,
                           mask_columns: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Read the common PLY columns of HAC/HAC++/ContextGS into arrays (see module docstring);
    ``mask_columns`` lists the allowed numbers of ``f_mask_*`` columns."""
    fields, _ = read_ply(ply)
    src = str(ply)
    require_fields(fields, ["x", "y", "z", *(f"scale_{i}" for i in range(6))], source=src)
    feat = ply_columns(fields, "f_anchor_feat_", source=src)
    if feat.shape[1] != feat_dim:
        raise FileFormatError(f"{src}: {feat.shape[1]} f_anchor_feat_* fields, the configuration says feat_dim={feat_dim}")
    mask = ply_columns(fields, "f_mask_", source=src)
    if mask.shape[1] not in mask_columns:
        raise FileFormatError(f"{src}: {mask.shape[1]} f_mask_* fields, expected {' or '.join(map(str, mask_columns))} "
                              f"for n_offsets={n_offsets}")
    out = {
        "anchor": ply_xyz(fields),
        "offset": ply_offsets(fields, n_offsets, source=src), "mask": mask[:, :, None], "anchor_feat": feat,
        "scaling": ply_columns(fields, "scale_", count=6, source=src),
    }
    if "rot_0" in fields:
        out["rotation"] = ply_columns(fields, "rot_", count=4, source=src)
    if "f_hyper_latent_0" in fields:
        out["hyper_latent"] = ply_columns(fields, "f_hyper_latent_", source=src)
    return out


def resolve_decoded(decoded: bool | None, arrays: dict[str, np.ndarray], *, extra_mask_column: bool, allow_unquantized: bool,
                    source: str, family: str, why: str) -> bool:
    """Resolve decoded-vs-raw (explicit, else inferred by :func:`infer_decoded`) and refuse a raw
    model unless allowed. A file that does not tell is refused whatever ``allow_unquantized`` says:
    reading decoded linear scales as log scales (or the reverse) would be silently wrong."""
    if decoded is None:
        decoded = infer_decoded(arrays["scaling"], arrays["mask"][:, :, 0], extra_mask_column=extra_mask_column)
        if decoded is None:
            negative = int((arrays["scaling"] < 0).sum())
            raise FileFormatError(
                f"{source}: cannot tell whether this {family} model is decoded: its masks are 0/1 as the codec writes "
                f"them, but {negative} scale_* value(s) are negative (decoded scales are linear, >= 0). Pass "
                f"decoded=True if training wrote it with run_codec=True (linear scales), decoded=False for a raw "
                f"checkpoint (log scales; also needs allow_unquantized=True)")
    if not decoded and not allow_unquantized:
        raise FileFormatError(
            f"{source}: holds the raw (not decoded) {family} model (mask logits and log scales, not the 0/1 masks and "
            f"linear scales its codec writes). Its evaluation quantises features {why}, which this library does not "
            f"reimplement. Use the decoded PLY that training writes with run_codec=True (the default), wrap the live "
            f"model object, or pass allow_unquantized=True to decode the stored features unquantised (log scales "
            f"exponentiated; differs from {family}'s own evaluation at the quantisation step)."
        )
    return bool(decoded)


def load_hac_dir(path: str | Path, iteration: int | None = None, *, decoded: bool | None = None,
                 allow_unquantized: bool = False) -> HACModel:
    """Load a HAC++ or HAC output directory into a :class:`HACModel` (variant from the number of
    ``f_mask_*`` columns). ``decoded=None`` infers decoded-vs-raw (see :func:`infer_decoded`).
    Anchors whose offsets are all masked off (HAC's zero padding included) are dropped;
    ``model.source_index`` keeps each remaining anchor's PLY row.

    Raises:
        FileFormatError: a missing/inconsistent file, or a raw model without ``allow_unquantized``.
    """
    root = Path(path)
    cfg_path = root / "cfg_args"
    cfg = read_cfg_args(cfg_path)
    k, f = int(cfg.get("n_offsets", 10)), int(cfg.get("feat_dim", 50))
    if bool(cfg.get("use_feat_bank", False)) and f % 4:
        raise FileFormatError(
            f"{cfg_path}: use_feat_bank=True with feat_dim={f} is not supported: the feature-bank re-weighting repeats "
            f"every 4th feature channel 4 times, which needs feat_dim divisible by 4 ({f} channels give "
            f"{4 * -(-f // 4)}); HAC++'s own renderer fails on it as well")
    folder = iteration_dir(root, iteration, family="HAC/HAC++")
    ply = folder / "point_cloud.ply"
    arrays = read_masked_anchor_ply(ply, n_offsets=k, feat_dim=f, mask_columns=(k, k + 1))  # HAC: K, HAC++: K + 1
    variant = "hac++" if arrays["mask"].shape[1] == k + 1 else "hac"
    is_decoded = resolve_decoded(decoded, arrays, extra_mask_column=variant == "hac++", allow_unquantized=allow_unquantized,
                                 source=str(ply), family=variant.upper(), why="with the hash grid + mlp_grid "
                                 "(interpolated inside x_bound, which bitstreams/x_bound_*.pkl hold)")
    voxel_size = float(cfg.get("voxel_size", 0.0))
    if not is_decoded and voxel_size <= 0:
        raise FileFormatError(f"{cfg_path}: voxel_size={voxel_size}: the raw model's anchors are snapped to a voxel grid "
                              f"whose size was estimated at training time and not saved; cannot reproduce get_anchor")
    ckpt = folder / "checkpoint.pth"
    decoders = decoders_from_checkpoint(load_state_dict_file(ckpt), ckpt, feature_bank=bool(cfg.get("use_feat_bank", False)))
    model = HACModel(voxel_size=voxel_size, variant=variant, decoded_version=is_decoded, **anchor_tensors(arrays), **decoders)
    for dec in ("mlp_opacity", "mlp_cov", "mlp_color"):
        check_first_width(getattr(model, dec), f + 4, name=dec, source=str(folder / "checkpoint.pth"), layout="feat, view 3, dist 1")
    return drop_invalid(model)


def anchor_tensors(arrays: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """The arrays of :func:`read_masked_anchor_ply` that :class:`MaskedAnchorModel` takes, as tensors."""
    keep = ("anchor", "offset", "mask", "anchor_feat", "scaling", "rotation")
    return {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in arrays.items() if k in keep}


MaskedModel = TypeVar("MaskedModel", bound=MaskedAnchorModel)


def drop_invalid(model: MaskedModel) -> MaskedModel:
    """Keep only anchors with some offset switched on (in place; returns the model)."""
    keep = model.get_mask_anchor
    if bool(keep.all()):
        return model
    for name in ("_anchor", "_offset", "_mask", "_anchor_feat", "_scaling", "_rotation", "_opacity", "_hyper_latent"):
        p = getattr(model, name, None)
        if isinstance(p, nn.Parameter):
            setattr(model, name, nn.Parameter(p.data[keep].clone(), requires_grad=False))
    model.source_index = model.source_index[keep].clone()
    return model
