"""Tests of ``controlgs_adapter.backends.models.train_backbone``."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers.scaffold_oracle import camera_looking_down_z

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.models.train_backbone import _lr_at, camera_target, grid_points, train_reference_model
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import Camera


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


def test_grid_points_fill_the_box_evenly():
    pts = grid_points(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), 200)
    spacing = (2.0 / 200) ** (1 / 3)
    assert abs(pts.shape[0] - 200) < 80
    assert bool((pts >= 0).all()) and bool((pts[:, 0] <= 2).all()) and bool((pts[:, 1:] <= 1).all())
    assert pts.shape[0] == len(torch.unique(pts, dim=0))
    assert float(pts[:, 0].min()) == pytest.approx(float(2.0 - pts[:, 0].max()), abs=1e-6)
    assert float(pts[:, 0].min()) < spacing


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


def test_backbone_learning_rate_is_log_linear_from_init_to_final():
    from controlgs_adapter.backends.models.train_backbone import _lr_at

    assert _lr_at(1e-2, 1e-4, 0.0) == pytest.approx(1e-2, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 1.0) == pytest.approx(1e-4, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 0.5) == pytest.approx(1e-3, rel=1e-12)  # geometric mean
    assert _lr_at(1e-2, 1e-4, 0.25) == pytest.approx(1e-2 * 10 ** -0.5, rel=1e-12)
    assert _lr_at(0.4, 0.0, 0.75) == pytest.approx(0.1, rel=1e-12)  # final 0: linear decay


def test_lr_schedule_is_log_linear():
    # by hand: halfway between 1e-2 and 1e-4 in log space is 1e-3; t = 0 and 1 give the ends; final 0 -> linear
    assert _lr_at(1e-2, 1e-4, 0.5) == pytest.approx(1e-3, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 0.0) == pytest.approx(1e-2, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 1.0) == pytest.approx(1e-4, rel=1e-12)
    assert _lr_at(0.4, 0.0, 0.25) == pytest.approx(0.3, rel=1e-12)


def _look_at(eye: tuple[float, float, float], size: int = 12) -> Camera:
    """A pinhole camera at ``eye`` looking at the origin (OpenCV axes: x right, y down, z forward)."""
    c = torch.tensor(eye, dtype=torch.float32)
    z = -c / c.norm()
    up = torch.tensor([0.0, 1.0, 0.0]) if abs(float(z[1])) < 0.9 else torch.tensor([1.0, 0.0, 0.0])
    x = torch.linalg.cross(up, z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    r = torch.stack([x, y, z])
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = r, -(r @ c)
    k = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, size, size)


def test_reference_trainer_follows_its_seed_not_the_global_generator():
    """Two fits with the same ``seed`` are the same model to the bit, whatever the global generator
    holds (the view order of every epoch is drawn from the seeded generator), and the global generator is
    left as it was."""
    cams = [_look_at((0.0, 0.0, -3.0)), _look_at((3.0, 0.0, 0.0)), _look_at((0.0, -3.0, 0.5))]
    g = torch.Generator().manual_seed(0)
    images = torch.rand(3, 3, 12, 12, generator=g)
    pts = torch.rand(30, 3, generator=g) - 0.5
    kw = dict(iterations=9, feat_dim=4, n_offsets=2, max_anchors=12, progress=False, seed=5)
    fits = []
    for global_seed in (1, 2):
        torch.manual_seed(global_seed)
        before = torch.get_rng_state()
        fits.append(dict(train_reference_model(images, cams, pts, **kw).state_dict()))
        assert torch.equal(torch.get_rng_state(), before)  # the caller's generator is left as it was
    a, b = fits
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


# ------------------------------------------------------------------------------ reference trainer seed
def test_train_reference_model_default_seed_is_documented_and_is_seed_0():
    """Without ``seed`` the fit is the ``seed=0`` fit to the bit (the documented default), and not the
    ``seed=1`` fit."""
    from controlgs_adapter.backends.models.train_backbone import train_reference_model

    assert "default 0" in (train_reference_model.__doc__ or "")
    cams = []
    for eye, r in (((0.0, 0.0, -3.0), torch.eye(3)),
                   ((3.0, 0.0, 0.0), torch.tensor([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]))):
        w2c = torch.eye(4)
        w2c[:3, :3], w2c[:3, 3] = r, -(r @ torch.tensor(eye))
        cams.append(Camera(w2c, torch.tensor([[12.0, 0.0, 6.0], [0.0, 12.0, 6.0], [0.0, 0.0, 1.0]]), 12, 12))
    g = torch.Generator().manual_seed(3)
    images = torch.rand(2, 3, 12, 12, generator=g)
    pts = torch.rand(20, 3, generator=g) - 0.5
    kw = dict(iterations=3, feat_dim=4, n_offsets=2, max_anchors=10, progress=False)
    fits = [dict(train_reference_model(images, cams, pts, **kw, **extra).state_dict())
            for extra in ({}, {"seed": 0}, {"seed": 1})]
    default, zero, one = fits
    assert default.keys() == zero.keys() == one.keys()
    assert all(torch.equal(default[k], zero[k]) for k in default)
    assert not all(torch.equal(default[k], one[k]) for k in default)


def _look_at_2(eye, target=(0.0, 0.0, 0.0), size=12, f=12.0) -> Camera:
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
    cams = [_look_at_2((0.0, 0.0, -3.0)), _look_at_2((3.0, 0.0, 0.0)), _look_at_2((0.0, -3.0, 0.5))]
    g = torch.Generator().manual_seed(0)
    images = torch.rand(3, 3, 12, 12, generator=g)
    pts = torch.rand(30, 3, generator=g) - 0.5
    return images, cams, pts


def _delta(a: torch.nn.Module, b: torch.nn.Module, name: str) -> float:
    pa, pb = dict(a.named_parameters()), dict(b.named_parameters())
    keys = [k for k in pa if k == name or k.startswith(name + ".")]
    assert keys, name
    return max(float((pa[k] - pb[k]).detach().abs().max()) for k in keys)


def test_camera_target_is_where_the_optical_axes_cross():
    # optical axes: x = 1, y = 2 (looking along +z); y = 2, z = 0 (along -x); x = 1, z = 0.5 (along -y). The
    # sum of squared distances (x-1)^2 + (y-2)^2 + (y-2)^2 + z^2 + (x-1)^2 + (z-0.5)^2 is least at (1, 2, 0.25)
    cams = [_look_at_2((1.0, 2.0, -5.0), (1.0, 2.0, 0.0)), _look_at_2((6.0, 2.0, 0.0), (1.0, 2.0, 0.0)),
            _look_at_2((1.0, 9.0, 0.5), (1.0, 2.0, 0.5))]
    assert torch.allclose(camera_target(cams), torch.tensor([1.0, 2.0, 0.25]), atol=1e-5)
    # parallel axes: one unit in front of the first camera
    par = [camera_looking_down_z(center=(0.0, 0.0, 0.0)), camera_looking_down_z(center=(1.0, 0.0, 0.0))]
    assert torch.allclose(camera_target(par), torch.tensor([0.0, 0.0, 1.0]))
    assert torch.allclose(camera_target(par[:1]), torch.tensor([0.0, 0.0, 1.0]))


def test_grid_points_by_hand_and_refusals():
    # box 2 x 1 x 1, 2 points: spacing (2 / 2)^(1/3) = 1 -> 2 x 1 x 1 cells, centres at x = 0.5, 1.5
    pts = grid_points(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), 2)
    assert pts.tolist() == [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]]
    for bounds, count in (([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0]], 5), ([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], 0)):
        with pytest.raises(InputValueError, match="bounds must have max > min on every axis and count >= 1"):
            grid_points(torch.tensor(bounds), count)


def test_trainer_refusals():
    images, cams, pts = _tiny_scene()
    with pytest.raises(InputValueError, match=r"images must be \[V, 3, H, W\], got \[3, 12, 12\]"):
        train_reference_model(images[0], cams[:1], pts, iterations=0, progress=False)
    bad = Camera(cams[1].world_to_camera, cams[1].intrinsics, 12, 6)
    with pytest.raises(InputValueError, match=r"cameras\[1\] is 12x6, images are 12x12"):
        train_reference_model(images, [cams[0], bad, cams[2]], pts, iterations=0, progress=False)
    for it, mx in ((-1, 10), (0, 0)):
        with pytest.raises(InputValueError, match=f"need iterations >= 0 and max_anchors >= 1, got {it}, {mx}"):
            train_reference_model(images, cams, pts, iterations=it, max_anchors=mx, progress=False)


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


def test_trainer_defaults_without_points():
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


def test_learning_rate_schedule_is_log_linear():
    from controlgs_adapter.backends.models.train_backbone import _lr_at

    # exp((1 - t) log a + t log b): the geometric mean at t = 0.5; the ends exactly; final 0: linear decay
    assert _lr_at(1e-2, 1e-4, 0.0) == pytest.approx(1e-2) and _lr_at(1e-2, 1e-4, 1.0) == pytest.approx(1e-4)
    assert _lr_at(1e-2, 1e-4, 0.5) == pytest.approx(1e-3)
    assert _lr_at(1e-2, 1e-4, 0.25) == pytest.approx(1e-2 ** 0.75 * 1e-4 ** 0.25)
    assert _lr_at(0.01, 0.0, 0.25) == pytest.approx(0.0075) and _lr_at(0.01, 0.0, 1.0) == 0.0


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


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
