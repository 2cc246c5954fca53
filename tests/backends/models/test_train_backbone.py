"""Fitting the reference model to images (``backends.models.train_backbone``): Scaffold-GS's learning rates
and their schedule, anchors from points or a grid around where the cameras look, the seed, the loss going
down, and every refusal of its inputs."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.scaffold_oracle import camera_looking_down_z

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.models.train_backbone import (
    _lr_at,
    _param_groups,
    camera_target,
    grid_points,
    train_reference_model,
)
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import Camera

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _look_at(eye, target=(0.0, 0.0, 0.0), size=12, f=12.0) -> Camera:
    """OpenCV world-to-camera looking from ``eye`` at ``target`` (independent of the library's helpers)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.stack([x, y, z])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = r, -r @ eye
    k = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.from_numpy(w2c).float(), k, size, size)


def _tiny_scene():
    """Three 12 x 12 random images seen from three sides of the origin, 30 points about it."""
    cams = [_look_at((0.0, 0.0, -3.0)), _look_at((3.0, 0.0, 0.0)), _look_at((0.0, -3.0, 0.5))]
    g = torch.Generator().manual_seed(0)
    images = torch.rand(3, 3, 12, 12, generator=g)
    pts = torch.rand(30, 3, generator=g) - 0.5
    return images, cams, pts


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


def _delta(a: torch.nn.Module, b: torch.nn.Module, name: str) -> float:
    pa, pb = dict(a.named_parameters()), dict(b.named_parameters())
    keys = [k for k in pa if k == name or k.startswith(name + ".")]
    assert keys, name
    return max(float((pa[k] - pb[k]).detach().abs().max()) for k in keys)


# ----------------------------------------------------------------------------------- learning rates
@pytest.mark.parametrize("bank, appearance", [(False, 0), (True, 4)])
def test_param_groups_have_scaffold_gs_learning_rates(bank, appearance):
    model = NeuralGaussianModel(3, feat_dim=8, n_offsets=2, use_feat_bank=bank, appearance_dim=appearance, num_cameras=2)
    groups = _param_groups(model, 2.5)
    # Scaffold-GS arguments/__init__.py OptimizationParams: (lr_init, lr_final); the offsets' rates x extent
    want = {"offset": (0.01 * 2.5, 0.0001 * 2.5), "feature": (0.0075, 0.0075), "scaling": (0.007, 0.007),
            "mlp_opacity": (0.002, 0.00002), "mlp_cov": (0.004, 0.004), "mlp_color": (0.008, 0.00005)}
    if bank:
        want["mlp_featurebank"] = (0.01, 0.00001)
    if appearance:
        want["appearance"] = (0.05, 0.0005)
    assert [n for n, *_ in groups] == list(want)
    for name, _, lr0, lr1 in groups:
        assert (lr0, lr1) == pytest.approx(want[name], rel=1e-12), name
    # every trainable tensor sits in exactly one group
    ids = [id(p) for _, ps, _, _ in groups for p in ps]
    assert len(ids) == len(set(ids))
    assert sorted(n for n, p in model.named_parameters() if id(p) not in ids) == ["_anchor", "_opacity", "_rotation"]


def test_learning_rate_schedule_is_log_linear():
    # exp((1 - t) log a + t log b): the ends exactly, the geometric mean at t = 0.5; final 0: linear decay
    assert _lr_at(1e-2, 1e-4, 0.0) == pytest.approx(1e-2, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 1.0) == pytest.approx(1e-4, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 0.5) == pytest.approx(1e-3, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 0.25) == pytest.approx(1e-2 ** 0.75 * 1e-4 ** 0.25, rel=1e-12)
    assert _lr_at(0.4, 0.0, 0.25) == pytest.approx(0.3, rel=1e-12)
    assert _lr_at(0.4, 0.0, 0.75) == pytest.approx(0.1, rel=1e-12)
    assert _lr_at(0.01, 0.0, 1.0) == 0.0


def test_first_adam_step_moves_each_group_by_its_scaffold_gs_learning_rate():
    # Adam's first step moves every parameter with a non-zero gradient by exactly lr (m / sqrt(v) = sign(g),
    # eps 1e-15); the first of N steps uses each group's initial rate (Scaffold-GS OptimizationParams)
    images, cams, pts = _tiny_scene()
    kw = dict(feat_dim=4, n_offsets=2, max_anchors=12, progress=False, seed=3, use_feat_bank=True, appearance_dim=2)
    cols = torch.rand(pts.shape[0], 3, generator=torch.Generator().manual_seed(1))  # non-zero features
    m0 = train_reference_model(images, cams, pts, cols, iterations=0, **kw)
    m1 = train_reference_model(images, cams, pts, cols, iterations=1, **kw)
    assert (m1.feat_dim, m1.n_offsets, m1.use_feat_bank, m1.appearance_dim) == (4, 2, True, 2)
    centres = torch.stack([c.center for c in cams]).double()
    extent = 1.1 * float((centres - centres.mean(0)).norm(dim=1).max())  # 3DGS's cameras_extent
    want = {"_offset": 0.01 * extent, "_anchor_feat": 0.0075, "_scaling": 0.007, "mlp_opacity": 0.002, "mlp_cov": 0.004,
            "mlp_color": 0.008, "mlp_feature_bank": 0.01, "embedding_appearance": 0.05}
    for name, lr in want.items():
        assert _delta(m1, m0, name) == pytest.approx(lr, rel=1e-3), name
    assert _delta(m1, m0, "_anchor") == 0.0  # anchor positions are not trained (position_lr_init = 0)
    m2 = train_reference_model(images, cams, pts, cols, iterations=1, lr_scale=2.0, **kw)
    assert _delta(m2, m0, "mlp_cov") == pytest.approx(0.008, rel=1e-3)  # every rate times lr_scale


# ------------------------------------------------------------------------------------------ anchors
def test_camera_target_is_where_the_optical_axes_cross():
    # optical axes: x = 1, y = 2 (looking along +z); y = 2, z = 0 (along -x); x = 1, z = 0.5 (along -y). The
    # sum of squared distances (x-1)^2 + (y-2)^2 + (y-2)^2 + z^2 + (x-1)^2 + (z-0.5)^2 is least at (1, 2, 0.25)
    cams = [_look_at((1.0, 2.0, -5.0), (1.0, 2.0, 0.0)), _look_at((6.0, 2.0, 0.0), (1.0, 2.0, 0.0)),
            _look_at((1.0, 9.0, 0.5), (1.0, 2.0, 0.5))]
    assert torch.allclose(camera_target(cams), torch.tensor([1.0, 2.0, 0.25]), atol=1e-5)
    # parallel axes: one unit in front of the first camera
    par = [camera_looking_down_z(center=(0.0, 0.0, 0.0)), camera_looking_down_z(center=(1.0, 0.0, 0.0))]
    assert torch.allclose(camera_target(par), torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(camera_target(par[:1]), torch.tensor([0.0, 0.0, 1.0]))


def test_grid_points_fill_the_box_evenly_and_refuse_an_empty_box():
    # box 2 x 1 x 1, 2 points: spacing (2 / 2)^(1/3) = 1 -> 2 x 1 x 1 cells, centres at x = 0.5, 1.5
    pts = grid_points(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), 2)
    assert pts.tolist() == [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]]
    pts = grid_points(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), 200)
    spacing = (2.0 / 200) ** (1 / 3)
    assert abs(pts.shape[0] - 200) < 80
    assert bool((pts >= 0).all()) and bool((pts[:, 0] <= 2).all()) and bool((pts[:, 1:] <= 1).all())
    assert pts.shape[0] == len(torch.unique(pts, dim=0))
    assert float(pts[:, 0].min()) == pytest.approx(float(2.0 - pts[:, 0].max()), abs=1e-6)  # centred in the box
    assert float(pts[:, 0].min()) < spacing
    for bounds, count in (([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0]], 5), ([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], 0)):
        with pytest.raises(InputValueError, match="bounds must have max > min on every axis and count >= 1"):
            grid_points(torch.tensor(bounds), count)


def test_without_points_the_anchors_are_a_grid_around_the_camera_target():
    images, cams, _ = _tiny_scene()
    m = train_reference_model(images, cams, iterations=0, progress=False)
    # defaults: feat_dim 32, n_offsets 5, at most 3000 anchors from a grid of 3000 points around camera_target
    assert (m.feat_dim, m.n_offsets) == (32, 5) and not m.training
    # the three optical axes cross at the origin and the median camera distance is 3 (3, 3, 3.04): the box
    # is the origin +- 0.5 * 3. 3000 points in a 3 x 3 x 3 box: spacing (27 / 3000)^(1/3) = 0.208 ->
    # round(3 / 0.208) = 14 per axis, 14^3 = 2744 <= 3000 anchors at the grid's spacing 3 / 14, which snaps
    # the outermost centres (+-1.393) to +-7 * 3 / 14 = +-1.5
    assert m.num_anchors == 2744 and m.voxel_size == pytest.approx(3 / 14, rel=1e-5)
    assert torch.allclose(m._anchor.detach().abs().amax(0), torch.full((3,), 1.5), atol=1e-5)
    small = train_reference_model(images, cams, iterations=0, feat_dim=4, n_offsets=2, max_anchors=64, progress=False)
    assert 0 < small.num_anchors <= 64


def test_offset_jitter_depends_on_the_seed_only_and_spans_the_voxel():
    """The K offsets of each anchor start uniform over its voxel, [-0.5, 0.5) in voxel units, drawn from
    the seed alone: the same with model options that draw other random numbers before them (a feature
    bank, appearance codes), different with another seed."""
    images, cams, pts = _tiny_scene()
    kw = dict(feat_dim=4, n_offsets=8, max_anchors=30, iterations=0, progress=False)
    plain = train_reference_model(images, cams, pts, seed=5, **kw)._offset.detach()
    extra = train_reference_model(images, cams, pts, seed=5, use_feat_bank=True, appearance_dim=3, **kw)._offset.detach()
    other = train_reference_model(images, cams, pts, seed=6, **kw)._offset.detach()
    assert torch.equal(plain, extra) and not torch.equal(plain, other)
    assert float(plain.min()) >= -0.5 and float(plain.max()) < 0.5
    assert float(plain.min()) < -0.45 and float(plain.max()) > 0.45 and abs(float(plain.mean())) < 0.05


# ------------------------------------------------------------------------------------------ fitting
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


def test_the_fit_follows_its_seed_default_0_not_the_global_generator():
    """Two fits with the same ``seed`` are the same model to the bit, whatever the global generator holds
    (the view order of every epoch is drawn from the seeded generator), and the global generator is left as
    it was; without ``seed`` the fit is the ``seed=0`` fit, not the ``seed=1`` one."""
    images, cams, pts = _tiny_scene()
    kw = dict(feat_dim=4, n_offsets=2, max_anchors=12, progress=False)
    fits = []
    for global_seed in (1, 2):
        torch.manual_seed(global_seed)
        before = torch.get_rng_state()
        fits.append(dict(train_reference_model(images, cams, pts, iterations=9, seed=5, **kw).state_dict()))
        assert torch.equal(torch.get_rng_state(), before)  # the caller's generator is left as it was
    a, b = fits
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    default, zero, one = (dict(train_reference_model(images[:2], cams[:2], pts[:20], iterations=3, **kw, **extra).state_dict())
                          for extra in ({}, {"seed": 0}, {"seed": 1}))
    assert default.keys() == zero.keys() == one.keys()
    assert all(torch.equal(default[k], zero[k]) for k in default)
    assert not all(torch.equal(default[k], one[k]) for k in default)


def test_fit_refusals_name_the_input():
    images, cams, pts = _tiny_scene()
    with pytest.raises(InputValueError, match=r"images must be \[V, 3, H, W\], got \[3, 12, 12\]"):
        train_reference_model(images[0], cams[:1], pts, iterations=0, progress=False)
    with pytest.raises(ShapeError, match="images"):
        train_reference_model(images[:, :2], cams, pts, iterations=0, progress=False)
    with pytest.raises(InputValueError, match="one camera per image"):
        train_reference_model(images, cams[:1], pts, iterations=0, progress=False)
    bad = Camera(cams[1].world_to_camera, cams[1].intrinsics, 12, 6)
    with pytest.raises(InputValueError, match=r"cameras\[1\] is 12x6, images are 12x12"):
        train_reference_model(images, [cams[0], bad, cams[2]], pts, iterations=0, progress=False)
    for it, mx in ((-1, 10), (0, 0)):
        with pytest.raises(InputValueError, match=f"need iterations >= 0 and max_anchors >= 1, got {it}, {mx}"):
            train_reference_model(images, cams, pts, iterations=it, max_anchors=mx, progress=False)
