"""Tests of ``controlgs_adapter.formats.torchscript_live``."""

from __future__ import annotations

import io
import warnings

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import TargetError
from controlgs_adapter.formats.torchscript import eager_from_archive, eager_from_script


def test_eager_from_script_default_name_is_decoder():
    with pytest.raises(TargetError, match=r"^decoder 'decoder': expected a TorchScript module, got Linear$"):
        eager_from_script(nn.Linear(2, 2))  # type: ignore[arg-type]
    with pytest.raises(TargetError, match=r"^decoder 'decoder': the TorchScript module holds no Linear layer$"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())))
    with pytest.raises(TargetError, match=r"^decoder 'mlp_color': "):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())), "mlp_color")


def _jit(module: nn.Module, how: str, in_features: int) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.trace(module, torch.randn(2, in_features)) if how == "trace" else torch.jit.script(module)


@pytest.mark.parametrize("how", ["trace", "script"])
def test_script_rebuild_reads_each_setting(how):
    torch.manual_seed(4)
    # settings away from torch's defaults (LeakyReLU 0.01, Softplus beta 1 / threshold 20, Softmax dim None)
    m = nn.Sequential(nn.Linear(3, 6), nn.LeakyReLU(0.3), nn.Linear(6, 6), nn.Softplus(beta=3.0, threshold=0.5),
                      nn.Linear(6, 4), nn.Softmax(dim=0)).eval()
    got = eager_from_script(_jit(m, how, 3), name="dec")
    assert got[1].negative_slope == 0.3
    assert (got[3].beta, got[3].threshold) == (3.0, 0.5)
    assert got[5].dim == 0
    x = torch.randn(7, 3) * 4
    assert torch.equal(got(x), m(x))


def test_script_rebuild_keeps_mode_grad_flags_and_refuses():
    torch.manual_seed(5)
    m = nn.Sequential(nn.Linear(3, 2), nn.ReLU()).train()
    m[0].bias.requires_grad_(False)
    got = eager_from_script(_jit(m, "script", 3))
    assert got.training and got[0].weight.requires_grad and not got[0].bias.requires_grad
    m.eval()
    assert not eager_from_script(_jit(m, "script", 3)).training
    nobias = nn.Sequential(nn.Linear(3, 2, bias=False))
    got = eager_from_script(_jit(nobias, "trace", 3))
    assert got[0].bias is None and torch.equal(got[0].weight, nobias[0].weight)
    with pytest.raises(TargetError, match="decoder 'act': the TorchScript module holds no Linear layer"):
        eager_from_script(_jit(nn.Sequential(nn.ReLU()), "script", 3), name="act")
    with pytest.raises(TargetError, match="decoder 'x': expected a TorchScript module, got Sequential"):
        eager_from_script(m, name="x")  # type: ignore[arg-type]
    with pytest.raises(TargetError, match=r"decoder 'g.1': TorchScript layer of type 'GELU' cannot be rebuilt"):
        eager_from_script(_jit(nn.Sequential(nn.Linear(3, 2), nn.GELU()), "script", 3), name="g")


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


def _trace(module: nn.Module) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return torch.jit.trace(module, torch.randn(2, 3))


def test_eager_from_script_refusals():
    from controlgs_adapter.errors import TargetError
    from controlgs_adapter.formats.torchscript import eager_from_script

    with pytest.raises(TargetError, match=r"decoder 'mlp_x': the TorchScript module holds no Linear layer"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.ReLU())), "mlp_x")
    with pytest.raises(TargetError, match=r"decoder 'mlp_x.1': TorchScript layer of type 'GELU' cannot be rebuilt .*"
                                          r"\(supported: Sequential of Identity, LeakyReLU, Linear, ReLU, SiLU, Sigmoid, "
                                          r"Softmax, Softplus, Tanh\)"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.GELU())), "mlp_x")
    with pytest.raises(TargetError, match=r"decoder 'mlp_x': the TorchScript module does not take a \[rows, 3\] input"):
        eager_from_script(torch.jit.script(nn.Sequential(nn.Linear(3, 2), nn.Linear(4, 1))), "mlp_x")
    with pytest.raises(TargetError, match=r"decoder 'mlp_x': the eager rebuild .* does not reproduce its output"):
        eager_from_script(_trace(nn.Sequential(Linear())), "mlp_x")
    with pytest.raises(TargetError, match=r"mlp_x.1: cannot read LeakyReLU.negative_slope from its TorchScript code"):
        eager_from_script(_trace(nn.Sequential(nn.Linear(3, 2), LeakyReLU())), "mlp_x")


@pytest.mark.parametrize("convert", ["trace", "script"])
def test_eager_from_script_reads_each_setting(convert):
    """Settings from the traced code's constants (trace) or the module's attributes (script), each a
    different number so a swapped index or attribute shows; mode as stored."""
    from controlgs_adapter.formats.torchscript import eager_from_script

    module = nn.Sequential(nn.Linear(3, 3), nn.LeakyReLU(0.3), nn.Softplus(beta=1.5, threshold=7.0), nn.Softmax(dim=0))
    module.eval()
    sm = _trace(module) if convert == "trace" else torch.jit.script(module)
    eager = eager_from_script(sm)
    assert eager[1].negative_slope == 0.3 and (eager[2].beta, eager[2].threshold) == (1.5, 7.0) and eager[3].dim == 0
    assert not eager.training and not eager[1].training


def test_settings_with_signs_and_exponents(tmp_path):
    """Negative and exponent-written constants in traced code read exactly, live and from the file."""
    from controlgs_adapter.formats.torchscript import eager_from_script

    module = nn.Sequential(nn.Linear(3, 3), nn.LeakyReLU(-0.5), nn.Softplus(beta=2.5e-7, threshold=1e20), nn.Softmax(dim=-1))
    sm = _trace(module)
    path = tmp_path / "s.pt"
    torch.jit.save(sm, str(path))
    for eager in (eager_from_script(sm), eager_from_archive(path)):
        assert eager[1].negative_slope == -0.5 and (eager[2].beta, eager[2].threshold) == (2.5e-7, 1e20)
        assert eager[3].dim == -1


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
