"""Tests of ``controlgs_adapter.backends.compgs``."""

from __future__ import annotations

import math

import helpers.compgs_files as compgs_t
import helpers.contextgs_files as contextgs_t
import helpers.hac_files as hac_t
import helpers.octree_files as octree_t
import numpy as np
import pytest
import torch
from helpers.compgs_files import A, C, G, K, _arrays, _model, _write_checkpoint
from helpers.family_checks import STATE, check_wrap_identity_and_rows, make_camera, outputs
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backend import get_attr_path
from controlgs_adapter.backends.compgs import (
    COMPGS_DECODERS,
    CompGSBackend,
    CompGSModel,
    ResidualBlock,
    ResidualMLP,
    load_compgs_dir,
)
from controlgs_adapter.backends.contextgs import ContextGSBackend, ContextGSModel
from controlgs_adapter.backends.hac import HACBackend, HACModel
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import FileFormatError, TargetError
from controlgs_adapter.formats.backbone import write_ply


#: CompGS's state-dict keys of one ResidualMLP with n residual blocks (from its BasicBlocks layout)
def _keys(n_res: int) -> set[str]:
    keys = {"net.0.weight", "net.0.bias", f"net.{2 + n_res}.weight", f"net.{2 + n_res}.bias", "skip.weight", "skip.bias"}
    for i in range(n_res):
        keys |= {f"net.{2 + i}.net.0.weight", f"net.{2 + i}.net.0.bias", f"net.{2 + i}.net.2.weight", f"net.{2 + i}.net.2.bias"}
    return keys


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
    from helpers.family_checks import make_camera

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
    from helpers.family_checks import make_camera

    arr = _arrays(7)
    arr["means"][0] = (0.0, 0.0, -9.0)  # behind the camera at z = -5
    model = _model(arr, 7)
    cam = make_camera()
    visible = model.visible_anchors(cam)
    assert not bool(visible[0]) and bool(visible[1:].any())
    with torch.no_grad():
        out = model.render(cam)
    assert out.color.shape == (3, cam.height, cam.width) and torch.isfinite(out.color).all()


D = torch.float64


def _camera(uid: int | None = None) -> Camera:
    """Non-square camera about 5 units from the origin, turned 0.1 rad about y, principal point off centre."""
    c, s = math.cos(0.1), math.sin(0.1)
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    w2c[:3, 3] = torch.tensor([-0.3, 0.2, 5.0])
    k = torch.tensor([[52.0, 0.0, 37.0], [0.0, 47.0, 21.0], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, 72, 40, {} if uid is None else {"uid": uid})


def _centre(cam: Camera) -> torch.Tensor:
    """Camera centre -R^T t in float64 from the world-to-camera matrix."""
    w2c = cam.world_to_camera.to(D)
    return -(w2c[:3, :3].T @ w2c[:3, 3])


def _mlp(mod: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """Evaluate ``mod`` layer by layer in float64 by hand (Linear, ReLU, LeakyReLU, Tanh, Sigmoid,
    Softmax over dim 1, Sequential, CompGS's ResidualBlock / ResidualMLP)."""
    if isinstance(mod, nn.Sequential):
        for layer in mod:
            x = _mlp(layer, x)
        return x
    if isinstance(mod, nn.Linear):
        return x @ mod.weight.detach().to(D).T + mod.bias.detach().to(D)
    if isinstance(mod, nn.ReLU):
        return torch.where(x > 0, x, torch.zeros_like(x))
    if isinstance(mod, nn.LeakyReLU):
        return torch.where(x > 0, x, 0.01 * x)
    if isinstance(mod, nn.Tanh):
        return (torch.exp(x) - torch.exp(-x)) / (torch.exp(x) + torch.exp(-x))
    if isinstance(mod, nn.Sigmoid):
        return 1.0 / (1.0 + torch.exp(-x))
    if isinstance(mod, nn.Softmax):
        e = torch.exp(x - x.max(dim=1, keepdim=True).values)
        return e / e.sum(dim=1, keepdim=True)
    if isinstance(mod, ResidualBlock):
        return x + _mlp(mod.net, x)
    if isinstance(mod, ResidualMLP):
        skip = x if isinstance(mod.skip, nn.Identity) else _mlp(mod.skip, x)
        return _mlp(mod.tail_activation, _mlp(mod.net, x) + skip)
    if isinstance(mod, nn.Identity):
        return x
    raise TypeError(type(mod))


def _check(got, expected: dict[tuple[int, int], dict[str, torch.Tensor]]) -> None:
    """``got`` (NeuralGaussians) holds exactly the (anchor, offset) pairs of ``expected``, with its values."""
    pairs = [(int(a), int(k)) for a, k in zip(got.anchor_of, got.offset_of)]
    assert sorted(pairs) == sorted(expected)
    for g, key in enumerate(pairs):
        e = expected[key]
        for name in ("means", "scales", "rotations", "colors"):
            torch.testing.assert_close(getattr(got, name)[g].to(D), e[name], rtol=1e-5, atol=1e-6, msg=f"{name} {key}")
        torch.testing.assert_close(got.opacities[g].to(D), e["opacity"], rtol=1e-5, atol=1e-6)


def _gaussian(anchor, offset, s, opacity, color, cov) -> dict[str, torch.Tensor]:
    """One Scaffold-family Gaussian: mean = anchor + offset * s[:3], scale = s[3:] * sigmoid(cov[:3]),
    rotation = cov[3:7] / |cov[3:7]|."""
    return {"means": anchor + offset * s[:3], "scales": s[3:] / (1.0 + torch.exp(-cov[:3])),
            "rotations": cov[3:7] / cov[3:7].norm(), "colors": color, "opacity": opacity}


def _visible_by_hand(cam: Camera, means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """3DGS's prefilter in float64: depth > 0.2 and the square of half-width ceil(3 sqrt(lambda_max)) about
    the projected centre overlaps [0, W] x [0, H]; 2D covariance J W R S^2 R^T W^T J^T + 0.3 I."""
    w2c = cam.world_to_camera.to(D)
    k = cam.intrinsics.to(D)
    out = torch.zeros(means.shape[0], dtype=torch.bool)
    for i in range(means.shape[0]):
        t = w2c[:3, :3] @ means[i] + w2c[:3, 3]
        if t[2] <= 0.2:
            continue
        w, x, y, z = (quats[i] / quats[i].norm()).tolist()
        r = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=D)
        cov3 = r @ torch.diag(scales[i] ** 2) @ r.T
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        # x/z, y/z clamped to the image widened by 15 % of its size on each side (3DGS's 1.3 x FoV)
        tx = min(max(float(t[0] / t[2]), -float(cx + 0.15 * cam.width) / fx), float(1.15 * cam.width - cx) / fx)
        ty = min(max(float(t[1] / t[2]), -float(cy + 0.15 * cam.height) / fy), float(1.15 * cam.height - cy) / fy)
        j = torch.tensor([[fx / t[2], 0, -fx * tx / t[2]], [0, fy / t[2], -fy * ty / t[2]]], dtype=D)
        m = j @ w2c[:3, :3]
        c2 = m @ cov3 @ m.T + 0.3 * torch.eye(2, dtype=D)
        det = c2[0, 0] * c2[1, 1] - c2[0, 1] ** 2
        mid = 0.5 * (c2[0, 0] + c2[1, 1])
        radius = math.ceil(3.0 * math.sqrt(mid + math.sqrt(max(float(mid * mid - det), 0.1))))
        u, v = fx * t[0] / t[2] + k[0, 2], fy * t[1] / t[2] + k[1, 2]
        out[i] = bool(det > 0 and u + radius > 0 and u - radius < cam.width and v + radius > 0 and v - radius < cam.height)
    return out


# ----------------------------------------------------------------------------------------- CompGS
def test_compgs_by_hand_residual_mlp_skip_and_res_feat_layout():
    """CompGS: per coupled primitive (anchor i, slot j) the input is [ref_feat_i, res_feat_ij] (+ view, dist
    for opacity and colour); each decoder is tail(net(x) + skip(x)); mean = anchor + means_pred * exp(s[:3])."""
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
    cam = _camera()
    centre = _centre(cam)
    with torch.no_grad():
        got = model.decode(cam, None)
    expected = {}
    for i in range(a):
        d = means[i].to(D) - centre
        for j in range(k):
            x = torch.cat([ref[i].to(D), res[i, j].to(D)])[None]
            xv = torch.cat([x[0], d / d.norm(), d.norm()[None]])[None]
            off = _mlp(net.means_pred_mlp, x)[0]
            cov = _mlp(net.covariance_pred_mlp, x)[0]
            op = _mlp(net.opacity_pred_mlp, xv)[0, 0]
            col = _mlp(net.color_pred_mlp, xv)[0]
            if op > 0:
                s = torch.exp(scales[i].to(D))
                expected[(i, j)] = _gaussian(means[i].to(D), off, s, op, col, cov)
    assert 0 < len(expected) < a * k
    _check(got, expected)


def test_compgs_prefilter_by_hand_with_the_offset_scales():
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
    cam = _camera()
    want = _visible_by_hand(cam, means.to(D), torch.exp(scales.to(D)[:, :3]), rot.to(D))
    assert 0 < int(want.sum()) < a
    assert not torch.equal(want, _visible_by_hand(cam, means.to(D), torch.exp(scales.to(D)[:, 3:]), rot.to(D)))
    assert torch.equal(model.visible_anchors(cam), want)


# --------------------------------------------------------------------------- CompGS: frozen, eval
def test_compgs_model_is_frozen_and_in_eval_mode():
    g = torch.Generator().manual_seed(0)
    a, k, c, r = 5, 4, 8, 3
    model = CompGSModel(means=torch.randn(a, 3, generator=g), scales_before_exp=torch.randn(a, 6, generator=g),
                        ref_feats=torch.randn(a, c, generator=g), res_feats=torch.randn(a, k, r, generator=g))
    params = list(model.parameters())
    assert len(params) > 10  # the four decoders' weights and biases
    assert [n for n, p in model.named_parameters() if p.requires_grad] == []
    assert [n for n, m in model.named_modules() if m.training] == []


#: anchors 0-1 on camera A's optical axis (depth 5), 2-4 on camera B's; each has one scale 0.5 and two 0.01
_POS = torch.tensor([[0.0, 0, 5], [0, 0, 5], [0, 5, 0], [0, 5, 0], [0, 5, 0]])


_LIN = torch.tensor([[0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.01, 0.5, 0.01]])


def _stand_ins_without_rotation() -> dict[str, object]:
    n, lin = len(_POS), torch.cat([_LIN, torch.full((len(_POS), 3), 0.02)], dim=1)
    ca = compgs_t._arrays(0)
    comp = CompGSModel(means=_POS, scales_before_exp=lin.log(), ref_feats=torch.from_numpy(ca["ref"][:n]),
                       res_feats=torch.from_numpy(ca["res"][:n]))
    ha = hac_t._arrays(0, decoded=True, mask_cols=hac_t.K + 1, n=n)
    hac = HACModel(voxel_size=0.001, decoded_version=True, anchor=_POS, offset=torch.from_numpy(ha["offset"]),
                   mask=torch.ones(n, hac_t.K + 1, 1), anchor_feat=torch.from_numpy(ha["feat"]), scaling=lin,
                   **hac_t._decoders(0))
    xa = {k: torch.from_numpy(v[:n]) for k, v in contextgs_t._arrays(0, decoded=True).items()}
    ctx = ContextGSModel(anchor=_POS, offset=xa["offset"], mask=torch.ones(n, contextgs_t.K, 1), anchor_feat=xa["feat"],
                         scaling=lin, hyper_latent=xa["hyper"], decoded_version=True, **contextgs_t._decoders(0))
    oa = octree_t._arrays(0)
    octo = OctreeGSModel(anchor=_POS, offset=torch.from_numpy(oa["offset"][:n]), anchor_feat=torch.from_numpy(oa["feat"][:n]),
                         scaling=lin.log(), level=torch.zeros(n, 1, dtype=torch.int32), extra_level=torch.zeros(n),
                         voxel_size=0.1, standard_dist=3.0, **octree_t._decoders(torch.Generator().manual_seed(0)))
    return {"compgs": comp, "hac": hac, "contextgs": ctx, "octree_gs": octo}


def _quaternions(n: int) -> np.ndarray:
    return np.random.default_rng(5).normal(size=(n, 4)).astype(np.float32)


def _compgs_dir(root, g: int, *, rot: np.ndarray | None = None):
    """CompGS's training checkpoint with res_feats_dim g (f_res_feat_{k*g + j}, k-major)."""
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


def test_stand_ins_default_anchor_opacity_is_one_column():
    """Scaffold-GS's anchor ``_opacity`` is ``[A, 1]`` (one PLY ``opacity`` column per anchor)."""
    for name, model in _stand_ins_without_rotation().items():
        if name != "compgs":  # CompGS keeps no anchor opacity
            assert model._opacity.shape == (len(_POS), 1), name


def test_compgs_loads_a_one_channel_residual_feature(tmp_path):
    """G = res_feats_dim is C_in - C - 4 of color_pred_mlp.net.0; G = 1 is a valid width."""
    model, res = _compgs_dir(tmp_path / "e", 1)
    got = load_compgs_dir(tmp_path / "e", allow_unquantized=True)
    assert got.gaussian_params.res_feats.shape == (4, 3, 1) and torch.equal(got.gaussian_params.res_feats, torch.from_numpy(res))
    w = "color_pred_mlp.net.0.weight"
    assert torch.equal(got.network.prediction_net.state_dict()[w], model.network.prediction_net.state_dict()[w])


def test_compgs_training_checkpoint_loads_beside_the_final_bitstreams(tmp_path):
    """CompGS's trainer writes point_cloud/bitstreams.npz at the end next to the iteration folders: only a
    folder with nothing but the bitstreams is refused."""
    _compgs_dir(tmp_path / "e", 2)
    (tmp_path / "e" / "point_cloud" / "bitstreams.npz").write_bytes(b"")
    assert load_compgs_dir(tmp_path / "e", allow_unquantized=True).gaussian_params.means.shape == (4, 3)


def test_compgs_loader_keeps_the_ply_rotations_and_refuses_a_truncated_set(tmp_path):
    q = _quaternions(4)
    _compgs_dir(tmp_path / "e", 2, rot=q)
    got = load_compgs_dir(tmp_path / "e", allow_unquantized=True)
    assert torch.equal(got.gaussian_params.rotations_before_norm, torch.from_numpy(q))
    _compgs_dir(tmp_path / "t", 2, rot=q[:, :3])
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_compgs_dir(tmp_path / "t", allow_unquantized=True)


def test_stand_ins_are_frozen():
    """The stand-ins are for evaluation: every parameter is frozen (load_model_dir: "eval mode, frozen")."""
    for name, model in _stand_ins_without_rotation().items():
        assert not any(p.requires_grad for p in model.parameters()), name
        assert not model.training, name


def _compgs_dir_2(tmp_path):
    arr = compgs_t._arrays(3)
    root = compgs_t._write_checkpoint(tmp_path / "exp", arr, compgs_t._model(arr, 3))
    return root, root / "point_cloud" / "iteration_30000" / "weights.pth"


def _hac_kw(n_mask_cols: int, seed: int = 0) -> dict:
    arr = hac_t._arrays(seed, decoded=True, mask_cols=n_mask_cols)
    return dict(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                scaling=torch.from_numpy(arr["scale"]), decoded_version=True, **hac_t._decoders(seed))


class NeuralGaussianModelForTest(nn.Module):  # Scaffold-GS names only
    def __init__(self) -> None:
        super().__init__()
        self.mlp_opacity, self.mlp_cov, self.mlp_color = nn.Linear(1, 1), nn.Linear(1, 1), nn.Linear(1, 1)
        self._anchor = torch.zeros(2, 3)


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


def test_compgs_loader_refusals_name_the_file_and_the_key(tmp_path):
    root, w = _compgs_dir_2(tmp_path)
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


def test_every_family_prefilter_uses_the_first_three_linear_scales():
    """make_camera(): 64 x 48, f = 40, at z = -5 looking along +z. An anchor at (-4.625, 0, 0) (depth 5)
    projects to u = 32 + 40 * (-4.625) / 5 = -5 px, 5 px left of the image. Its footprint radius is
    ceil(3 sqrt(64 s^2 + 0.3)) px for an isotropic world scale s: 12 px for s = 0.5 (touches the image),
    2 px for s = 0.01 (does not). Anchor 0 has s = 0.5 in scales[:3] and 0.01 in scales[3:], anchor 1 the
    reverse: only anchor 0 is kept, whatever the family stores (log or linear scales)."""
    from controlgs_adapter.backends.compgs import CompGSModel

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


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
