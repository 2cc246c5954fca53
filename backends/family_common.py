"""Pieces shared by the Octree-GS, HAC/HAC++, ContextGS and CompGS backends: reading their output
directories (iteration folders, PLY column groups, state-dict MLPs, ``config.yaml`` scalars),
turning masks into the anchor ids that :meth:`ControlGS.conditioned` takes, and the stand-ins'
prefilter/decode/splat steps (shared with the reference Scaffold-GS model).

Every reader raises :class:`~controlgs_adapter.errors.FileFormatError` naming the file and what is
missing; nothing here unpickles arbitrary objects.
"""

from __future__ import annotations

import re
from pathlib import Path
from types import SimpleNamespace
from typing import Mapping, Sequence

import numpy as np
import torch
from torch import nn

from controlgs_adapter.checks import check_tensor
from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.rasterizers import rasterize_gaussians
from controlgs_adapter.state import Camera

from .reference_model import NeuralGaussianModel, NeuralGaussians
from .splatter import RasterOutput

__all__ = [
    "anchor_ids_from_mask", "iteration_dir", "ply_columns", "ply_offsets", "mlp_from_state_dict", "check_first_width",
    "as_param", "has_attrs", "voxel_snap", "read_yaml_scalars", "anchor_visibility", "assemble_gaussians",
    "render_gaussians",
]


def has_attrs(obj: object, names: Sequence[str]) -> bool:
    """True if every dotted name resolves on ``obj`` (values may be None)."""
    for name in names:
        cur = obj
        for part in name.split("."):
            if not hasattr(cur, part):
                return False
            cur = getattr(cur, part)
    return True


def anchor_ids_from_mask(mask: torch.Tensor, num_anchors: int | None = None, *, name: str = "visible_mask") -> torch.Tensor:
    """``[A]`` bool mask -> ``[R]`` ascending anchor ids: the order boolean indexing gives, i.e.
    row ``i`` of a decoder input sliced with ``mask`` is anchor ``ids[i]``."""
    check_tensor(name, mask, ["A"] if num_anchors is None else [num_anchors], dtypes=(torch.bool,))
    return mask.nonzero().squeeze(1)


def voxel_snap(anchor: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """HAC/HAC++ ``get_anchor`` of a not-decoded model: ``round(anchor / voxel_size) * voxel_size``. ``[A, 3]``."""
    return torch.round(anchor / voxel_size) * voxel_size


def bitstreams_only(root: str | Path) -> str:
    """A sentence for a folder that holds the compressed ``bitstreams/`` but no decoded point cloud
    (empty when it holds no ``bitstreams/``)."""
    if not (Path(root) / "bitstreams").is_dir():
        return ""
    return ("; bitstreams/ was found, but it cannot be decoded here (it needs the family's arithmetic coders, and "
            "G-PCC for HAC++ positions): keep the point_cloud/iteration_<N> folder training writes next to it "
            "(with run_codec=True it holds the decoded model)")


def iteration_dir(root: str | Path, iteration: int | None, *, family: str) -> Path:
    """``<root>/point_cloud/iteration_<it>``: the given iteration or the highest one present."""
    pc = Path(root) / "point_cloud"
    if not pc.is_dir():
        raise FileFormatError(f"{Path(root)}: not a {family} output directory (no 'point_cloud/iteration_<N>' folder)"
                              + bitstreams_only(root))
    found = {int(m.group(1)): p for p in pc.iterdir() if p.is_dir() and (m := re.fullmatch(r"iteration_(\d+)", p.name))}
    if iteration is None:
        if not found:
            raise FileFormatError(f"{pc}: no 'iteration_<N>' folder (not a {family} output directory)"
                                  + bitstreams_only(root))
        return found[max(found)]
    if iteration not in found:
        raise FileFormatError(f"{pc}: no 'iteration_{iteration}' folder (present: {sorted(found)})")
    return found[iteration]


_YAML_SCALAR = re.compile(r"^\s*([A-Za-z_]\w*)\s*:\s*([^{}\[\]]*?)\s*,?\s*$")


def _yaml_value(text: str) -> object:
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("null", "none", "~"):
        return None
    for cast in (int, float):
        try:
            return cast(text)  # int("40_000") works as in YAML 1.1
        except ValueError:
            pass
    return text


YAML_MAX_BYTES = 1 << 20


def read_yaml_scalars(path: str | Path) -> dict[str, list[object]]:
    """The ``key: scalar`` entries of a YAML file, block or flow style (Octree-AnyGS's
    ``config.yaml``), without a YAML dependency: ``{key: [value, ...]}`` in file order (a key may
    occur in several sections). Nested structure, lists and multi-line scalars are not read."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"{path}: no such file")
    if path.stat().st_size > YAML_MAX_BYTES:
        raise FileFormatError(f"{path}: {path.stat().st_size} bytes, more than a config file holds (<= {YAML_MAX_BYTES})")
    out: dict[str, list[object]] = {}
    for line in path.read_text(errors="replace").splitlines():
        line = line.split(" #", 1)[0] if not line.lstrip().startswith("#") else ""
        m = _YAML_SCALAR.match(line)
        if m and m.group(2):
            out.setdefault(m.group(1), []).append(_yaml_value(m.group(2)))
    return out


def ply_columns(fields: Mapping[str, np.ndarray], prefix: str, *, source: str, count: int | None = None) -> np.ndarray:
    """Stack ``<prefix>0 .. <prefix>{n-1}`` into ``[V, n]`` float32 (n = ``count`` or all present)."""
    n = count
    if n is None:
        n = 0
        while f"{prefix}{n}" in fields:
            n += 1
    names = [f"{prefix}{i}" for i in range(n)]
    missing = [k for k in names if k not in fields]
    if missing or n == 0:
        raise FileFormatError(f"{source}: missing PLY field(s) {missing or [prefix + '0']}")
    return np.stack([fields[k].astype(np.float32) for k in names], axis=1)


def ply_offsets(fields: Mapping[str, np.ndarray], n_offsets: int, *, source: str) -> np.ndarray:
    """Scaffold-family offsets: ``f_offset_{c*K + k}`` is coordinate c of offset k. -> ``[V, K, 3]``."""
    flat = ply_columns(fields, "f_offset_", source=source)
    if flat.shape[1] != 3 * n_offsets:
        raise FileFormatError(f"{source}: expected {3 * n_offsets} f_offset_* fields (3 x n_offsets={n_offsets}), got {flat.shape[1]}")
    return np.ascontiguousarray(flat.reshape(-1, 3, n_offsets).transpose(0, 2, 1))


def mlp_from_state_dict(state: Mapping[str, torch.Tensor], activations: Mapping[int, nn.Module], *, name: str,
                        source: str) -> nn.Sequential:
    """Rebuild an ``nn.Sequential`` of Linears (at the indices the keys ``<i>.weight`` name) with
    the given activation modules at the other indices, e.g. ``{1: ReLU(), 3: Tanh()}``.

    Raises :class:`FileFormatError` naming ``source``/``name`` if a Linear index collides with an
    activation or the layer widths do not chain.
    """
    if not isinstance(state, Mapping):
        raise FileFormatError(f"{source}: entry {name!r} is not a state dict (got {type(state).__name__})")
    linear_ids = sorted({int(k.split(".")[0]) for k in state if re.fullmatch(r"\d+\.weight", k)})
    if not linear_ids:
        raise FileFormatError(f"{source}: entry {name!r} holds no '<i>.weight' Linear weights (keys: {sorted(state)[:6]})")
    size = max([*linear_ids, *activations]) + 1
    layers: list[nn.Module] = []
    prev_out = None
    for i in range(size):
        if i in linear_ids:
            if i in activations:
                raise FileFormatError(f"{source}: {name!r} has a Linear at index {i} where an activation was expected")
            w = state[f"{i}.weight"]
            b = state.get(f"{i}.bias")
            if w.dim() != 2 or (prev_out is not None and w.shape[1] != prev_out):
                raise FileFormatError(f"{source}: {name!r} layer {i} weight {list(w.shape)} does not take the previous width {prev_out}")
            lin = nn.Linear(w.shape[1], w.shape[0], bias=b is not None)
            with torch.no_grad():
                lin.weight.copy_(w)
                if b is not None:
                    lin.bias.copy_(b)
            layers.append(lin)
            prev_out = w.shape[0]
        elif i in activations:
            layers.append(activations[i])
        else:
            raise FileFormatError(f"{source}: {name!r} has no layer at index {i} (keys: {sorted(state)})")
    return nn.Sequential(*layers)


def check_first_width(decoder: nn.Module, want_in: int, *, name: str, source: str, layout: str) -> None:
    """Raise if the decoder's first Linear does not take ``want_in`` inputs (the family's layout)."""
    fc1 = next(m for m in decoder.modules() if isinstance(m, nn.Linear))
    if fc1.in_features != want_in:
        raise FileFormatError(f"{source}: {name} takes {fc1.in_features} inputs, the configuration gives {want_in} ({layout})")


def as_param(x: np.ndarray | torch.Tensor, requires_grad: bool = False) -> nn.Parameter:
    """A float32 frozen parameter from an array."""
    t = torch.as_tensor(np.ascontiguousarray(x) if isinstance(x, np.ndarray) else x, dtype=torch.float32)
    return nn.Parameter(t.clone(), requires_grad=requires_grad)


def anchor_visibility(camera: Camera, means: torch.Tensor, scales: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """``[A]`` bool: anchors (as Gaussians with ``means [A, 3]``, linear ``scales [A, 3+]``,
    ``rotations [A, 4]``) whose footprint can touch the image: the prefilter of the Scaffold
    family, with the reference model's rule (:meth:`NeuralGaussianModel.visible_anchors`)."""
    view = SimpleNamespace(get_anchor=means, get_scaling=scales, _rotation=rotations)
    return NeuralGaussianModel.visible_anchors(view, camera)


def assemble_gaussians(ids: torch.Tensor, k: int, anchor: torch.Tensor, offsets: torch.Tensor, scaling: torch.Tensor,
                       neural_opacity: torch.Tensor, color: torch.Tensor, scale_rot: torch.Tensor,
                       keep: torch.Tensor) -> NeuralGaussians:
    """Scaffold-family Gaussians from decoder outputs (R anchors, K per anchor, anchor-major rows).

    Args:
        ids: ``[R]`` anchor ids; anchor ``[R, 3]``; scaling ``[R, 6]`` linear (offset scale, base scale).
        offsets: ``[R*K, 3]`` offsets in units of ``scaling[:, :3]`` (CompGS: the means decoder's output).
        neural_opacity ``[R*K]``, color ``[R*K, 3]``, scale_rot ``[R*K, 7]``, keep ``[R*K]`` bool.
    Mean = anchor + offset * scaling[:, :3]; scale = scaling[:, 3:] * sigmoid(scale_rot[:, :3]);
    rotation = normalize(scale_rot[:, 3:7]).
    """
    flat = keep.nonzero().squeeze(1)  # [G]
    row = flat // k
    s = scaling[row]
    return NeuralGaussians(
        means=anchor[row] + offsets[flat] * s[:, :3], scales=s[:, 3:] * torch.sigmoid(scale_rot[flat, :3]),
        rotations=torch.nn.functional.normalize(scale_rot[flat, 3:7], dim=-1), opacities=neural_opacity[flat],
        colors=color[flat], anchor_of=ids[row], offset_of=flat % k, visible_ids=ids, neural_opacity=neural_opacity)


def render_gaussians(g: NeuralGaussians, camera: Camera, background: torch.Tensor | None = None) -> RasterOutput:
    """Splat decoded Gaussians with the rasterizer chosen for their device
    (:func:`~controlgs_adapter.rasterizers.rasterize_gaussians`; ``RasterOutput``)."""
    return rasterize_gaussians(g.means, g.scales, g.rotations, g.opacities, g.colors, camera, background)
