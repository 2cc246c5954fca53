"""Tests of ``controlgs_adapter.backends.models.reference_model``."""

from __future__ import annotations

import math
import os
import time
from types import SimpleNamespace

import helpers.compgs_files as compgs_t
import helpers.hac_files as hac_t
import helpers.octree_files as octree_t
import numpy as np
import pytest
import torch
from helpers.family_checks import make_camera as make_camera_3
from helpers.scaffold_oracle import camera_looking_down_z, decode_by_hand
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from controlgs_adapter.backends.compgs import CompGSModel, ResidualBlock, ResidualMLP
from controlgs_adapter.backends.hac import HACModel
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, _knn_sq_dists, median_spacing
from controlgs_adapter.backends.models.train_backbone import _param_groups
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.backends.scaffold_io import save_scaffold_dir
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.formats.backbone import read_cfg_args
from controlgs_adapter.scene import load_builtin_scene
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig, Trainer


def test_saved_model_folders_get_the_umask_mode(tmp_path):
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.backends.scaffold_io import save_scaffold_dir

    old = os.umask(0o022)
    try:
        model = NeuralGaussianModel.from_points(torch.rand(20, 3), torch.rand(20, 3), feat_dim=8, n_offsets=2,
                                                voxel_size=0.3, color_fit_steps=1)
        final = save_scaffold_dir(model, tmp_path / "m", iteration=1)
        assert final.stat().st_mode & 0o777 == 0o755
        assert all(p.stat().st_mode & 0o777 == 0o644 for p in final.iterdir())
    finally:
        os.umask(old)


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


def test_trainer_samples_states_from_the_configured_ranges_by_hand():
    """max_downsample / max_power_saving / seed off their defaults: each draw is (randint view,
    d = max_d ** u0, rho = max_rho * u1) from the seeded generator, as the docstring says."""
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.training import TrainConfig, Trainer

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=2)
    views = scene.views("train")
    config = TrainConfig(iterations=1, checkpoint_every=0, max_downsample=3.0, max_power_saving=0.5, seed=11)
    t = Trainer(model.eval(), views, config, effects={"resample": True, "display": True})
    try:
        g = torch.Generator().manual_seed(11)
        for _ in range(50):
            view = int(torch.randint(len(views), (1,), generator=g))
            u = torch.rand(2, generator=g, dtype=D)
            got_view, state = t.sample()
            assert got_view == view
            assert state.downsample == pytest.approx(3.0 ** float(u[0]), rel=1e-12)
            assert state.power_saving == pytest.approx(0.5 * float(u[1]), rel=1e-12)
    finally:
        t.cgs.unwrap()


def _random_model(a=20, f=8, k=4, seed=0, **opts) -> NeuralGaussianModel:
    torch.manual_seed(seed)
    m = NeuralGaussianModel(a, feat_dim=f, n_offsets=k, **opts)
    with torch.no_grad():
        m._anchor.normal_()
        m._anchor[:, 2] += 5.0
        m._offset.normal_()
        m._anchor_feat.normal_()
        m._scaling.normal_(-2.0, 0.3)
        m._rotation.normal_()
    return m


def _raw(m: NeuralGaussianModel) -> dict:
    """The model's tensors in the oracle's format (the oracle reads weights only, never calls the modules)."""
    return {"anchor": m._anchor.detach(), "offset": m._offset.detach(), "feat": m._anchor_feat.detach(),
            "scaling": m._scaling.detach(), "mlp_opacity": m.mlp_opacity, "mlp_cov": m.mlp_cov,
            "mlp_color": m.mlp_color, "mlp_feature_bank": m.mlp_feature_bank, "embedding": m.embedding_appearance,
            "feat_bank": m.use_feat_bank, "appearance_dim": m.appearance_dim,
            "dists": (m.opacity_dist_dim, m.cov_dist_dim, m.color_dist_dim)}


def _footprint_oracle(m: NeuralGaussianModel, cam: Camera) -> torch.Tensor:
    """3DGS's visible_filter per anchor in float64, the projection Jacobian by autograd."""
    w2c, k = cam.world_to_camera.double(), cam.intrinsics.double()
    out = []
    for v in range(m.num_anchors):
        p = w2c[:3, :3] @ m._anchor[v].detach().double() + w2c[:3, 3]
        if p[2] <= 0.2:
            out.append(False)
            continue
        proj = lambda q: torch.stack([k[0, 0] * q[0] / q[2] + k[0, 2], k[1, 1] * q[1] / q[2] + k[1, 2]])  # noqa: E731
        lim = torch.tensor([1.3 * cam.width / (2 * k[0, 0]), 1.3 * cam.height / (2 * k[1, 1])], dtype=torch.float64)
        clamped = torch.cat([torch.minimum(torch.maximum(p[:2] / p[2], -lim), lim) * p[2], p[2:]])
        jac = torch.autograd.functional.jacobian(proj, clamped)  # [2, 3], at x/z, y/z clamped to 1.3 x FoV (3DGS)
        q = m._rotation[v].detach().double()
        w, x, y, z = q / q.norm()
        rot = torch.stack([torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)]),
                           torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)]),
                           torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)])])
        s = torch.exp(m._scaling[v, :3].detach().double())
        cov3 = rot @ torch.diag(s * s) @ rot.T
        t = jac @ w2c[:3, :3]
        cov2 = t @ cov3 @ t.T + 0.3 * torch.eye(2, dtype=torch.float64)
        lam = torch.linalg.eigvalsh(cov2).max()
        r = math.ceil(3.0 * math.sqrt(float(lam)))
        u, vv = proj(p)
        out.append(bool(u + r > 0 and u - r < cam.width and vv + r > 0 and vv - r < cam.height))
    return torch.tensor(out)


@settings(max_examples=12, deadline=None)
@given(a=st.integers(1, 12), k=st.integers(1, 5), f=st.sampled_from([4, 8]), seed=st.integers(0, 1000),
       bank=st.booleans(), app=st.sampled_from([0, 3]), dists=st.tuples(st.booleans(), st.booleans(), st.booleans()))
def test_decode_equals_hand_written_scaffold_decode(a, k, f, seed, bank, app, dists):
    m = _random_model(a, f, k, seed, use_feat_bank=bank, appearance_dim=app, num_cameras=4, add_opacity_dist=dists[0],
                      add_cov_dist=dists[1], add_color_dist=dists[2])
    cam = camera_looking_down_z(center=(0.3, -0.2, 0.5))
    cam.extra["uid"] = 3
    visible = torch.rand(a, generator=torch.Generator().manual_seed(seed)) > 0.4
    got = m.decode(cam, visible)
    want = decode_by_hand(_raw(m), cam.center, visible, uid=3)
    if not want["anchor_of"].numel():
        assert got.means.shape == (0, 3)
        return
    assert torch.equal(got.anchor_of, want["anchor_of"])
    for name in ("means", "scales", "rotations", "opacities", "colors"):
        torch.testing.assert_close(getattr(got, name).double(), want[name], rtol=1e-5, atol=2e-6, msg=name)
    assert torch.equal(got.visible_ids, visible.nonzero().squeeze(1))


@pytest.mark.parametrize("with_dist", [False, True])
def test_decoder_row_i_is_the_i_th_visible_anchor(with_dist):
    m = _random_model(15, 8, 3, add_opacity_dist=with_dist, add_cov_dist=with_dist, add_color_dist=with_dist)
    seen = {}
    for name in ("mlp_opacity", "mlp_cov", "mlp_color"):
        getattr(m, name)[0].register_forward_pre_hook(lambda mod, args, name=name: seen.__setitem__(name, args[0]))
    visible = torch.zeros(15, dtype=torch.bool)
    visible[[1, 4, 5, 11, 14]] = True
    cam = camera_looking_down_z(center=(1.0, 2.0, -1.0))
    m.decode(cam, visible)
    ids = [1, 4, 5, 11, 14]
    d = m._anchor.detach()[ids] - torch.tensor([1.0, 2.0, -1.0])
    for name, x in seen.items():
        assert x.shape == (5, 8 + 3 + int(with_dist)), name
        assert torch.equal(x[:, :8], m._anchor_feat.detach()[ids])
        torch.testing.assert_close(x[:, 8:11], d / d.norm(dim=1, keepdim=True))
        if with_dist:
            torch.testing.assert_close(x[:, 11], d.norm(dim=1))


def test_opacity_mask_and_anchor_major_offset_order():
    m = _random_model(6, 8, 5)
    with torch.no_grad():  # opacity of offset k is +0.5 for even k, -0.5 for odd k, for every anchor
        m.mlp_opacity[2].weight.zero_()
        m.mlp_opacity[2].bias.copy_(torch.tensor([0.55, -0.55, 0.55, -0.55, 0.55]).atanh())
    visible = torch.tensor([True, False, True, True, False, True])
    g = m.decode(camera_looking_down_z(), visible)
    assert torch.equal(g.anchor_of, torch.tensor([0, 2, 3, 5]).repeat_interleave(3))
    assert torch.equal(g.offset_of, torch.tensor([0, 2, 4]).repeat(4))
    torch.testing.assert_close(g.opacities, torch.full((12,), 0.55))
    assert g.neural_opacity.shape == (4 * 5,) and int((g.neural_opacity > 0).sum()) == 12
    s = m.get_scaling.detach()
    want = m._anchor.detach()[g.anchor_of] + m._offset.detach()[g.anchor_of, g.offset_of] * s[g.anchor_of, :3]
    torch.testing.assert_close(g.means, want)


def test_decode_is_differentiable_in_float64():
    m = _random_model(3, 4, 2).double()
    cam = camera_looking_down_z()
    cam = Camera(cam.world_to_camera.double(), cam.intrinsics.double(), cam.width, cam.height)
    params = (m._offset, m._anchor_feat, m._scaling)

    def f(off, feat, scal):
        saved = [p.data for p in params]
        m._offset.data, m._anchor_feat.data, m._scaling.data = off, feat, scal
        try:
            g = m.decode(cam)
            return g.means, g.scales, g.rotations, g.opacities, g.colors
        finally:
            for p, d in zip(params, saved):
                p.data = d

    inputs = tuple(p.detach().clone().requires_grad_(True) for p in params)
    # the opacity mask is piecewise constant: keep every opacity away from 0 for the finite differences
    assert (m.decode(cam).neural_opacity.abs() > 1e-3).all()
    torch.autograd.gradcheck(lambda *x: f(*x), inputs, eps=1e-6, atol=1e-6)


def test_bad_visible_mask_is_named():
    m = _random_model(5)
    with pytest.raises(ShapeError, match="visible_mask"):
        m.decode(camera_looking_down_z(), torch.ones(4, dtype=torch.bool))
    with pytest.raises(InputValueError, match="visible_mask"):
        m.decode(camera_looking_down_z(), torch.ones(5))


def test_unknown_decode_option_is_named():
    """The model takes no decode option: one passed to render or decode is named, not ignored."""
    m = _random_model(5)
    with pytest.raises(InputValueError, match=r"NeuralGaussianModel\.decode got unknown option\(s\) \['appearance_id'\]"):
        m.render(camera_looking_down_z(), appearance_id=0)
    with pytest.raises(InputValueError, match=r"\['a', 'b'\]"):
        m.decode(camera_looking_down_z(), None, b=1, a=2)


def test_visible_anchors_match_a_float64_footprint_oracle():
    torch.manual_seed(4)
    a = 300
    m = NeuralGaussianModel(a, feat_dim=4, n_offsets=2)
    with torch.no_grad():
        z = torch.empty(a).uniform_(-1.0, 6.0)  # some behind the camera and on the near plane
        m._anchor[:, 2] = z
        m._anchor[:5, 2] = torch.tensor([0.0, 0.1, 0.19, 0.21, 0.25])  # about the near plane (0.2)
        # x/z, y/z up to 1.5 (the image ends at 0.5, the Jacobian clamp at 0.65)
        m._anchor[:, :2] = m._anchor[:, 2:].abs().clamp_min(0.3) * torch.empty(a, 2).uniform_(-1.5, 1.5)
        m._scaling.copy_(torch.empty(a, 6).uniform_(-5.0, 0.0))
        m._rotation.normal_()
    cam = camera_looking_down_z(size=40, f=40.0)  # tan of the half field of view = 0.5
    got = m.visible_anchors(cam)
    want = _footprint_oracle(m, cam)
    assert 0 < int(want.sum()) < a
    assert torch.equal(got, want)


def test_prefilter_never_changes_the_image():
    torch.manual_seed(1)
    pts = torch.rand(400, 3) * torch.tensor([8.0, 8.0, 6.0]) - torch.tensor([4.0, 4.0, 1.0])
    m = NeuralGaussianModel.from_points(pts, torch.rand(400, 3), feat_dim=8, n_offsets=3, voxel_size=0.3,
                                        color_fit_steps=10)
    with torch.no_grad():
        m._offset.uniform_(-0.5, 0.5)
    cam = camera_looking_down_z(size=24, f=24.0)
    visible = m.visible_anchors(cam)
    assert 0 < int(visible.sum()) < m.num_anchors
    with torch.no_grad():
        culled = m.render(cam)
        full = m.render(cam, torch.ones(m.num_anchors, dtype=torch.bool))
    torch.testing.assert_close(culled.color, full.color, atol=1e-5, rtol=0)
    torch.testing.assert_close(culled.alpha, full.alpha, atol=1e-5, rtol=0)


def test_from_points_snaps_to_the_voxel_grid_like_scaffold_gs():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(200, 3))
    m = NeuralGaussianModel.from_points(torch.from_numpy(pts).float(), voxel_size=0.25, feat_dim=8, n_offsets=2)
    want = np.unique(np.round(pts.astype(np.float32).astype(np.float64) / 0.25), axis=0) * 0.25
    np.testing.assert_allclose(m._anchor.detach().numpy(), want, atol=1e-6)
    d2 = ((want[:, None] - want[None]) ** 2).sum(-1)
    np.fill_diagonal(d2, np.inf)
    knn = np.sort(d2, axis=1)[:, :3].mean(1)
    np.testing.assert_allclose(m.get_scaling.detach().numpy(), np.sqrt(knn)[:, None].repeat(6, 1), rtol=1e-5)
    assert torch.equal(m._offset, torch.zeros_like(m._offset)) and torch.equal(m._anchor_feat, torch.zeros_like(m._anchor_feat))


def test_default_voxel_is_the_median_nearest_neighbour_spacing():
    g = torch.arange(6, dtype=torch.float64) * 0.1
    grid = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pts = torch.cat([grid, grid[:20] + 0.01])  # 20 extra points 0.017 from a grid point: a minority
    assert median_spacing(pts) == pytest.approx(0.1)
    m = NeuralGaussianModel.from_points(pts.float(), feat_dim=4, n_offsets=2)
    assert m.voxel_size == pytest.approx(0.1) and m.num_anchors == 216


def test_from_points_colours_warm_start_the_colour_decoder():
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(60, 3, generator=g)
    cols = torch.rand(60, 3, generator=g)
    m = NeuralGaussianModel.from_points(pts, cols, voxel_size=0.25, feat_dim=16, n_offsets=3, color_fit_steps=100)
    cells, inv = torch.unique(torch.round(pts.double() / 0.25), dim=0, return_inverse=True)
    mean = torch.zeros(len(cells), 3, dtype=torch.float64).index_add_(0, inv, cols.double())
    mean /= torch.bincount(inv).double()[:, None]
    cam = camera_looking_down_z(center=(0.5, 0.5, -3.0))
    with torch.no_grad():
        g = m.decode(cam, torch.ones(m.num_anchors, dtype=torch.bool))
        x = torch.cat([m._anchor_feat, torch.nn.functional.normalize(m._anchor - cam.center, dim=1)], 1)
        colours = m.mlp_color(x).reshape(m.num_anchors, 3, 3)
    err = (colours.double() - mean[:, None]).abs().mean()
    spread = (mean - mean.mean(0)).abs().mean()
    assert err < 0.35 * spread, (float(err), float(spread))


def test_bad_points_are_named():
    with pytest.raises(InputValueError, match="points"):
        NeuralGaussianModel.from_points(torch.tensor([[0.0, float("nan"), 1.0]]))
    with pytest.raises(ShapeError, match="colors"):
        NeuralGaussianModel.from_points(torch.zeros(4, 3), torch.zeros(3, 3))
    with pytest.raises(InputValueError, match="feat_dim divisible by 4"):
        NeuralGaussianModel(2, feat_dim=6, use_feat_bank=True)


# --------------------------------------------------------------------------- initial anchor scales
def _brute_scale(anchors: np.ndarray, voxel: float) -> np.ndarray:
    """log(sqrt(mean of the squared distances to the min(3, A - 1) nearest other anchors)), one loop per anchor;
    a single anchor takes the voxel size."""
    n = anchors.shape[0]
    if n == 1:
        return np.array([math.log(voxel)])
    out = []
    for i in range(n):
        d2 = sorted(float(((anchors[i] - anchors[j]) ** 2).sum()) for j in range(n) if j != i)
        out.append(math.log(math.sqrt(sum(d2[:3]) / len(d2[:3]))))
    return np.array(out)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5])
def test_from_points_initial_scales_for_few_anchors_match_brute_force(n):
    voxel = 0.5
    # voxel-centred points (no two in one voxel) at irregular spacings so that every k in 1..3 gives
    # a different mean
    cells = torch.tensor([[0, 0, 0], [3, 0, 0], [0, 1, 0], [7, 5, 2], [1, 1, 4]], dtype=torch.float64)[:n]
    model = NeuralGaussianModel.from_points((cells * voxel).float(), feat_dim=4, n_offsets=2, voxel_size=voxel)
    anchors = model._anchor.detach().double().numpy()
    assert anchors.shape == (n, 3)
    want = _brute_scale(anchors, voxel)
    got = model._scaling.detach().double()
    assert got.shape == (n, 6)
    np.testing.assert_allclose(got.numpy(), np.repeat(want[:, None], 6, axis=1), rtol=0, atol=1e-6)


def test_from_points_two_anchors_one_voxel_apart_scale_is_log_of_their_distance():
    # by hand: anchors at 0 and 0.25 (voxel 0.25): each one's only neighbour is 0.25 away -> log(0.25)
    model = NeuralGaussianModel.from_points(torch.tensor([[0.0, 0, 0], [0.25, 0, 0]]), feat_dim=4, n_offsets=2,
                                            voxel_size=0.25)
    torch.testing.assert_close(model._scaling.detach(), torch.full((2, 6), math.log(0.25)), rtol=0, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_knn_sq_dists_keeps_the_points_dtype_and_matches_brute_force(dtype):
    g = torch.Generator().manual_seed(3)
    pts = torch.randn(7, 3, generator=g, dtype=torch.float64)
    for k in (1, 3, 6, 9):
        got = _knn_sq_dists(pts.to(dtype), k)
        assert got.dtype == dtype
        kk = min(k, 6)
        want = torch.stack([torch.sort(torch.tensor([float(((pts[i] - pts[j]) ** 2).sum()) for j in range(7) if j != i],
                                                    dtype=torch.float64))[0][:kk] for i in range(7)])
        torch.testing.assert_close(got.double(), want, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=1e-6)
    rows = torch.tensor([5, 0])
    torch.testing.assert_close(_knn_sq_dists(pts.to(dtype), 2, rows), _knn_sq_dists(pts.to(dtype), 2)[rows])
    # a single point has no neighbour: zeros of the requested width, in the points' dtype
    one = _knn_sq_dists(pts[:1].to(dtype), 3)
    assert one.dtype == dtype and one.shape == (1, 3) and not one.any()


# --------------------------------------------------------------------------- trainer learning rates
@pytest.mark.parametrize("bank, appearance", [(False, 0), (True, 4)])
def test_backbone_param_groups_are_scaffold_gs_learning_rates(bank, appearance):
    model = NeuralGaussianModel(3, feat_dim=8, n_offsets=2, use_feat_bank=bank, appearance_dim=appearance, num_cameras=2)
    extent = 2.5
    groups = _param_groups(model, extent)
    # Scaffold-GS arguments/__init__.py OptimizationParams: (lr_init, lr_final); the offsets' rates x extent
    want = {"offset": (0.01 * 2.5, 0.0001 * 2.5), "feature": (0.0075, 0.0075), "scaling": (0.007, 0.007),
            "mlp_opacity": (0.002, 0.00002), "mlp_cov": (0.004, 0.004), "mlp_color": (0.008, 0.00005)}
    if bank:
        want["mlp_featurebank"] = (0.01, 0.00001)
    if appearance:
        want["appearance"] = (0.05, 0.0005)
    assert [n for n, *_ in groups] == list(want)
    for name, params, lr0, lr1 in groups:
        assert (lr0, lr1) == pytest.approx(want[name], rel=1e-12), name
    # every trainable tensor sits in exactly one group
    ids = [id(p) for _, ps, _, _ in groups for p in ps]
    assert len(ids) == len(set(ids))
    assert sorted(n for n, p in model.named_parameters() if id(p) not in ids) == ["_anchor", "_opacity", "_rotation"]  # not trained


def test_from_points_squared_spacing_is_clamped_at_1e_7_as_scaffold_gs():
    # Scaffold-GS create_from_pcd: dist2 = clamp_min(distCUDA2(points), 1e-7). Two anchors 1e-4 apart:
    # d2 = 1e-8 -> 1e-7, scale = log(sqrt(1e-7)) = 0.5 * ln(1e-7) = -8.0590 (unclamped: ln(1e-4) = -9.2103)
    model = NeuralGaussianModel.from_points(torch.tensor([[0.0, 0, 0], [1e-4, 0, 0]]), feat_dim=4, n_offsets=2,
                                            voxel_size=1e-4)
    torch.testing.assert_close(model._scaling.detach(), torch.full((2, 6), 0.5 * math.log(1e-7)), rtol=0, atol=1e-5)
    # just above the clamp it is the distance: 1e-3 apart -> ln(1e-3)
    model = NeuralGaussianModel.from_points(torch.tensor([[0.0, 0, 0], [1e-3, 0, 0]]), feat_dim=4, n_offsets=2,
                                            voxel_size=1e-3)
    torch.testing.assert_close(model._scaling.detach(), torch.full((2, 6), math.log(1e-3)), rtol=0, atol=1e-5)


# --------------------------------------------------------------------------- backends defaults
def test_neural_gaussian_model_constructor_defaults_are_scaffold_gs():
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel as M

    m = M()
    assert m.extra_repr() == ("anchors=0, feat_dim=32, n_offsets=10, voxel_size=0.01, use_feat_bank=False, "
                              "appearance_dim=0, dist=(opacity=False, cov=False, color=False)")
    assert (m.opacity_dist_dim, m.cov_dist_dim, m.color_dist_dim) == (0, 0, 0)
    assert m.mlp_feature_bank is None and m.embedding_appearance is None
    # decoder widths follow the defaults: opacity MLP in = F + 3 (view dir) + 1 if distance, out = K
    assert m.mlp_opacity[0].in_features == 32 + 3 and m.mlp_opacity[-2].out_features == 10


def test_from_points_defaults_feat_32_offsets_10_median_voxel():
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [3.0, 2.0, 0]])
    m = NeuralGaussianModel.from_points(pts)
    # nearest-neighbour distances 1, 1, 2, 2 -> torch's median (lower of the two middle values) = 1
    assert (m.feat_dim, m.n_offsets, m.voxel_size) == (32, 10, 1.0)
    assert not m._anchor_feat.detach().any() and not m._offset.detach().any()  # no colours: zero features


def test_median_spacing_default_samples_4096_strides_rows():
    from controlgs_adapter.backends.models.reference_model import median_spacing

    g = torch.Generator().manual_seed(0)
    pts = torch.rand(8200, 3, generator=g, dtype=torch.float64)
    # 8200 // 4096 = 2: rows 0, 2, 4, ... (4100 of them), each against all points; median as torch (lower middle)
    def ref(stride: int) -> float:
        ds = []
        for s in range(0, 8200, 1000):
            idx = torch.arange(s, min(s + 1000, 8200))
            idx = idx[idx % stride == 0]
            d = torch.cdist(pts[idx], pts)
            d[torch.arange(idx.shape[0]), idx] = float("inf")
            ds.append(d.min(1).values)
        return float(torch.cat(ds).median())
    want2, want1 = ref(2), ref(1)
    assert want1 != want2  # the stride matters for these points
    assert median_spacing(pts) == pytest.approx(want2, rel=1e-12)
    assert median_spacing(pts, 8200) == pytest.approx(want1, rel=1e-12)
    # all points coincident: 1.0 by contract
    assert median_spacing(torch.zeros(5, 3)) == 1.0


# ------------------------------------------------------------------------------ spacing of a large cloud
@pytest.mark.slow
def test_median_spacing_of_a_cloud_past_2_24_points():
    """``median_spacing`` works on clouds of any size, also past 2^24 points (where fewer than one row of
    distances fits the 2^24 chunk): points every 0.5 on a line have a nearest neighbour at 0.5."""
    from controlgs_adapter.backends.models.reference_model import median_spacing

    n = (1 << 24) + 1
    pts = torch.zeros(n, 3, dtype=torch.float64)
    pts[:, 0] = torch.arange(n, dtype=torch.float64) * 0.5
    assert median_spacing(pts, samples=2) == 0.5


# ------------------------------------------------------------------------------ Scaffold-GS cfg_args
def test_saved_scaffold_cfg_args_records_scaffold_gs_default_undistorted_false(tmp_path):
    """``cfg_args`` is Scaffold-GS's ``ModelParams`` as its ``train.py`` records them; Scaffold-GS defaults
    ``undistorted = False`` (the images were not undistorted by it), and a model made here was not either."""
    torch.manual_seed(0)
    model = NeuralGaussianModel(5, feat_dim=4, n_offsets=2, voxel_size=0.05)
    save_scaffold_dir(model, tmp_path, 10, mlp_mode="unite")
    cfg = read_cfg_args(tmp_path / "cfg_args")
    assert cfg["undistorted"] is False
    assert (cfg["feat_dim"], cfg["n_offsets"]) == (4, 2)


def test_colour_warm_start_takes_adam_steps_of_learning_rate_0_01():
    """The colour fit of ``from_points`` is Adam at learning rate 1e-2: Adam's first step moves every parameter
    by ``lr * g / (|g| + eps)``, i.e. by 0.01 wherever its gradient is not tiny, and never by more."""
    g = torch.Generator().manual_seed(3)
    pts = torch.rand(300, 3, generator=g, dtype=torch.float64)
    cols = torch.rand(300, 3, generator=g, dtype=torch.float64)

    def feats(steps: int) -> torch.Tensor:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            m = NeuralGaussianModel.from_points(pts, cols, feat_dim=8, n_offsets=2, voxel_size=0.2,
                                                color_fit_steps=steps, seed=5)
        return m._anchor_feat.detach().double()

    step = (feats(1) - feats(0)).abs().flatten()
    assert step.numel() > 200
    assert float(step.max()) <= 0.01 * (1 + 1e-5)
    assert float(step.median()) == pytest.approx(0.01, rel=2e-3)  # eps 1e-8 against gradients ~1e-5


def test_a_trainer_starts_in_its_first_iterations_optics_mode():
    """Before any step the pipeline's optics stage is in iteration 0's mode (``distortion`` while
    ``psf_fraction`` leaves iterations to it), and the switch to ``psf_mode`` comes at its iteration."""
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    torch.manual_seed(0)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=5)
    effects = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}
    config = TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.5, psf_mode="exact")
    t = Trainer(model.eval(), scene.views("train"), config, effects=effects)
    try:
        assert [t.optics_mode(i) for i in (0, 1)] == ["distortion", "exact"]
        assert t.pipeline["optics"].mode == "distortion"
        t.step()
        assert t.pipeline["optics"].mode == "distortion"
        t.step()
        assert t.pipeline["optics"].mode == "exact"
    finally:
        t.cgs.unwrap()


def test_from_points_with_colours_starts_features_small_and_random():
    """With colours and no fitting steps, the features are the documented small random start: normal with
    standard deviation 0.1 (checked on 4000 values), drawn from ``seed``."""
    g = torch.Generator().manual_seed(0)
    pts = torch.rand(500, 3, generator=g, dtype=torch.float64)
    cols = torch.rand(500, 3, generator=g, dtype=torch.float64)
    m = NeuralGaussianModel.from_points(pts, cols, feat_dim=8, n_offsets=2, voxel_size=1e-3, color_fit_steps=0, seed=4)
    f = m._anchor_feat.detach().double().flatten()
    assert f.numel() == 4000
    assert abs(float(f.mean())) < 0.01 and 0.095 < float(f.std()) < 0.105 and float(f.abs().max()) < 0.6
    again = NeuralGaussianModel.from_points(pts, cols, feat_dim=8, n_offsets=2, voxel_size=1e-3, color_fit_steps=0, seed=4)
    assert torch.equal(again._anchor_feat, m._anchor_feat)


def test_scaffold_layout_keeps_a_one_wide_appearance_code():
    """Scaffold-GS appends the appearance code (appearance_dim wide, any size > 0) last to the colour
    decoder's input; a 1-wide code is still an input column."""
    m = NeuralGaussianModel(2, feat_dim=4, n_offsets=2, appearance_dim=1, num_cameras=3)
    layout = ScaffoldGSBackend().input_layout(m, "mlp_color")
    assert layout == [("feat", 4), ("view", 3), ("appearance", 1)]
    assert sum(w for _, w in layout) == m.mlp_color[0].in_features  # the decoder's own FC1 width: 4 + 3 + 1


# ----------------------------------------------------------------------------- Trainer.seconds
def test_trainer_seconds_is_zero_before_training_then_the_wall_time_of_train():
    """``Trainer`` docstring: ``seconds`` is the wall time of the last ``train()`` call, 0.0 before the
    first; after ``train()`` it lies between 0 and the wall time measured around the call."""
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.training import TrainConfig, Trainer

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=2)
    t = Trainer(model.eval(), scene.views("train"), TrainConfig(iterations=1, checkpoint_every=0),
                effects={"resample": True})
    try:
        assert t.seconds == 0.0 and t.iteration == 0
        t0 = time.perf_counter()
        t.train(progress=False)
        wall = time.perf_counter() - t0
        assert t.iteration == 1 and 0.0 < t.seconds <= wall
    finally:
        t.cgs.unwrap()


def _hac_kw(n_mask_cols: int, seed: int = 0) -> dict:
    arr = hac_t._arrays(seed, decoded=True, mask_cols=n_mask_cols)
    return dict(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                scaling=torch.from_numpy(arr["scale"]), decoded_version=True, **hac_t._decoders(seed))


def _zero_some_opacities(seq: nn.Sequential, k: int) -> None:
    """Last Linear of a Scaffold-family opacity decoder: output k is atanh(0.5) for even k and exactly 0 for
    odd k (tanh(0) = 0), for every anchor."""
    with torch.no_grad():
        seq[2].weight.zero_()
        seq[2].bias.copy_(torch.tensor([math.atanh(0.5) if i % 2 == 0 else 0.0 for i in range(k)]))


def test_scaffold_backend_layout_positions_and_matching():

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


def test_every_family_drops_gaussians_whose_neural_opacity_is_exactly_zero():
    """Scaffold-GS (and every family after it) keeps a Gaussian only where neural opacity > 0."""
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel

    cam = make_camera_3()
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


def test_reference_model_defaults_are_scaffold_gs_s():
    m = NeuralGaussianModel(2)
    # Scaffold-GS ModelParams: feat_dim 32, n_offsets 10, no feature bank; appearance 0 as its scripts pass
    assert (m.feat_dim, m.n_offsets, m.use_feat_bank, m.appearance_dim, m.voxel_size) == (32, 10, False, 0, 0.01)
    assert m.embedding_appearance is None and m.mlp_feature_bank is None
    assert not (m.add_opacity_dist or m.add_cov_dist or m.add_color_dist)
    # decoders: Linear(F + 3, F) -> ReLU -> Linear(F, K | 7K | 3K) -> Tanh | - | Sigmoid
    for dec, out, act in ((m.mlp_opacity, 10, nn.Tanh), (m.mlp_cov, 70, None), (m.mlp_color, 30, nn.Sigmoid)):
        assert (dec[0].in_features, dec[0].out_features, dec[2].out_features) == (35, 32, out)
        assert isinstance(dec[1], nn.ReLU) and (len(dec) == 3 if act is None else isinstance(dec[3], act))
    # anchor opacity starts at sigmoid^-1(0.1) = log(0.1 / 0.9) = -2.1972; rotation at the identity quaternion
    assert torch.allclose(m._opacity, torch.full((2, 1), -2.1972245773362196))
    assert torch.allclose(m.get_opacity, torch.full((2, 1), 0.1))
    assert torch.equal(m._rotation, torch.tensor([[1.0, 0, 0, 0]] * 2))
    with torch.no_grad():
        m._rotation.copy_(torch.tensor([[2.0, 0.0, 0.0, 0.0], [0.0, 3.0, 0.0, 4.0]]))
    assert torch.allclose(m.get_rotation, torch.tensor([[1.0, 0, 0, 0], [0.0, 0.6, 0.0, 0.8]]))
    assert torch.allclose(NeuralGaussianModel.rotation_activation(m._rotation), m.get_rotation)
    q = torch.tensor([[[0.0, 0.0, 3.0, 4.0]], [[2.0, 0.0, 0.0, 0.0]]])  # [2, 1, 4]: normalised along the last axis
    assert torch.allclose(NeuralGaussianModel.rotation_activation(q), torch.tensor([[[0.0, 0.0, 0.6, 0.8]], [[1.0, 0, 0, 0]]]))
    # with every option: widths grow by the distance (1) and the appearance code (last, colour only)
    o = NeuralGaussianModel(1, feat_dim=8, n_offsets=2, use_feat_bank=True, appearance_dim=3, num_cameras=5,
                            add_opacity_dist=True, add_color_dist=True)
    assert (o.mlp_opacity[0].in_features, o.mlp_cov[0].in_features, o.mlp_color[0].in_features) == (12, 11, 15)
    assert o.mlp_feature_bank[0].in_features == 4 and isinstance(o.mlp_feature_bank[3], nn.Softmax)
    assert tuple(o.embedding_appearance.embedding.weight.shape) == (5, 3)


@pytest.mark.parametrize("kw, words", [
    ({"num_anchors": -1}, "need num_anchors >= 0"), ({"feat_dim": 0}, "feat_dim >= 1"), ({"n_offsets": 0}, "n_offsets >= 1"),
    ({"appearance_dim": -1}, "appearance_dim >= 0"), ({"num_cameras": 0}, "num_cameras >= 1"),
    ({"use_feat_bank": True, "feat_dim": 6}, "use_feat_bank needs feat_dim divisible by 4, got 6"),
    ({"voxel_size": 0.0}, "voxel_size must be a finite number > 0, got 0.0"),
    ({"voxel_size": float("inf")}, "voxel_size must be a finite number > 0, got inf"),
])
def test_reference_model_refusals(kw, words):
    kw = {"num_anchors": 1, **kw}
    with pytest.raises(InputValueError, match=words):
        NeuralGaussianModel(kw.pop("num_anchors"), **kw)
    NeuralGaussianModel(0, feat_dim=1, n_offsets=1, appearance_dim=0, num_cameras=1)  # every lower bound accepted


def test_from_points_defaults_scales_and_refusals():
    # four points at the corners of a unit square (voxel 0.5 keeps them apart): each anchor's 3 nearest
    # others are at squared distances 1, 1, 2 -> log-scale log(sqrt(4/3)) = 0.143841 on all 6 axes
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    m = NeuralGaussianModel.from_points(pts, voxel_size=0.5)
    assert (m.feat_dim, m.n_offsets, m.num_anchors) == (32, 10, 4)  # create_from_pcd with ModelParams defaults
    assert torch.allclose(m._scaling, torch.full((4, 6), math.log(math.sqrt(4 / 3))))
    assert torch.equal(m._anchor_feat, torch.zeros(4, 32)) and torch.equal(m._offset, torch.zeros(4, 10, 3))
    # ascending lexicographic anchors (np.unique order)
    assert m._anchor.tolist() == [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]]
    # one anchor has no neighbour: its scale is the voxel size, log(0.25)
    one = NeuralGaussianModel.from_points(torch.tensor([[0.1, 0.2, 0.3]]), voxel_size=0.25, feat_dim=4, n_offsets=1)
    assert torch.allclose(one._scaling, torch.full((1, 6), math.log(0.25)))
    assert torch.allclose(one._anchor, torch.tensor([[0.0, 0.25, 0.25]]))  # round(p / 0.25) * 0.25
    # a fifth point far away leaves the corners' 3 nearest as they were; its own 3 nearest are the corners at
    # squared distances 16, 17, 25, 26 -> the closest three: mean 58 / 3
    five = NeuralGaussianModel.from_points(torch.cat([pts, torch.tensor([[5.0, 0.0, 0.0]])]), voxel_size=0.5,
                                           feat_dim=4, n_offsets=1)
    assert five._anchor[4].tolist() == [5.0, 0.0, 0.0]
    assert torch.allclose(five._scaling[:4], torch.full((4, 6), math.log(math.sqrt(4 / 3))))
    assert torch.allclose(five._scaling[4], torch.full((6,), math.log(math.sqrt(58 / 3))))
    with pytest.raises(ShapeError, match=r"points must hold at least one point, got shape \[0, 3\]"):
        NeuralGaussianModel.from_points(torch.zeros(0, 3))
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputValueError, match="voxel_size must be a finite number > 0"):
            NeuralGaussianModel.from_points(pts, voxel_size=bad)


def test_from_points_colour_fit_with_distance_and_appearance_inputs():
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cols = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.7, 0.9]])
    with torch.random.fork_rng(devices=[]):  # the decoders' initial weights come from the global generator
        torch.manual_seed(0)
        m = NeuralGaussianModel.from_points(pts, cols, voxel_size=0.5, feat_dim=8, n_offsets=2, add_color_dist=True,
                                            appearance_dim=2, color_fit_steps=150)
    # the fitted colour decoder on [feat, random view, dist 1, camera 0's code] gives each anchor's colour
    view = torch.nn.functional.normalize(torch.randn(2, 3, generator=torch.Generator().manual_seed(5)), dim=1)
    code = m.embedding_appearance(torch.zeros(2, dtype=torch.long))
    with torch.no_grad():
        pred = m.mlp_color(torch.cat([m._anchor_feat, view, torch.ones(2, 1), code], 1)).reshape(2, 2, 3)
    # 150 steps (seed 0) bring it within 0.0077 at the distance it was fitted at (1); at distance 0 it is 0.033 off
    assert (pred - cols[:, None]).abs().max() < 0.02


def test_median_spacing_samples_4096_rows_by_default():
    # 8192 points: even rows far from every other point (their nearest neighbour at 10), odd rows in pairs
    # 1 apart. All rows: half 1, half 10 -> lower median 1; every 2nd row (8192 // 4096 = 2, the default
    # sample of 4096) reads only the even rows: 10
    n = 8192
    pts = torch.zeros(n, 3, dtype=torch.float64)
    pts[0::2, 0] = torch.arange(n // 2, dtype=torch.float64) * 10.0
    pts[0::2, 1] = 1000.0
    odd = torch.arange(n // 2)
    pts[1::2, 0] = (odd // 2) * 100.0
    pts[1::2, 2] = (odd % 2).double()
    pts[1::2, 1] = -1000.0
    assert median_spacing(pts) == 10.0
    assert median_spacing(pts[:4000]) == 1.0  # fewer than 4096 points: every row


def test_nearest_neighbour_helpers_by_hand():
    assert torch.equal(_knn_sq_dists(torch.zeros(1, 3, dtype=torch.float64), 3), torch.zeros(1, 3, dtype=torch.float64))
    # points on a line at 0, 1, 3: nearest-neighbour distances 1, 1, 2 -> median 1; squared 2-NN of x=0: 1, 9
    line = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]], dtype=torch.float64)
    assert median_spacing(line) == 1.0
    assert torch.equal(_knn_sq_dists(line, 2)[0], torch.tensor([1.0, 9.0], dtype=torch.float64))
    assert median_spacing(torch.ones(5, 3)) == 1.0  # all points coincide
    # at most `samples` rows: stride 2 over 0, 1, 3, 7 takes 0 and 3 (distances 1 and 2: median 1 of [1, 2]
    # with torch's lower median)
    assert median_spacing(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]]), samples=2) == 1.0
    assert median_spacing(torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]]), samples=2) == 1.0
    assert median_spacing(torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [5.0, 0, 0], [7.0, 0, 0]]), samples=2) == 2.0


def test_from_points_default_seed_0_and_200_colour_fit_steps():
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cols = torch.tensor([[0.9, 0.1, 0.2], [0.2, 0.7, 0.9]])

    def build(**kw):
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(0)
            return NeuralGaussianModel.from_points(pts, cols, voxel_size=0.5, feat_dim=4, n_offsets=1, **kw)

    default = build()
    assert torch.equal(default._anchor_feat, build(seed=0, color_fit_steps=200)._anchor_feat)
    assert not torch.equal(default._anchor_feat, build(seed=1)._anchor_feat)
    assert not torch.equal(default._anchor_feat, build(color_fit_steps=199)._anchor_feat)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
