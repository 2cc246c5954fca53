"""Rebuilding TorchScript decoders as eager modules."""

from __future__ import annotations

import io
import warnings

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import TargetError
from controlgs_adapter.formats.torchscript import eager_from_script


def _roundtrip(module: nn.Module, mode: str, in_features: int) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        sm = torch.jit.trace(module, torch.randn(3, in_features)) if mode == "trace" else torch.jit.script(module)
        buf = io.BytesIO()
        torch.jit.save(sm, buf)
        buf.seek(0)
        return torch.jit.load(buf)


DECODERS = {
    "opacity": lambda: nn.Sequential(nn.Linear(35, 32), nn.ReLU(True), nn.Linear(32, 10), nn.Tanh()),
    "cov": lambda: nn.Sequential(nn.Linear(36, 32), nn.ReLU(True), nn.Linear(32, 70)),
    "color": lambda: nn.Sequential(nn.Linear(35, 32), nn.ReLU(True), nn.Linear(32, 30), nn.Sigmoid()),
    "feature_bank": lambda: nn.Sequential(nn.Linear(4, 32), nn.ReLU(True), nn.Linear(32, 3), nn.Softmax(dim=1)),
    "misc": lambda: nn.Sequential(nn.Linear(6, 8), nn.LeakyReLU(0.1), nn.Sequential(nn.Linear(8, 8, bias=False), nn.SiLU()),
                                  nn.Linear(8, 5), nn.Softplus(beta=2.0, threshold=10.0), nn.Identity(), nn.Softmax(-1)),
}


@pytest.mark.parametrize("mode", ["trace", "script"])
@pytest.mark.parametrize("name", list(DECODERS))
def test_rebuild_reproduces_outputs_exactly(name, mode):
    torch.manual_seed(0)
    eager = DECODERS[name]()
    in_features = eager[0].in_features
    sm = _roundtrip(eager, mode, in_features)
    rebuilt = eager_from_script(sm, name=name)
    assert not isinstance(rebuilt, torch.jit.ScriptModule)
    assert isinstance(rebuilt[0], nn.Linear)
    x = torch.randn(257, in_features) * 3
    assert torch.equal(rebuilt(x), sm(x))
    assert torch.equal(rebuilt(x), eager(x))
    assert rebuilt.state_dict().keys() == sm.state_dict().keys()


def test_unknown_layer_names_the_decoder_and_the_layer():
    sm = _roundtrip(nn.Sequential(nn.Linear(4, 4), nn.GELU()), "trace", 4)
    with pytest.raises(TargetError, match=r"'mlp_color\.1'.*'GELU'"):
        eager_from_script(sm, name="mlp_color")


def test_custom_forward_is_detected():
    class Residual(nn.Sequential):
        def forward(self, x):
            return super().forward(x) + x

    sm = _roundtrip(Residual(nn.Linear(4, 4), nn.ReLU()), "trace", 4)
    sm_name = sm.original_name
    assert sm_name == "Residual"  # not a Sequential: refused as an unknown layer type
    with pytest.raises(TargetError, match="Residual"):
        eager_from_script(sm, name="dec")


def test_not_a_script_module():
    with pytest.raises(TargetError, match="expected a TorchScript module"):
        eager_from_script(nn.Linear(2, 2), name="dec")
