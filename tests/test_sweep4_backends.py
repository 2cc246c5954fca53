"""Backbone-family backends and loaders (facts in /work/shared/notes/backbones.md): behaviours a line-by-line
mutation audit of backends/{scaffold_gs, scaffold_io, model_dir, octree_gs, hac, contextgs, compgs}.py found
unobserved, each checked through the public functions against the family's published layout or a value worked
out by hand (how is said next to each literal)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import InputValueError
from scaffold_oracle import make_raw_model, write_scaffold_dir_by_hand

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace: the format under test


# ---------------------------------------------------------------- Scaffold-GS backend

def test_scaffold_layout_keeps_a_one_wide_appearance_code():
    """Scaffold-GS appends the appearance code (appearance_dim wide, any size > 0) last to the colour
    decoder's input; a 1-wide code is still an input column."""
    m = NeuralGaussianModel(2, feat_dim=4, n_offsets=2, appearance_dim=1, num_cameras=3)
    layout = ScaffoldGSBackend().input_layout(m, "mlp_color")
    assert layout == [("feat", 4), ("view", 3), ("appearance", 1)]
    assert sum(w for _, w in layout) == m.mlp_color[0].in_features  # the decoder's own FC1 width: 4 + 3 + 1


def test_scaffold_anchor_positions_refuse_a_non_tensor_attribute():
    """A ``get_anchor`` that is neither a tensor nor callable (here an array) is refused as not a tensor,
    not called."""
    decs = dict(mlp_opacity=nn.Linear(1, 1), mlp_cov=nn.Linear(1, 1), mlp_color=nn.Linear(1, 1))
    model = SimpleNamespace(get_anchor=np.zeros((2, 3), np.float32), **decs)
    with pytest.raises(InputValueError, match="get_anchor must be a torch.Tensor, got ndarray"):
        ScaffoldGSBackend().anchor_positions(model)


# ---------------------------------------------------------------- model folders

def test_load_model_dir_with_an_iteration_ignores_a_half_written_later_one(tmp_path):
    """``iteration=N`` reads ``point_cloud/iteration_N`` for detection too: a later iteration folder that
    a crashed save left without its PLY does not stop the asked one from loading."""
    raw = make_raw_model(5, 4, 2, seed=3)
    root = tmp_path / "m"
    write_scaffold_dir_by_hand(root, raw, iteration=100)
    (root / "point_cloud" / "iteration_200").mkdir()
    model = load_model_dir(root, iteration=100)
    assert torch.equal(model._anchor, raw["anchor"])
