"""Decoded Gaussians of Octree-GS, ContextGS, CompGS and Scaffold-GS by hand in float64, from the raw
arrays and the decoder weights (each layer evaluated here, not by the module), following each
family's ``generate_neural_gaussians`` / ``PredictionNetwork.forward`` (docs: /work/shared/notes/backbones.md
and each backend's module docstring). The family tests compare with the reference model, which shares
``assemble_gaussians`` and ``feature_bank`` with the stand-ins; these do not."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import ResidualBlock, ResidualMLP
from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.octree_gs import OctreeGSModel

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

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


def test_camera_centre_of_a_turned_camera_by_hand():
    cam = _camera()
    torch.testing.assert_close(cam.center.to(D), _centre(cam), rtol=0, atol=1e-6)
    torch.testing.assert_close(cam.to_camera(cam.center[None]), torch.zeros(1, 3), rtol=0, atol=1e-5)


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


def _bank(feat: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's feature bank for one anchor: channel c mixes feat[4*(c mod F/4)], feat[2*(c mod F/2)]
    and feat[c] with the softmax weights w[0], w[1], w[2]."""
    f = feat.shape[0]
    c = torch.arange(f)
    return feat[4 * (c % (f // 4))] * w[0] + feat[2 * (c % (f // 2))] * w[1] + feat * w[2]


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


def _seq(d_in: int, d_hidden: int, d_out: int, tail: nn.Module | None) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.ReLU(), nn.Linear(d_hidden, d_out), *([tail] if tail else []))


# ----------------------------------------------------------------------------------------- Octree-GS
def test_octree_gs_by_hand_with_level_bank_appearance_and_lod():
    """Octree-GS with add_level, add_opacity/color_dist, the feature bank (input [view, level]) and an
    appearance code (camera uid 2): the LOD mask (voxel-centre distance, round, clamp to the levels) and
    every decoded Gaussian by hand."""
    a, k, f, fork, voxel, std = 40, 3, 8, 2, 0.2, 10.0
    rng = np.random.default_rng(3)
    anchor = torch.from_numpy(rng.uniform(-1.0, 1.0, (a, 3))).float()
    offset, feat = torch.randn(a, k, 3), torch.randn(a, f)
    scaling = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    level = torch.from_numpy(rng.integers(0, 3, (a, 1))).int()
    extra = torch.from_numpy(rng.uniform(-0.5, 0.5, a)).float()
    torch.manual_seed(5)
    decs = {"mlp_opacity": _seq(f + 5, f, k, nn.Tanh()), "mlp_cov": _seq(f + 4, f, 7 * k, None),
            "mlp_color": _seq(f + 5 + 2, f, 3 * k, nn.Sigmoid()), "mlp_feature_bank": _seq(4, f, 3, nn.Softmax(dim=1)),
            "embedding_appearance": nn.Embedding(4, 2)}
    model = OctreeGSModel(anchor=anchor, offset=offset, anchor_feat=feat, scaling=scaling, level=level, extra_level=extra,
                          voxel_size=voxel, standard_dist=std, fork=fork, levels=3, add_level=True,
                          add_opacity_dist=True, add_color_dist=True, **decs)
    cam = _camera(uid=2)
    centre = _centre(cam)
    # LOD by hand: level(dist) = round(log2(std / dist) / log2(fork) + extra), clamped to [0, 2]
    pos = anchor.to(D) + (voxel / 2) / fork ** level.to(D)
    pred = torch.log2(std / (pos - centre).norm(dim=1)) / math.log2(fork) + extra.to(D)
    lod = level[:, 0] <= torch.round(pred).clamp(0, 2).int()
    assert 0 < int(lod.sum()) < a  # the LOD mask drops some anchors
    visible = model.visible_anchors(cam)
    assert torch.equal(visible, lod)  # every anchor is inside the frustum: visible = LOD
    with torch.no_grad():
        got = model.decode(cam, visible)
    code = decs["embedding_appearance"].weight.detach().to(D)[2]
    expected = {}
    for i in lod.nonzero()[:, 0].tolist():
        d = anchor[i].to(D) - centre
        dist, view, lv = d.norm(), d / d.norm(), level[i].to(D)
        w = _mlp(decs["mlp_feature_bank"], torch.cat([view, lv])[None])[0]
        fb = _bank(feat[i].to(D), w)
        op = _mlp(decs["mlp_opacity"], torch.cat([fb, view, dist[None], lv])[None])[0]
        cov = _mlp(decs["mlp_cov"], torch.cat([fb, view, lv])[None])[0].reshape(k, 7)
        col = _mlp(decs["mlp_color"], torch.cat([fb, view, dist[None], lv, code])[None])[0].reshape(k, 3)
        s = torch.exp(scaling[i].to(D))
        for j in range(k):
            if op[j] > 0:
                expected[(i, j)] = _gaussian(anchor[i].to(D), offset[i, j].to(D), s, op[j], col[j], cov[j])
    assert expected
    _check(got, expected)


# ----------------------------------------------------------------------------------------- ContextGS
def test_contextgs_raw_model_by_hand_quantised_anchors_masks_and_anchor0_prefilter():
    """A not-decoded ContextGS model: anchors quantised to 16 bits in the bound (floor, 2^16 - 1 levels,
    step + 1e-6), masks sigmoid(logit) > 0.01, log scales; every decoded Gaussian by hand. The prefilter
    uses anchor 0's rotation for every anchor: by hand with a float64 EWA projection."""
    a, k, f = 80, 3, 8
    rng = np.random.default_rng(4)
    lo, hi = torch.tensor([-7.5, -5.0, -1.0]), torch.tensor([7.3, 5.1, 1.6])
    anchor = torch.from_numpy(rng.uniform((-7.4, -4.9, -0.9), (7.2, 5.0, 1.5), (a, 3))).float()
    offset, feat = torch.randn(a, k, 3), torch.randn(a, f)
    mask = torch.from_numpy(rng.normal(-3.0, 3.0, (a, k, 1))).float()
    scaling = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    scaling[:, 0] += 2.5  # needle-like anchors: their footprint depends on the rotation
    rotation = torch.nn.functional.normalize(torch.randn(a, 4), dim=1)
    torch.manual_seed(6)
    decs = {"mlp_opacity": _seq(f + 4, f, k, nn.Tanh()), "mlp_cov": _seq(f + 4, f, 7 * k, None),
            "mlp_color": _seq(f + 4, f, 3 * k, nn.Sigmoid())}
    model = ContextGSModel(anchor=anchor, offset=offset, mask=mask, anchor_feat=feat, scaling=scaling, rotation=rotation,
                           hyper_latent=torch.randn(a, 2), x_bound_min=lo, x_bound_max=hi, decoded_version=False, **decs)
    cam = _camera()
    centre = _centre(cam)
    step = (hi.to(D) - lo.to(D)) / 65535 + 1e-6
    q = torch.floor((anchor.to(D) - lo.to(D)) / step).clamp(0, 65535)
    pos = q * step + lo.to(D)
    torch.testing.assert_close(model.get_anchor.to(D), pos, rtol=0, atol=1e-6)
    on = 1.0 / (1.0 + torch.exp(-mask.to(D)[:, :, 0])) > 0.01
    with torch.no_grad():
        got = model.decode(cam, None)
    expected = {}
    for i in range(a):
        d = pos[i] - centre
        x = torch.cat([feat[i].to(D), d / d.norm(), d.norm()[None]])[None]
        op = _mlp(decs["mlp_opacity"], x)[0]
        cov = _mlp(decs["mlp_cov"], x)[0].reshape(k, 7)
        col = _mlp(decs["mlp_color"], x)[0].reshape(k, 3)
        s = torch.exp(scaling[i].to(D))
        for j in range(k):
            if op[j] > 0 and on[i, j]:
                expected[(i, j)] = _gaussian(pos[i], offset[i, j].to(D), s, op[j], col[j], cov[j])
    assert 0 < len(expected) < a * k
    _check(got, expected)
    # prefilter: anchors as Gaussians with anchor 0's rotation, near the image border so the rotation matters
    want = _visible_by_hand(cam, pos, torch.exp(scaling.to(D)[:, :3]), rotation.to(D)[0].expand(a, 4))
    assert 0 < int(want.sum()) < a
    assert not torch.equal(want, _visible_by_hand(cam, pos, torch.exp(scaling.to(D)[:, :3]), rotation.to(D)))
    assert torch.equal(model.visible_anchors(cam), want)


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


# ----------------------------------------------------------------------------------------- Scaffold-GS
@pytest.mark.parametrize("dists", [(True, False, False), (False, True, True)])
def test_scaffold_gs_by_hand_feature_bank_appearance_and_dist_options(dists):
    """Scaffold-GS with use_feat_bank (bank input [view, dist]), an appearance code (camera uid 1 of 3)
    and add_{opacity,cov,color}_dist per ``dists``: every decoded Gaussian by hand."""
    a, k, f = 15, 3, 8
    add_op, add_cov, add_col = dists
    torch.manual_seed(8)
    model = NeuralGaussianModel(a, feat_dim=f, n_offsets=k, use_feat_bank=True, appearance_dim=3, num_cameras=3,
                                add_opacity_dist=add_op, add_cov_dist=add_cov, add_color_dist=add_col)
    with torch.no_grad():
        model._anchor.copy_(torch.rand(a, 3) * 2 - 1)
        model._offset.copy_(torch.randn(a, k, 3))
        model._anchor_feat.copy_(torch.randn(a, f))
        model._scaling.copy_(torch.randn(a, 6) * 0.3 - 2.0)
        model.embedding_appearance.embedding.weight.copy_(torch.randn(3, 3))
    cam = _camera(uid=1)
    centre = _centre(cam)
    with torch.no_grad():
        got = model.decode(cam, None)
    code = model.embedding_appearance.embedding.weight.detach().to(D)[1]
    expected = {}
    for i in range(a):
        d = model._anchor[i].detach().to(D) - centre
        dist, view = d.norm()[None], d / d.norm()
        fb = _bank(model._anchor_feat[i].detach().to(D), _mlp(model.mlp_feature_bank, torch.cat([view, dist])[None])[0])
        def inp(with_dist: bool) -> torch.Tensor:
            return torch.cat([fb, view, *([dist] if with_dist else [])])
        op = _mlp(model.mlp_opacity, inp(add_op)[None])[0]
        cov = _mlp(model.mlp_cov, inp(add_cov)[None])[0].reshape(k, 7)
        col = _mlp(model.mlp_color, torch.cat([inp(add_col), code])[None])[0].reshape(k, 3)
        s = torch.exp(model._scaling[i].detach().to(D))
        for j in range(k):
            if op[j] > 0:
                expected[(i, j)] = _gaussian(model._anchor[i].detach().to(D), model._offset[i, j].detach().to(D), s,
                                             op[j], col[j], cov[j])
    assert 0 < len(expected) < a * k
    _check(got, expected)
