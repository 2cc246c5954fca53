"""Every built-in backbone family, in each of its on-disk layouts, meets the family contract of
``helpers.family_contract``: its folder loads, the adapter attaches to every target decoder, is
bit-identical to the backbone at zero strength and outside ``conditioned``, reaches exactly the rows the
backend maps to an anchor, round-trips through a file, and damaged or foreign folders are refused."""

from __future__ import annotations

from pathlib import Path

import helpers.contextgs_files as contextgs_files
import helpers.hac_files as hac_files
import helpers.octree_files as octree_files
import pytest
import torch
from helpers.family_checks import make_camera
from helpers.family_contract import Family, check_family
from helpers.family_dirs import write_family_dir

from controlgs_adapter.backends.compgs import load_compgs_dir
from controlgs_adapter.backends.contextgs import load_contextgs_dir
from controlgs_adapter.backends.hac import load_hac_dir
from controlgs_adapter.backends.octree_gs import load_octree_gs_dir
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # TorchScript decoders: part of the formats


def _iteration(root: Path) -> Path:
    (folder,) = root.glob("point_cloud/iteration_*")
    return folder


def _octree_split(root: Path) -> Path:
    """Octree-GS with the level and distance inputs, TorchScript decoders."""
    arr = octree_files._arrays(2)
    octree_files._write_dir(root, arr, octree_files._decoders(torch.Generator().manual_seed(2)), mode="split")
    return _iteration(root) / "opacity_mlp.pt"


def _octree_anygs(root: Path) -> Path:
    return octree_files.write_anygs_dir(root, octree_files._arrays(6), octree_files.anygs_decoders(6)) / "opacity_mlp.pt"


def _hac_zero_padded(root: Path) -> Path:
    """HAC (no extra mask column): decoded arrays zero-padded after the valid anchors."""
    arr = hac_files._arrays(2, decoded=True, mask_cols=hac_files.K)
    for key in arr:
        arr[key][-3:] = 0.0
    hac_files._write_dir(root, arr, hac_files._decoders(2))
    return _iteration(root) / "checkpoint.pth"


def _contextgs_zero_padded(root: Path) -> Path:
    contextgs_files._write_dir(root, contextgs_files._arrays(1, decoded=True), contextgs_files._decoders(1))
    return _iteration(root) / "checkpoint.pth"


def _written(family: str):
    return lambda root: write_family_dir(family, root)


def _compgs(root: Path):
    return load_compgs_dir(root, allow_unquantized=True)


SCAFFOLD = _written("scaffold_gs")
FAMILIES = {
    "scaffold_gs": Family("scaffold_gs", SCAFFOLD, load_scaffold_dir, _written("compgs")),
    "scaffold_gs-torchscript": Family("scaffold_gs", _written("scaffold_gs_split"), load_scaffold_dir, _written("compgs")),
    "octree_gs": Family("octree_gs", _written("octree_gs"), load_octree_gs_dir, SCAFFOLD),
    "octree_gs-level-torchscript": Family("octree_gs", _octree_split, load_octree_gs_dir, SCAFFOLD),
    # Octree-AnyGS's levels of detail keep few anchors of this scene from afar: a closer view
    "octree_gs-anygs": Family("octree_gs", _octree_anygs, load_octree_gs_dir, SCAFFOLD, make_camera(distance=1.5)),
    "hac": Family("hac", _written("hac"), load_hac_dir, SCAFFOLD),
    "hac-zero-padded": Family("hac", _hac_zero_padded, load_hac_dir, SCAFFOLD),
    "contextgs": Family("contextgs", _written("contextgs"), load_contextgs_dir, _written("hac")),
    "contextgs-zero-padded": Family("contextgs", _contextgs_zero_padded, load_contextgs_dir, SCAFFOLD),
    "compgs": Family("compgs", _written("compgs"), _compgs, SCAFFOLD),
}


@pytest.mark.parametrize("layout", list(FAMILIES))
def test_family_meets_the_contract(layout, tmp_path):
    check_family(FAMILIES[layout], tmp_path)
