"""The Scaffold-GS backend: which models it recognises, their decoders and input layouts (from the
configuration, else from the first layer's width), anchor positions and visible rows."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.scaffold_standin import ScaffoldStandIn, script_decoders
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import InputValueError, TargetError

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

DECODERS = ("mlp_opacity", "mlp_cov", "mlp_color")


def _with_first_width(width: int, *, scripted: bool) -> ScaffoldStandIn:
    """A stand-in (32 features, no ``add_<x>_dist`` attributes) whose decoders take ``width`` inputs."""
    model = ScaffoldStandIn(8, feat_dim=32, n_offsets=2, seed=3)
    assert not any(hasattr(model, f"add_{d[4:]}_dist") for d in DECODERS)
    for name in DECODERS:
        mlp = getattr(model, name)
        mlp[0] = nn.Linear(width, 32)
    model.use_feat_bank = False
    return script_decoders(model) if scripted else model


def test_decoders_and_layouts_follow_the_models_options():
    b = ScaffoldGSBackend()
    m = NeuralGaussianModel(3, feat_dim=8, n_offsets=2, use_feat_bank=True, appearance_dim=5, num_cameras=2,
                            add_cov_dist=True, add_color_dist=True)
    assert b.matches(m) and b.decoder_paths(m) == ["mlp_opacity", "mlp_cov", "mlp_color", "mlp_feature_bank"]
    assert b.default_targets(m) == ["mlp_opacity", "mlp_cov", "mlp_color"]
    # Scaffold-GS's generate_neural_gaussians: [feat, view, (dist)] (+ appearance last, colour only)
    assert b.input_layout(m, "mlp_opacity") == [("feat", 8), ("view", 3)]
    assert b.input_layout(m, "mlp_cov") == [("feat", 8), ("view", 3), ("dist", 1)]
    assert b.input_layout(m, "mlp_color") == [("feat", 8), ("view", 3), ("dist", 1), ("appearance", 5)]
    assert b.input_layout(m, "mlp_feature_bank") is None
    plain = NeuralGaussianModel(3, feat_dim=8, n_offsets=2)
    assert b.decoder_paths(plain) == ["mlp_opacity", "mlp_cov", "mlp_color"]
    assert b.input_layout(plain, "mlp_color") == [("feat", 8), ("view", 3)]
    # a 1-wide appearance code is still an input column, as wide as the colour decoder's FC1 says
    one = NeuralGaussianModel(2, feat_dim=4, n_offsets=2, appearance_dim=1, num_cameras=3)
    layout = b.input_layout(one, "mlp_color")
    assert layout == [("feat", 4), ("view", 3), ("appearance", 1)]
    assert sum(w for _, w in layout) == one.mlp_color[0].in_features


@pytest.mark.parametrize("scripted", [False, True], ids=["eager", "torchscript"])
def test_distance_input_is_inferred_from_the_first_layer_without_configuration(scripted):
    model = _with_first_width(36, scripted=scripted)
    backend = ScaffoldGSBackend()
    for name in DECODERS:
        assert backend.input_layout(model, name) == [("feat", 32), ("view", 3), ("dist", 1)]
    cgs = ControlGS.wrap(model)
    assert [t.in_features for t in cgs.targets] == [36, 36, 36]
    x = torch.randn(5, 36)
    with torch.no_grad():  # outside a conditioned block the wrapped decoders are the backbone's
        assert model.mlp_opacity(x).shape == (5, 2)
    assert ScaffoldGSBackend().input_layout(_with_first_width(35, scripted=False), "mlp_cov") == [("feat", 32), ("view", 3)]


@pytest.mark.parametrize("scripted", [False, True], ids=["eager", "torchscript"])
def test_a_width_that_fits_no_layout_or_contradicts_the_configuration_is_refused(scripted):
    with pytest.raises(TargetError, match=r"mlp_opacity\[0\] takes 37 inputs, the model's configuration gives 35"):
        ControlGS.wrap(_with_first_width(37, scripted=scripted))
    model = _with_first_width(36, scripted=scripted)
    model.add_opacity_dist = False  # says no distance input: the 36-wide layer contradicts it
    with pytest.raises(TargetError, match=r"mlp_opacity\[0\] takes 36 inputs, the model's configuration gives 35"):
        ControlGS.wrap(model)
    model.add_opacity_dist = True  # an explicit configuration wins over the width
    assert ScaffoldGSBackend().input_layout(model, "mlp_opacity") == [("feat", 32), ("view", 3), ("dist", 1)]


def test_anchor_positions_matching_and_visible_rows():
    b = ScaffoldGSBackend()
    model = ScaffoldStandIn(8)
    assert b.matches(model) and b.anchor_positions(model) is model._anchor
    # anchors: a get_anchor property, a get_anchor() method (Scaffold-GS's GaussianModel), or _anchor alone
    pos = torch.arange(6.0).reshape(2, 3)
    decs = dict(mlp_opacity=nn.Linear(1, 1), mlp_cov=nn.Linear(1, 1), mlp_color=nn.Linear(1, 1))
    by_attr = SimpleNamespace(_anchor=pos, **decs)
    by_method = SimpleNamespace(get_anchor=lambda: pos + 1, **decs)
    assert b.matches(by_attr) and b.matches(by_method)
    assert torch.equal(b.anchor_positions(by_attr), pos) and torch.equal(b.anchor_positions(by_method), pos + 1)
    assert b.input_layout(by_attr, "mlp_cov") is None  # no feat_dim: the layout is unknown
    assert not b.matches(SimpleNamespace(**decs))  # no anchors
    assert not b.matches(SimpleNamespace(_anchor=pos, mlp_opacity=nn.Linear(1, 1), mlp_cov=nn.Linear(1, 1), mlp_color=3))
    # a get_anchor that is neither a tensor nor callable (here an array) is refused as not a tensor, not called
    with pytest.raises(InputValueError, match="get_anchor must be a torch.Tensor, got ndarray"):
        b.anchor_positions(SimpleNamespace(get_anchor=np.zeros((2, 3), np.float32), **decs))
    mask = torch.tensor([0, 1, 1, 0, 0, 1, 0, 1], dtype=torch.bool)
    assert b.visible_rows_to_anchor_ids(mask).tolist() == [1, 2, 5, 7]
    with pytest.raises(InputValueError, match="bool"):
        b.visible_rows_to_anchor_ids(mask.long())
