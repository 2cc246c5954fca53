"""CompGS backend: recognition, ResidualMLP net[0] targets with the skip path untouched, K rows per
anchor, decoded geometry, loading a training checkpoint written in CompGS's layout, refusing the
G-PCC bitstream, wrap/identity/injection/save-load."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from _family_checks import STATE, check_wrap_identity_and_rows, outputs
from controlgs_adapter.backend import get_attr_path
from controlgs_adapter.backends.compgs import COMPGS_DECODERS, CompGSBackend, CompGSModel, load_compgs_dir
from controlgs_adapter.formats.backbone import write_ply
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import FileFormatError, TargetError

A, K, C, G = 9, 10, 32, 8  # CompGS MipNeRF360 config: derive_factor 10, ref_feats_dim 32, res_feats_dim 8

#: CompGS's state-dict keys of one ResidualMLP with n residual blocks (from its BasicBlocks layout)
def _keys(n_res: int) -> set[str]:
    keys = {"net.0.weight", "net.0.bias", f"net.{2 + n_res}.weight", f"net.{2 + n_res}.bias", "skip.weight", "skip.bias"}
    for i in range(n_res):
        keys |= {f"net.{2 + i}.net.0.weight", f"net.{2 + i}.net.0.bias", f"net.{2 + i}.net.2.weight", f"net.{2 + i}.net.2.bias"}
    return keys


def _arrays(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(size=(A, 3)).astype(np.float32), "scales": rng.normal(-3, 0.4, (A, 6)).astype(np.float32),
            "ref": rng.normal(size=(A, C)).astype(np.float32), "res": rng.normal(size=(A, K, G)).astype(np.float32)}


def _model(arr, seed: int) -> CompGSModel:
    torch.manual_seed(seed)
    return CompGSModel(means=torch.from_numpy(arr["means"]), scales_before_exp=torch.from_numpy(arr["scales"]),
                       ref_feats=torch.from_numpy(arr["ref"]), res_feats=torch.from_numpy(arr["res"]))


def _write_checkpoint(root, arr, model, *, iteration=30000):
    """CompGS's training checkpoint: <exp>/point_cloud/iteration_N/{point_cloud.ply, weights.pth}."""
    it = root / "point_cloud" / f"iteration_{iteration}"
    it.mkdir(parents=True)
    fields = {"x": arr["means"][:, 0], "y": arr["means"][:, 1], "z": arr["means"][:, 2]}
    fields.update({f"n{c}": np.zeros(A, np.float32) for c in "xyz"})
    res = arr["res"].reshape(A, K * G)  # k-major, no transpose: f_res_feat_{k*G + g}
    fields.update({f"f_res_feat_{i}": res[:, i] for i in range(K * G)})
    fields.update({f"f_ref_feat_{i}": arr["ref"][:, i] for i in range(C)})
    fields.update({f"scale_{i}": arr["scales"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    state = {f"prediction_net.{k}": v for k, v in model.network.prediction_net.state_dict().items()}
    state["entropy_model.entropy_bottleneck.quantiles"] = torch.zeros(4, 1, 3)  # compressai parts are ignored
    torch.save(state, it / "weights.pth")
    return root


def test_recognition_targets_and_rows():
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
    for name, n_res in (("means", 1), ("covariance", 1), ("opacity", 1), ("color", 2)):
        assert set(get_attr_path(model, f"network.prediction_net.{name}_pred_mlp").state_dict()) == _keys(n_res)


def test_rows_are_coupled_primitives():
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


def test_injection_skips_skip_path_and_moves_means(tmp_path):
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


def test_load_checkpoint_and_wrap(tmp_path):
    arr = _arrays(3)
    src = _model(arr, 3)
    root = _write_checkpoint(tmp_path / "exp", arr, src)
    with pytest.raises(FileFormatError, match="unquantised.*allow_unquantized"):
        load_compgs_dir(root)
    model = load_compgs_dir(root, allow_unquantized=True)
    assert torch.equal(model.gaussian_params.res_feats, torch.from_numpy(arr["res"]))
    assert torch.equal(model.gaussian_params.ref_feats, torch.from_numpy(arr["ref"]))
    assert model.derive_factor == K
    cam = torch.tensor([0.3, -0.1, -6.0])
    ids = torch.tensor([1, 2, 6, 7])
    inputs = model.decoder_inputs(cam, ids)
    want = outputs(src, src.decoder_inputs(cam, ids))
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, want[p]), p
    check_wrap_identity_and_rows(model, inputs, ids, "compgs", K, tmp_path,
                                 lambda: load_compgs_dir(root, allow_unquantized=True))


def test_loading_errors(tmp_path):
    arr = _arrays(4)
    final = tmp_path / "final" / "point_cloud"
    final.mkdir(parents=True)
    np.savez(final / "bitstreams.npz", voxel_size=np.float32(0.001), means_strings=np.zeros(4, np.uint8))
    torch.save({}, final / "weights.pth")
    with pytest.raises(FileFormatError, match="bitstreams.npz.*G-PCC"):
        load_compgs_dir(tmp_path / "final")
    root = _write_checkpoint(tmp_path / "exp", arr, _model(arr, 4))
    w = root / "point_cloud" / "iteration_30000" / "weights.pth"
    other = {k: v for k, v in torch.load(w, weights_only=True).items() if "color_pred_mlp.skip" not in k}
    torch.save(other, w)
    with pytest.raises(FileFormatError, match="weights.pth.*color_pred_mlp.skip"):
        load_compgs_dir(root, allow_unquantized=True)
    w.unlink()
    with pytest.raises(FileFormatError, match="weights.pth"):
        load_compgs_dir(root, allow_unquantized=True)


def test_decode_matches_per_primitive_float64_loop():
    from _family_checks import make_camera

    arr = _arrays(6)
    model = _model(arr, 6)
    cam = make_camera()
    with torch.no_grad():
        g = model.decode(cam)
        net = model.double().network.prediction_net
        t = {k: torch.from_numpy(v).double() for k, v in arr.items()}
        c = cam.center.double()
        want = {}
        for a in range(A):
            d = t["means"][a] - c
            for s in range(K):
                x = torch.cat([t["ref"][a], t["res"][a, s]])[None]
                xv = torch.cat([x[0], d / d.norm(), d.norm()[None]])[None]
                op = net.opacity_pred_mlp(xv)[0, 0]
                if op > 0:
                    cov = net.covariance_pred_mlp(x)[0]
                    want[(a, s)] = (t["means"][a] + net.means_pred_mlp(x)[0] * torch.exp(t["scales"][a, :3]),
                                    torch.sigmoid(cov[:3]) * torch.exp(t["scales"][a, 3:]), op)
    assert [(int(a), int(s)) for a, s in zip(g.anchor_of, g.offset_of)] == sorted(want)
    for i, key in enumerate(sorted(want)):
        assert torch.allclose(g.means[i].double(), want[key][0], atol=1e-5)
        assert torch.allclose(g.scales[i].double(), want[key][1], atol=1e-6)
        assert abs(float(g.opacities[i]) - float(want[key][2])) < 1e-5


def test_visible_anchors_and_render():
    from _family_checks import make_camera

    arr = _arrays(7)
    arr["means"][0] = (0.0, 0.0, -9.0)  # behind the camera at z = -5
    model = _model(arr, 7)
    cam = make_camera()
    visible = model.visible_anchors(cam)
    assert not bool(visible[0]) and bool(visible[1:].any())
    with torch.no_grad():
        out = model.render(cam)
    assert out.color.shape == (3, cam.height, cam.width) and torch.isfinite(out.color).all()
