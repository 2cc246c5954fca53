"""The targets of an injection: which decoders' first layers ``ControlGS.wrap`` hooks, the records it
keeps of them, and the refusals (unknown, repeated or shared first layers, layers a TorchScript
decoder cannot be rebuilt from, a first layer already carrying an injector) before the model changes."""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, Callable

import pytest
import torch
from helpers.scaffold_standin import ScaffoldStandIn
from helpers.wrapping import DECODERS, assert_unchanged, model_record, refusing_stand_in, stand_in
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import LifecycleError, TargetError


def _reference_model() -> NeuralGaussianModel:
    torch.manual_seed(0)
    return NeuralGaussianModel(6, feat_dim=8, n_offsets=2)


def _hooks(layer: nn.Module) -> int:
    return len(layer._forward_hooks) + len(layer._forward_pre_hooks)


def _share_cov_and_opacity_layer(model: Any) -> None:
    model.mlp_cov[0] = model.mlp_opacity[0]  # one Linear in both decoders


def _alias_color_to_opacity(model: Any) -> None:
    model.mlp_color = model.mlp_opacity  # one decoder under two names


@pytest.mark.parametrize("share, targets, allowed", [
    (_share_cov_and_opacity_layer, None, ("mlp_opacity", "mlp_color")),
    (_share_cov_and_opacity_layer, ("mlp_opacity", "mlp_cov"), ("mlp_opacity", "mlp_color")),
    (_share_cov_and_opacity_layer, ("mlp_color", "mlp_cov", "mlp_opacity"), ("mlp_cov", "mlp_color")),
    (_alias_color_to_opacity, ("mlp_opacity", "mlp_color"), ("mlp_opacity", "mlp_cov")),
], ids=["defaults", "two", "three", "alias"])
def test_targets_sharing_a_first_layer_are_refused_and_nothing_changes(
        share: Callable[[Any], None], targets: tuple[str, ...] | None, allowed: tuple[str, ...]) -> None:
    """A hook per target would inject into a shared first layer twice: refused, naming both targets and
    layers, before anything changes; one of them alone wraps, with one hook on the shared layer."""
    model = _reference_model()
    share(model)
    before = model_record(model)
    with pytest.raises(TargetError, match=r"'(mlp_opacity|mlp_cov|mlp_color)' and '(mlp_opacity|mlp_cov|mlp_color)'.*"
                                          r"'mlp_\w+\.0' is 'mlp_\w+\.0'"):
        ControlGS.wrap(model, targets=targets)
    assert_unchanged(before, model)
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model, targets=allowed)
    assert all(_hooks(getattr(model, d)[0]) == 1 for d in DECODERS)
    cgs.unwrap()
    assert_unchanged(before, model)


def test_decoders_with_tied_weights_but_their_own_layers_wrap() -> None:
    """Two Linear modules holding one weight are two first layers: one hook each, the injection not doubled."""
    model = _reference_model()
    model.mlp_cov[0].weight = model.mlp_opacity[0].weight
    cgs = ControlGS.wrap(model, targets=("mlp_opacity", "mlp_cov"))
    assert [_hooks(m[0]) for m in (model.mlp_opacity, model.mlp_cov)] == [1, 1]
    cgs.unwrap()


@pytest.mark.parametrize("targets, pattern", [
    (["mlp_opacity", "mlp_nope"], r"'mlp_nope'.*\['mlp_opacity', 'mlp_cov', 'mlp_color'\]"),
    (["mlp_opacity", "mlp_opacity"], r"targets.*more than once.*\['mlp_opacity', 'mlp_opacity'\]"),
    ("mlp_cov", r"targets.*got 'mlp_cov'"),
    ([], r"targets.*got \[\]"),
], ids=["unknown", "repeated", "a string", "empty"])
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bad_targets_are_refused_before_the_model_changes(kind: str, targets: Any, pattern: str) -> None:
    model = refusing_stand_in(kind)
    before = model_record(model)
    with pytest.raises(TargetError, match=pattern):
        ControlGS.wrap(model, targets=targets)
    assert_unchanged(before, model)
    assert ControlGS.attached(model) is None


def test_an_unsupported_torchscript_layer_in_the_last_target_leaves_the_others_untouched() -> None:
    model = stand_in("script")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        model.mlp_color = torch.jit.trace(nn.Sequential(nn.Linear(35, 32), nn.GELU(), nn.Linear(32, 30)), torch.randn(2, 35))
    before = model_record(model)
    with pytest.raises(TargetError, match="mlp_color.*GELU"):
        ControlGS.wrap(model)
    assert_unchanged(before, model)


class _FC1Elsewhere(ScaffoldGSBackend):
    """FC1-elsewhere test backend."""

    name = "fc1_elsewhere"

    def __init__(self, fc1: str) -> None:
        self.fc1 = fc1

    def first_linear_path(self, model: Any, decoder_path: str) -> str:
        return self.fc1.format(decoder_path)


@pytest.mark.parametrize("fc1, pattern", [
    ("mlp_color.0", r"fc1_elsewhere: .*'mlp_color\.0'.*TorchScript decoder 'mlp_opacity'"),
    ("{}.7", r"fc1_elsewhere: .*'mlp_opacity'.*'mlp_opacity\.7'"),
    ("{}.1", r"fc1_elsewhere: .*'mlp_opacity'.*Linear, got ReLU"),
], ids=["outside the decoder", "no such layer", "not a Linear"])
def test_a_first_layer_path_outside_the_decoder_or_not_a_linear_is_refused(fc1: str, pattern: str) -> None:
    model = stand_in("script", num_anchors=6, feat_dim=4, n_offsets=2, seed=1)
    before = model_record(model)
    with pytest.raises(TargetError, match=pattern):
        ControlGS.wrap(model, backend=_FC1Elsewhere(fc1))
    assert_unchanged(before, model)


def test_wrapped_targets_are_read_only_hashable_records() -> None:
    """``cgs.targets`` records what the wrapper attached to (``unwrap`` finds its hooks by them): a Target
    cannot be edited afterwards, and as a value it hashes like its equal."""
    cgs = ControlGS.wrap(ScaffoldStandIn(5, seed=1))
    try:
        first = cgs.targets[0]
        with pytest.raises(dataclasses.FrozenInstanceError):
            first.fc1 = "mlp_cov.0"  # type: ignore[misc]
        assert first.fc1 == "mlp_opacity.0"
        copy = dataclasses.replace(first)
        assert copy == first and hash(copy) == hash(first)
        assert len(set(cgs.targets)) == 3 and {first: "x"}[copy] == "x"
    finally:
        model = cgs.unwrap()
    assert all(not getattr(model, d)[0]._forward_hooks for d in DECODERS)


def test_a_first_layer_carrying_an_injector_is_refused_and_the_feature_bank_is_targetable() -> None:
    model = stand_in(use_feat_bank=True)
    cgs = ControlGS.wrap(model)
    with pytest.raises(LifecycleError, match=r"'mlp_opacity\.0'.*ControlGS\(backend='scaffold_gs'"):
        ControlGS.wrap(model)
    assert ControlGS.attached(model) is cgs
    ControlGS.attached(model).unwrap()
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model, targets=["mlp_feature_bank", "mlp_color"])
    assert [(t.decoder, t.fc1, t.in_features, t.out_features) for t in cgs.targets] == [
        ("mlp_feature_bank", "mlp_feature_bank.0", 4, 32), ("mlp_color", "mlp_color.0", 35, 32)]
    assert "mlp_feature_bank.0: Linear(4 -> 32)" in cgs.summary()
    cgs.unwrap()
