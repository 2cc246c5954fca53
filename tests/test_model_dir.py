"""load_model_dir: the family of a trained output folder is told from its files (folders written by
the families' layouts, as the backend tests write them), forced with family=, refused when unknown."""

from __future__ import annotations

import pytest
import torch

import test_backend_compgs as compgs_t
import test_backend_contextgs as contextgs_t
import test_backend_hac as hac_t
import test_backend_octree_gs as octree_t
from controlgs_adapter.backends import detect_family, load_model_dir
from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.backends.hac import HACModel
from controlgs_adapter.backends.octree_gs import OctreeGSModel
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.errors import FileFormatError, InputValueError
from scaffold_oracle import make_raw_model, write_scaffold_dir_by_hand


def _folders(root):
    """{family: (folder, model class, loader kwargs)} of one folder per family and layout."""
    out = {}
    for mode in ("split", "unite"):
        raw = make_raw_model(12, 8, 4, seed=1)
        write_scaffold_dir_by_hand(root / f"scaffold-{mode}", raw, mode=mode)
        out[f"scaffold-{mode}"] = ("scaffold_gs", NeuralGaussianModel, {})
        octree_t._write_dir(root / f"octree-{mode}", octree_t._arrays(0), octree_t._decoders(torch.Generator().manual_seed(0)),
                            mode=mode)
        out[f"octree-{mode}"] = ("octree_gs", OctreeGSModel, {})
    for variant, cols in (("hac++", hac_t.K + 1), ("hac", hac_t.K)):
        hac_t._write_dir(root / variant, hac_t._arrays(0, decoded=True, mask_cols=cols), hac_t._decoders(0))
        out[variant] = ("hac", HACModel, {})
    contextgs_t._write_dir(root / "contextgs", contextgs_t._arrays(0, decoded=True), contextgs_t._decoders(0))
    out["contextgs"] = ("contextgs", ContextGSModel, {})
    arr = compgs_t._arrays(0)
    compgs_t._write_checkpoint(root / "compgs", arr, compgs_t._model(arr, 0))
    out["compgs"] = ("compgs", CompGSModel, {"allow_unquantized": True})
    return out


def test_every_family_is_detected_and_loaded(tmp_path):
    for name, (family, cls, kw) in _folders(tmp_path).items():
        assert detect_family(tmp_path / name) == family, name
        model = load_model_dir(tmp_path / name, **kw)
        assert isinstance(model, cls) and not model.training, name
        assert isinstance(load_model_dir(tmp_path / name, family=family, **kw), cls)


def test_detection_reads_no_decoder(tmp_path, monkeypatch):
    """Detection opens only the PLY header: no torch.load, no TorchScript, no PLY body."""
    folders = _folders(tmp_path)
    import controlgs_adapter.formats.backbone as formats

    def boom(*a, **k):
        raise AssertionError("detection loaded a file")

    monkeypatch.setattr(torch, "load", boom)
    monkeypatch.setattr(torch.jit, "load", boom)
    monkeypatch.setattr(formats, "read_ply", boom)
    for name, (family, _, _) in folders.items():
        assert detect_family(tmp_path / name) == family


def test_unrecognised_folder_and_unknown_family(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileFormatError, match=r"empty: not a trained model folder.*scaffold_gs: .*compgs: "):
        load_model_dir(tmp_path / "empty")
    with pytest.raises(FileFormatError, match="no such model folder"):
        load_model_dir(tmp_path / "missing")
    folders = _folders(tmp_path)
    assert folders
    (tmp_path / "hac" / "point_cloud" / "iteration_30000" / "checkpoint.pth").unlink()
    with pytest.raises(FileFormatError, match=r"hac: not a trained model folder.*f_mask_0"):
        detect_family(tmp_path / "hac")
    with pytest.raises(InputValueError, match="unknown family 'gsplat'"):
        load_model_dir(tmp_path / "compgs", family="gsplat")
    with pytest.raises(FileFormatError, match="iteration_5"):
        load_model_dir(tmp_path / "compgs", iteration=5)
    # a forced family goes to that family's loader, which names what is missing
    with pytest.raises(FileFormatError):
        load_model_dir(tmp_path / "scaffold-split", family="compgs", allow_unquantized=True)


def _family_folders(root, seed: int) -> dict[str, dict]:
    """One folder per family (layouts as the backend tests write them) from ``seed``; {name: loader kwargs}."""
    write_scaffold_dir_by_hand(root / "scaffold", make_raw_model(12, 8, 4, seed=seed))
    octree_t._write_dir(root / "octree", octree_t._arrays(seed), octree_t._decoders(torch.Generator().manual_seed(seed)))
    hac_t._write_dir(root / "hac", hac_t._arrays(seed, decoded=True, mask_cols=hac_t.K + 1), hac_t._decoders(seed))
    contextgs_t._write_dir(root / "contextgs", contextgs_t._arrays(seed, decoded=True), contextgs_t._decoders(seed))
    arr = compgs_t._arrays(seed)
    compgs_t._write_checkpoint(root / "compgs", arr, compgs_t._model(arr, seed))
    return {"scaffold": {}, "octree": {}, "hac": {}, "contextgs": {}, "compgs": {"allow_unquantized": True}}


def test_iteration_picks_that_folder_for_every_family(tmp_path):
    """A folder holding iteration_7000 (seed 1) next to iteration_30000 (seed 0): every family loads the
    older one when asked for it, and the newest by default; compared with each iteration loaded alone."""
    import shutil

    from controlgs_adapter.plugins import select_backend as _select_backend

    names = _family_folders(tmp_path / "new", 0)
    _family_folders(tmp_path / "old", 1)
    for name, kw in names.items():
        both = tmp_path / "both" / name
        shutil.copytree(tmp_path / "new" / name, both)
        shutil.copytree(tmp_path / "old" / name / "point_cloud" / "iteration_30000", both / "point_cloud" / "iteration_7000")

        def anchors(path, **more):
            model = load_model_dir(path, **kw, **more)
            return _select_backend(model, None).anchor_positions(model)

        old, new = anchors(tmp_path / "old" / name), anchors(tmp_path / "new" / name)
        assert old.shape != new.shape or not torch.equal(old, new), name
        assert torch.equal(anchors(both, iteration=7000), old), name
        assert torch.equal(anchors(both), new), name
        assert torch.equal(anchors(both, iteration=30000), new), name
