"""ControlGS.wrap refuses targets that share a first layer (the injection would be doubled), before it
changes anything on the model."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.errors import TargetError


def _model() -> NeuralGaussianModel:
    torch.manual_seed(0)
    return NeuralGaussianModel(6, feat_dim=8, n_offsets=2)


def _snapshot(model: nn.Module) -> dict[str, object]:
    return {"hooks": [(name, len(m._forward_hooks), len(m._forward_pre_hooks)) for name, m in model.named_modules()],
            "modules": {name: id(m) for name, m in model.named_modules(remove_duplicate=False)},
            "grad": [(name, p.requires_grad) for name, p in model.named_parameters(remove_duplicate=False)],
            "state": {k: v.clone() for k, v in model.state_dict().items()}}


def _same(a: dict[str, object], b: dict[str, object]) -> bool:
    sa, sb = a["state"], b["state"]
    assert isinstance(sa, dict) and isinstance(sb, dict)
    return (all(a[k] == b[k] for k in ("hooks", "modules", "grad")) and sa.keys() == sb.keys()
            and all(torch.equal(sa[k], sb[k]) for k in sa))


@pytest.mark.parametrize("targets", [None, ("mlp_opacity", "mlp_cov"), ("mlp_color", "mlp_cov", "mlp_opacity")])
def test_targets_sharing_a_first_layer_are_refused_and_nothing_changes(targets: tuple[str, ...] | None) -> None:
    model = _model()
    model.mlp_cov[0] = model.mlp_opacity[0]  # one Linear in both decoders
    before = _snapshot(model)
    with pytest.raises(TargetError, match=r"targets '(mlp_opacity|mlp_cov)' and '(mlp_cov|mlp_opacity)' share one first "
                                          r"layer \('mlp_\w+\.0' is 'mlp_\w+\.0'\)"):
        ControlGS.wrap(model, targets=targets)
    assert _same(before, _snapshot(model))
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model, targets=("mlp_opacity", "mlp_color"))  # one of them: wraps, one hook on the shared layer
    assert len(model.mlp_cov[0]._forward_hooks) + len(model.mlp_cov[0]._forward_pre_hooks) == 1
    cgs.unwrap()
    assert _same(before, _snapshot(model))


def test_one_decoder_under_two_names_is_refused() -> None:
    model = _model()
    model.mlp_color = model.mlp_opacity  # an alias: same first layer (and widths)
    before = _snapshot(model)
    with pytest.raises(TargetError, match=r"targets 'mlp_opacity' and 'mlp_color' share one first layer"):
        ControlGS.wrap(model, targets=("mlp_opacity", "mlp_color"))
    assert _same(before, _snapshot(model))
    assert ControlGS.attached(model) is None


def test_decoders_with_tied_weights_but_their_own_layers_wrap() -> None:
    model = _model()
    model.mlp_cov[0].weight = model.mlp_opacity[0].weight  # two Linear modules, one weight: one hook each, not doubled
    cgs = ControlGS.wrap(model, targets=("mlp_opacity", "mlp_cov"))
    assert [len(m[0]._forward_hooks) + len(m[0]._forward_pre_hooks) for m in (model.mlp_opacity, model.mlp_cov)] == [1, 1]
    cgs.unwrap()
