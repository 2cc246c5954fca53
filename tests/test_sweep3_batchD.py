"""Misses of the fresh sample of 2026-11-23 evening (seed 11230001): the reference model's colour warm start,
the Octree-GS loader's smallest file and the PSF bank's repr, each pinned by what the code is for."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import test_backend_octree_gs as octree_t
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.octree_gs import load_octree_gs_dir
from controlgs_adapter.formats.backbone import read_ply, write_ply
from test_optics_bank import tiny_bank

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace in the Octree-GS fixture


def test_colour_warm_start_takes_adam_steps_of_learning_rate_0_01():
    """The colour fit of ``from_points`` is Adam at learning rate 1e-2: Adam's first step moves every parameter
    by ``lr * g / (|g| + eps)``, i.e. by 0.01 wherever its gradient is not tiny, and never by more."""
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(300, 3, generator=g, dtype=torch.float64)
    cols = torch.rand(300, 3, generator=g, dtype=torch.float64)

    def feats(steps: int) -> torch.Tensor:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            m = NeuralGaussianModel.from_points(pts, cols, feat_dim=8, n_offsets=2, voxel_size=0.2,
                                                color_fit_steps=steps, seed=5)
        return m._anchor_feat.detach().double()

    step = (feats(1) - feats(0)).abs().flatten()
    assert step.numel() > 200
    assert float(step.max()) <= 0.01 * (1 + 1e-5)
    assert float(step.median()) == pytest.approx(0.01, rel=2e-3)  # eps 1e-8 against gradients ~1e-5


def test_octree_folder_with_two_anchors_loads_voxel_size_and_standard_dist_from_info(tmp_path):
    """Octree-GS keeps voxel_size and standard_dist in rows 0 and 1 of the 'info' column: a file with exactly
    two anchors holds both and loads, with those two values."""
    arr = octree_t._arrays(2)
    decs = octree_t._decoders(torch.Generator().manual_seed(2))
    root = octree_t._write_dir(tmp_path / "o", arr, decs, mode="unite")
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {n: np.ascontiguousarray(c[:2]) for n, c in fields.items()})
    m = load_octree_gs_dir(root)
    assert m.get_anchor.shape[0] == 2
    assert m.voxel_size == pytest.approx(octree_t.VOXEL, rel=1e-6)
    assert m.standard_dist == pytest.approx(octree_t.STD_DIST, rel=1e-6)


def test_psf_bank_repr_shows_the_bank_not_its_resample_cache():
    """A bank's repr names its fields; the resampling cache is not part of what the bank is: the repr is the
    same before and after a resample is cached, and never mentions the cache."""
    torch.manual_seed(0)
    bank = tiny_bank()
    before = repr(bank)
    bank.resample_to(8, 8)
    after = repr(bank)
    assert before.startswith("PSFBank(psf=") and "display_mm=(24.0, 24.0)" in before
    assert after == before and "_cache" not in after
