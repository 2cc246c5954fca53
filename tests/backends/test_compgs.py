"""CompGS: its backend (residual-MLP decoders, K coupled primitives per anchor), its model's decoding and
prefilter against float64 references, and its checkpoint loader with every refusal."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.anchor_oracle import D, assert_gaussians, camera_centre, gaussian64, mlp64, oblique_camera, visible64
from helpers.compgs_files import A, C, G, K, _arrays, _model, _write_checkpoint
from helpers.family_checks import STATE, make_camera, outputs
from torch import nn

from controlgs_adapter.backend import get_attr_path
from controlgs_adapter.backends.compgs import (
    COMPGS_DECODERS,
    CompGSBackend,
    CompGSModel,
    ResidualBlock,
    ResidualMLP,
    load_compgs_dir,
)
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import FileFormatError, TargetError
from controlgs_adapter.formats.backbone import write_ply

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _residual_mlp_keys(n_res: int) -> set[str]:
    """CompGS's state-dict keys of one ResidualMLP with ``n_res`` residual blocks (its BasicBlocks layout)."""
    keys = {"net.0.weight", "net.0.bias", f"net.{2 + n_res}.weight", f"net.{2 + n_res}.bias", "skip.weight", "skip.bias"}
    for i in range(n_res):
        keys |= {f"net.{2 + i}.net.0.weight", f"net.{2 + i}.net.0.bias", f"net.{2 + i}.net.2.weight", f"net.{2 + i}.net.2.bias"}
    return keys


def _small_checkpoint(root, g: int, *, rot: np.ndarray | None = None):
    """CompGS's training checkpoint of 4 anchors, 3 primitives each, C = 5 and res_feats_dim ``g``
    (f_res_feat_{k*g + j}, k-major); ``rot``: rot_* columns to write. Returns the model and its res_feats."""
    a, k, c = 4, 3, 5
    rng = np.random.default_rng(g)
    means, scales = rng.normal(size=(a, 3)).astype(np.float32), rng.normal(-3, 0.4, (a, 6)).astype(np.float32)
    ref, res = rng.normal(size=(a, c)).astype(np.float32), rng.normal(size=(a, k, g)).astype(np.float32)
    torch.manual_seed(g)
    model = CompGSModel(means=torch.from_numpy(means), scales_before_exp=torch.from_numpy(scales),
                        ref_feats=torch.from_numpy(ref), res_feats=torch.from_numpy(res))
    it = root / "point_cloud" / "iteration_100"
    it.mkdir(parents=True)
    fields = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    flat = res.reshape(a, k * g)
    fields.update({f"f_res_feat_{i}": flat[:, i] for i in range(k * g)})
    fields.update({f"f_ref_feat_{i}": ref[:, i] for i in range(c)})
    fields.update({f"scale_{i}": scales[:, i] for i in range(6)})
    if rot is not None:
        fields.update({f"rot_{i}": rot[:a, i] for i in range(rot.shape[1])})
    write_ply(it / "point_cloud.ply", fields)
    torch.save({f"prediction_net.{n}": v for n, v in model.network.prediction_net.state_dict().items()}, it / "weights.pth")
    return model, res


class _ScaffoldNames(nn.Module):
    """A model with Scaffold-GS's decoder and anchor names only."""

    def __init__(self) -> None:
        super().__init__()
        self.mlp_opacity, self.mlp_cov, self.mlp_color = nn.Linear(1, 1), nn.Linear(1, 1), nn.Linear(1, 1)
        self._anchor = torch.zeros(2, 3)


# ------------------------------------------------------------------------------------------ backend
def test_backend_recognises_compgs_and_knows_its_decoders_and_rows():
    model = _model(_arrays(0), 0)
    b = CompGSBackend()
    assert b.matches(model)
    assert not any(o.matches(model) for o in (ScaffoldGSBackend(), HACBackend(), OctreeGSBackend(), ContextGSBackend()))
    assert b.default_targets(model) == list(COMPGS_DECODERS)
    widths = {p.split(".")[-1]: (b.check_decoder(model, p).in_features, b.check_decoder(model, p).out_features)
              for p in b.decoder_paths(model)}
    assert widths == {"means_pred_mlp": (C + G, C), "covariance_pred_mlp": (C + G, C),
                      "opacity_pred_mlp": (C + G + 4, C), "color_pred_mlp": (C + G + 4, C)}
    assert b.rows_per_anchor(model) == K
    assert b.input_layout(model, COMPGS_DECODERS[3]) == [("ref_feat", C), ("res_feat", G), ("view", 3), ("dist", 1)]
    with torch.no_grad():  # features that do not fit the decoders: a named error
        model.gaussian_params.res_feats = torch.nn.Parameter(torch.zeros(A, K, G + 1), requires_grad=False)
    with pytest.raises(TargetError, match="means_pred_mlp.net.0. takes 40 inputs"):
        b.check_decoder(model, COMPGS_DECODERS[0])
    assert b.row_anchor_ids(torch.tensor([4, 1]), K).tolist() == [4] * K + [1] * K


def test_backend_needs_every_marker_and_residual_mlp_decoders():
    b = CompGSBackend()
    ca = _arrays(0)
    model = _model(ca, 0)
    model.network.prediction_net.color_pred_mlp = nn.Linear(44, 3)  # no .net: not CompGS's ResidualMLP
    assert not b.matches(model)
    other = _model(ca, 0)
    del other.gaussian_params.res_feats  # a marker missing
    assert not b.matches(other)
    assert not b.matches(_ScaffoldNames())


def test_decoder_rows_are_the_coupled_primitives_of_each_anchor():
    arr = _arrays(1)
    model = _model(arr, 1)
    cam = torch.tensor([0.1, 0.2, -5.0])
    ids = torch.tensor([2, 5])
    x = model.decoder_inputs(cam, ids)
    means_in = x[COMPGS_DECODERS[0]]
    assert means_in.shape == (2 * K, C + G)
    for r in range(2 * K):  # row r = anchor ids[r // K], slot r % K
        a, s = int(ids[r // K]), r % K
        assert torch.equal(means_in[r], torch.cat([torch.from_numpy(arr["ref"][a]), torch.from_numpy(arr["res"][a, s])]))
    d = torch.from_numpy(arr["means"][5]) - cam
    assert torch.allclose(x[COMPGS_DECODERS[3]][K, C + G:], torch.cat([d / d.norm(), d.norm()[None]]))


def test_injection_leaves_the_skip_path_and_moves_only_the_conditioned_anchors_means():
    arr = _arrays(2)
    model = _model(arr, 2)
    cam = torch.tensor([0.0, 0.0, -4.0])
    ids = torch.tensor([0, 3, 4, 8])
    inputs = model.decoder_inputs(cam, ids)
    means_mlp = get_attr_path(model, COMPGS_DECODERS[0])
    with torch.no_grad():
        skip_before, off_before = means_mlp.skip(inputs[COMPGS_DECODERS[0]]), means_mlp(inputs[COMPGS_DECODERS[0]])
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=4)
    with torch.no_grad():
        cgs.injector.condition("display")[3] = 1.0
    with cgs.conditioned(STATE, anchor_ids=ids), torch.no_grad():
        skip_after, off_after = means_mlp.skip(inputs[COMPGS_DECODERS[0]]), means_mlp(inputs[COMPGS_DECODERS[0]])
    assert torch.equal(skip_after, skip_before)  # the parallel skip Linear is never conditioned
    # Gaussian mean = anchor + means_pred(x) * exp(scale[:, :3]): anchor 3's K primitives move
    scale = torch.exp(torch.from_numpy(arr["scales"][ids.numpy(), :3])).repeat_interleave(K, 0)
    moved = ((off_after - off_before) * scale).norm(dim=1) > 0
    assert moved.nonzero().squeeze(1).tolist() == list(range(K, 2 * K))
    cgs.unwrap()


# ------------------------------------------------------------------------------------- decoders
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


def test_decoder_tails_residual_depths_and_widths_follow_compgs():
    # CompGS Prediction.py: means/covariance: no tail, 1 residual layer; opacity: Tanh, 1; colour: Sigmoid, 2;
    # inputs C + G (means, covariance) and C + G + 4 (opacity, colour), hidden width C, outputs 3 / 7 / 1 / 3
    net = _model(_arrays(0), 0).network.prediction_net
    want = {"means": (None, 1, C + G, 3), "covariance": (None, 1, C + G, 7), "opacity": (nn.Tanh, 1, C + G + 4, 1),
            "color": (nn.Sigmoid, 2, C + G + 4, 3)}
    for name, (tail, blocks, d_in, d_out) in want.items():
        m = getattr(net, f"{name}_pred_mlp")
        assert type(m.tail_activation) is (tail or nn.Identity), name
        assert sum(isinstance(b, ResidualBlock) for b in m.net) == blocks, name
        assert set(m.state_dict()) == _residual_mlp_keys(blocks), name
        assert (m.net[0].in_features, m.net[0].out_features, m.net[-1].out_features) == (d_in, C, d_out), name
        assert (m.skip.in_features, m.skip.out_features) == (d_in, d_out), name


# ------------------------------------------------------------------------------ decoding, prefilter
def test_decode_by_hand_in_float64():
    """Per coupled primitive (anchor i, slot j) the input is [ref_feat_i, res_feat_ij] (+ view, dist for
    opacity and colour); each decoder is tail(net(x) + skip(x)); mean = anchor + means_pred * exp(s[:3]),
    scale = exp(s[3:]) * sigmoid(cov[:3]); kept where opacity > 0, anchor-major."""
    a, k, c, g = 12, 3, 8, 4
    rng = np.random.default_rng(5)
    means = torch.from_numpy(rng.uniform(-1.0, 1.0, (a, 3))).float()
    scales = torch.from_numpy(rng.normal(-2.0, 0.3, (a, 6))).float()
    ref, res = torch.randn(a, c), torch.randn(a, k, g)
    torch.manual_seed(7)
    model = CompGSModel(means=means, scales_before_exp=scales, ref_feats=ref, res_feats=res)
    net = model.network.prediction_net
    with torch.no_grad():
        for p in net.parameters():  # larger weights than the default init, so the skip path and every layer matter
            p.mul_(2.0)
    assert all(isinstance(getattr(net, f"{n}_pred_mlp").skip, nn.Linear) for n in ("means", "covariance", "opacity", "color"))
    cam = oblique_camera()
    centre = camera_centre(cam)
    with torch.no_grad():
        got = model.decode(cam, None)
    expected = {}
    for i in range(a):
        d = means[i].to(D) - centre
        for j in range(k):
            x = torch.cat([ref[i].to(D), res[i, j].to(D)])[None]
            xv = torch.cat([x[0], d / d.norm(), d.norm()[None]])[None]
            off = mlp64(net.means_pred_mlp, x)[0]
            cov = mlp64(net.covariance_pred_mlp, x)[0]
            op = mlp64(net.opacity_pred_mlp, xv)[0, 0]
            col = mlp64(net.color_pred_mlp, xv)[0]
            if op > 0:
                s = torch.exp(scales[i].to(D))
                expected[(i, j)] = gaussian64(means[i].to(D), off, s, op, col, cov)
    assert 0 < len(expected) < a * k
    assert_gaussians(got, expected)
    pairs = [(int(i), int(j)) for i, j in zip(got.anchor_of, got.offset_of)]
    assert pairs == sorted(pairs)  # anchor by anchor, slot by slot


def test_prefilter_by_hand_with_the_offset_scales():
    """CompGS's prefilter: anchors as Gaussians with scales exp(scales_before_exp[:, :3]) (the offset
    scales, not the base scales [:, 3:]) and their own rotations, by hand with a float64 EWA projection."""
    a = 80
    rng = np.random.default_rng(9)
    means = torch.from_numpy(rng.uniform((-7.4, -4.9, -0.9), (7.2, 5.0, 1.5), (a, 3))).float()
    scales = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    scales[:, :3] += torch.from_numpy(rng.uniform(0.5, 2.5, (a, 1))).float()  # offset scales larger than base scales
    rot = torch.nn.functional.normalize(torch.randn(a, 4), dim=1)
    model = CompGSModel(means=means, scales_before_exp=scales, ref_feats=torch.randn(a, 4), res_feats=torch.randn(a, 2, 2),
                        rotations_before_norm=rot)
    cam = oblique_camera()
    want = visible64(cam, means.to(D), torch.exp(scales.to(D)[:, :3]), rot.to(D))
    assert 0 < int(want.sum()) < a
    assert not torch.equal(want, visible64(cam, means.to(D), torch.exp(scales.to(D)[:, 3:]), rot.to(D)))
    assert torch.equal(model.visible_anchors(cam), want)


def test_anchor_behind_the_camera_is_not_visible_and_the_render_is_finite():
    arr = _arrays(7)
    arr["means"][0] = (0.0, 0.0, -9.0)  # behind the camera at z = -5
    model = _model(arr, 7)
    cam = make_camera()
    visible = model.visible_anchors(cam)
    assert not bool(visible[0]) and bool(visible[1:].any())
    with torch.no_grad():
        out = model.render(cam)
    assert out.color.shape == (3, cam.height, cam.width) and torch.isfinite(out.color).all()


# ------------------------------------------------------------------------------------------- loader
def test_loader_reads_the_features_and_the_prediction_network(tmp_path):
    """A training checkpoint (its entropy-model entries ignored) loads with the PLY's features, K from
    the fields, and decoders whose outputs are the source model's."""
    arr = _arrays(3)
    src = _model(arr, 3)
    root = _write_checkpoint(tmp_path / "exp", arr, src)
    model = load_compgs_dir(root, allow_unquantized=True)
    assert torch.equal(model.gaussian_params.res_feats, torch.from_numpy(arr["res"]))
    assert torch.equal(model.gaussian_params.ref_feats, torch.from_numpy(arr["ref"]))
    assert model.derive_factor == K
    cam = torch.tensor([0.3, -0.1, -6.0])
    ids = torch.tensor([1, 2, 6, 7])
    want = outputs(src, src.decoder_inputs(cam, ids))
    for p, y in outputs(model, model.decoder_inputs(cam, ids)).items():
        assert torch.equal(y, want[p]), p


def test_loader_takes_a_one_channel_residual_feature(tmp_path):
    """G = res_feats_dim is C_in - C - 4 of color_pred_mlp.net.0; G = 1 is a valid width."""
    model, res = _small_checkpoint(tmp_path / "e", 1)
    got = load_compgs_dir(tmp_path / "e", allow_unquantized=True)
    assert got.gaussian_params.res_feats.shape == (4, 3, 1) and torch.equal(got.gaussian_params.res_feats, torch.from_numpy(res))
    w = "color_pred_mlp.net.0.weight"
    assert torch.equal(got.network.prediction_net.state_dict()[w], model.network.prediction_net.state_dict()[w])


def test_training_checkpoint_loads_beside_the_final_bitstreams(tmp_path):
    """CompGS's trainer writes point_cloud/bitstreams.npz at the end next to the iteration folders: only a
    folder with nothing but the bitstreams is refused."""
    _small_checkpoint(tmp_path / "e", 2)
    (tmp_path / "e" / "point_cloud" / "bitstreams.npz").write_bytes(b"")
    assert load_compgs_dir(tmp_path / "e", allow_unquantized=True).gaussian_params.means.shape == (4, 3)
    final = tmp_path / "final" / "point_cloud"
    final.mkdir(parents=True)
    np.savez(final / "bitstreams.npz", voxel_size=np.float32(0.001), means_strings=np.zeros(4, np.uint8))
    torch.save({}, final / "weights.pth")
    with pytest.raises(FileFormatError, match="bitstreams.npz.*G-PCC"):
        load_compgs_dir(tmp_path / "final")


def test_loader_keeps_the_ply_rotations_and_refuses_a_truncated_set(tmp_path):
    q = np.random.default_rng(5).normal(size=(4, 4)).astype(np.float32)
    _small_checkpoint(tmp_path / "e", 2, rot=q)
    got = load_compgs_dir(tmp_path / "e", allow_unquantized=True)
    assert torch.equal(got.gaussian_params.rotations_before_norm, torch.from_numpy(q))
    _small_checkpoint(tmp_path / "t", 2, rot=q[:, :3])
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_compgs_dir(tmp_path / "t", allow_unquantized=True)


def test_loader_refusals_name_the_file_and_the_key(tmp_path):
    arr = _arrays(3)
    root = _write_checkpoint(tmp_path / "exp", arr, _model(arr, 3))
    w = root / "point_cloud" / "iteration_30000" / "weights.pth"
    state = torch.load(w, weights_only=True)
    key = "prediction_net.color_pred_mlp.net.0.weight"
    torch.save({k: v for k, v in state.items() if k != key}, w)
    with pytest.raises(FileFormatError, match=rf"weights.pth: missing '{key}'"):
        load_compgs_dir(root, allow_unquantized=True)
    torch.save({k: v for k, v in state.items() if "color_pred_mlp.skip" not in k}, w)
    with pytest.raises(FileFormatError, match="weights.pth.*color_pred_mlp.skip"):
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
    with pytest.raises(FileFormatError, match=r"unquantised.*allow_unquantized=True"):
        load_compgs_dir(root)
    assert load_compgs_dir(root, allow_unquantized=True).derive_factor == K  # K = 80 f_res_feat_* / G = 8
    w.unlink()
    with pytest.raises(FileFormatError, match="weights.pth"):
        load_compgs_dir(root, allow_unquantized=True)
