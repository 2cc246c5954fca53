"""The Backend interface of a model family: dotted attribute paths, the mask -> anchor ids conversion,
the defaults a family inherits (targets, first layers, rows, the decoder check against its input
layout) and the backbone fingerprint."""

from __future__ import annotations

import types

import pytest
import torch
from torch import nn

from controlgs_adapter.backend import Backend, anchor_ids_from_mask, get_attr_path, has_attrs, set_attr_path
from controlgs_adapter.errors import InputValueError, ShapeError, TargetError


class _Toy(Backend):
    """Toy backend: two Sequential decoders."""

    name = "toy"

    def __init__(self, layout=None):
        self.layout = layout

    def matches(self, model):
        return hasattr(model, "dec_a")

    def decoder_paths(self, model):
        return ["dec_a", "dec_b"]

    def anchor_positions(self, model):
        return model.pos

    def input_layout(self, model, decoder_path):
        return self.layout


def _toy_model(n=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    return types.SimpleNamespace(pos=torch.rand(n, 3, generator=g),
                                 dec_a=nn.Sequential(nn.Linear(5, 4), nn.ReLU()), dec_b=nn.Sequential(nn.ReLU()))


def test_attr_paths_on_modules_lists_and_plain_objects():
    seq = nn.Sequential(nn.Linear(2, 3), nn.ReLU())
    obj = types.SimpleNamespace(net=seq, layers=[types.SimpleNamespace(w=1), types.SimpleNamespace(w=2)], none=None)
    assert get_attr_path(obj, "net.0") is seq[0]
    assert get_attr_path(obj, "layers.1.w") == 2
    set_attr_path(obj, "layers.0.w", 5)
    set_attr_path(obj, "layers.1", "x")
    new = nn.Linear(2, 3)
    set_attr_path(obj, "net.0", new)
    set_attr_path(obj, "top", 9)
    assert obj.layers[0].w == 5 and obj.layers[1] == "x" and seq[0] is new and obj.top == 9
    assert has_attrs(obj, ["net.0.weight", "none", "layers"]) and not has_attrs(obj, ["net.0.weights"])
    assert not has_attrs(obj, ["net", "missing.x"])
    with pytest.raises(IndexError):
        get_attr_path(obj, "layers.2")


def test_anchor_ids_from_mask_are_its_true_positions_in_order():
    mask = torch.tensor([False, True, True, False, True])
    assert anchor_ids_from_mask(mask).tolist() == [1, 2, 4]
    assert anchor_ids_from_mask(mask, 5).tolist() == [1, 2, 4]
    assert anchor_ids_from_mask(torch.zeros(3, dtype=torch.bool), 3).tolist() == []
    with pytest.raises(ShapeError, match="vis must have size 4"):
        anchor_ids_from_mask(mask, 4, name="vis")
    with pytest.raises(InputValueError, match="visible_mask.*dtype.*torch.int64"):
        anchor_ids_from_mask(mask.long())


def test_backend_defaults_and_check_decoder():
    b, m = _Toy(), _toy_model()
    assert b.first_linear_path(m, "dec_a") == "dec_a.0" and b.rows_per_anchor(m) == 1 and b.num_anchors(m) == 4
    assert b.default_targets(m) == ["dec_a", "dec_b"] and b.input_layout(m, "dec_a") is None
    assert b.rows_for(m, torch.tensor([True, False, False, True])).tolist() == [0, 3]
    with pytest.raises(ShapeError):
        b.rows_for(m, torch.tensor([True, False, True]))  # the mask must cover the model's 4 anchors
    assert b.make_hookable(m, "dec_a") is None and b.renderer(m) is None
    assert b.check_decoder(m, "dec_a") is m.dec_a[0]
    with pytest.raises(TargetError, match="toy: .*'dec_b'.*Linear, got ReLU"):
        b.check_decoder(m, "dec_b")
    with pytest.raises(TargetError, match="toy: .*'dec_c'.*first layer"):
        b.check_decoder(m, "dec_c")
    assert _Toy([("feat", 3), ("view", 2)]).check_decoder(m, "dec_a") is m.dec_a[0]
    with pytest.raises(TargetError, match=r"toy: dec_a\[0\] takes 5 inputs.*gives 6 \(\[\('feat', 3\), \('view', 3\)\]\)"):
        _Toy([("feat", 3), ("view", 3)]).check_decoder(m, "dec_a")
    for name in ("matches", "decoder_paths", "anchor_positions"):
        with pytest.raises(NotImplementedError):
            getattr(Backend(), name)(m)


def test_backend_fingerprint_follows_positions_weights_and_selected_anchors():
    b = _Toy()
    m, same = _toy_model(seed=0), _toy_model(seed=0)
    same.dec_a.load_state_dict(m.dec_a.state_dict())
    fp = b.fingerprint(m)
    assert len(fp) == 16 and int(fp, 16) >= 0 and fp == b.fingerprint(same)
    with torch.no_grad():
        same.dec_a[0].bias[0] += 1e-3
    assert b.fingerprint(same) != fp  # decoder weights count
    moved = _toy_model(seed=0)
    moved.dec_a.load_state_dict(m.dec_a.state_dict())
    moved.pos[2, 1] += 1e-3
    assert b.fingerprint(moved) != fp  # positions count
    # anchor_ids: exactly the fingerprint of a model holding those anchors, in that order
    sub = types.SimpleNamespace(pos=m.pos[[3, 1]].clone(), dec_a=m.dec_a, dec_b=m.dec_b)
    assert b.fingerprint(m, torch.tensor([3, 1])) == b.fingerprint(sub)
    assert b.fingerprint(m, torch.tensor([1, 3])) != b.fingerprint(sub)
