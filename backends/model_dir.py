"""Trained output folders of any supported family: which family wrote a folder, told from its file
names and PLY header alone (nothing is executed, unpickled or fully read), and its loader.

Layouts (``docs/reference/backends.md``), ``<it>`` = ``point_cloud/iteration_<N>``:

| family | tell-tale files |
|---|---|
| ``compgs`` | ``<it>/weights.pth``, PLY ``f_ref_feat_*`` / ``f_res_feat_*`` |
| ``contextgs`` | ``<it>/checkpoint.pth``, PLY ``f_mask_*`` and ``f_hyper_latent_*`` |
| ``hac`` (HAC++ / HAC) | ``<it>/checkpoint.pth``, PLY ``f_mask_*`` |
| ``octree_gs`` (Octree-GS / Octree-AnyGS) | ``cfg_args`` or ``config.yaml``, PLY ``level`` and ``extra_level`` |
| ``scaffold_gs`` | PLY ``f_anchor_feat_*`` / ``f_offset_*``, ``<it>/opacity_mlp.pt`` or ``<it>/checkpoints.pth`` |
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING

from controlgs_adapter.errors import FileFormatError, InputValueError

from controlgs_adapter.formats.layout import bitstreams_only, check_iteration, iteration_dirs
from controlgs_adapter.formats.backbone import ply_field_names

if TYPE_CHECKING:  # the loaders (and the model base) are imported by load_model_dir when it runs
    from .models.anchor_model import AnchorModel

__all__ = ["FAMILIES", "detect_family", "load_model_dir"]

#: family name -> what its output folder holds (for messages)
FAMILIES: dict[str, str] = {
    "scaffold_gs": "point_cloud/iteration_<N>/point_cloud.ply with f_anchor_feat_*/f_offset_* fields and the decoders "
                   "opacity_mlp.pt, cov_mlp.pt, color_mlp.pt (or checkpoints.pth); cfg_args optional",
    "octree_gs": "cfg_args (Octree-GS) or config.yaml (Octree-AnyGS) and point_cloud/iteration_<N>/point_cloud.ply with "
                 "level and extra_level fields plus the decoders (*_mlp.pt or checkpoints.pth)",
    "hac": "cfg_args and point_cloud/iteration_<N>/{point_cloud.ply with f_mask_* fields, checkpoint.pth}",
    "contextgs": "cfg_args and point_cloud/iteration_<N>/{point_cloud.ply with f_mask_* and f_hyper_latent_* fields, "
                 "checkpoint.pth}",
    "compgs": "point_cloud/iteration_<N>/{point_cloud.ply with f_ref_feat_*/f_res_feat_* fields, weights.pth}",
}
_FILES = ("opacity_mlp.pt", "checkpoints.pth", "checkpoint.pth", "weights.pth")


def _iteration_folder(root: Path, iteration: int | None) -> Path | None:
    """``point_cloud/iteration_<N>`` (``iteration`` or the largest N); None when there is none."""
    pc = root / "point_cloud"
    found = iteration_dirs(root)
    iteration = check_iteration(iteration)
    if iteration is not None:
        if iteration not in found:
            raise FileFormatError(f"{pc}: no 'iteration_{iteration}' folder (present: {sorted(found)})")
        return found[iteration]
    return found[max(found)] if found else None


def _unrecognised(root: Path, found: str) -> FileFormatError:
    needs = "; ".join(f"{name}: {what}" for name, what in FAMILIES.items())
    return FileFormatError(f"{root}: not a trained model folder of a supported family ({found}). Each family needs: {needs}")


def detect_family(path: str | Path, *, iteration: int | None = None) -> str:
    """The family (a key of :data:`FAMILIES`) whose output folder ``path`` is, from its file names and
    PLY header. Raises :class:`FileFormatError` naming the folder, what it holds and what each family needs."""
    root = Path(path)
    if not root.is_dir():
        raise FileFormatError(f"{root}: no such model folder")
    folder = _iteration_folder(root, iteration)
    if folder is None:
        if (root / "point_cloud" / "bitstreams.npz").is_file():
            return "compgs"  # CompGS's final compressed model: its loader says why it is refused
        raise _unrecognised(root, "no point_cloud/iteration_<N> folder" + bitstreams_only(root))
    ply = folder / "point_cloud.ply"
    if not ply.is_file():
        raise _unrecognised(root, f"no {ply.relative_to(root)}")
    fields = ply_field_names(ply)
    files = [n for n in _FILES if (folder / n).is_file()]

    def has(prefix: str) -> bool:
        return any(f.startswith(prefix) for f in fields)

    if "weights.pth" in files or has("f_ref_feat_"):
        return "compgs"
    if "checkpoint.pth" in files and has("f_mask_"):
        return "contextgs" if has("f_hyper_latent_") else "hac"
    if "level" in fields and "extra_level" in fields:
        return "octree_gs"
    if has("f_anchor_feat_") and has("f_offset_") and ("opacity_mlp.pt" in files or "checkpoints.pth" in files):
        return "scaffold_gs"
    shown = [f for f in fields if not re.search(r"_\d+$", f) or f.endswith("_0")]
    raise _unrecognised(root, f"{ply.relative_to(root)} has fields {shown}, {folder.relative_to(root)} holds "
                              f"{files or 'none of ' + ', '.join(_FILES)}")


def load_model_dir(path: str | Path, *, family: str | None = None, iteration: int | None = None,
                   allow_unquantized: bool = False, trust_code: bool = False) -> AnchorModel:
    """Load a trained output folder of any supported family as its stand-in model (eval mode, frozen).

    Args:
        path: the folder the family's training wrote (``-m`` / ``model_path``).
        family: force a family (a key of :data:`FAMILIES`); None detects it (:func:`detect_family`).
        iteration: which ``point_cloud/iteration_<N>``; None = the largest N.
        allow_unquantized: HAC++/HAC/ContextGS raw checkpoints and CompGS: decode the stored
            (unquantised) values (see ``docs/reference/backends.md``).
        trust_code: Scaffold-GS / Octree-GS TorchScript decoders read with ``torch.jit.load``.

    Raises:
        FileFormatError: an unrecognised folder, or what the family's loader refuses.
        InputValueError: an unknown ``family``.
    """
    if family is None:
        family = detect_family(path, iteration=iteration)
    elif family not in FAMILIES:
        raise InputValueError(f"unknown family {family!r} (supported: {', '.join(FAMILIES)})")
    model: AnchorModel
    if family == "scaffold_gs":
        from .scaffold_io import load_scaffold_dir

        model = load_scaffold_dir(path, iteration, trust_code=trust_code)
    elif family == "octree_gs":
        from .octree_gs import load_octree_gs_dir

        model = load_octree_gs_dir(path, iteration, trust_code=trust_code)
    elif family == "hac":
        from .hac import load_hac_dir

        model = load_hac_dir(path, iteration, allow_unquantized=allow_unquantized)
    elif family == "contextgs":
        from .contextgs import load_contextgs_dir

        model = load_contextgs_dir(path, iteration, allow_unquantized=allow_unquantized)
    else:
        from .compgs import load_compgs_dir

        model = load_compgs_dir(path, iteration, allow_unquantized=allow_unquantized)
    return model.eval()
