"""The reference neural-Gaussian model: Scaffold-GS decoding semantics, prefilter, construction, training."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings, strategies as st

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, median_spacing
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.backends.models.train_backbone import grid_points, train_reference_model
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import Camera
from scaffold_oracle import camera_looking_down_z, decode_by_hand


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


# ------------------------------------------------------------------------------------- prefilter

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


def test_render_is_the_splat_of_the_decoded_gaussians_and_reaches_every_parameter():
    m = _random_model(12, 8, 3)
    cam = camera_looking_down_z(size=20, f=20.0)
    out = m.render(cam, background=torch.tensor([0.2, 0.3, 0.4]))
    g = m.decode(cam, m.visible_anchors(cam))
    ref = rasterize(g.means, g.scales, g.rotations, g.opacities, g.colors, cam, torch.tensor([0.2, 0.3, 0.4]))
    assert out.color.shape == (3, 20, 20) and torch.equal(out.color, ref.color)
    out.color.sum().backward()
    for name in ("_offset", "_anchor_feat", "_scaling", "mlp_opacity.0.weight", "mlp_cov.2.bias", "mlp_color.0.weight"):
        p = dict(m.named_parameters())[name]
        assert p.grad is not None and bool(p.grad.abs().sum() > 0), name


# ---------------------------------------------------------------------------------- construction

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


def test_grid_points_fill_the_box_evenly():
    pts = grid_points(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), 200)
    spacing = (2.0 / 200) ** (1 / 3)
    assert abs(pts.shape[0] - 200) < 80
    assert bool((pts >= 0).all()) and bool((pts[:, 0] <= 2).all()) and bool((pts[:, 1:] <= 1).all())
    assert pts.shape[0] == len(torch.unique(pts, dim=0))
    assert float(pts[:, 0].min()) == pytest.approx(float(2.0 - pts[:, 0].max()), abs=1e-6)
    assert float(pts[:, 0].min()) < spacing


# -------------------------------------------------------------------------------------- training

def _plane_scene(views=2, size=20):
    """A textured square (colour = smooth function of position) at z = 4, seen from a few cameras,
    rendered from a teacher whose colour decoder is sigmoid(feature[:3]) (weights set by hand)."""
    u = torch.linspace(-1, 1, 21)
    gy, gx = torch.meshgrid(u, u, indexing="ij")
    pts = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((21 * 21,), 4.0)], 1)
    cols = torch.stack([0.5 + 0.4 * torch.sin(3 * pts[:, 0]), 0.5 + 0.4 * torch.cos(2 * pts[:, 1]),
                        0.5 + 0.3 * torch.sin(pts[:, 0] + pts[:, 1])], 1)
    cams = [camera_looking_down_z(size=size, f=size * 1.2, center=(0.3 * (i - 1), 0.1 * i, 0.0)) for i in range(views)]
    teacher = NeuralGaussianModel.from_points(pts, feat_dim=8, n_offsets=1, voxel_size=0.1)
    eye = torch.eye(3)
    with torch.no_grad():  # opaque, isotropic Gaussians of colour sigmoid(feat[:3]) = cols
        teacher._anchor_feat[:, :3] = torch.logit(cols)
        teacher.mlp_color[0].weight.zero_()
        teacher.mlp_color[0].bias.zero_()
        teacher.mlp_color[0].weight[:3, :3] = eye
        teacher.mlp_color[0].weight[3:6, :3] = -eye
        teacher.mlp_color[2].weight.zero_()
        teacher.mlp_color[2].weight[:, :6] = torch.cat([eye, -eye], 1)
        teacher.mlp_color[2].bias.zero_()
        teacher.mlp_opacity[2].weight.zero_()
        teacher.mlp_opacity[2].bias.fill_(3.0)
        teacher.mlp_cov[2].weight.zero_()
        teacher.mlp_cov[2].bias.copy_(torch.tensor([2.0, 2.0, 2.0, 1.0, 0.0, 0.0, 0.0]))
        images = torch.stack([teacher.render(c).color for c in cams])
    return images, cams, pts, cols


def test_training_reduces_the_image_loss():
    images, cams, pts, _ = _plane_scene(size=16)

    def l1(model):
        with torch.no_grad():
            return float(torch.stack([(model.render(c).color - im).abs().mean() for c, im in zip(cams, images)]).mean())

    # no colours: features start at 0; a short run needs larger steps than the default schedule
    kw = dict(feat_dim=8, n_offsets=2, max_anchors=80, progress=False, seed=0, lr_scale=4.0)
    before = l1(train_reference_model(images, cams, pts, iterations=0, **kw))
    after = l1(train_reference_model(images, cams, pts, iterations=25, **kw))
    assert after < 0.6 * before, (before, after)


def test_training_without_points_uses_a_grid_around_the_camera_target():
    images, cams, _, _ = _plane_scene(size=16)
    m = train_reference_model(images, cams, iterations=2, feat_dim=4, n_offsets=2, max_anchors=64, progress=False)
    assert 0 < m.num_anchors <= 64 and not m.training


def test_training_inputs_are_checked():
    images, cams, pts, _ = _plane_scene(size=16)
    with pytest.raises(InputValueError, match="one camera per image"):
        train_reference_model(images, cams[:1], pts, iterations=0, progress=False)
    with pytest.raises(ShapeError, match="images"):
        train_reference_model(images[:, :2], cams, pts, iterations=0, progress=False)
