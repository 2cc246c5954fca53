"""Backend and loader for ContextGS (wyf0912/ContextGS).

ContextGS is HAC-like: the render decoders ``mlp_opacity``, ``mlp_cov``, ``mlp_color`` take
``[feat, view, dist]`` (54 -> 50 by default; FC1 = ``mlp_x[0]``, D1 = ``feat_dim``), decoder row
i is anchor ``visible_mask.nonzero()[i]``. Its compression modules are an anchor-level context
model (``latent_codec`` entropy bottleneck over per-anchor hyper-latents ``_hyper_latent [A, F/4]``,
``mlp_grid`` ModuleList), none of which feeds a decoder's FC1.

Anchor positions as the decoder sees them: ``get_anchor`` quantises ``_anchor`` to 16 bits per
axis inside ``[x_bound_min, x_bound_max]`` (``q = clamp(floor((a - lo) / step), 0, 2^16 - 1)``,
``step = (hi - lo) / (2^16 - 1) + 1e-6``, position ``q * step + lo``) unless ``decoded_version``.

Invalid anchors: the decoded model is **zero-padded** from the valid count to the full count
(padding rows: position 0, all masks 0) and anchors with every offset masked off produce no
Gaussian; see :mod:`backends.hac` for how they interact with the condition table.
:func:`load_contextgs_dir` drops them.

On disk: ``point_cloud/iteration_<it>/point_cloud.ply`` (``x,y,z,nx,ny,nz, f_offset_*,
f_mask_0..K-1, f_anchor_feat_*, f_hyper_latent_*, opacity, scale_*, rot_*``), ``checkpoint.pth``
(``opacity_mlp, cov_mlp, color_mlp, [mlp_feature_bank], latent_codec, grid_mlp,
bound=[x_bound_min, x_bound_max], level_scale``) and ``cfg_args``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from controlgs_adapter.backend import has_attrs
from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.anchor_model import anchor_visibility, as_param
from controlgs_adapter.formats.decoders import check_first_width
from controlgs_adapter.formats.backbone import check_finite_weights, load_state_dict_file, read_cfg_args
from controlgs_adapter.formats.layout import iteration_dir
from .hac import (CONTEXTGS_MARKERS, HACBackend, MaskedAnchorModel, anchor_tensors, decoders_from_checkpoint,
                  drop_invalid, read_masked_anchor_ply, resolve_decoded)
from .scaffold_gs import ATTRIBUTE_DECODERS, ScaffoldGSBackend

__all__ = ["ContextGSBackend", "ContextGSModel", "load_contextgs_dir", "quantize_anchor"]

ANCHOR_BITS = 16


def quantize_anchor(anchor: torch.Tensor, x_bound_min: torch.Tensor, x_bound_max: torch.Tensor) -> torch.Tensor:
    """ContextGS's anchor quantisation (``get_anchor`` of a not-decoded model). ``[A, 3]`` ->
    ``[A, 3]``; bounds ``[1, 3]`` or ``[3]``."""
    levels = 2 ** ANCHOR_BITS - 1
    lo, hi = x_bound_min.to(anchor).reshape(1, 3), x_bound_max.to(anchor).reshape(1, 3)
    step = (hi - lo) * (1.0 / levels) + 1e-6
    q = torch.clamp(torch.div(anchor - lo, step, rounding_mode="floor"), 0, levels)
    return q * step + lo


class ContextGSBackend(HACBackend):
    """ContextGS: HAC-style decoders on ``[feat, view, dist]``; anchors 16-bit quantised in a bound."""

    name = "contextgs"

    def matches(self, model: Any) -> bool:
        return ScaffoldGSBackend.matches(self, model) and has_attrs(model, ("_mask", *CONTEXTGS_MARKERS))

    def decoder_paths(self, model: Any) -> list[str]:
        """The three attribute decoders: ContextGS's renderer never calls ``mlp_feature_bank``."""
        return list(ATTRIBUTE_DECODERS)


class ContextGSModel(MaskedAnchorModel):
    """Stand-in for ContextGS's ``GaussianModel`` at evaluation (see :class:`MaskedAnchorModel`),
    plus ``_hyper_latent [A, F/4]`` and ``x_bound_min``/``x_bound_max`` ``[1, 3]``. The context
    model (``latent_codec``, ``mlp_grid``) is not loaded (None): a decoded model does not use it."""

    # buffers (registered in __init__; nn.Module's attribute lookup does not type them)
    x_bound_min: torch.Tensor | None
    x_bound_max: torch.Tensor | None
    prefilter_rotation: torch.Tensor

    def __init__(self, *, hyper_latent: torch.Tensor, x_bound_min: torch.Tensor | None = None,
                 x_bound_max: torch.Tensor | None = None, **kw: Any) -> None:
        super().__init__(**kw)
        check_tensor("hyper_latent", hyper_latent, [self._anchor.shape[0], "H"])
        self._hyper_latent = as_param(hyper_latent)
        if (x_bound_min is None) != (x_bound_max is None):
            raise FileFormatError("x_bound_min and x_bound_max must be given together")
        if x_bound_min is None and not self.decoded_version:
            raise FileFormatError("a not-decoded ContextGS model needs x_bound_min/x_bound_max (its anchors are quantised in them)")
        self.register_buffer("x_bound_min", None if x_bound_min is None else x_bound_min.float().reshape(1, 3).clone())
        self.register_buffer("x_bound_max", None if x_bound_max is None else x_bound_max.float().reshape(1, 3).clone())
        self.latent_codec = None
        self.mlp_grid = None
        # ContextGS's prefilter gives every anchor the rotation of the model's anchor 0 (row 0 of the
        # file: kept here before invalid anchors are dropped)
        self.register_buffer("prefilter_rotation", self._rotation[:1].detach().clone())

    @torch.no_grad()
    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        """``[A]`` bool: ContextGS's ``prefilter_voxel``: anchors as Gaussians as in HAC, but with the
        rotation of its anchor 0 (``rotations[[0], :].repeat(...)``) for every anchor."""
        rot = self.prefilter_rotation.to(self._rotation).expand(self._anchor.shape[0], 4)
        return anchor_visibility(camera, self.get_anchor, self.get_scaling, rot)  # the first 3 scales are used

    @property
    def get_anchor(self) -> torch.Tensor:
        """``[A, 3]``: stored positions if decoded, else 16-bit quantised in the bound."""
        if self.decoded_version:
            return self._anchor
        if self.x_bound_min is None or self.x_bound_max is None:
            raise InputValueError("a not-decoded ContextGS model needs x_bound_min/x_bound_max (its anchors are "
                                  "quantised in them); this one was built as a decoded model")
        return quantize_anchor(self._anchor, self.x_bound_min, self.x_bound_max)


def load_contextgs_dir(path: str | Path, iteration: int | None = None, *, decoded: bool | None = None,
                       allow_unquantized: bool = False) -> ContextGSModel:
    """Load a ContextGS output directory into a :class:`ContextGSModel`. ``decoded=None`` infers
    decoded-vs-raw from the PLY (linear scales and binary masks = decoded). Zero-padding and other
    anchors with every offset masked off are dropped (``model.source_index`` keeps PLY rows).

    Raises:
        FileFormatError: a missing/inconsistent file, or a raw model without ``allow_unquantized``.
    """
    root = Path(path)
    cfg = read_cfg_args(root / "cfg_args")
    k, f = int(cfg.get("n_offsets", 10)), int(cfg.get("feat_dim", 50))
    folder = iteration_dir(root, iteration, family="ContextGS")
    ply = folder / "point_cloud.ply"
    arrays = read_masked_anchor_ply(ply, n_offsets=k, feat_dim=f, mask_columns=(k,))
    if "hyper_latent" not in arrays:
        raise FileFormatError(f"{ply}: missing PLY field(s) ['f_hyper_latent_0'] (not a ContextGS point cloud?)")
    is_decoded = resolve_decoded(decoded, arrays, extra_mask_column=False, allow_unquantized=allow_unquantized,
                                 source=str(ply), family="ContextGS",
                                 why="with its anchor-level context model (latent_codec entropy bottleneck + mlp_grid)")
    ckpt = folder / "checkpoint.pth"
    sd = load_state_dict_file(ckpt)
    decoders = decoders_from_checkpoint(sd, ckpt, feature_bank=False)  # its renderer never applies the bank
    bound = sd.get("bound")
    lo = hi = None
    if bound is not None:
        if not (isinstance(bound, (list, tuple)) and len(bound) == 2 and all(torch.is_tensor(b) and b.numel() == 3 for b in bound)):
            raise FileFormatError(f"{ckpt}: entry 'bound' must be [x_bound_min, x_bound_max], two 3-vectors")
        check_finite_weights({"bound": bound}, source=str(ckpt))
        lo, hi = bound
    elif not is_decoded:
        raise FileFormatError(f"{ckpt}: missing entry 'bound' ([x_bound_min, x_bound_max]) needed to quantise the raw model's anchors")
    model = ContextGSModel(hyper_latent=torch.from_numpy(np.ascontiguousarray(arrays["hyper_latent"])), x_bound_min=lo,
                           x_bound_max=hi, decoded_version=is_decoded, **anchor_tensors(arrays), **decoders)
    for dec in ("mlp_opacity", "mlp_cov", "mlp_color"):
        check_first_width(getattr(model, dec), f + 4, name=dec, source=str(ckpt), layout="feat, view 3, dist 1")
    return drop_invalid(model)
