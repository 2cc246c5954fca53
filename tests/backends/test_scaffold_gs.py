"""Scaffold-GS backend: the decoder input layout of a model laid out like Scaffold-GS."""

from __future__ import annotations

import pytest
import torch
from helpers.scaffold_standin import ScaffoldStandIn, script_decoders
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import TargetError

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


@pytest.mark.parametrize("scripted", [False, True], ids=["eager", "torchscript"])
def test_without_configuration_a_width_that_fits_no_layout_is_refused_alike(scripted):
    model = _with_first_width(37, scripted=scripted)
    with pytest.raises(TargetError, match=r"mlp_opacity\[0\] takes 37 inputs, the model's configuration gives 35"):
        ControlGS.wrap(model)


@pytest.mark.parametrize("scripted", [False, True], ids=["eager", "torchscript"])
def test_an_explicit_configuration_wins_over_the_width(scripted):
    model = _with_first_width(36, scripted=scripted)
    model.add_opacity_dist = False  # says no distance input: the 36-wide layer contradicts it
    with pytest.raises(TargetError, match=r"mlp_opacity\[0\] takes 36 inputs, the model's configuration gives 35"):
        ControlGS.wrap(model)
    model.add_opacity_dist = True
    assert ScaffoldGSBackend().input_layout(model, "mlp_opacity") == [("feat", 32), ("view", 3), ("dist", 1)]


def test_no_distance_input_when_the_width_is_the_plain_layout():
    model = _with_first_width(35, scripted=False)
    assert ScaffoldGSBackend().input_layout(model, "mlp_cov") == [("feat", 32), ("view", 3)]


from types import SimpleNamespace

import numpy as np

from controlgs_adapter.errors import InputValueError


def make_model(kind: str, **kw) -> ScaffoldStandIn:
    model = ScaffoldStandIn(**kw)
    return script_decoders(model) if kind == "script" else model


def test_backend_positions_and_visible_rows():
    model = make_model("eager", num_anchors=8)
    backend = ScaffoldGSBackend()
    assert backend.matches(model) and backend.anchor_positions(model) is model._anchor
    mask = torch.tensor([0, 1, 1, 0, 0, 1, 0, 1], dtype=torch.bool)
    assert backend.visible_rows_to_anchor_ids(mask).tolist() == [1, 2, 5, 7]
    with pytest.raises(InputValueError, match="bool"):
        backend.visible_rows_to_anchor_ids(mask.long())


def test_scaffold_anchor_positions_refuse_a_non_tensor_attribute():
    """A ``get_anchor`` that is neither a tensor nor callable (here an array) is refused as not a tensor,
    not called."""
    decs = dict(mlp_opacity=nn.Linear(1, 1), mlp_cov=nn.Linear(1, 1), mlp_color=nn.Linear(1, 1))
    model = SimpleNamespace(get_anchor=np.zeros((2, 3), np.float32), **decs)
    with pytest.raises(InputValueError, match="get_anchor must be a torch.Tensor, got ndarray"):
        ScaffoldGSBackend().anchor_positions(model)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
