"""Trained output folders of any family: which family wrote a folder (from file names and the PLY header
alone), loading it with ``load_model_dir`` and the options it passes on, and the refusals every family's
loader shares (non-finite weights, malformed cfg_args values, a malformed iteration) naming file and key."""

from __future__ import annotations

import re
import shutil

import helpers.compgs_files as compgs_files
import helpers.contextgs_files as contextgs_files
import helpers.hac_files as hac_files
import helpers.octree_files as octree_files
import numpy as np
import pytest
import torch
from helpers.family_dirs import FAMILIES, poison_first_weight, write_family_dir
from helpers.scaffold_oracle import make_raw_model, write_scaffold_dir_by_hand
from torch import nn

import controlgs_adapter.formats.backbone as backbone_format
from controlgs_adapter import plugins
from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.backends.hac import HACModel
from controlgs_adapter.backends.model_dir import detect_family, load_model_dir
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.octree_gs import OctreeGSModel
from controlgs_adapter.backends.scaffold_io import save_scaffold_dir
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.backbone import write_ply

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # TorchScript decoders: the format under test
WITH_CFG = [f for f in FAMILIES if f != "compgs"]  # CompGS keeps no cfg_args


def _folders(root, seed: int = 0) -> dict[str, tuple[str, type, dict]]:
    """One folder per family and layout under ``root``: {name: (family, model class, loader kwargs)}."""
    out = {}
    for mode in ("split", "unite"):
        write_scaffold_dir_by_hand(root / f"scaffold-{mode}", make_raw_model(12, 8, 4, seed=seed + 1), mode=mode)
        out[f"scaffold-{mode}"] = ("scaffold_gs", NeuralGaussianModel, {})
        octree_files._write_dir(root / f"octree-{mode}", octree_files._arrays(seed),
                                octree_files._decoders(torch.Generator().manual_seed(seed)), mode=mode)
        out[f"octree-{mode}"] = ("octree_gs", OctreeGSModel, {})
    for variant, cols in (("hac++", hac_files.K + 1), ("hac", hac_files.K)):
        hac_files._write_dir(root / variant, hac_files._arrays(seed, decoded=True, mask_cols=cols), hac_files._decoders(seed))
        out[variant] = ("hac", HACModel, {})
    contextgs_files._write_dir(root / "contextgs", contextgs_files._arrays(seed, decoded=True), contextgs_files._decoders(seed))
    out["contextgs"] = ("contextgs", ContextGSModel, {})
    arr = compgs_files._arrays(seed)
    compgs_files._write_checkpoint(root / "compgs", arr, compgs_files._model(arr, seed))
    out["compgs"] = ("compgs", CompGSModel, {"allow_unquantized": True})
    return out


def _fake_folder(root, fields: list[str], files: list[str]):
    """point_cloud/iteration_1 with a 2-vertex PLY holding ``fields`` and empty ``files`` (detection reads
    only the PLY header and the file names)."""
    it = root / "point_cloud" / "iteration_1"
    it.mkdir(parents=True)
    write_ply(it / "point_cloud.ply", {f: np.zeros(2, np.float32) for f in fields})
    for f in files:
        (it / f).write_bytes(b"")
    return root


def _anchors(model) -> int:
    return plugins.select_backend(model, None).num_anchors(model)


# ----------------------------------------------------------------------------------------- detection
def test_every_family_is_detected_and_loaded(tmp_path):
    for name, (family, cls, kw) in _folders(tmp_path).items():
        assert detect_family(tmp_path / name) == family, name
        model = load_model_dir(tmp_path / name, **kw)
        assert isinstance(model, cls) and not model.training and _anchors(model) > 0, name
        assert isinstance(load_model_dir(tmp_path / name, family=family, **kw), cls)


def test_detection_reads_no_decoder(tmp_path, monkeypatch):
    """Detection opens only the PLY header: no torch.load, no TorchScript, no PLY body."""
    folders = _folders(tmp_path)

    def boom(*a, **k):
        raise AssertionError("detection loaded a file")

    monkeypatch.setattr(torch, "load", boom)
    monkeypatch.setattr(torch.jit, "load", boom)
    monkeypatch.setattr(backbone_format, "read_ply", boom)
    for name, (family, _, _) in folders.items():
        assert detect_family(tmp_path / name) == family


@pytest.mark.parametrize("fields, files, family", [
    (["x", "f_ref_feat_0"], [], "compgs"),
    (["x", "f_anchor_feat_0", "f_offset_0"], ["weights.pth", "opacity_mlp.pt"], "compgs"),
    (["x", "f_mask_0", "f_hyper_latent_0", "f_anchor_feat_0"], ["checkpoint.pth"], "contextgs"),
    (["x", "f_mask_0", "f_anchor_feat_0"], ["checkpoint.pth"], "hac"),
    (["x", "level", "extra_level", "f_anchor_feat_0", "f_offset_0"], ["opacity_mlp.pt"], "octree_gs"),
    (["x", "f_mask_0", "level", "extra_level"], [], "octree_gs"),  # masks without checkpoint.pth: not HAC
    (["x", "f_anchor_feat_0", "f_offset_0"], ["opacity_mlp.pt"], "scaffold_gs"),
    (["x", "f_anchor_feat_0", "f_offset_0"], ["checkpoints.pth"], "scaffold_gs"),
])
def test_detection_rules_from_fields_and_file_names(tmp_path, fields, files, family):
    assert detect_family(_fake_folder(tmp_path / "m", fields, files)) == family


def test_a_folder_with_only_compgs_bitstreams_is_detected_as_compgs(tmp_path):
    (tmp_path / "c" / "point_cloud").mkdir(parents=True)
    (tmp_path / "c" / "point_cloud" / "bitstreams.npz").write_bytes(b"")
    assert detect_family(tmp_path / "c") == "compgs"


def test_detection_reads_the_largest_iteration_unless_told(tmp_path):
    root = _fake_folder(tmp_path / "m", ["x", "f_ref_feat_0"], [])  # iteration_1: CompGS
    it7 = root / "point_cloud" / "iteration_7"
    it7.mkdir()
    write_ply(it7 / "point_cloud.ply", {f: np.zeros(2, np.float32) for f in ("x", "f_mask_0", "f_anchor_feat_0")})
    (it7 / "checkpoint.pth").write_bytes(b"")
    assert detect_family(root) == "hac"  # iteration 7 (HAC files), not 1
    assert detect_family(root, iteration=1) == "compgs"


@pytest.mark.parametrize("fields, files, shown, held", [
    (["x", "y", "f_anchor_feat_0", "f_anchor_feat_1", "f_offset_0"], [], "['x', 'y', 'f_anchor_feat_0', 'f_offset_0']",
     "none of opacity_mlp.pt, checkpoints.pth, checkpoint.pth, weights.pth"),
    (["x", "level", "f_anchor_feat_0"], ["opacity_mlp.pt"], "['x', 'level', 'f_anchor_feat_0']", "['opacity_mlp.pt']"),
    (["x", "f_offset_0", "f_offset_1"], ["checkpoints.pth"], "['x', 'f_offset_0']", "['checkpoints.pth']"),
])
def test_unrecognised_folder_names_its_fields_and_files(tmp_path, fields, files, shown, held):
    root = _fake_folder(tmp_path / "m", fields, files)
    with pytest.raises(FileFormatError, match=re.escape(f"point_cloud/iteration_1/point_cloud.ply has fields {shown}, "
                                                        f"point_cloud/iteration_1 holds {held}")):
        detect_family(root)


def test_detection_and_loading_refusals_name_what_is_missing(tmp_path):
    for load in (detect_family, load_model_dir):
        with pytest.raises(FileFormatError, match="nowhere: no such model folder"):
            load(tmp_path / "nowhere")
    (tmp_path / "e").mkdir()
    with pytest.raises(FileFormatError, match=r"e: not a trained model folder.*\(no point_cloud/iteration_<N> folder"
                                              r".*scaffold_gs: .*compgs: "):
        load_model_dir(tmp_path / "e")
    with pytest.raises(InputValueError, match="unknown family 'scaffold' \\(supported: scaffold_gs, octree_gs, hac, "
                                              "contextgs, compgs\\)"):
        load_model_dir(tmp_path / "e", family="scaffold")
    (tmp_path / "m" / "point_cloud" / "iteration_7").mkdir(parents=True)
    with pytest.raises(FileFormatError, match=r"m: .*\(no point_cloud/iteration_7/point_cloud.ply\)"):
        detect_family(tmp_path / "m")
    with pytest.raises(FileFormatError, match=r"no 'iteration_3' folder \(present: \[7\]\)"):
        detect_family(tmp_path / "m", iteration=3)
    folders = _folders(tmp_path / "f")
    assert folders
    (tmp_path / "f" / "hac" / "point_cloud" / "iteration_30000" / "checkpoint.pth").unlink()
    with pytest.raises(FileFormatError, match=r"hac: not a trained model folder.*f_mask_0"):
        detect_family(tmp_path / "f" / "hac")
    with pytest.raises(FileFormatError, match="iteration_5"):
        load_model_dir(tmp_path / "f" / "compgs", iteration=5)
    # a forced family goes to that family's loader, which names what is missing
    with pytest.raises(FileFormatError, match="weights.pth"):
        load_model_dir(tmp_path / "f" / "scaffold-split", family="compgs", allow_unquantized=True)


# ---------------------------------------------------------------------------------------- iterations
def test_iteration_picks_that_folder_for_every_family(tmp_path):
    """A folder holding iteration_7000 (seed 1) next to iteration_30000 (seed 0): every family loads the
    older one when asked for it, and the newest by default; compared with each iteration loaded alone."""
    new, old = _folders(tmp_path / "new", 0), _folders(tmp_path / "old", 1)
    assert new.keys() == old.keys()
    for name in ("scaffold-split", "octree-split", "hac++", "contextgs", "compgs"):
        kw = new[name][2]
        both = tmp_path / "both" / name
        shutil.copytree(tmp_path / "new" / name, both)
        shutil.copytree(tmp_path / "old" / name / "point_cloud" / "iteration_30000", both / "point_cloud" / "iteration_7000")

        def anchors(path, **more):
            model = load_model_dir(path, **kw, **more)
            return plugins.select_backend(model, None).anchor_positions(model)

        older, newer = anchors(tmp_path / "old" / name), anchors(tmp_path / "new" / name)
        assert older.shape != newer.shape or not torch.equal(older, newer), name
        assert torch.equal(anchors(both, iteration=7000), older), name
        assert torch.equal(anchors(both), newer), name
        assert torch.equal(anchors(both, iteration=30000), newer), name


def test_an_asked_iteration_loads_beside_a_half_written_later_one(tmp_path):
    """``iteration=N`` reads ``point_cloud/iteration_N`` for detection too: a later iteration folder that
    a crashed save left without its PLY does not stop the asked one from loading."""
    raw = make_raw_model(5, 4, 2, seed=3)
    root = tmp_path / "m"
    write_scaffold_dir_by_hand(root, raw, iteration=100)
    (root / "point_cloud" / "iteration_200").mkdir()
    model = load_model_dir(root, iteration=100)
    assert torch.equal(model._anchor, raw["anchor"])


@pytest.mark.parametrize("family", FAMILIES)
def test_a_malformed_iteration_argument_is_refused_naming_it(tmp_path, family):
    write_family_dir(family, tmp_path)
    for fam in (None, family.removesuffix("_split")):
        with pytest.raises(InputValueError, match=r"^iteration must be a whole number >= 0.*got 'abc'"):
            load_model_dir(tmp_path, family=fam, iteration="abc", allow_unquantized=True)
    assert _anchors(load_model_dir(tmp_path, iteration="100", allow_unquantized=True)) > 0


# --------------------------------------------------------------------------------- passed-on options
def test_allow_unquantized_reaches_the_hac_and_contextgs_loaders(tmp_path):
    hac_root = hac_files._write_dir(tmp_path / "h", hac_files._arrays(5, decoded=False, mask_cols=hac_files.K + 1),
                                    hac_files._decoders(5))
    ctx_root = contextgs_files._write_dir(tmp_path / "c", contextgs_files._arrays(5, decoded=False), contextgs_files._decoders(5))
    for root, cls in ((hac_root, HACModel), (ctx_root, ContextGSModel)):
        with pytest.raises(FileFormatError, match="raw \\(not decoded\\)"):
            load_model_dir(root)
        m = load_model_dir(root, allow_unquantized=True)
        assert isinstance(m, cls) and not m.decoded_version and not m.training


class Sequential(nn.Sequential):  # a decoder outside the safe TorchScript subset (a class of its own), harmless
    @torch.jit.export
    def extra(self) -> int:
        return 1


def test_trust_code_reaches_the_scaffold_and_octree_loaders(tmp_path):
    torch.manual_seed(6)
    m = NeuralGaussianModel(6, feat_dim=8, n_offsets=3)
    folder = save_scaffold_dir(m, tmp_path / "s", 3)
    octree = octree_files._write_dir(tmp_path / "o", octree_files._arrays(1),
                                     octree_files._decoders(torch.Generator().manual_seed(1)))
    for root, it, dec in ((tmp_path / "s", folder, m.mlp_opacity),
                          (octree, octree / "point_cloud" / "iteration_30000", load_model_dir(octree).mlp_opacity)):
        odd = Sequential(*[layer for layer in dec])
        torch.jit.script(odd).save(str(it / "opacity_mlp.pt"))
        with pytest.raises(FileFormatError, match="opacity_mlp.pt"):
            load_model_dir(root)  # read as data by default: refused
        x = torch.randn(4, dec[0].in_features)
        trusted = load_model_dir(root, trust_code=True)
        assert torch.allclose(trusted.mlp_opacity(x), dec(x))


# ---------------------------------------------------------------------------- refusals every loader shares
@pytest.mark.parametrize("family", [f for f in FAMILIES if f != "scaffold_gs_split"])
def test_a_nan_decoder_weight_is_refused_naming_file_and_tensor(tmp_path, family):
    weights = write_family_dir(family, tmp_path)
    tensor = poison_first_weight(weights)
    with pytest.raises(FileFormatError, match=rf"{re.escape(str(weights))}.*: tensor '{re.escape(tensor)}' holds 1 NaN/Inf"):
        load_model_dir(tmp_path, allow_unquantized=True)


def test_a_nan_bound_of_contextgs_is_refused(tmp_path):
    ckpt = write_family_dir("contextgs", tmp_path)
    blob = torch.load(ckpt, weights_only=True)
    blob["bound"][1][0, 2] = float("nan")
    torch.save(blob, ckpt)
    with pytest.raises(FileFormatError, match=rf"{re.escape(str(ckpt))}: tensor 'bound.1' holds 1 NaN/Inf"):
        load_model_dir(tmp_path)


@pytest.mark.parametrize("family", WITH_CFG)
@pytest.mark.parametrize("key, value", [("voxel_size", "abc"), ("feat_dim", "abc"), ("n_offsets", 2.5),
                                        ("voxel_size", float("nan"))])
def test_a_malformed_cfg_args_value_is_refused_naming_file_and_key(tmp_path, family, key, value):
    write_family_dir(family, tmp_path, **{key: value})
    with pytest.raises(FileFormatError, match=rf"{re.escape(str(tmp_path / 'cfg_args'))}: {key}=.* must be"):
        load_model_dir(tmp_path, allow_unquantized=True)
