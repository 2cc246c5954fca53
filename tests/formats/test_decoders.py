"""Decoders stored as state dicts or TorchScript traces (``formats.decoders``): the Scaffold-family MLPs
rebuilt from their weights, the appearance embedding, the first layer's width, and both on-disk modes
with every refusal naming the file and entry."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.decoders import (
    Decoders,
    build_mlp,
    check_first_width,
    decoders_from_state_dicts,
    embedding_from_state,
)

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _sd(*shapes: tuple[int, int], at: tuple[int, ...] | None = None, bias: bool = True) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(1)
    out = {}
    for i, (o, n) in zip(at or range(0, 2 * len(shapes), 2), shapes):
        out[f"{i}.weight"] = torch.randn(o, n, generator=g)
        if bias:
            out[f"{i}.bias"] = torch.randn(o, generator=g)
    return out


def test_build_mlp_computes_the_family_decoders_by_hand():
    x = torch.randn(5, 3, dtype=torch.float64)
    sd = {k: v.double() for k, v in _sd((4, 3), (2, 4)).items()}
    h = torch.relu(x @ sd["0.weight"].T + sd["0.bias"])
    z = h @ sd["2.weight"].T + sd["2.bias"]
    for attr, want in [("mlp_opacity", torch.tanh(z)), ("mlp_color", torch.sigmoid(z)),
                       ("mlp_feature_bank", torch.softmax(z, dim=1))]:
        torch.testing.assert_close(build_mlp(attr, sd, name="n", source="s").double()(x), want, rtol=1e-12, atol=1e-12)
    cov = build_mlp("mlp_cov", sd, name="n", source="s").double()
    torch.testing.assert_close(cov(x), z, rtol=1e-12, atol=1e-12)  # cov: no activation after the last Linear
    nobias = build_mlp("mlp_cov", _sd((4, 3), (2, 4), bias=False), name="n", source="s")
    assert nobias[0].bias is None and nobias[2].bias is None


@pytest.mark.parametrize("state, words", [
    ([1, 2], "s: entry 'n' is not a state dict (got list)"),
    ({"weight": torch.zeros(2, 2)}, "s: entry 'n' holds no '<i>.weight' Linear weights (keys: ['weight'])"),
    (_sd((4, 3), (2, 4), at=(0, 1)), "s: 'n' has a Linear at index 1 where an activation was expected"),
    (_sd((4, 3), (2, 5)), "s: 'n' layer 2 weight [2, 5] does not take the previous width 4"),
    ({"0.weight": torch.zeros(4)}, "s: 'n' layer 0 weight [4] does not take the previous width None"),
    (_sd((4, 3), (2, 4), at=(0, 4)), "s: 'n' has no layer at index 2 (keys: "),
])
def test_mlp_from_state_dict_refusals(state, words):
    with pytest.raises(FileFormatError) as e:
        build_mlp("mlp_opacity", state, name="n", source="s")
    assert words in str(e.value)


def test_decoders_from_state_dicts_optional_entries_embedding_and_first_width():
    sd = {"op": _sd((4, 3), (1, 4)), "cov": _sd((4, 3), (7, 4))}
    got = decoders_from_state_dicts(sd, {"mlp_opacity": "op", "mlp_cov": "cov", "mlp_color": "col"}, source="f.pth",
                                    optional=("mlp_color",))
    assert sorted(got) == ["mlp_cov", "mlp_opacity"] and isinstance(got["mlp_opacity"][3], nn.Tanh)
    with pytest.raises(FileFormatError, match=r"^f.pth: missing entry 'col' \(has \['cov', 'op'\]\)$"):
        decoders_from_state_dicts(sd, {"mlp_color": "col"}, source="f.pth")  # nothing is optional unless said
    x = torch.randn(5, 3, dtype=torch.float64)
    w = {k: v.double() for k, v in sd["op"].items()}
    want = torch.tanh(torch.relu(x @ w["0.weight"].T + w["0.bias"]) @ w["2.weight"].T + w["2.bias"])  # ReLU between, Tanh after
    torch.testing.assert_close(got["mlp_opacity"].double()(x), want)
    table = torch.arange(6.0).view(3, 2)
    emb = embedding_from_state({"embedding.weight": table.double()}, source="e")
    assert emb(torch.tensor([2, 0])).tolist() == [[4.0, 5.0], [0.0, 1.0]] and emb.weight.dtype == torch.float32
    assert not emb.weight.requires_grad
    for bad in ({}, {"a.weight": table, "b.weight": table}, {"weight": torch.zeros(3)}):
        with pytest.raises(FileFormatError, match=r"^e: .*\[num_cameras, appearance_dim\]"):
            embedding_from_state(bad, source="e")
    check_first_width(got["mlp_cov"], 3, name="mlp_cov", source="f", layout="L")
    with pytest.raises(FileFormatError, match=r"^f: mlp_cov takes 3 inputs, the configuration gives 5 \(L\)$"):
        check_first_width(got["mlp_cov"], 5, name="mlp_cov", source="f", layout="L")


def test_decoders_unite_file_modes_and_refusals(tmp_path):
    with pytest.raises(FileFormatError, match=r"missing MLPs: neither the TorchScript traces \['opacity_mlp.pt', "
                                              r"'cov_mlp.pt', 'color_mlp.pt'\] nor checkpoints.pth is there"):
        Decoders(tmp_path)
    blob = {"opacity_mlp": _sd((4, 3), (1, 4)), "cov_mlp": _sd((4, 3), (7, 4)), "color_mlp": _sd((4, 3), (3, 4)),
            "appearance": {"embedding.weight": torch.ones(2, 5)}}
    torch.save(blob, tmp_path / "checkpoints.pth")
    dec = Decoders(tmp_path)
    assert dec.mode == "unite" and sorted(dec.state) == ["embedding_appearance", "mlp_color", "mlp_cov", "mlp_opacity"]
    assert dec.source["mlp_cov"] == f"{tmp_path / 'checkpoints.pth'} ['cov_mlp']"
    mods = dec.modules()
    assert mods["embedding_appearance"].weight.shape == (2, 5) and mods["mlp_color"][2].out_features == 3
    assert torch.equal(dec.weight("mlp_cov", "2.bias"), blob["cov_mlp"]["2.bias"])
    with pytest.raises(FileFormatError, match=r"\['cov_mlp'\]: decoder 'mlp_cov' has no tensor '4.weight' \(keys: "):
        dec.weight("mlp_cov", "4.weight")
    torch.save({**blob, "cov_mlp": [1]}, tmp_path / "checkpoints.pth")
    with pytest.raises(FileFormatError, match=r"checkpoints.pth: entry 'cov_mlp' is not a state dict$"):
        Decoders(tmp_path)
    torch.save({k: v for k, v in blob.items() if k not in ("color_mlp", "opacity_mlp")}, tmp_path / "checkpoints.pth")
    with pytest.raises(FileFormatError, match=r"checkpoints.pth: missing MLP entr\(y/ies\) \['opacity_mlp', 'color_mlp'\]"):
        Decoders(tmp_path)
    torch.save([blob], tmp_path / "checkpoints.pth")
    with pytest.raises(FileFormatError, match="checkpoints.pth: expected a dict of state dicts, got list"):
        Decoders(tmp_path)


def test_decoders_split_mode_from_traces(tmp_path):
    torch.manual_seed(0)
    nets = {"opacity_mlp.pt": nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 1), nn.Tanh()),
            "cov_mlp.pt": nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 7))}
    for name, net in nets.items():
        torch.jit.trace(net, torch.zeros(2, 3)).save(str(tmp_path / name))
    with pytest.raises(FileFormatError, match=r"missing MLP file\(s\) \['color_mlp.pt'\] \(split mode"):
        Decoders(tmp_path)
    torch.save({"opacity_mlp": {}}, tmp_path / "checkpoints.pth")  # ignored: any trace present means split mode
    nets["color_mlp.pt"] = nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 3), nn.Sigmoid())
    torch.jit.trace(nets["color_mlp.pt"], torch.zeros(2, 3)).save(str(tmp_path / "color_mlp.pt"))
    dec = Decoders(tmp_path)
    assert dec.mode == "split" and dec.source["mlp_cov"] == str(tmp_path / "cov_mlp.pt")
    assert dec.layers["mlp_opacity"] == [("Linear", (3, 4)), ("ReLU", None), ("Linear", (4, 1)), ("Tanh", None)]
    x = torch.randn(5, 3)
    mods = dec.modules()
    for attr, file in [("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")]:
        assert torch.equal(mods[attr](x), nets[file](x))
