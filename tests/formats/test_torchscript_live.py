"""Loaded TorchScript decoders rebuilt as eager modules (``formats.torchscript_live``), so hooks can attach:
outputs bit-identical, each layer's settings, mode and gradient flags kept, anything else refused naming
the decoder and the layer."""

from __future__ import annotations

import io
import warnings

import pytest
import torch
from helpers.decoder_kinds import DECODERS
from torch import nn

from controlgs_adapter.errors import TargetError
from controlgs_adapter.formats.torchscript import eager_from_archive
from controlgs_adapter.formats.torchscript_live import eager_from_script

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _jit(module: nn.Module, how: str = "trace", in_features: int = 3) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.trace(module, torch.randn(2, in_features)) if how == "trace" else torch.jit.script(module)


def _roundtrip(module: nn.Module, mode: str, in_features: int) -> torch.jit.ScriptModule:
    """``module`` traced or scripted, saved and loaded back (as a checkpoint's decoder is)."""
    buf = io.BytesIO()
    torch.jit.save(_jit(module, mode, in_features), buf)
    buf.seek(0)
    return torch.jit.load(buf)


class Linear(nn.Module):
    """Named like torch's Linear (so ``original_name`` says Linear), but its forward doubles the output."""

    def __init__(self) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.randn(2, 3))
        self.bias = nn.Parameter(torch.randn(2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 2.0 * torch.nn.functional.linear(x, self.weight, self.bias)


class LeakyReLU(nn.Module):
    """Named like torch's LeakyReLU, with no slope anywhere."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x)


class Residual(nn.Sequential):
    def forward(self, x):
        return super().forward(x) + x


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


@pytest.mark.parametrize("how", ["trace", "script"])
def test_each_setting_is_read_from_the_code_or_the_attributes(how):
    """Settings away from torch's defaults (LeakyReLU 0.01, Softplus beta 1 / threshold 20, Softmax dim None),
    each a different number so a swapped index or attribute shows: from the traced code's constants or the
    scripted module's attributes."""
    torch.manual_seed(4)
    m = nn.Sequential(nn.Linear(3, 6), nn.LeakyReLU(0.3), nn.Linear(6, 6), nn.Softplus(beta=1.5, threshold=7.0),
                      nn.Linear(6, 4), nn.Softmax(dim=0)).eval()
    got = eager_from_script(_jit(m, how), name="dec")
    assert got[1].negative_slope == 0.3
    assert (got[3].beta, got[3].threshold) == (1.5, 7.0)
    assert got[5].dim == 0
    x = torch.randn(7, 3) * 4
    assert torch.equal(got(x), m(x))


def test_settings_with_signs_and_exponents(tmp_path):
    """Negative and exponent-written constants in traced code read exactly, live and from the file."""
    module = nn.Sequential(nn.Linear(3, 3), nn.LeakyReLU(-0.5), nn.Softplus(beta=2.5e-7, threshold=1e20), nn.Softmax(dim=-1))
    sm = _jit(module)
    path = tmp_path / "s.pt"
    torch.jit.save(sm, str(path))
    for eager in (eager_from_script(sm), eager_from_archive(path)):
        assert eager[1].negative_slope == -0.5 and (eager[2].beta, eager[2].threshold) == (2.5e-7, 1e20)
        assert eager[3].dim == -1


def test_mode_and_gradient_flags_are_kept():
    torch.manual_seed(5)
    m = nn.Sequential(nn.Linear(3, 2), nn.ReLU()).train()
    m[0].bias.requires_grad_(False)
    got = eager_from_script(_jit(m, "script"))
    assert got.training and got[0].weight.requires_grad and not got[0].bias.requires_grad
    m.eval()
    got = eager_from_script(_jit(m, "script"))
    assert not got.training and not got[1].training
    nobias = nn.Sequential(nn.Linear(3, 2, bias=False))
    got = eager_from_script(_jit(nobias))
    assert got[0].bias is None and torch.equal(got[0].weight, nobias[0].weight)


def test_refusals_name_the_decoder_and_the_layer():
    for module in (nn.Linear(2, 2), nn.Sequential(nn.Linear(3, 2), nn.ReLU())):
        with pytest.raises(TargetError, match=rf"^decoder 'decoder': expected a TorchScript module, got {type(module).__name__}$"):
            eager_from_script(module)  # type: ignore[arg-type]
    with pytest.raises(TargetError, match=r"^decoder 'decoder': the TorchScript module holds no Linear layer$"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())))  # the default name
    with pytest.raises(TargetError, match=r"^decoder 'mlp_x': the TorchScript module holds no Linear layer"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())), "mlp_x")
    for how in ("trace", "script"):
        with pytest.raises(TargetError, match=r"^decoder 'mlp_x\.1': TorchScript layer of type 'GELU' cannot be rebuilt .*"
                                              r"\(supported: Sequential of Identity, LeakyReLU, Linear, ReLU, SiLU, Sigmoid, "
                                              r"Softmax, Softplus, Tanh\)"):
            eager_from_script(_roundtrip(nn.Sequential(nn.Linear(3, 2), nn.GELU()), how, 3), "mlp_x")
    sm = _roundtrip(Residual(nn.Linear(4, 4), nn.ReLU()), "trace", 4)
    assert sm.original_name == "Residual"  # a Sequential with its own forward: an unknown layer type
    with pytest.raises(TargetError, match="^decoder 'dec': .*'Residual'"):
        eager_from_script(sm, name="dec")
    with pytest.raises(TargetError, match=r"^decoder 'mlp_x': the TorchScript module does not take a \[rows, 3\] input"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.Linear(4, 1))), "mlp_x")
    with pytest.raises(TargetError, match=r"^decoder 'mlp_x': the eager rebuild .* does not reproduce its output"):
        eager_from_script(_jit(nn.Sequential(Linear())), "mlp_x")
    with pytest.raises(TargetError, match=r"mlp_x\.1: cannot read LeakyReLU\.negative_slope from its TorchScript code"):
        eager_from_script(_jit(nn.Sequential(nn.Linear(3, 2), LeakyReLU())), "mlp_x")
