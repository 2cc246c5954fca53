"""Read and write Scaffold-GS output directories without the original repository or CUDA.

Layout (exactly as Scaffold-GS's ``Scene.save`` / ``train.py`` write it)::

    <model>/cfg_args                                   str(argparse.Namespace(**model_params))
    <model>/point_cloud/iteration_<N>/point_cloud.ply  binary little-endian, float32 vertex fields
        x, y, z, nx, ny, nz (zeros), f_offset_0 .. f_offset_{3K-1}, f_anchor_feat_0 .. f_anchor_feat_{F-1},
        opacity, scale_0 .. scale_5 (log), rot_0 .. rot_3
    <model>/point_cloud/iteration_<N>/{opacity,cov,color}_mlp.pt   torch.jit.trace of each decoder ('split')
        [+ feature_bank_mlp.pt if use_feat_bank] [+ embedding_appearance.pt if appearance_dim > 0]
    or  <model>/point_cloud/iteration_<N>/checkpoints.pth          ('unite') dict of state dicts:
        opacity_mlp, cov_mlp, color_mlp [, feature_bank_mlp] [, appearance]

``f_offset_{c * K + k}`` is coordinate ``c`` of offset ``k`` (Scaffold-GS saves
``_offset.transpose(1, 2).flatten(1)``). Nothing in the folder is run or unpickled: TorchScript
archives are read as data (:func:`controlgs_adapter.formats.torchscript.eager_from_archive`; ``torch.jit.load``
only with ``trust_code=True``), state dicts go through ``torch.load(weights_only=True)``,
``cfg_args`` through an ``ast`` literal parser. See ``docs/reference/reference-model.md``.
"""

from __future__ import annotations

import copy
import os
import shutil
import tempfile
from argparse import Namespace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.safetensors import atomic_write, folder_mode

from controlgs_adapter.formats.decoders import MLP_FILES, UNITE_FILE, Decoders
from controlgs_adapter.formats.backbone import ply_columns, ply_field_names, ply_offsets, ply_xyz, read_cfg_args, read_ply, require_fields, write_ply
from controlgs_adapter.formats.layout import iteration_dir
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, median_spacing

__all__ = ["save_scaffold_dir", "load_scaffold_dir", "latest_iteration", "MLP_FILES"]

_OPTION_KEYS = ("feat_dim", "n_offsets", "use_feat_bank", "appearance_dim", "add_opacity_dist", "add_cov_dist",
                "add_color_dist")


# ============================================================================ saving

def _cfg_namespace(model: NeuralGaussianModel, model_path: Path) -> Namespace:
    """Scaffold-GS's ``ModelParams`` as ``train.py`` records them (same keys, same order)."""
    return Namespace(
        sh_degree=3, feat_dim=model.feat_dim, n_offsets=model.n_offsets, voxel_size=model.voxel_size,
        update_depth=3, update_init_factor=16, update_hierachy_factor=4, use_feat_bank=model.use_feat_bank,
        source_path="", model_path=str(model_path), images="images", resolution=-1, white_background=False,
        data_device="cuda", eval=True, lod=0, appearance_dim=model.appearance_dim, lowpoly=False, ds=1, ratio=1,
        undistorted=False, add_opacity_dist=model.add_opacity_dist, add_cov_dist=model.add_cov_dist,
        add_color_dist=model.add_color_dist,
    )


def _ply_fields(model: NeuralGaussianModel) -> dict[str, np.ndarray]:
    def cols(prefix: str, x: torch.Tensor) -> dict[str, np.ndarray]:
        arr = x.detach().to("cpu", torch.float32).numpy()
        return {f"{prefix}{i}": np.ascontiguousarray(arr[:, i]) for i in range(arr.shape[1])}

    a = model.num_anchors
    anchor = model._anchor.detach().to("cpu", torch.float32).numpy()
    offsets = model._offset.detach().transpose(1, 2).flatten(1)  # [A, 3K]: column c*K + k
    return {
        "x": anchor[:, 0].copy(), "y": anchor[:, 1].copy(), "z": anchor[:, 2].copy(),
        "nx": np.zeros(a, np.float32), "ny": np.zeros(a, np.float32), "nz": np.zeros(a, np.float32),
        **cols("f_offset_", offsets), **cols("f_anchor_feat_", model._anchor_feat),
        "opacity": model._opacity.detach().to("cpu", torch.float32).numpy()[:, 0].copy(),
        **cols("scale_", model._scaling), **cols("rot_", model._rotation),
    }


def _mlp_inputs(model: NeuralGaussianModel) -> dict[str, int]:
    f = model.feat_dim
    widths = {"mlp_opacity": f + 3 + model.opacity_dist_dim, "mlp_cov": f + 3 + model.cov_dist_dim,
              "mlp_color": f + 3 + model.color_dist_dim + model.appearance_dim}
    if model.use_feat_bank:
        widths["mlp_feature_bank"] = 3 + 1
    return widths


def save_scaffold_dir(model: NeuralGaussianModel, path: str | os.PathLike, iteration: int,
                      mlp_mode: str = "split") -> Path:
    """Write ``model`` as a Scaffold-GS output directory (module docstring) and return the
    ``point_cloud/iteration_<iteration>`` folder.

    ``mlp_mode="split"`` traces each decoder with ``torch.jit.trace`` on a ``torch.rand(1, width)``
    example in eval mode (as Scaffold-GS's ``save_mlp_checkpoints``; traced from a float32 CPU copy
    so the files load anywhere); ``"unite"`` writes one ``checkpoints.pth`` of state dicts. The
    iteration folder is assembled in a temporary sibling and renamed into place, and ``cfg_args``
    is written atomically, so a reader never sees a half-written model.
    """
    if mlp_mode not in ("split", "unite"):
        raise InputValueError(f"mlp_mode must be 'split' or 'unite', got {mlp_mode!r}")
    if int(iteration) < 0:
        raise InputValueError(f"iteration must be >= 0, got {iteration!r}")
    root = Path(path)
    parent = root / "point_cloud"
    parent.mkdir(parents=True, exist_ok=True)
    final = parent / f"iteration_{int(iteration)}"
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", dir=parent))
    os.chmod(tmp, folder_mode())  # mkdtemp makes it 0700; the model folder gets the umask's mode
    try:
        write_ply(tmp / "point_cloud.ply", _ply_fields(model))
        modules = {name: getattr(model, name) for name in MLP_FILES if getattr(model, name, None) is not None}
        if mlp_mode == "split":
            examples = {name: torch.rand(1, width) for name, width in _mlp_inputs(model).items()}
            examples["embedding_appearance"] = torch.zeros((1,), dtype=torch.long)
            for name, module in modules.items():
                cpu = copy.deepcopy(module).to("cpu", torch.float32).eval()
                torch.jit.trace(cpu, examples[name]).save(str(tmp / MLP_FILES[name][0]))
        else:
            state = {MLP_FILES[name][1]: {k: v.detach().to("cpu", torch.float32) for k, v in m.state_dict().items()}
                     for name, m in modules.items()}
            torch.save(state, tmp / UNITE_FILE)
        backup = None
        if final.exists():
            backup = Path(tempfile.mkdtemp(prefix=f".{final.name}.old.", dir=parent))
            os.replace(final, backup / final.name)
        os.replace(tmp, final)
        if backup is not None:
            shutil.rmtree(backup, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    cfg = str(_cfg_namespace(model, root))
    atomic_write(root / "cfg_args", lambda p: Path(p).write_text(cfg))
    return final


# ============================================================================ loading

def latest_iteration(path: str | os.PathLike) -> int:
    """Largest ``N`` of the ``<path>/point_cloud/iteration_<N>`` folders."""
    return int(iteration_dir(Path(path), None, family="Scaffold-GS").name.removeprefix("iteration_"))


def _read_anchors(ply: Path) -> dict[str, np.ndarray]:
    fields, _ = read_ply(ply)
    src = str(ply)
    require_fields(fields, ["x", "y", "z", "opacity", *(f"scale_{i}" for i in range(6)),
                            *(f"rot_{i}" for i in range(4)), "f_offset_0", "f_anchor_feat_0"], source=src)
    for name, col in fields.items():
        if col.dtype.kind != "f":
            raise FileFormatError(f"{src}: PLY field {name!r} must be float, got {col.dtype}")
        bad = int((~np.isfinite(col)).sum())
        if bad:
            raise FileFormatError(f"{src}: PLY field {name!r} holds {bad} non-finite value(s)")
    n_offset = ply_columns(fields, "f_offset_", source=src).shape[1]
    if n_offset % 3:
        raise FileFormatError(f"{src}: {n_offset} PLY fields f_offset_* is not 3 x n_offsets")
    scales, rots = ply_columns(fields, "scale_", source=src), ply_columns(fields, "rot_", source=src)
    if scales.shape[1] != 6 or rots.shape[1] != 4:
        raise FileFormatError(f"{src}: expected PLY fields scale_0..scale_5 and rot_0..rot_3, got "
                              f"{scales.shape[1]} scale_* and {rots.shape[1]} rot_*")
    return {
        "anchor": ply_xyz(fields),
        "offset": ply_offsets(fields, n_offset // 3, source=src),  # [A, K, 3]
        "feat": ply_columns(fields, "f_anchor_feat_", source=src),
        "opacity": fields["opacity"].astype(np.float32)[:, None],
        "scaling": scales,
        "rotation": rots,
    }


def _expected_layers(name: str, opts: dict[str, Any]) -> list[tuple[str, tuple[int, int] | None]]:
    """``[(layer type, (in, out) for Linear)]`` of a decoder for the given widths and options."""
    f, k, a = opts["feat_dim"], opts["n_offsets"], opts["appearance_dim"]
    d_in, d_out, act = {
        "mlp_opacity": (f + 3 + int(opts["add_opacity_dist"]), k, "Tanh"),
        "mlp_cov": (f + 3 + int(opts["add_cov_dist"]), 7 * k, None),
        "mlp_color": (f + 3 + int(opts["add_color_dist"]) + a, 3 * k, "Sigmoid"),
        "mlp_feature_bank": (4, 3, "Softmax"),
    }[name]
    return [("Linear", (d_in, f)), ("ReLU", None), ("Linear", (f, d_out)), *([(act, None)] if act else [])]


def _infer_options(anchors: dict[str, np.ndarray], dec: Decoders, cfg: dict[str, Any], cfg_src: str) -> dict[str, Any]:
    """Widths/options from cfg_args where present, else from the files; then every width is checked."""
    f, k = anchors["feat"].shape[1], anchors["offset"].shape[1]
    emb = dec.weight("embedding_appearance", "embedding.weight") if "embedding_appearance" in dec.state else None
    a = int(emb.shape[1]) if emb is not None else 0

    def first_in(name: str) -> int:
        w = dec.weight(name, "0.weight")
        if w.dim() != 2:
            raise FileFormatError(f"{dec.source[name]}: decoder {name!r} layer 0 weight must be 2-D, got {list(w.shape)}")
        return int(w.shape[1])

    inferred = {"feat_dim": f, "n_offsets": k, "appearance_dim": a, "use_feat_bank": "mlp_feature_bank" in dec.state,
                "add_opacity_dist": first_in("mlp_opacity") - f - 3 == 1, "add_cov_dist": first_in("mlp_cov") - f - 3 == 1,
                "add_color_dist": first_in("mlp_color") - f - 3 - a == 1}
    opts = {key: cfg.get(key, inferred[key]) for key in _OPTION_KEYS}
    for key in _OPTION_KEYS:  # cfg_args against the PLY and the MLP files
        if key in cfg and type(inferred[key])(cfg[key]) != inferred[key]:
            where = {"feat_dim": "PLY fields f_anchor_feat_*", "n_offsets": "PLY fields f_offset_* (3 x n_offsets)",
                     "appearance_dim": "embedding_appearance", "use_feat_bank": "feature bank MLP"}.get(key, "MLP input width")
            raise FileFormatError(f"{cfg_src}: {key}={cfg[key]!r} disagrees with the files ({where} give {inferred[key]!r})")
    for name in ("mlp_opacity", "mlp_cov", "mlp_color", "mlp_feature_bank"):
        if name not in dec.state:
            continue
        want = _expected_layers(name, opts)
        got = dec.layers.get(name)
        if got is None:  # unite mode: only the Linear shapes are in the file
            got = [("Linear", tuple(dec.weight(name, f"{i}.weight").shape[::-1])) if kind == "Linear" else (kind, None)
                   for i, (kind, _) in enumerate(want)]
        if got != want:
            raise FileFormatError(
                f"{dec.source[name]}: decoder {name!r} has layers {got}, expected {want} for feat_dim={f}, "
                f"n_offsets={k} (PLY: {k} offsets, {f} features) and the options "
                f"{ {key: opts[key] for key in _OPTION_KEYS[2:]} }")
    return opts


def _refuse_octree(root: Path, ply: Path, cfg: dict[str, Any]) -> None:
    """An Octree-GS / Octree-AnyGS folder has Scaffold-GS's files plus levels of detail: loading it
    flat would decode every level at once, so it is refused naming its loader."""
    fields = set(ply_field_names(ply)) if ply.is_file() else set()
    signs = sorted(fields & {"level", "extra_level", "info"})
    signs += [f"cfg_args {k}" for k in ("fork", "dist2level", "add_level") if k in cfg]
    if (root / "config.yaml").is_file():
        signs.append("config.yaml")
    if signs:
        raise FileFormatError(f"{root}: an Octree-GS / Octree-AnyGS output folder ({', '.join(signs)}), not a flat "
                              "Scaffold-GS one: load it with controlgs_adapter.backends.octree_gs.load_octree_gs_dir "
                              "or controlgs_adapter.backends.load_model_dir (levels of detail selected per view)")


def load_scaffold_dir(path: str | os.PathLike, iteration: int | None = None, *,
                      device: str | torch.device = "cpu", trust_code: bool = False) -> NeuralGaussianModel:
    """Load a Scaffold-GS output directory as a :class:`NeuralGaussianModel` (eager decoders).

    Args:
        path: the model directory (holding ``cfg_args`` and ``point_cloud/``).
        iteration: which ``point_cloud/iteration_<N>``; None = the largest N.
        device: where the returned model lives.
        trust_code: read TorchScript decoders with ``torch.jit.load``, which can run code stored in
            the archives: only for folders you trust whose decoders are outside the supported
            subset. By default nothing in the folder runs.

    Widths and options come from ``cfg_args`` (keys ``feat_dim, n_offsets, appearance_dim,
    use_feat_bank, add_{opacity,cov,color}_dist, voxel_size``) and are checked against the PLY and
    every decoder's layer types and shapes; keys missing from ``cfg_args`` (or a missing
    ``cfg_args``) are inferred from the files. TorchScript decoders are read as data, never run,
    and rebuilt as eager ``nn.Sequential`` s (:func:`controlgs_adapter.formats.torchscript.eager_from_archive`).

    Raises:
        FileFormatError: naming the file and the field: no iteration folder, missing/truncated
            PLY or missing PLY fields, non-finite values, missing MLP, MLP widths that do not fit
            the PLY's feature/offset counts or cfg_args, unreadable TorchScript or state dict
            (arbitrary pickled objects are refused), a TorchScript decoder outside the supported
            subset (code beyond a chain of layers, ``__setstate__``, foreign globals, NaN weights).
    """
    root = Path(path)
    folder = iteration_dir(root, iteration, family="Scaffold-GS")
    cfg_path = root / "cfg_args"
    cfg = read_cfg_args(cfg_path) if cfg_path.is_file() else {}
    _refuse_octree(root, folder / "point_cloud.ply", cfg)
    anchors = _read_anchors(folder / "point_cloud.ply")
    dec = Decoders(folder, trust_code)
    opts = _infer_options(anchors, dec, cfg, str(cfg_path))
    voxel = float(cfg.get("voxel_size", 0) or 0)
    if voxel <= 0:  # Scaffold-GS picks it from the point cloud when the argument is <= 0
        voxel = median_spacing(torch.from_numpy(anchors["anchor"]))
    num_cameras = int(dec.state["embedding_appearance"]["embedding.weight"].shape[0]) if opts["appearance_dim"] else 1
    model = NeuralGaussianModel(anchors["anchor"].shape[0], voxel_size=voxel, num_cameras=num_cameras,
                                **{key: opts[key] for key in _OPTION_KEYS})
    with torch.no_grad():
        for attr, key in (("_anchor", "anchor"), ("_offset", "offset"), ("_anchor_feat", "feat"),
                          ("_opacity", "opacity"), ("_scaling", "scaling"), ("_rotation", "rotation")):
            getattr(model, attr).copy_(torch.from_numpy(np.ascontiguousarray(anchors[key])))
    for name, sd in dec.state.items():
        try:
            getattr(model, name).load_state_dict(sd, strict=True)
        except RuntimeError as e:
            raise FileFormatError(f"{dec.source[name]}: decoder {name!r} does not fit: {str(e).splitlines()[0]} "
                                  f"{' '.join(str(e).split())[:300]}") from e
    return model.to(device).eval()
