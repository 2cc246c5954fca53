"""Backbone families (facts in /work/shared/notes/backbones.md): the refusals, defaults and option
branches no other test reaches, each pinned against the family's published layout or a value worked
out by hand (how is said next to each literal)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

import test_backend_compgs as compgs_t
import test_backend_contextgs as contextgs_t
import test_backend_hac as hac_t
import test_backend_octree_gs as octree_t
from _family_checks import make_camera, write_cfg_args
from controlgs_adapter.backends import detect_family, load_model_dir
from controlgs_adapter.backends.compgs import ResidualBlock, ResidualMLP, load_compgs_dir
from controlgs_adapter.backends.contextgs import ContextGSModel, load_contextgs_dir, quantize_anchor
from controlgs_adapter.backends.hac import HACModel, decoders_from_checkpoint, load_hac_dir, voxel_snap
from controlgs_adapter.backends.models.anchor_model import feature_bank
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel, load_octree_gs_dir
from controlgs_adapter.errors import FileFormatError, InputValueError

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace: the format under test


# ---------------------------------------------------------------- CompGS

def test_residual_mlp_structure_default_and_forward_by_hand():
    torch.manual_seed(0)
    m = ResidualMLP(5, 6, 2)  # CompGS's ResidualMLP: one residual block unless told otherwise
    assert [type(x).__name__ for x in m.net] == ["Linear", "LeakyReLU", "ResidualBlock", "Linear"]
    assert isinstance(m.skip, nn.Linear) and isinstance(m.tail_activation, nn.Identity)
    x = torch.randn(4, 5, dtype=torch.float64)
    m = m.double()

    def lin(layer, v):
        return v @ layer.weight.T + layer.bias

    def leaky(v):  # nn.LeakyReLU's default slope 0.01
        return torch.where(v > 0, v, 0.01 * v)

    h = leaky(lin(m.net[0], x))
    blk = m.net[2].net
    h = h + lin(blk[2], leaky(lin(blk[0], h)))
    want = lin(m.net[3], h) + lin(m.skip, x)
    assert torch.allclose(m(x), want, atol=1e-12)
    # in == out: the skip path is the identity; a tail is applied to the sum
    sq = ResidualMLP(3, 4, 3, num_res_layer=2, tail=nn.Tanh()).double()
    assert isinstance(sq.skip, nn.Identity) and sum(isinstance(b, ResidualBlock) for b in sq.net) == 2
    y = torch.randn(2, 3, dtype=torch.float64)
    assert torch.allclose(sq(y), torch.tanh(sq.net(y) + y), atol=1e-12)


def test_compgs_decoder_tails_and_residual_depths_follow_compgs():
    # CompGS Prediction.py: means/covariance: no tail, 1 residual layer; opacity: Tanh, 1; colour: Sigmoid, 2;
    # inputs C + G (means, covariance) and C + G + 4 (opacity, colour), hidden width C, outputs 3 / 7 / 1 / 3
    arr = compgs_t._arrays(0)
    net = compgs_t._model(arr, 0).network.prediction_net
    c, g = compgs_t.C, compgs_t.G
    want = {"means": (None, 1, c + g, 3), "covariance": (None, 1, c + g, 7), "opacity": (nn.Tanh, 1, c + g + 4, 1),
            "color": (nn.Sigmoid, 2, c + g + 4, 3)}
    for name, (tail, blocks, d_in, d_out) in want.items():
        m = getattr(net, f"{name}_pred_mlp")
        assert type(m.tail_activation) is (tail or nn.Identity), name
        assert sum(isinstance(b, ResidualBlock) for b in m.net) == blocks, name
        assert (m.net[0].in_features, m.net[0].out_features, m.net[-1].out_features) == (d_in, c, d_out), name
        assert (m.skip.in_features, m.skip.out_features) == (d_in, d_out), name


def _compgs_dir(tmp_path):
    arr = compgs_t._arrays(3)
    root = compgs_t._write_checkpoint(tmp_path / "exp", arr, compgs_t._model(arr, 3))
    return root, root / "point_cloud" / "iteration_30000" / "weights.pth"


def test_compgs_loader_refusals_name_the_file_and_the_key(tmp_path):
    root, w = _compgs_dir(tmp_path)
    state = torch.load(w, weights_only=True)
    key = "prediction_net.color_pred_mlp.net.0.weight"
    torch.save({k: v for k, v in state.items() if k != key}, w)
    with pytest.raises(FileFormatError, match=rf"weights.pth: missing '{key}' \(not a CompGS network state dict\?\)"):
        load_compgs_dir(root, allow_unquantized=True)
    # colour FC1 [C + 1, C + G + 4]: its row count is not C = 32 f_ref_feat_* fields
    torch.save({**state, key: torch.zeros(33, 44)}, w)
    with pytest.raises(FileFormatError, match=r"is \[33, 44\], which does not fit C=32 f_ref_feat_\* and 80 f_res_feat_\*"):
        load_compgs_dir(root, allow_unquantized=True)
    # G = in - C - 4 = 36 - 32 - 4 = 0 < 1
    torch.save({**state, key: torch.zeros(32, 36)}, w)
    with pytest.raises(FileFormatError, match=r"\[C, C \+ G \+ 4\] expected"):
        load_compgs_dir(root, allow_unquantized=True)
    # G = 47 - 32 - 4 = 11 does not divide the 80 f_res_feat_* fields
    torch.save({**state, key: torch.zeros(32, 47)}, w)
    with pytest.raises(FileFormatError, match=r"\[C, C \+ G \+ 4\] expected"):
        load_compgs_dir(root, allow_unquantized=True)
    # the colour FC1 fits but another weight does not
    bad = "prediction_net.means_pred_mlp.net.0.weight"
    torch.save({**state, bad: torch.zeros(32, 41)}, w)
    with pytest.raises(FileFormatError, match=r"weight shapes do not fit the point cloud: \['prediction_net.means_pred_mlp"
                                              r".net.0.weight \[32, 41\] != \[32, 40\]'\]"):
        load_compgs_dir(root, allow_unquantized=True)
    torch.save(state, w)
    with pytest.raises(FileFormatError, match="allow_unquantized=True"):
        load_compgs_dir(root)
    model = load_compgs_dir(root, allow_unquantized=True)
    assert model.derive_factor == compgs_t.K  # K = 80 f_res_feat_* / G = 8


# ---------------------------------------------------------------- ContextGS

def test_quantize_anchor_by_hand():
    # lo = 0, hi = 65.535 on every axis: step = 65.535 / 65535 + 1e-6 = 0.001001;
    # 0.0025 / 0.001001 = 2.497 -> q = 2 -> 0.002002; below lo -> q = 0 -> lo; far above hi -> q = 65535
    lo, hi = torch.zeros(3, dtype=torch.float64), torch.full((3,), 65.535, dtype=torch.float64)
    a = torch.tensor([[0.0025, -1.0, 100.0]], dtype=torch.float64)
    got = quantize_anchor(a, lo, hi)
    assert torch.allclose(got, torch.tensor([[0.002002, 0.0, 65535 * 0.001001]], dtype=torch.float64), atol=1e-12)
    # a lower bound of -1 shifts everything: (0.0025 + 1) / 0.001001 = 1001.5 -> 1001 -> 1001 * 0.001001 - 1
    got = quantize_anchor(torch.tensor([[0.0025, 0.0025, 0.0025]], dtype=torch.float64), lo - 1.0, hi)
    step = 66.535 / 65535 + 1e-6
    assert torch.allclose(got, torch.full((1, 3), math.floor(1.0025 / step) * step - 1.0, dtype=torch.float64), atol=1e-12)


def test_contextgs_bound_refusals(tmp_path):
    arr = contextgs_t._arrays(0, decoded=False)
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    kw = dict(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"], scaling=t["scale"],
              hyper_latent=t["hyper"], **contextgs_t._decoders(0))
    with pytest.raises(FileFormatError, match="x_bound_min and x_bound_max must be given together"):
        ContextGSModel(x_bound_min=contextgs_t.LO, decoded_version=False, **kw)
    with pytest.raises(FileFormatError, match="x_bound_min and x_bound_max must be given together"):
        ContextGSModel(x_bound_max=contextgs_t.HI, decoded_version=True, **kw)
    with pytest.raises(FileFormatError, match="a not-decoded ContextGS model needs x_bound_min/x_bound_max"):
        ContextGSModel(decoded_version=False, **kw)
    decoded = ContextGSModel(decoded_version=True, **kw)  # a decoded model needs no bound: positions as stored
    assert torch.equal(decoded.get_anchor, t["anchor"])
    # checkpoint.pth entry 'bound' malformed
    root = contextgs_t._write_dir(tmp_path / "c", arr, contextgs_t._decoders(0))
    ckpt = root / "point_cloud" / "iteration_30000" / "checkpoint.pth"
    sd = torch.load(ckpt, weights_only=True)
    for bad in ([contextgs_t.LO], [contextgs_t.LO, torch.zeros(2)], (contextgs_t.LO, [0.0, 0.0, 0.0])):
        torch.save({**sd, "bound": bad}, ckpt)
        with pytest.raises(FileFormatError, match=r"checkpoint.pth: entry 'bound' must be \[x_bound_min, x_bound_max\]"):
            load_contextgs_dir(root, allow_unquantized=True)
    torch.save({**sd, "bound": (contextgs_t.LO, contextgs_t.HI)}, ckpt)  # a tuple is as good as a list
    m = load_contextgs_dir(root, allow_unquantized=True)
    assert torch.equal(m.x_bound_min, contextgs_t.LO) and torch.equal(m.x_bound_max, contextgs_t.HI)


def test_contextgs_defaults_feat_dim_50_and_n_offsets_10(tmp_path):
    # ContextGS ModelParams: feat_dim 50, n_offsets 10: a cfg_args without them reads the test folder (F 50, K 10)
    root = contextgs_t._write_dir(tmp_path / "c", contextgs_t._arrays(1, decoded=True), contextgs_t._decoders(1))
    write_cfg_args(root / "cfg_args", hyper_divisor=4, use_feat_bank=False)
    m = load_contextgs_dir(root)
    assert (m.feat_dim, m.n_offsets) == (50, 10)


# ---------------------------------------------------------------- HAC / HAC++

def _hac_kw(n_mask_cols: int, seed: int = 0) -> dict:
    arr = hac_t._arrays(seed, decoded=True, mask_cols=n_mask_cols)
    return dict(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                scaling=torch.from_numpy(arr["scale"]), decoded_version=True, **hac_t._decoders(seed))


def test_hac_model_variant_and_mask_column_refusals():
    k = hac_t.K
    with pytest.raises(InputValueError, match=r"variant must be 'hac\+\+' or 'hac', got 'hac\+'"):
        HACModel(voxel_size=0.01, variant="hac+", **_hac_kw(k + 1))
    with pytest.raises(InputValueError, match=rf"hac\+\+: mask must have {k + 1} columns \(n_offsets={k}\), got {k}"):
        HACModel(voxel_size=0.01, variant="hac++", **_hac_kw(k))
    with pytest.raises(InputValueError, match=rf"hac: mask must have {k} columns \(n_offsets={k}\), got {k + 1}"):
        HACModel(voxel_size=0.01, variant="hac", **_hac_kw(k + 1))
    assert HACModel(voxel_size=0.01, **_hac_kw(k + 1)).variant == "hac++"  # the default variant


def test_hac_feature_bank_input_by_hand():
    # HAC++'s renderer: feat re-weighted by mlp_feature_bank([view, dist]) before [feat, view, dist]
    f = hac_t.F
    torch.manual_seed(2)
    bank = nn.Sequential(nn.Linear(4, f), nn.ReLU(), nn.Linear(f, 3), nn.Softmax(dim=1))
    kw = _hac_kw(hac_t.K + 1, seed=2)
    kw["anchor_feat"] = kw["anchor_feat"][:, :48]  # the bank needs F divisible by 4
    kw.update(mlp_opacity=nn.Linear(52, 2), mlp_cov=nn.Linear(52, 2), mlp_color=nn.Linear(52, 2))
    bank = nn.Sequential(nn.Linear(4, 48), nn.ReLU(), nn.Linear(48, 3), nn.Softmax(dim=1))
    model = HACModel(voxel_size=0.01, mlp_feature_bank=bank, **kw)
    cam = torch.tensor([0.3, -0.2, 4.0])
    ids = torch.tensor([5, 1, 9])
    x = model.decoder_inputs(cam, ids)["mlp_opacity"]
    anchor = kw["anchor"][ids].double()
    v = anchor - cam.double()
    dist = v.norm(dim=1, keepdim=True)
    view = v / dist
    w = bank.double()(torch.cat([view, dist], dim=1))
    feat = kw["anchor_feat"][ids].double()
    # every 4th channel repeated 4 times, every 2nd twice, all channels; mixed by the three weights
    mixed = feat[:, ::4].repeat(1, 4) * w[:, :1] + feat[:, ::2].repeat(1, 2) * w[:, 1:2] + feat * w[:, 2:]
    assert torch.allclose(x.double(), torch.cat([mixed, view, dist], dim=1), atol=1e-5)
    assert torch.allclose(feature_bank(feat, w), mixed)


def test_hac_checkpoint_and_ply_refusals(tmp_path):
    sd = {"opacity_mlp": {}, "cov_mlp": {}, "color_mlp": {}}
    with pytest.raises(FileFormatError, match=r"ck.pth: missing entry 'mlp_feature_bank' \(cfg_args has use_feat_bank=True\)"):
        decoders_from_checkpoint(sd, tmp_path / "ck.pth", feature_bank=True)
    root = hac_t._write_dir(tmp_path / "h", hac_t._arrays(0, decoded=True, mask_cols=hac_t.K + 1), hac_t._decoders(0))
    write_cfg_args(root / "cfg_args", feat_dim=48, n_offsets=hac_t.K, voxel_size=0.01, use_feat_bank=False)
    with pytest.raises(FileFormatError, match="point_cloud.ply: 50 f_anchor_feat_\\* fields, the configuration says feat_dim=48"):
        load_hac_dir(root)
    write_cfg_args(root / "cfg_args", feat_dim=50, n_offsets=9, voxel_size=0.01, use_feat_bank=False)
    with pytest.raises(FileFormatError, match=r"11 f_mask_\* fields, expected 9 or 10 for n_offsets=9"):
        load_hac_dir(root)
    # HAC++ ModelParams defaults feat_dim 50, n_offsets 10: a cfg_args without them reads the folder
    write_cfg_args(root / "cfg_args", voxel_size=0.01)
    m = load_hac_dir(root)
    assert (m.feat_dim, m.n_offsets, m.variant, m.voxel_size) == (50, 10, "hac++", 0.01)
    # a raw model without voxel_size in cfg_args cannot be snapped: refused
    raw = hac_t._write_dir(tmp_path / "raw", hac_t._arrays(1, decoded=False, mask_cols=hac_t.K + 1), hac_t._decoders(1))
    write_cfg_args(raw / "cfg_args", feat_dim=50, n_offsets=hac_t.K)
    with pytest.raises(FileFormatError, match=r"voxel_size=0.0: the raw model's anchors are snapped to a voxel grid"):
        load_hac_dir(raw, allow_unquantized=True)


def test_voxel_snap_by_hand():
    # round(0.026 / 0.01) = 3 -> 0.03; round(-0.014 / 0.01) = -1 -> -0.01; round(0.004 / 0.01) = 0
    got = voxel_snap(torch.tensor([[0.026, -0.014, 0.004]], dtype=torch.float64), 0.01)
    assert torch.allclose(got, torch.tensor([[0.03, -0.01, 0.0]], dtype=torch.float64), atol=1e-15)


# ---------------------------------------------------------------- Octree-GS / Octree-AnyGS

def test_octree_refusals_and_appearance_id():
    arr = octree_t._arrays(0)
    decs = octree_t._decoders(torch.Generator().manual_seed(0))

    class NoMask:
        pass

    with pytest.raises(InputValueError, match="model has no _anchor_mask: call model.set_anchor_mask"):
        OctreeGSBackend().anchor_ids(NoMask(), torch.ones(3, dtype=torch.bool))
    with pytest.raises(InputValueError, match="dist2level must be 'round', 'floor', 'ceil' or 'progressive', got 'nearest'"):
        OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                      anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                      level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                      voxel_size=0.1, standard_dist=3.0, dist2level="nearest", **decs)
    emb = nn.Embedding(3, 2)
    f, k = octree_t.F, octree_t.K
    decs["mlp_color"] = nn.Sequential(nn.Linear(f + 3 + 1 + 2, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid())
    m = OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                      anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                      level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                      voxel_size=0.1, standard_dist=3.0, add_level=True, add_opacity_dist=True, embedding_appearance=emb,
                      **decs)
    ids = torch.tensor([0, 3])
    with pytest.raises(InputValueError, match="appearance_id is required"):
        m.decoder_inputs(torch.zeros(3), ids)
    x = m.decoder_inputs(torch.zeros(3), ids, appearance_id=2)["mlp_color"]
    assert torch.equal(x[:, -2:], emb.weight[2].detach().expand(2, 2))  # the code of camera 2, last
    assert m.fork == 2 and m.dist2level == "round"  # Octree-GS defaults (arguments/__init__.py)
    # decode() takes camera.extra["uid"] (default 0) when no appearance_id is given
    cam = make_camera()
    g0 = m.decode(cam)
    g2 = m.decode(cam, appearance_id=2)
    cam.extra["uid"] = 2
    assert torch.equal(m.decode(cam).colors, g2.colors) and not torch.equal(g0.colors, g2.colors)


def test_octree_loader_refusals_and_cfg_defaults(tmp_path):
    arr = octree_t._arrays(1)
    decs = octree_t._decoders(torch.Generator().manual_seed(1))
    root = octree_t._write_dir(tmp_path / "o", arr, decs, mode="unite")
    cfg = dict(octree_t.CFG)
    write_cfg_args(root / "cfg_args", **{**cfg, "feat_dim": 16})
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: 32 f_anchor_feat_\* fields, .*cfg_args says feat_dim=16"):
        load_octree_gs_dir(root)
    # keys missing from cfg_args take Octree-GS's ModelParams defaults: fork 2, dist2level 'round', n_offsets 10
    # (the folder has 4 offsets, so n_offsets must be given), feat_dim 32
    write_cfg_args(root / "cfg_args", n_offsets=octree_t.K, add_opacity_dist=True, add_level=True)
    m = load_octree_gs_dir(root)
    assert (m.fork, m.dist2level, m.feat_dim, m.add_level, m.add_cov_dist, m.add_color_dist) == (2, "round", 32, True,
                                                                                             False, False)
    # one anchor: the 'info' column cannot hold voxel_size and standard_dist in rows 0 and 1
    from controlgs_adapter.formats.backbone import read_ply, write_ply

    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {n: c[:1] for n, c in fields.items()})
    with pytest.raises(FileFormatError, match=r"'info' column holds voxel_size and standard_dist in rows 0 and 1; the "
                                              r"file has 1 anchors"):
        load_octree_gs_dir(root)


def test_octree_anygs_yaml_key_with_two_values_is_refused(tmp_path):
    root = tmp_path / "anygs"
    (root / "point_cloud" / "iteration_1").mkdir(parents=True)
    (root / "config.yaml").write_text("a: {\n  feat_dim: 32,\n}\nb: {\n  feat_dim: 16,\n}\n")
    with pytest.raises(FileFormatError, match=r"config.yaml: key 'feat_dim' has several values \[32, 16\]"):
        load_octree_gs_dir(root)
    (root / "config.yaml").write_text("a: {\n  base_model: 'gaussians',\n}\n")
    with pytest.raises(FileFormatError, match="base_model 'gaussians': only Octree-AnyGS's Scaffold-GS base model"):
        load_octree_gs_dir(root)
    (root / "config.yaml").unlink()
    with pytest.raises(FileFormatError, match="neither 'cfg_args' \\(Octree-GS\\) nor 'config.yaml'"):
        load_octree_gs_dir(root)


# ---------------------------------------------------------------- model folders

def test_detect_family_refusals_name_what_is_missing(tmp_path):
    with pytest.raises(FileFormatError, match="nowhere: no such model folder"):
        detect_family(tmp_path / "nowhere")
    (tmp_path / "m" / "point_cloud" / "iteration_7").mkdir(parents=True)
    with pytest.raises(FileFormatError, match=r"not a trained model folder of a supported family \(no point_cloud/"
                                              r"iteration_7/point_cloud.ply\)"):
        detect_family(tmp_path / "m")
    with pytest.raises(FileFormatError, match=r"no 'iteration_3' folder \(present: \[7\]\)"):
        detect_family(tmp_path / "m", iteration=3)
    (tmp_path / "e").mkdir()
    with pytest.raises(FileFormatError, match=r"\(no point_cloud/iteration_<N> folder"):
        detect_family(tmp_path / "e")
    with pytest.raises(InputValueError, match="unknown family 'scaffold' \\(supported: scaffold_gs, octree_gs, hac, "
                                              "contextgs, compgs\\)"):
        load_model_dir(tmp_path / "e", family="scaffold")


# ---------------------------------------------------------------- Scaffold-GS backend (duck-typed)

def test_scaffold_backend_layout_positions_and_matching():
    from types import SimpleNamespace

    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend

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
    assert torch.equal(b.visible_rows_to_anchor_ids(torch.tensor([False, True, True, False, True])), torch.tensor([1, 2, 4]))


# ---------------------------------------------------------------- stand-in constructors check every per-anchor tensor

def _family_kwargs():
    """(class, kwargs, per-anchor tensor arguments) of every family stand-in."""
    from controlgs_adapter.backends.compgs import CompGSModel

    h = _hac_kw(hac_t.K + 1)
    hac = (HACModel, {"voxel_size": 0.01, **h}, ["anchor", "offset", "mask", "anchor_feat", "scaling"])
    arr = contextgs_t._arrays(0, decoded=True)
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    ctx = (ContextGSModel, dict(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                                scaling=t["scale"], hyper_latent=t["hyper"], decoded_version=True, **contextgs_t._decoders(0)),
           ["anchor", "offset", "mask", "anchor_feat", "scaling", "hyper_latent"])
    oa = octree_t._arrays(0)
    octo = (OctreeGSModel, dict(anchor=torch.from_numpy(oa["anchor"]), offset=torch.from_numpy(oa["offset"]),
                                anchor_feat=torch.from_numpy(oa["feat"]), scaling=torch.from_numpy(oa["scale"]),
                                level=torch.from_numpy(oa["level"][:, None]), extra_level=torch.from_numpy(oa["extra"]),
                                voxel_size=0.1, standard_dist=3.0, **octree_t._decoders(torch.Generator().manual_seed(0))),
            ["anchor", "offset", "anchor_feat", "scaling", "level", "extra_level"])
    ca = compgs_t._arrays(0)
    comp = (CompGSModel, dict(means=torch.from_numpy(ca["means"]), scales_before_exp=torch.from_numpy(ca["scales"]),
                              ref_feats=torch.from_numpy(ca["ref"]), res_feats=torch.from_numpy(ca["res"])),
            ["means", "scales_before_exp", "ref_feats", "res_feats"])
    return [hac, ctx, octo, comp]


def test_stand_in_constructors_refuse_a_tensor_with_another_anchor_count():
    from controlgs_adapter.errors import ShapeError

    for cls, kw, names in _family_kwargs():
        cls(**kw)  # as built: accepted
        for i, name in enumerate(names):
            short = {**kw, name: kw[name][:-1]}
            # the first tensor sets A: the next one is named as disagreeing with it
            with pytest.raises(ShapeError, match=names[1] if i == 0 else name):
                cls(**short)
    # the fixed trailing sizes: positions 3, scales 6, offsets [K, 3], mask [M, 1], level [A, 1]
    for cls, kw, _ in _family_kwargs():
        for name, bad in (("scaling", lambda x: x[:, :5]), ("scales_before_exp", lambda x: x[:, :5]),
                          ("anchor", lambda x: x[:, :2]), ("means", lambda x: x[:, :2]),
                          ("offset", lambda x: x[:, :, :2]), ("mask", lambda x: x[:, :, :1].repeat(1, 1, 2)),
                          ("level", lambda x: x.repeat(1, 2))):
            if name in kw:
                with pytest.raises(ShapeError, match=name):
                    cls(**{**kw, name: bad(kw[name])})


def _fake_folder(root, fields: list[str], files: list[str]):
    """point_cloud/iteration_1 with a 2-vertex PLY holding ``fields`` and empty ``files`` (detection reads
    only the PLY header and the file names)."""
    from controlgs_adapter.formats.backbone import write_ply

    it = root / "point_cloud" / "iteration_1"
    it.mkdir(parents=True)
    write_ply(it / "point_cloud.ply", {f: np.zeros(2, np.float32) for f in fields})
    for f in files:
        (it / f).write_bytes(b"")
    return root


@pytest.mark.parametrize("fields, files, family", [
    (["x", "f_ref_feat_0"], [], "compgs"),
    (["x", "f_anchor_feat_0", "f_offset_0"], ["weights.pth", "opacity_mlp.pt"], "compgs"),
    (["x", "f_mask_0", "f_hyper_latent_0", "f_anchor_feat_0"], ["checkpoint.pth"], "contextgs"),
    (["x", "f_mask_0", "f_anchor_feat_0"], ["checkpoint.pth"], "hac"),
    (["x", "level", "extra_level", "f_anchor_feat_0", "f_offset_0"], ["opacity_mlp.pt"], "octree_gs"),
    (["x", "f_mask_0", "level", "extra_level"], [], "octree_gs"),  # masks without checkpoint.pth: not HAC
    (["x", "f_anchor_feat_0", "f_offset_0"], ["opacity_mlp.pt"], "scaffold_gs"),
    (["x", "f_anchor_feat_0", "f_offset_0"], ["checkpoints.pth"], "scaffold_gs"),
])
def test_detection_rules_from_fields_and_file_names(tmp_path, fields, files, family):
    assert detect_family(_fake_folder(tmp_path / "m", fields, files)) == family


@pytest.mark.parametrize("fields, files, shown, held", [
    (["x", "y", "f_anchor_feat_0", "f_anchor_feat_1", "f_offset_0"], [], "['x', 'y', 'f_anchor_feat_0', 'f_offset_0']",
     "none of opacity_mlp.pt, checkpoints.pth, checkpoint.pth, weights.pth"),
    (["x", "level", "f_anchor_feat_0"], ["opacity_mlp.pt"], "['x', 'level', 'f_anchor_feat_0']", "['opacity_mlp.pt']"),
    (["x", "f_offset_0", "f_offset_1"], ["checkpoints.pth"], "['x', 'f_offset_0']", "['checkpoints.pth']"),
])
def test_unrecognised_folder_names_its_fields_and_files(tmp_path, fields, files, shown, held):
    import re

    root = _fake_folder(tmp_path / "m", fields, files)
    with pytest.raises(FileFormatError, match=re.escape(f"point_cloud/iteration_1/point_cloud.ply has fields {shown}, "
                                                        f"point_cloud/iteration_1 holds {held}")):
        detect_family(root)


def test_bitstreams_only_compgs_folder_is_detected_as_compgs(tmp_path):
    (tmp_path / "c" / "point_cloud").mkdir(parents=True)
    (tmp_path / "c" / "point_cloud" / "bitstreams.npz").write_bytes(b"")
    assert detect_family(tmp_path / "c") == "compgs"


# ---------------------------------------------------------------- the prefilter reads the anchor's first 3 scales

def test_every_family_prefilter_uses_the_first_three_linear_scales():
    """make_camera(): 64 x 48, f = 40, at z = -5 looking along +z. An anchor at (-4.625, 0, 0) (depth 5)
    projects to u = 32 + 40 * (-4.625) / 5 = -5 px, 5 px left of the image. Its footprint radius is
    ceil(3 sqrt(64 s^2 + 0.3)) px for an isotropic world scale s: 12 px for s = 0.5 (touches the image),
    2 px for s = 0.01 (does not). Anchor 0 has s = 0.5 in scales[:3] and 0.01 in scales[3:], anchor 1 the
    reverse: only anchor 0 is kept, whatever the family stores (log or linear scales)."""
    from controlgs_adapter.backends.compgs import CompGSModel
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel

    cam = make_camera()
    pos = torch.tensor([[-4.625, 0.0, 0.0], [-4.625, 0.0, 0.0]])
    lin = torch.tensor([[0.5] * 3 + [0.01] * 3, [0.01] * 3 + [0.5] * 3])
    want = [True, False]
    n = 2
    ca = compgs_t._arrays(0)
    comp = CompGSModel(means=pos, scales_before_exp=lin.log(), ref_feats=torch.from_numpy(ca["ref"][:n]),
                       res_feats=torch.from_numpy(ca["res"][:n]))
    assert comp.visible_anchors(cam).tolist() == want
    for decoded in (True, False):
        kw = _hac_kw(hac_t.K + 1)
        kw = {k: (v[:n] if torch.is_tensor(v) else v) for k, v in kw.items()}
        kw.update(anchor=pos, scaling=lin if decoded else lin.log(), decoded_version=decoded)
        assert HACModel(voxel_size=0.001, **kw).visible_anchors(cam).tolist() == want, decoded
    t = {k: torch.from_numpy(v[:n]) for k, v in contextgs_t._arrays(0, decoded=True).items()}
    ctx = ContextGSModel(anchor=pos, offset=t["offset"], mask=torch.ones(n, contextgs_t.K, 1), anchor_feat=t["feat"],
                         scaling=lin, hyper_latent=t["hyper"], decoded_version=True, **contextgs_t._decoders(0))
    assert ctx.visible_anchors(cam).tolist() == want
    oa = octree_t._arrays(0)
    octo = OctreeGSModel(anchor=pos, offset=torch.from_numpy(oa["offset"][:n]), anchor_feat=torch.from_numpy(oa["feat"][:n]),
                         scaling=lin.log(), level=torch.zeros(n, 1, dtype=torch.int32), extra_level=torch.zeros(n),
                         voxel_size=0.1, standard_dist=3.0, **octree_t._decoders(torch.Generator().manual_seed(0)))
    assert octo.visible_anchors(cam).tolist() == want  # level 0 is always in the LOD set
    ref = NeuralGaussianModel(n, feat_dim=4, n_offsets=1)
    with torch.no_grad():
        ref._anchor.copy_(pos)
        ref._scaling.copy_(lin.log())
    assert ref.visible_anchors(cam).tolist() == want


def test_octree_lod_distance_is_scaled_by_the_resolution_scale():
    """Octree-GS's set_anchor_mask: dist = |voxel centre - camera| * resolution_scale; a float64 reference
    at resolution_scale 2 and 0.5 (a larger scale reads as farther: coarser levels)."""
    arr = octree_t._arrays(1)
    model = octree_t._model(arr, octree_t._decoders(torch.Generator().manual_seed(1)))
    cam = torch.tensor([0.3, -0.2, 4.0])
    levels = int(arr["level"].max() - arr["level"].min() + 1)
    masks = {}
    for scale in (2.0, 0.5):
        model.set_anchor_mask(cam, -1, scale)
        want = []
        for a in range(octree_t.A):
            lv = int(arr["level"][a])
            pos = arr["anchor"][a].astype(np.float64) + (octree_t.VOXEL / 2) / octree_t.FORK ** lv
            d = float(np.linalg.norm(pos - cam.double().numpy())) * scale
            pred = math.log2(octree_t.STD_DIST / d) / math.log2(octree_t.FORK) + float(arr["extra"][a])
            want.append(lv <= min(max(int(np.round(pred)), 0), levels - 1))
        assert model._anchor_mask.tolist() == want, scale
        masks[scale] = want
    assert sum(masks[2.0]) < sum(masks[0.5])  # the two scales select different sets
    # visible_anchors passes its resolution_scale on to the LOD selection
    c = make_camera()
    model.visible_anchors(c, resolution_scale=0.25)
    m2 = model._anchor_mask.clone()
    model.set_anchor_mask(c.center, -1, 0.25)
    assert torch.equal(m2, model._anchor_mask)
    model.set_anchor_mask(c.center, -1, 1.0)
    assert not torch.equal(m2, model._anchor_mask)  # for this camera, scales 1 and 0.25 select different sets


def test_detection_reads_the_largest_iteration_unless_told(tmp_path):
    root = _fake_folder(tmp_path / "m", ["x", "f_ref_feat_0"], [])  # iteration_1: CompGS
    it7 = root / "point_cloud" / "iteration_7"
    it7.mkdir()
    from controlgs_adapter.formats.backbone import write_ply

    write_ply(it7 / "point_cloud.ply", {f: np.zeros(2, np.float32) for f in ("x", "f_mask_0", "f_anchor_feat_0")})
    (it7 / "checkpoint.pth").write_bytes(b"")
    assert detect_family(root) == "hac"  # iteration 7 (HAC files), not 1
    assert detect_family(root, iteration=1) == "compgs"


def test_infer_decoded_by_hand():
    from controlgs_adapter.backends.hac import infer_decoded

    s = np.array([[0.1] * 6, [0.0] * 6, [0.2] * 6])
    m = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    assert infer_decoded(s, m, extra_mask_column=True) is True
    one_off = m.copy()
    one_off[2, 1] = 0.5  # a single mask value that is not 0/1: a raw model's logits
    assert infer_decoded(s, one_off, extra_mask_column=False) is False
    neg = s.copy()
    neg[1, 3] = -0.1  # 0/1 masks but a negative scale: the file does not tell
    assert infer_decoded(neg, m, extra_mask_column=False) is None
    # an all-zero row (zero padding) is left out: without it, a raw model's logits decide
    raw = np.array([[0.3, -2.0, 1.5], [0.0, 0.0, 0.0]])
    raw_s = np.array([[-3.0] * 6, [0.0] * 6])
    assert infer_decoded(raw_s, raw, extra_mask_column=False) is False
    pad = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert infer_decoded(np.array([[0.1] * 6, [0.0] * 6]), pad, extra_mask_column=True) is True
    # zero masks with a negative scale are not padding: that row makes the file undecidable
    assert infer_decoded(np.array([[0.1] * 6, [-0.5] + [0.0] * 5]), pad, extra_mask_column=True) is None


# ---------------------------------------------------------------- a neural opacity of exactly 0 is dropped

def _zero_some_opacities(seq: nn.Sequential, k: int) -> None:
    """Last Linear of a Scaffold-family opacity decoder: output k is atanh(0.5) for even k and exactly 0 for
    odd k (tanh(0) = 0), for every anchor."""
    with torch.no_grad():
        seq[2].weight.zero_()
        seq[2].bias.copy_(torch.tensor([math.atanh(0.5) if i % 2 == 0 else 0.0 for i in range(k)]))


def test_every_family_drops_gaussians_whose_neural_opacity_is_exactly_zero():
    """Scaffold-GS (and every family after it) keeps a Gaussian only where neural opacity > 0."""
    from controlgs_adapter.backends.compgs import CompGSModel
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel

    cam = make_camera()
    even = lambda k: torch.arange(0, k, 2)  # noqa: E731
    ref = NeuralGaussianModel(3, feat_dim=4, n_offsets=4)
    _zero_some_opacities(ref.mlp_opacity, 4)
    g = ref.decode(cam)
    assert torch.equal(g.offset_of, even(4).repeat(3)) and torch.allclose(g.opacities, torch.full((6,), 0.5))
    kw = _hac_kw(hac_t.K + 1)
    kw["mask"] = torch.ones_like(kw["mask"])
    hac = HACModel(voxel_size=0.01, **kw)
    _zero_some_opacities(hac.mlp_opacity, hac_t.K)
    assert torch.equal(hac.decode(cam).offset_of, even(hac_t.K).repeat(hac_t.A))
    oa = octree_t._arrays(0)
    octo = octree_t._model(oa, octree_t._decoders(torch.Generator().manual_seed(0)))
    _zero_some_opacities(octo.mlp_opacity, octree_t.K)
    assert torch.equal(octo.decode(cam).offset_of, even(octree_t.K).repeat(octree_t.A))
    # CompGS: one opacity per coupled primitive; the skip path reads res_feat channel 0, zero for odd slots
    ca = compgs_t._arrays(0)
    res = torch.from_numpy(ca["res"]).clone()
    res[:, :, 0] = 1.0
    res[:, 1::2, 0] = 0.0
    comp = CompGSModel(means=torch.from_numpy(ca["means"]), scales_before_exp=torch.from_numpy(ca["scales"]),
                       ref_feats=torch.from_numpy(ca["ref"]), res_feats=res)
    op = comp.network.prediction_net.opacity_pred_mlp
    with torch.no_grad():
        op.net[-1].weight.zero_()
        op.net[-1].bias.zero_()
        op.skip.weight.zero_()
        op.skip.bias.zero_()
        op.skip.weight[0, compgs_t.C] = 1.0  # the first res_feat channel
    g = comp.decode(cam)
    assert torch.equal(g.offset_of, even(compgs_t.K).repeat(compgs_t.A))
    assert torch.allclose(g.opacities, torch.full_like(g.opacities, math.tanh(1.0)))


def test_load_model_dir_passes_allow_unquantized_to_hac_and_contextgs(tmp_path):
    hac_root = hac_t._write_dir(tmp_path / "h", hac_t._arrays(5, decoded=False, mask_cols=hac_t.K + 1), hac_t._decoders(5))
    ctx_root = contextgs_t._write_dir(tmp_path / "c", contextgs_t._arrays(5, decoded=False), contextgs_t._decoders(5))
    for root, cls in ((hac_root, HACModel), (ctx_root, ContextGSModel)):
        with pytest.raises(FileFormatError, match="raw \\(not decoded\\)"):
            load_model_dir(root)
        m = load_model_dir(root, allow_unquantized=True)
        assert isinstance(m, cls) and not m.decoded_version and not m.training


def test_abstract_bases_refuse_what_their_subclasses_must_define():
    from controlgs_adapter.backends.hac import MaskedAnchorModel
    from controlgs_adapter.backends.models.anchor_model import AnchorModel

    base = AnchorModel()
    with pytest.raises(NotImplementedError):
        base.visible_anchors(make_camera())
    with pytest.raises(NotImplementedError):
        base.decode(make_camera())
    masked = MaskedAnchorModel(**_hac_kw(hac_t.K + 1))
    with pytest.raises(NotImplementedError):
        masked.get_anchor  # noqa: B018 - the property is what is tested
    with pytest.raises(InputValueError, match=r"AnchorModel.decode got unknown option\(s\) \['x', 'y'\]"):
        base.refuse_options({"y": 1, "x": 2})
    base.refuse_options({})


def test_octree_anygs_defaults_for_keys_missing_from_config_yaml(tmp_path):
    """Octree-AnyGS's GaussianLoDModel defaults: feat_dim 32, n_offsets 10, fork 2, dist2level 'round',
    base model Scaffold-GS: a config.yaml naming none of them reads a folder of those widths."""
    from controlgs_adapter.formats.backbone import write_ply

    a, f, k = 6, 32, 10
    rng = np.random.default_rng(0)
    root = tmp_path / "anygs"
    it = root / "point_cloud" / "iteration_5"
    it.mkdir(parents=True)
    (root / "config.yaml").write_text("optim_params: {\n    iterations: 40_000,\n}\n")
    fields = {c: rng.normal(size=a).astype(np.float32) for c in "xyz"}
    fields.update(level=np.zeros(a, np.float32), extra_level=np.zeros(a, np.float32))
    fields.update({f"f_offset_{i}": rng.normal(size=a).astype(np.float32) for i in range(3 * k)})
    fields.update({f"f_anchor_feat_{i}": rng.normal(size=a).astype(np.float32) for i in range(f)})
    fields.update({f"scale_{i}": np.full(a, -2.0, np.float32) for i in range(6)})
    write_ply(it / "point_cloud.ply", fields, comments=["standard_dist 3.0", "levels 2"], comment_keyword="obj_info")
    torch.manual_seed(0)
    torch.save({"opacity_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()).state_dict(),
                "cov_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 7 * k)).state_dict(),
                "color_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid()).state_dict()},
               it / "checkpoints.pth")
    m = load_octree_gs_dir(root)
    assert (m.feat_dim, m.n_offsets, m.fork, m.dist2level, m.levels, m.standard_dist) == (32, 10, 2, "round", 2, 3.0)
    assert not m.voxel_centre and m.voxel_size == 0.0
    # the LOD header lines are required
    write_ply(it / "point_cloud.ply", fields, comments=["standard_dist 3.0"], comment_keyword="obj_info")
    with pytest.raises(FileFormatError, match="must carry 'obj_info standard_dist <v>' and 'obj_info levels <v>'"):
        load_octree_gs_dir(root)


def test_compgs_backend_needs_every_decoder_to_be_a_residual_mlp():
    from controlgs_adapter.backends.compgs import CompGSBackend

    b = CompGSBackend()
    ca = compgs_t._arrays(0)
    model = compgs_t._model(ca, 0)
    assert b.matches(model)
    model.network.prediction_net.color_pred_mlp = nn.Linear(44, 3)  # no .net: not CompGS's ResidualMLP
    assert not b.matches(model)
    other = compgs_t._model(ca, 0)
    del other.gaussian_params.res_feats  # a marker missing
    assert not b.matches(other)
    assert not b.matches(NeuralGaussianModelForTest())


class NeuralGaussianModelForTest(nn.Module):  # Scaffold-GS names only
    def __init__(self) -> None:
        super().__init__()
        self.mlp_opacity, self.mlp_cov, self.mlp_color = nn.Linear(1, 1), nn.Linear(1, 1), nn.Linear(1, 1)
        self._anchor = torch.zeros(2, 3)


def test_as_param_is_a_frozen_float32_copy_unless_asked():
    from controlgs_adapter.backends.models.anchor_model import as_param

    src = np.arange(6, dtype=np.float64).reshape(2, 3)
    p = as_param(src)
    assert isinstance(p, nn.Parameter) and p.dtype == torch.float32 and not p.requires_grad
    assert torch.equal(p, torch.arange(6.0).reshape(2, 3))
    t = torch.ones(3)
    q = as_param(t, requires_grad=True)
    assert q.requires_grad and q.data_ptr() != t.data_ptr()  # a copy: the caller's tensor is not shared
    with torch.no_grad():
        q.add_(1.0)
    assert torch.equal(t, torch.ones(3))
    # a non-contiguous array (a column slice) is read correctly
    assert torch.equal(as_param(src[:, 1]), torch.tensor([1.0, 4.0]))
