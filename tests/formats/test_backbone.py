"""Backbone file readers: typed cfg_args keys, non-finite weights."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter.errors import FileFormatError
from controlgs_adapter.formats.backbone import CFG_KEYS, cfg_value, check_finite_weights, parse_cfg_args, read_cfg_args


@pytest.mark.parametrize("entry, key", [
    ("voxel_size='abc'", "voxel_size"), ("voxel_size=nan", "voxel_size"), ("voxel_size=inf", "voxel_size"),
    ("feat_dim='abc'", "feat_dim"), ("feat_dim=32.5", "feat_dim"), ("feat_dim=0", "feat_dim"),
    ("n_offsets=None", "n_offsets"), ("appearance_dim=-1", "appearance_dim"), ("fork=[2]", "fork"),
    ("use_feat_bank='maybe'", "use_feat_bank"), ("add_color_dist=2", "add_color_dist"), ("dist2level=3", "dist2level"),
])
def test_a_key_the_loaders_read_with_a_wrong_value_names_file_and_key(tmp_path, entry, key):
    path = tmp_path / "cfg_args"
    path.write_text(f"Namespace(sh_degree=3, {entry}, model_path='/out')")
    with pytest.raises(FileFormatError, match=rf"^{path}: {key}=.* must be"):
        read_cfg_args(path)


def test_the_keys_the_loaders_read_come_back_typed():
    cfg = parse_cfg_args("Namespace(feat_dim=32.0, n_offsets='10', voxel_size=1, use_feat_bank=0, add_cov_dist='True', "
                         "add_color_dist=False, dist2level='round', far=nan, iteration='abc')")
    assert cfg["feat_dim"] == 32 and isinstance(cfg["feat_dim"], int)
    assert cfg["n_offsets"] == 10 and isinstance(cfg["n_offsets"], int)
    assert cfg["voxel_size"] == 1.0 and isinstance(cfg["voxel_size"], float)
    assert cfg["use_feat_bank"] is False and cfg["add_cov_dist"] is True and cfg["add_color_dist"] is False
    assert cfg["dist2level"] == "round"
    assert math.isnan(cfg["far"]) and cfg["iteration"] == "abc"  # keys no loader reads stay as written
    assert "far" not in CFG_KEYS and "iteration" not in CFG_KEYS


def test_cfg_value_by_hand():
    assert cfg_value("0.5", float, key="k", source="s") == 0.5
    assert cfg_value(True, bool, key="k", source="s") is True
    assert cfg_value("false", bool, key="k", source="s") is False
    with pytest.raises(FileFormatError, match=r"^s: k=True must be a number"):
        cfg_value(True, int, key="k", source="s")
    with pytest.raises(FileFormatError, match=r"^s: k=3 must be at least 4"):
        cfg_value(3, int, key="k", source="s", low=4)


def test_check_finite_weights_names_the_tensor():
    state = {"opacity_mlp": {"0.weight": torch.ones(2, 2), "0.bias": torch.zeros(2)}, "step": torch.tensor(3),
             "bound": [torch.zeros(3), torch.tensor([0.0, math.inf, 1.0])]}
    with pytest.raises(FileFormatError, match=r"^f.pth: tensor 'bound.1' holds 1 NaN/Inf value\(s\) of 3$"):
        check_finite_weights(state, source="f.pth")
    state["bound"][1][1] = 0.0
    check_finite_weights(state, source="f.pth")
    state["opacity_mlp"]["0.bias"][1] = math.nan
    with pytest.raises(FileFormatError, match=r"^f.pth \['x'\]: tensor 'x.opacity_mlp.0.bias' holds 1 NaN/Inf"):
        check_finite_weights(state, source="f.pth ['x']", prefix="x")
