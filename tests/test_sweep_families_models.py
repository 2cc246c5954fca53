"""The reference Scaffold-GS model, its small trainer and the Scaffold-GS folder reader/writer: defaults,
refusals and option branches no other test reaches, pinned against Scaffold-GS's published defaults
(/work/shared/notes/backbones.md) or values worked out by hand (how is said next to each literal)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, _knn_sq_dists, median_spacing
from controlgs_adapter.backends.models.train_backbone import camera_target, grid_points, train_reference_model
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir, save_scaffold_dir
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError
from controlgs_adapter.state import Camera
from scaffold_oracle import camera_looking_down_z, make_raw_model, write_scaffold_dir_by_hand

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace: the format under test


# ---------------------------------------------------------------- reference model

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


# ---------------------------------------------------------------- trainer

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


def test_grid_points_by_hand_and_refusals():
    # box 2 x 1 x 1, 2 points: spacing (2 / 2)^(1/3) = 1 -> 2 x 1 x 1 cells, centres at x = 0.5, 1.5
    pts = grid_points(torch.tensor([[0.0, 0.0, 0.0], [2.0, 1.0, 1.0]]), 2)
    assert pts.tolist() == [[0.5, 0.5, 0.5], [1.5, 0.5, 0.5]]
    for bounds, count in (([[0.0, 0.0, 0.0], [1.0, 0.0, 1.0]], 5), ([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], 0)):
        with pytest.raises(InputValueError, match="bounds must have max > min on every axis and count >= 1"):
            grid_points(torch.tensor(bounds), count)


def _tiny_scene():
    cams = [_look_at((0.0, 0.0, -3.0)), _look_at((3.0, 0.0, 0.0)), _look_at((0.0, -3.0, 0.5))]
    g = torch.Generator().manual_seed(0)
    images = torch.rand(3, 3, 12, 12, generator=g)
    pts = torch.rand(30, 3, generator=g) - 0.5
    return images, cams, pts


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


def _delta(a: torch.nn.Module, b: torch.nn.Module, name: str) -> float:
    pa, pb = dict(a.named_parameters()), dict(b.named_parameters())
    keys = [k for k in pa if k == name or k.startswith(name + ".")]
    assert keys, name
    return max(float((pa[k] - pb[k]).detach().abs().max()) for k in keys)


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


# ---------------------------------------------------------------- Scaffold-GS folders

def _model(seed: int = 0, **opts) -> NeuralGaussianModel:
    torch.manual_seed(seed)
    m = NeuralGaussianModel(6, feat_dim=8, n_offsets=3, **opts)
    with torch.no_grad():
        for p in (m._anchor, m._offset, m._anchor_feat, m._scaling):
            p.normal_()
    return m.eval()


def test_save_refusals_overwrite_and_cleanup(tmp_path):
    m = _model()
    with pytest.raises(InputValueError, match="mlp_mode must be 'split' or 'unite', got 'both'"):
        save_scaffold_dir(m, tmp_path / "a", 10, mlp_mode="both")
    with pytest.raises(InputValueError, match="iteration must be >= 0, got -1"):
        save_scaffold_dir(m, tmp_path / "a", -1)
    save_scaffold_dir(m, tmp_path / "a", 0)  # iteration 0 is allowed
    # writing the same iteration again replaces it, leaving no temporary folder behind
    m2 = _model(1)
    save_scaffold_dir(m2, tmp_path / "a", 0, mlp_mode="unite")
    assert sorted(p.name for p in (tmp_path / "a" / "point_cloud").iterdir()) == ["iteration_0"]
    back = load_scaffold_dir(tmp_path / "a")
    assert torch.equal(back._anchor_feat, m2._anchor_feat) and torch.equal(back.mlp_cov[2].weight, m2.mlp_cov[2].weight)

    class Broken(nn.Module):
        def forward(self, x):
            raise RuntimeError("cannot trace")

    m3 = _model(2)
    m3.mlp_cov = Broken()
    with pytest.raises(RuntimeError, match="cannot trace"):
        save_scaffold_dir(m3, tmp_path / "a", 5)
    assert sorted(p.name for p in (tmp_path / "a" / "point_cloud").iterdir()) == ["iteration_0"]


@pytest.mark.parametrize("mode", ["split", "unite"])
def test_feature_bank_and_appearance_round_trip(tmp_path, mode):
    m = _model(3, use_feat_bank=True, appearance_dim=2, num_cameras=4, add_cov_dist=True)
    save_scaffold_dir(m, tmp_path / mode, 100, mlp_mode=mode)
    back = load_scaffold_dir(tmp_path / mode)
    assert (back.use_feat_bank, back.appearance_dim, back.add_cov_dist, back.add_opacity_dist) == (True, 2, True, False)
    assert back.embedding_appearance.embedding.weight.shape == (4, 2)
    cam = camera_looking_down_z(center=(0.1, 0.2, -4.0))
    cam.extra["uid"] = 3
    a, b = m.decode(cam), back.decode(cam)
    assert torch.equal(a.anchor_of, b.anchor_of) and torch.allclose(a.colors, b.colors, atol=1e-6)


def _scaffold_folder(tmp_path, mode="unite"):
    raw = make_raw_model(5, 8, 2, seed=4)
    return write_scaffold_dir_by_hand(tmp_path / "s", raw, mode=mode), raw


def test_ply_refusals_name_the_field(tmp_path):
    from controlgs_adapter.formats.backbone import read_ply, write_ply

    folder, _ = _scaffold_folder(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {**fields, "opacity": np.arange(5, dtype=np.int32)})
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: PLY field 'opacity' must be float, got int32"):
        load_scaffold_dir(tmp_path / "s")
    write_ply(ply, {k: v for k, v in fields.items() if k != "f_offset_5"})
    with pytest.raises(FileFormatError, match=r"5 PLY fields f_offset_\* is not 3 x n_offsets"):
        load_scaffold_dir(tmp_path / "s")
    write_ply(ply, {**fields, "scale_6": fields["scale_0"]})
    with pytest.raises(FileFormatError, match=r"expected PLY fields scale_0..scale_5 and rot_0..rot_3, got 7 scale_\* "
                                              r"and 4 rot_\*"):
        load_scaffold_dir(tmp_path / "s")
    write_ply(ply, {**fields, "rot_4": fields["rot_0"]})
    with pytest.raises(FileFormatError, match=r"got 6 scale_\* and 5 rot_\*"):
        load_scaffold_dir(tmp_path / "s")


def test_decoder_state_refusals_name_the_decoder(tmp_path):
    folder, raw = _scaffold_folder(tmp_path)
    ck = folder / "checkpoints.pth"
    sd = torch.load(ck, weights_only=True)
    torch.save({**sd, "opacity_mlp": {**sd["opacity_mlp"], "0.weight": torch.zeros(11)}}, ck)
    with pytest.raises(FileFormatError, match=r"decoder 'mlp_opacity' layer 0 weight must be 2-D, got \[11\]"):
        load_scaffold_dir(tmp_path / "s")
    # widths right, but a bias of the wrong size: refused when the weights are loaded
    torch.save({**sd, "cov_mlp": {**sd["cov_mlp"], "0.bias": torch.zeros(9)}}, ck)
    with pytest.raises(FileFormatError, match=r"checkpoints.pth \['cov_mlp'\]: decoder 'mlp_cov' does not fit"):
        load_scaffold_dir(tmp_path / "s")
    torch.save(sd, ck)
    m = load_scaffold_dir(tmp_path / "s")
    assert torch.equal(m.mlp_color[0].bias, raw["mlp_color"][0].bias.detach())


class Sequential(nn.Sequential):  # a decoder outside the safe TorchScript subset (a class of its own), harmless
    @torch.jit.export
    def extra(self) -> int:
        return 1


def test_load_model_dir_passes_trust_code_to_the_scaffold_and_octree_loaders(tmp_path):
    import test_backend_octree_gs as octree_t
    from controlgs_adapter.backends import load_model_dir

    m = _model(6)
    folder = save_scaffold_dir(m, tmp_path / "s", 3)
    octree = octree_t._write_dir(tmp_path / "o", octree_t._arrays(1), octree_t._decoders(torch.Generator().manual_seed(1)))
    oct_folder = octree / "point_cloud" / "iteration_30000"
    for root, it, dec in ((tmp_path / "s", folder, m.mlp_opacity),
                          (octree, oct_folder, load_model_dir(octree).mlp_opacity)):
        odd = Sequential(*[layer for layer in dec])
        torch.jit.script(odd).save(str(it / "opacity_mlp.pt"))
        with pytest.raises(FileFormatError, match="opacity_mlp.pt"):
            load_model_dir(root)  # read as data by default: refused
        x = torch.randn(4, dec[0].in_features)
        trusted = load_model_dir(root, trust_code=True)
        assert torch.allclose(trusted.mlp_opacity(x), dec(x))


@pytest.mark.parametrize("given", [0.0, -1.0, None])
def test_scaffold_voxel_size_not_given_is_the_median_anchor_spacing(tmp_path, given):
    # Scaffold-GS estimates the voxel from the point cloud when the argument is <= 0; it is not saved
    raw = make_raw_model(9, 8, 2, seed=8)
    over = {"voxel_size": given} if given is not None else {}
    write_scaffold_dir_by_hand(tmp_path / "s", raw, cfg_overrides=over)
    if given is None:  # no key at all
        import re

        cfg = (tmp_path / "s" / "cfg_args").read_text()
        (tmp_path / "s" / "cfg_args").write_text(re.sub(r"voxel_size=[^,]*, ", "", cfg))
    m = load_scaffold_dir(tmp_path / "s")
    a = raw["anchor"].double().numpy()
    d = np.sqrt(((a[:, None] - a[None]) ** 2).sum(-1))
    np.fill_diagonal(d, np.inf)
    nn_dist = np.sort(d.min(1))
    assert m.voxel_size == pytest.approx(nn_dist[(len(nn_dist) - 1) // 2], rel=1e-6)  # torch's lower median
    write_scaffold_dir_by_hand(tmp_path / "t", raw, cfg_overrides={"voxel_size": 0.25})
    assert load_scaffold_dir(tmp_path / "t").voxel_size == 0.25


def test_saved_cfg_args_holds_scaffold_gs_model_params(tmp_path):
    """cfg_args as Scaffold-GS's train.py writes it: str(Namespace(**vars(args))) of its ModelParams
    (arguments/__init__.py: sh_degree 3, update_depth 3, update_init_factor 16, update_hierachy_factor 4,
    images 'images', resolution -1, white_background False, data_device 'cuda', eval True, lod 0) with the
    model's own widths and options."""
    import ast

    m = _model(9, use_feat_bank=True, appearance_dim=2, num_cameras=3, add_opacity_dist=True)
    save_scaffold_dir(m, tmp_path / "s", 1)
    text = (tmp_path / "s" / "cfg_args").read_text()
    assert text.startswith("Namespace(") and text.endswith(")")
    call = ast.parse(text, mode="eval").body
    cfg = {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords}
    want = {"sh_degree": 3, "feat_dim": 8, "n_offsets": 3, "voxel_size": 0.01, "update_depth": 3, "update_init_factor": 16,
            "update_hierachy_factor": 4, "use_feat_bank": True, "source_path": "", "model_path": str(tmp_path / "s"),
            "images": "images", "resolution": -1, "white_background": False, "data_device": "cuda", "eval": True,
            "lod": 0, "appearance_dim": 2, "add_opacity_dist": True, "add_cov_dist": False, "add_color_dist": False}
    assert {k: cfg[k] for k in want} == want
    back = load_scaffold_dir(tmp_path / "s")  # and the loader reads its options back from it
    assert (back.voxel_size, back.add_opacity_dist, back.appearance_dim) == (0.01, True, 2)


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
