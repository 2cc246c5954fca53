"""Backend and loader for CompGS (LiuXiangrui/CompGS, neural-Gaussian CompGS).

CompGS's ``GaussianModel`` holds ``network.prediction_net`` (four ``ResidualMLP`` decoders) and
``gaussian_params`` (per anchor: ``means [A, 3]``, ``scales_before_exp [A, 6]``,
``rotations_before_norm [A, 4]``, ``ref_feats [A, C]``; per coupled primitive ``res_feats [A, K, G]``).

Decoders: ``means_pred_mlp``, ``covariance_pred_mlp`` (input ``[ref_feat, res_feat]``, C + G) and
``opacity_pred_mlp``, ``color_pred_mlp`` (``[ref_feat, res_feat, view 3, dist 1]``). A
``ResidualMLP`` is ``net = Sequential(Linear(in, C), LeakyReLU, ResidualBlock x n, Linear(C, out))``
plus a parallel ``skip = Linear(in, out)``; output ``tail(net(x) + skip(x))``. FC1 is ``net[0]``
(D1 = C); the skip path is left untouched, so the injection enters only through ``net``.

Rows: the decoders run per **coupled primitive**, K rows per visible anchor (row r is anchor
``anchor_ids[r // K]``, slot ``r % K``): :meth:`CompGSBackend.rows_per_anchor` = K.

Geometry is decoded too: Gaussian mean = anchor + ``means_pred_mlp(x) * exp(scales[:, :3])``, so
a condition injected into ``means_pred_mlp`` (a default target) can move Gaussian means, e.g. the
lens condition can learn a geometric pre-warp; leave it out with
``ControlGS.wrap(..., targets=[...])`` to keep geometry fixed.

On disk: training checkpoints ``<exp>/point_cloud/iteration_<it>/point_cloud.ply`` (``x,y,z,
nx,ny,nz, f_res_feat_0..K*G-1`` (k-major: ``f_res_feat_{k*G + g}``), ``f_ref_feat_0..C-1``,
``scale_0..5`` (before exp), ``rot_0..3``) + ``weights.pth`` (``network.state_dict()``). The final
``<exp>/point_cloud/weights.pth`` + ``bitstreams.npz`` holds G-PCC-coded, Morton-reordered anchors
and is refused (see :func:`load_compgs_dir`). No configuration file is saved: C, G, K come from
the weight shapes and PLY columns.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from torch import nn

from controlgs_adapter.backend import Backend, has_attrs
from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.state import Camera

from controlgs_adapter.backends.models.anchor_model import AnchorModel, NeuralGaussians, anchor_visibility, as_param, assemble_gaussians
from controlgs_adapter.formats.backbone import (check_finite_weights, load_state_dict_file, ply_columns, ply_xyz, read_ply,
                                                 require_fields)
from controlgs_adapter.formats.layout import iteration_dir

__all__ = ["CompGSBackend", "CompGSModel", "ResidualMLP", "load_compgs_dir", "COMPGS_DECODERS"]

#: Decoder paths (all targets by default) and their tail activations.
COMPGS_DECODERS: tuple[str, ...] = tuple(f"network.prediction_net.{n}_pred_mlp" for n in ("means", "covariance", "opacity", "color"))
_TAILS: dict[str, type[nn.Module] | None] = {"means": None, "covariance": None, "opacity": nn.Tanh, "color": nn.Sigmoid}
_RES_LAYERS = {"means": 1, "covariance": 1, "opacity": 1, "color": 2}
COMPGS_MARKERS: tuple[str, ...] = ("network.prediction_net", "gaussian_params.ref_feats", "gaussian_params.res_feats",
                                   "gaussian_params.means")


class ResidualBlock(nn.Module):
    """``x + net(x)``, ``net = Sequential(Linear(d, d), LeakyReLU, Linear(d, d))``."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(dim, dim), nn.LeakyReLU(), nn.Linear(dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.net(x)


class ResidualMLP(nn.Module):
    """CompGS's decoder: ``tail(net(x) + skip(x))`` (parameter names as in CompGS's state dict).
    ``x [rows, in_dim]`` -> ``[rows, out_dim]``."""

    def __init__(self, in_dim: int, internal_dim: int, out_dim: int, num_res_layer: int = 1,
                 tail: nn.Module | None = None) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, internal_dim), nn.LeakyReLU(),
                                 *(ResidualBlock(internal_dim) for _ in range(num_res_layer)),
                                 nn.Linear(internal_dim, out_dim))
        self.skip = nn.Identity() if in_dim == out_dim else nn.Linear(in_dim, out_dim)
        self.tail_activation = tail if tail is not None else nn.Identity()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.tail_activation(self.net(x) + self.skip(x))


class CompGSBackend(Backend):
    """CompGS: ``ResidualMLP`` decoders (FC1 = ``net[0]``, skip untouched), K rows per anchor,
    geometry decoded by ``means_pred_mlp``."""

    name = "compgs"

    def matches(self, model: Any) -> bool:
        return has_attrs(model, COMPGS_MARKERS) and all(has_attrs(model, (p + ".net",)) for p in COMPGS_DECODERS)

    def decoder_paths(self, model: Any) -> list[str]:
        return list(COMPGS_DECODERS)

    def first_linear_path(self, model: Any, decoder_path: str) -> str:
        return f"{decoder_path}.net.0"

    def input_layout(self, model: Any, decoder_path: str) -> list[tuple[str, int]]:
        """Inputs of a decoder's FC1 (``net[0]``) in order: ``[ref C, res G]`` (+ ``[view 3, dist 1]``
        for opacity and colour)."""
        p = model.gaussian_params
        layout = [("ref_feat", int(p.ref_feats.shape[1])), ("res_feat", int(p.res_feats.shape[2]))]
        if decoder_path.endswith(("opacity_pred_mlp", "color_pred_mlp")):
            layout += [("view", 3), ("dist", 1)]
        return layout

    def anchor_positions(self, model: Any) -> torch.Tensor:
        means = model.gaussian_params.means
        check_tensor("model.gaussian_params.means", means, ["A", 3])
        return means

    def rows_per_anchor(self, model: Any) -> int:
        res = model.gaussian_params.res_feats
        check_tensor("model.gaussian_params.res_feats", res, [self.num_anchors(model), "K", "G"])
        return int(res.shape[1])

    @staticmethod
    def row_anchor_ids(anchor_ids: torch.Tensor, rows_per_anchor: int) -> torch.Tensor:
        """``[R_a]`` anchor ids -> ``[R_a * K]`` anchor of each decoder row (``repeat_interleave``)."""
        return anchor_ids.repeat_interleave(rows_per_anchor)


class _Params(nn.Module):
    def __init__(self, means: torch.Tensor, scales_before_exp: torch.Tensor, rotations_before_norm: torch.Tensor,
                 ref_feats: torch.Tensor, res_feats: torch.Tensor) -> None:
        super().__init__()
        self.means, self.scales_before_exp = as_param(means), as_param(scales_before_exp)
        self.rotations_before_norm, self.ref_feats, self.res_feats = (as_param(rotations_before_norm), as_param(ref_feats),
                                                                       as_param(res_feats))


class _PredictionNet(nn.Module):
    # the four decoders (set in __init__ by name; nn.Module's attribute lookup does not type them)
    means_pred_mlp: ResidualMLP
    covariance_pred_mlp: ResidualMLP
    opacity_pred_mlp: ResidualMLP
    color_pred_mlp: ResidualMLP

    def __init__(self, ref_dim: int, res_dim: int, derive_factor: int) -> None:
        super().__init__()
        self.derive_factor = derive_factor
        c, g = ref_dim, res_dim
        for name in ("means", "covariance", "opacity", "color"):
            view = 4 if name in ("opacity", "color") else 0
            out = {"means": 3, "covariance": 7, "opacity": 1, "color": 3}[name]
            tail_cls = _TAILS[name]
            tail = tail_cls() if tail_cls is not None else None
            setattr(self, f"{name}_pred_mlp", ResidualMLP(c + g + view, c, out, _RES_LAYERS[name], tail))


class _Network(nn.Module):
    def __init__(self, prediction_net: _PredictionNet) -> None:
        super().__init__()
        self.prediction_net = prediction_net
        self.entropy_model = None


class CompGSModel(AnchorModel):
    """Stand-in for CompGS's ``GaussianModel`` (evaluation): ``network.prediction_net.*_pred_mlp``
    and ``gaussian_params.{means, scales_before_exp, rotations_before_norm, ref_feats, res_feats}``.
    The entropy model is not loaded (``network.entropy_model`` is None)."""

    def __init__(self, *, means: torch.Tensor, scales_before_exp: torch.Tensor, ref_feats: torch.Tensor,
                 res_feats: torch.Tensor, rotations_before_norm: torch.Tensor | None = None) -> None:
        super().__init__()
        dims = check_tensor("means", means, ["A", 3])
        check_tensor("scales_before_exp", scales_before_exp, ["A", 6], dims=dims)
        dims = check_tensor("ref_feats", ref_feats, ["A", "C"], dims=dims)
        dims = check_tensor("res_feats", res_feats, ["A", "K", "G"], dims=dims)
        rot = rotations_before_norm if rotations_before_norm is not None else torch.tensor([[1.0, 0, 0, 0]]).repeat(dims["A"], 1)
        self.gaussian_params = _Params(means, scales_before_exp, rot, ref_feats, res_feats)
        self.derive_factor = dims["K"]
        self.network = _Network(_PredictionNet(dims["C"], dims["G"], dims["K"]))
        self.requires_grad_(False)
        self.eval()

    def decoder_inputs(self, cam_center: torch.Tensor, anchor_ids: torch.Tensor) -> dict[str, torch.Tensor]:
        """Inputs of the four decoders for the anchors ``anchor_ids``: ``[R_a * K, ·]``, row r =
        anchor ``anchor_ids[r // K]``, slot ``r % K`` (CompGS's ``PredictionNetwork.forward``)."""
        p, k = self.gaussian_params, self.derive_factor
        ref = p.ref_feats[anchor_ids].repeat_interleave(k, dim=0)  # [R*K, C]
        res = p.res_feats[anchor_ids].reshape(-1, p.res_feats.shape[2])  # [R*K, G]
        feats = torch.cat([ref, res], dim=1)
        vec = p.means[anchor_ids] - cam_center.to(p.means)
        dist = torch.linalg.vector_norm(vec, dim=1, keepdim=True)
        view = torch.cat([vec / dist, dist], dim=1).repeat_interleave(k, dim=0)  # [R*K, 4]
        with_view = torch.cat([feats, view], dim=1)
        names = dict(zip(("means", "covariance", "opacity", "color"), COMPGS_DECODERS))
        return {names["means"]: feats, names["covariance"]: feats, names["opacity"]: with_view, names["color"]: with_view}

    @torch.no_grad()
    def visible_anchors(self, camera: Camera) -> torch.Tensor:
        """``[A]`` bool: CompGS's prefilter (anchors as Gaussians with scales ``exp(scale[:, :3])``).

        As its ``render_inference`` on decoded values: the training-time ``render`` first quantises
        the scales with the hyper-prior entropy model (``anchor_primitive_scales``), which is not
        reimplemented (as for the features, :meth:`decode`); on the stored values that step can only
        change the visibility of anchors whose footprint touches the image border."""
        p = self.gaussian_params
        return anchor_visibility(camera, p.means, torch.exp(p.scales_before_exp), p.rotations_before_norm)

    def decode(self, camera: Camera, visible_mask: torch.Tensor | None = None, **options: Any) -> NeuralGaussians:
        """Decode the coupled primitives of the anchors in ``visible_mask`` (``[A]`` bool; None =
        all) as CompGS's ``PredictionNetwork.forward`` on the stored (unquantised) features:
        mean = anchor + means_pred * exp(scale[:, :3]); scale = sigmoid(cov[:, :3]) * exp(scale[:, 3:]);
        rotation = normalize(cov[:, 3:]); kept where opacity > 0. No option is taken."""
        self.refuse_options(options)
        p, k = self.gaussian_params, self.derive_factor
        ids = self.decoded_ids(visible_mask, p.means)
        x = self.decoder_inputs(camera.center, ids)
        net = self.network.prediction_net
        offsets = net.means_pred_mlp(x[COMPGS_DECODERS[0]])  # [R*K, 3]
        scale_rot = net.covariance_pred_mlp(x[COMPGS_DECODERS[1]])  # [R*K, 7]
        opacity = net.opacity_pred_mlp(x[COMPGS_DECODERS[2]]).reshape(-1)  # [R*K]
        color = net.color_pred_mlp(x[COMPGS_DECODERS[3]])  # [R*K, 3]
        return assemble_gaussians(ids, k, p.means[ids], offsets, torch.exp(p.scales_before_exp[ids]), opacity, color,
                                  scale_rot, opacity > 0)


def _load_weights(model: CompGSModel, state: Mapping[str, torch.Tensor], source: str) -> None:
    want = {f"prediction_net.{k}": v for k, v in model.network.prediction_net.state_dict().items()}
    missing = [k for k in want if k not in state]
    check_finite_weights({k: state[k] for k in want if k in state}, source=source)
    if missing:
        raise FileFormatError(f"{source}: missing prediction-network weights {missing[:4]}{' ...' if len(missing) > 4 else ''}")
    bad = [f"{k} {list(state[k].shape)} != {list(v.shape)}" for k, v in want.items() if tuple(state[k].shape) != tuple(v.shape)]
    if bad:
        raise FileFormatError(f"{source}: prediction-network weight shapes do not fit the point cloud: {bad[:3]}")
    model.network.prediction_net.load_state_dict({k[len("prediction_net."):]: state[k] for k in want})


def load_compgs_dir(path: str | Path, iteration: int | None = None, *, allow_unquantized: bool = False) -> CompGSModel:
    """Load a CompGS training checkpoint (``<exp>/point_cloud/iteration_<it>/point_cloud.ply`` +
    ``weights.pth``) into a :class:`CompGSModel`. C, G, K are read from the weights and the PLY.

    CompGS's own evaluation quantises ``ref_feats``/``res_feats``/scales with its hyper-prior
    entropy model (compressai modules, not reimplemented here), so decoding the stored features
    differs from it at the quantisation step: loading needs ``allow_unquantized=True``.
    The final ``bitstreams.npz`` (G-PCC-coded positions, needs the external GPCC codec; anchors
    Morton-reordered with no stored mapping to the training order) is refused.

    Raises:
        FileFormatError: naming the file and what is missing or unsupported.
    """
    root = Path(path)
    pc = root / "point_cloud"
    has_iters = pc.is_dir() and any(p.name.startswith("iteration_") for p in pc.iterdir())
    if (pc / "bitstreams.npz").is_file() and not has_iters:
        raise FileFormatError(
            f"{pc / 'bitstreams.npz'}: CompGS's final compressed model is not supported: its anchor positions are "
            f"G-PCC-coded (decoding needs the external GPCC codec) and its anchors are Morton-reordered with no stored "
            f"mapping to the training order. Keep a training checkpoint (point_cloud/iteration_<N>/point_cloud.ply + "
            f"weights.pth) or wrap the live model object."
        )
    folder = iteration_dir(root, iteration, family="CompGS")
    ply, wpath = folder / "point_cloud.ply", folder / "weights.pth"
    state = load_state_dict_file(wpath)
    key = "prediction_net.color_pred_mlp.net.0.weight"
    if key not in state:
        raise FileFormatError(f"{wpath}: missing {key!r} (not a CompGS network state dict?)")
    fields, _ = read_ply(ply)
    src = str(ply)
    require_fields(fields, ["x", "y", "z", *(f"scale_{i}" for i in range(6))], source=src)
    ref = ply_columns(fields, "f_ref_feat_", source=src)
    res_flat = ply_columns(fields, "f_res_feat_", source=src)
    c = ref.shape[1]
    in_dim = int(state[key].shape[1])
    g = in_dim - c - 4
    if state[key].shape[0] != c or g < 1 or res_flat.shape[1] % g:
        raise FileFormatError(f"{wpath}: {key} is {list(state[key].shape)}, which does not fit C={c} f_ref_feat_* "
                              f"and {res_flat.shape[1]} f_res_feat_* fields of {src} ([C, C + G + 4] expected)")
    if not allow_unquantized:
        raise FileFormatError(
            f"{src}: holds CompGS's unquantised features; CompGS's evaluation quantises them with its hyper-prior entropy "
            f"model (in {wpath.name}, compressai modules not reimplemented here). Pass allow_unquantized=True to decode "
            f"the stored features as they are (differs from CompGS's own evaluation), or wrap the live model object."
        )
    k = res_flat.shape[1] // g
    rot = ply_columns(fields, "rot_", count=4, source=src) if "rot_0" in fields else None
    model = CompGSModel(
        means=torch.from_numpy(ply_xyz(fields)),
        scales_before_exp=torch.from_numpy(ply_columns(fields, "scale_", count=6, source=src)),
        ref_feats=torch.from_numpy(ref), res_feats=torch.from_numpy(np.ascontiguousarray(res_flat.reshape(-1, k, g))),
        rotations_before_norm=None if rot is None else torch.from_numpy(rot),
    )
    _load_weights(model, state, str(wpath))
    return model
