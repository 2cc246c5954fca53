"""The reference Scaffold-GS model (``backends.models.reference_model``): its defaults and refusals, decoding
and prefilter against float64 references, anchors, scales and colours made from a point cloud, and the
nearest-neighbour spacing behind its default voxel size."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.reference_models import random_reference_model
import torch
from helpers.anchor_oracle import camera_centre, oblique_camera, visible64
from helpers.scaffold_cameras import scaffold_camera
from helpers.scaffold_oracle import camera_looking_down_z, decode_by_hand
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, _knn_sq_dists, median_spacing
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.state import Camera

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _raw(m: NeuralGaussianModel) -> dict:
    """The model's tensors in the oracle's format (the oracle reads weights only, never calls the modules)."""
    return {"anchor": m._anchor.detach(), "offset": m._offset.detach(), "feat": m._anchor_feat.detach(),
            "scaling": m._scaling.detach(), "mlp_opacity": m.mlp_opacity, "mlp_cov": m.mlp_cov,
            "mlp_color": m.mlp_color, "mlp_feature_bank": m.mlp_feature_bank, "embedding": m.embedding_appearance,
            "feat_bank": m.use_feat_bank, "appearance_dim": m.appearance_dim,
            "dists": (m.opacity_dist_dim, m.cov_dist_dim, m.color_dist_dim)}


# ------------------------------------------------------------------------------ defaults, refusals
def test_defaults_are_scaffold_gs_s():
    assert NeuralGaussianModel().extra_repr() == (
        "anchors=0, feat_dim=32, n_offsets=10, voxel_size=0.01, use_feat_bank=False, "
        "appearance_dim=0, dist=(opacity=False, cov=False, color=False)")
    m = NeuralGaussianModel(2)
    # Scaffold-GS ModelParams: feat_dim 32, n_offsets 10, no feature bank; appearance 0 as its scripts pass
    assert (m.feat_dim, m.n_offsets, m.use_feat_bank, m.appearance_dim, m.voxel_size) == (32, 10, False, 0, 0.01)
    assert m.embedding_appearance is None and m.mlp_feature_bank is None
    assert not (m.add_opacity_dist or m.add_cov_dist or m.add_color_dist)
    assert (m.opacity_dist_dim, m.cov_dist_dim, m.color_dist_dim) == (0, 0, 0)
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


def test_constructor_refusals(kw, words):
    kw = {"num_anchors": 1, **kw}
    with pytest.raises(InputValueError, match=words):
        NeuralGaussianModel(kw.pop("num_anchors"), **kw)
    NeuralGaussianModel(0, feat_dim=1, n_offsets=1, appearance_dim=0, num_cameras=1)  # every lower bound accepted


# ---------------------------------------------------------------------------------------- decoding
@settings(max_examples=12, deadline=None)
@given(a=st.integers(1, 12), k=st.integers(1, 5), f=st.sampled_from([4, 8]), seed=st.integers(0, 1000),
       bank=st.booleans(), app=st.sampled_from([0, 3]), dists=st.tuples(st.booleans(), st.booleans(), st.booleans()))
def test_decode_equals_a_float64_decode_anchor_by_anchor(a, k, f, seed, bank, app, dists):
    """Every option (feature bank, appearance code of camera uid 3, distance inputs) against the float64
    decode of ``helpers.scaffold_oracle``, seen from a turned camera with an off-centre principal point."""
    m = random_reference_model(a, f, k, seed, use_feat_bank=bank, appearance_dim=app, num_cameras=4, add_opacity_dist=dists[0],
                      add_cov_dist=dists[1], add_color_dist=dists[2])
    cam = oblique_camera(uid=3)
    visible = torch.rand(a, generator=torch.Generator().manual_seed(seed)) > 0.4
    got = m.decode(cam, visible)
    want = decode_by_hand(_raw(m), camera_centre(cam), visible, uid=3)
    if not want["anchor_of"].numel():
        assert got.means.shape == (0, 3)
        return
    assert torch.equal(got.anchor_of, want["anchor_of"])
    for name in ("means", "scales", "rotations", "opacities", "colors"):
        torch.testing.assert_close(getattr(got, name).double(), want[name], rtol=1e-5, atol=2e-6, msg=name)
    assert torch.equal(got.visible_ids, visible.nonzero().squeeze(1))


@pytest.mark.parametrize("with_dist", [False, True])
def test_decoder_row_i_is_the_i_th_visible_anchor(with_dist):
    m = random_reference_model(15, 8, 3, add_opacity_dist=with_dist, add_cov_dist=with_dist, add_color_dist=with_dist)
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
    m = random_reference_model(6, 8, 5)
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
    m = random_reference_model(3, 4, 2).double()
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


def test_decode_refuses_a_bad_visible_mask_and_names_unknown_options():
    """The model takes no decode option: one passed to render or decode is named, not ignored."""
    m = random_reference_model(5)
    with pytest.raises(ShapeError, match="visible_mask"):
        m.decode(camera_looking_down_z(), torch.ones(4, dtype=torch.bool))
    with pytest.raises(InputValueError, match="visible_mask"):
        m.decode(camera_looking_down_z(), torch.ones(5))
    with pytest.raises(InputValueError, match=r"NeuralGaussianModel\.decode got unknown option\(s\) \['appearance_id'\]"):
        m.render(camera_looking_down_z(), appearance_id=0)
    with pytest.raises(InputValueError, match=r"\['a', 'b'\]"):
        m.decode(camera_looking_down_z(), None, b=1, a=2)


# --------------------------------------------------------------------------------------- prefilter
def test_visible_anchors_match_a_float64_reference():
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
    want = visible64(cam, m._anchor.detach(), torch.exp(m._scaling[:, :3].detach()), m._rotation.detach())
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


# ----------------------------------------------------------------------------- from a point cloud
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


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 200])
def test_from_points_snaps_to_the_voxel_grid_and_scales_match_brute_force(n):
    """Anchors are the distinct voxels round(p / voxel) * voxel in ascending order (np.unique), with zero
    features and offsets; each anchor's six log-scales are log(sqrt(mean squared distance to its min(3, A - 1)
    nearest anchors)), the voxel size for a lone anchor. Few anchors at irregular voxel spacings (every k in
    1..3 gives another mean), and 200 random points."""
    voxel = 0.5 if n <= 5 else 0.25
    if n <= 5:
        cells = torch.tensor([[0, 0, 0], [3, 0, 0], [0, 1, 0], [7, 5, 2], [1, 1, 4]], dtype=torch.float64)[:n]
        pts = (cells * voxel).numpy()
    else:
        pts = np.random.default_rng(0).uniform(-1, 1, size=(n, 3))
    model = NeuralGaussianModel.from_points(torch.from_numpy(pts).float(), feat_dim=8, n_offsets=2, voxel_size=voxel)
    want_anchors = np.unique(np.round(pts.astype(np.float32).astype(np.float64) / voxel), axis=0) * voxel
    np.testing.assert_allclose(model._anchor.detach().numpy(), want_anchors, atol=1e-6)
    want = _brute_scale(model._anchor.detach().double().numpy(), voxel)
    np.testing.assert_allclose(model._scaling.detach().double().numpy(), np.repeat(want[:, None], 6, axis=1), rtol=0,
                               atol=1e-5)
    assert not model._offset.detach().any() and not model._anchor_feat.detach().any()


def test_from_points_scales_by_hand_and_refusals():
    # four points at the corners of a unit square (voxel 0.5 keeps them apart): each anchor's 3 nearest
    # others are at squared distances 1, 1, 2 -> log-scale log(sqrt(4/3)) = 0.143841 on all 6 axes
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    m = NeuralGaussianModel.from_points(pts, voxel_size=0.5)
    assert m.num_anchors == 4
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
    # Scaffold-GS create_from_pcd: dist2 = clamp_min(distCUDA2(points), 1e-7). Two anchors 1e-4 apart:
    # d2 = 1e-8 -> 1e-7, scale = log(sqrt(1e-7)) = 0.5 * ln(1e-7) = -8.0590 (unclamped: ln(1e-4) = -9.2103)
    model = NeuralGaussianModel.from_points(torch.tensor([[0.0, 0, 0], [1e-4, 0, 0]]), feat_dim=4, n_offsets=2,
                                            voxel_size=1e-4)
    torch.testing.assert_close(model._scaling.detach(), torch.full((2, 6), 0.5 * math.log(1e-7)), rtol=0, atol=1e-5)
    # just above the clamp it is the distance: 1e-3 apart -> ln(1e-3)
    model = NeuralGaussianModel.from_points(torch.tensor([[0.0, 0, 0], [1e-3, 0, 0]]), feat_dim=4, n_offsets=2,
                                            voxel_size=1e-3)
    torch.testing.assert_close(model._scaling.detach(), torch.full((2, 6), math.log(1e-3)), rtol=0, atol=1e-5)
    with pytest.raises(InputValueError, match="points"):
        NeuralGaussianModel.from_points(torch.tensor([[0.0, float("nan"), 1.0]]))
    with pytest.raises(ShapeError, match="colors"):
        NeuralGaussianModel.from_points(torch.zeros(4, 3), torch.zeros(3, 3))
    with pytest.raises(InputValueError, match="feat_dim divisible by 4"):
        NeuralGaussianModel(2, feat_dim=6, use_feat_bank=True)


def test_from_points_defaults_feat_32_offsets_10_and_the_median_spacing_as_voxel():
    """Scaffold-GS's create_from_pcd with its ModelParams defaults; without a voxel size, the median
    nearest-neighbour spacing of the points (torch's lower median); without colours, zero features."""
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [3.0, 2.0, 0]])
    m = NeuralGaussianModel.from_points(pts)
    # nearest-neighbour distances 1, 1, 2, 2 -> torch's median (lower of the two middle values) = 1
    assert (m.feat_dim, m.n_offsets, m.voxel_size) == (32, 10, 1.0)
    assert not m._anchor_feat.detach().any() and not m._offset.detach().any()
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


# -------------------------------------------------------------------------------- nearest neighbours
def test_median_spacing_samples_4096_rows_by_default_by_hand():
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
    # points on a line at 0, 1, 3: nearest-neighbour distances 1, 1, 2 -> median 1; all points coincide: 1.0
    assert median_spacing(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]], dtype=torch.float64)) == 1.0
    assert median_spacing(torch.ones(5, 3)) == 1.0
    # at most `samples` rows: stride 2 over 0, 1, 3, 7 takes 0 and 3 (distances 1 and 2: median 1 of [1, 2]
    # with torch's lower median)
    assert median_spacing(torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]]), samples=2) == 1.0
    assert median_spacing(torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0], [7.0, 0, 0]]), samples=2) == 1.0
    assert median_spacing(torch.tensor([[0.0, 0, 0], [2.0, 0, 0], [5.0, 0, 0], [7.0, 0, 0]]), samples=2) == 2.0


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
    # squared 2-NN of x = 0 on the line 0, 1, 3: 1, 9
    line = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0]], dtype=dtype)
    assert torch.equal(_knn_sq_dists(line, 2)[0], torch.tensor([1.0, 9.0], dtype=dtype))


@pytest.mark.slow
def test_median_spacing_of_a_cloud_past_2_24_points():
    """``median_spacing`` works on clouds of any size, also past 2^24 points (where fewer than one row of
    distances fits the 2^24 chunk): points every 0.5 on a line have a nearest neighbour at 0.5."""
    n = (1 << 24) + 1
    pts = torch.zeros(n, 3, dtype=torch.float64)
    pts[:, 0] = torch.arange(n, dtype=torch.float64) * 0.5
    assert median_spacing(pts, samples=2) == 0.5


# ------------------------------------------------------------------------------ Camera.from_scaffold
def test_the_cameras_uid_picks_the_appearance_code():
    """A Scaffold-GS camera's ``uid`` travels in ``Camera.extra`` and selects the reference model's
    appearance embedding (another uid decodes other colours)."""
    cam = Camera.from_scaffold(scaffold_camera(32, 24, 1.0, 0.8, uid=3))
    torch.manual_seed(0)
    model = NeuralGaussianModel(6, feat_dim=8, n_offsets=2, appearance_dim=4, num_cameras=5)
    with torch.no_grad():
        model._anchor.copy_(torch.randn(6, 3) * 0.3)
        model._anchor_feat.copy_(torch.randn(6, 8))
        model.embedding_appearance.embedding.weight.copy_(torch.randn(5, 4) * 3)
        model.mlp_opacity[2].bias.fill_(5.0)  # every Gaussian kept
    want = model.decode(Camera(cam.world_to_camera, cam.intrinsics, 32, 24, {"uid": 3})).colors
    code0 = model.decode(Camera(cam.world_to_camera, cam.intrinsics, 32, 24)).colors
    got = model.decode(cam).colors
    assert torch.equal(got, want)
    assert (got - code0).abs().max() > 1e-2  # the code matters: uid 0 would decode other colours


def test_render_is_the_splat_of_the_decoded_gaussians_and_reaches_every_parameter():
    m = random_reference_model(12, 8, 3)
    cam = camera_looking_down_z(size=20, f=20.0)
    out = m.render(cam, background=torch.tensor([0.2, 0.3, 0.4]))
    g = m.decode(cam, m.visible_anchors(cam))
    ref = rasterize(g.means, g.scales, g.rotations, g.opacities, g.colors, cam, torch.tensor([0.2, 0.3, 0.4]))
    assert out.color.shape == (3, 20, 20) and torch.equal(out.color, ref.color)
    out.color.sum().backward()
    for name in ("_offset", "_anchor_feat", "_scaling", "mlp_opacity.0.weight", "mlp_cov.2.bias", "mlp_color.0.weight"):
        p = dict(m.named_parameters())[name]
        assert p.grad is not None and bool(p.grad.abs().sum() > 0), name
