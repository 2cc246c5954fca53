"""Sweep 2 (files area): behaviours the large mutation sweep found untested in backends/ and
controlgs_adapter/datasets|scene -- a CompGS model is frozen, the anchors' initial scales for tiny
anchor counts, the k-NN helper's dtype, the backbone trainer's documented learning rates,
``load_dataset``'s black default background, the Newton step of ``undistort_points`` and
``build.json`` written for people to read."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from _datasets_synth import ring_poses, write_json, write_png
from controlgs_adapter.backends.compgs import CompGSModel
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel, _knn_sq_dists
from controlgs_adapter.backends.models.train_backbone import _lr_at, _param_groups
from controlgs_adapter.datasets import load_dataset
from controlgs_adapter.datasets.images import distort_normalized, undistort_points


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


def test_lr_schedule_is_log_linear():
    # by hand: halfway between 1e-2 and 1e-4 in log space is 1e-3; t = 0 and 1 give the ends; final 0 -> linear
    assert _lr_at(1e-2, 1e-4, 0.5) == pytest.approx(1e-3, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 0.0) == pytest.approx(1e-2, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 1.0) == pytest.approx(1e-4, rel=1e-12)
    assert _lr_at(0.4, 0.0, 0.25) == pytest.approx(0.3, rel=1e-12)


# --------------------------------------------------------------------------- load_dataset default background
@pytest.mark.parametrize("kwargs, bg", [({}, 0.0), ({"white_background": True}, 1.0),
                                        ({"white_background": False}, 0.0)])
def test_load_dataset_composites_rgba_over_black_by_default(tmp_path, kwargs, bg):
    px = np.zeros((6, 8, 4), dtype=np.uint8)
    px[..., :3] = 200
    px[:3, :, 3] = 0      # top half transparent: shows the background
    px[3:, :, 3] = 255    # bottom half opaque: 200 / 255
    write_png(tmp_path / "train" / "r_0.png", px)
    write_json(tmp_path / "transforms_train.json",
               {"camera_angle_x": 0.8, "frames": [{"file_path": "train/r_0", "transform_matrix": ring_poses(1)[0].tolist()}]})
    image = load_dataset(tmp_path, **kwargs).views("train").image(0)
    torch.testing.assert_close(image[:, :3], torch.full((3, 3, 8), bg), rtol=0, atol=1e-6)
    torch.testing.assert_close(image[:, 3:], torch.full((3, 3, 8), 200 / 255), rtol=0, atol=1e-6)


# --------------------------------------------------------------------------- undistort_points
_K = torch.tensor([[300.0, 0, 160], [0, 280.0, 120], [0, 0, 1]], dtype=torch.float64)
_DIST = (-0.21, 0.05, 0.003, -0.002, 0.04)  # k3 != 0


def _newton_reference(uv: torch.Tensor, dist, steps: int) -> torch.Tensor:
    """Newton's method on distort_normalized(xy) = target with the Jacobian from autograd (float64)."""
    fx, fy, cx, cy = _K[0, 0], _K[1, 1], _K[0, 2], _K[1, 2]
    out = []
    for row in uv.double():
        target = torch.stack([(row[0] - cx) / fx, (row[1] - cy) / fy])
        xy = target.clone()
        for _ in range(steps):
            jac = torch.autograd.functional.jacobian(lambda v: distort_normalized(v, dist), xy)
            xy = xy - torch.linalg.solve(jac, distort_normalized(xy, dist) - target)
        out.append(torch.stack([fx * xy[0] + cx, fy * xy[1] + cy]))
    return torch.stack(out)


@pytest.mark.parametrize("steps", [1, 2])
def test_undistort_points_newton_steps_use_the_exact_jacobian(steps):
    uv = torch.tensor([[5.0, 7.0], [310.0, 20.0], [160.0, 230.0], [40.0, 200.0], [290.0, 215.0]], dtype=torch.float64)
    got = undistort_points(uv, _K, _DIST, iterations=steps)
    want = _newton_reference(uv, _DIST, steps)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-9)
    assert not torch.allclose(got, uv, atol=1e-3)  # the steps moved the points


def test_undistort_points_with_k3_inverts_opencv_projection():
    cv2 = pytest.importorskip("cv2")
    # ground truth: undistorted pixels -> OpenCV projectPoints with distortion -> undistort_points back
    truth = torch.tensor([[10.0, 15.0], [300.0, 25.0], [150.0, 110.0], [30.0, 225.0], [305.0, 230.0]], dtype=torch.float64)
    fx, fy, cx, cy = 300.0, 280.0, 160.0, 120.0
    obj = np.stack([(truth[:, 0].numpy() - cx) / fx, (truth[:, 1].numpy() - cy) / fy, np.ones(5)], axis=1)
    distorted, _ = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), _K.numpy(), np.array(_DIST))
    uv = torch.from_numpy(distorted.reshape(-1, 2))
    torch.testing.assert_close(undistort_points(uv, _K, _DIST), truth, rtol=0, atol=1e-7)
    # and against OpenCV's own inverse (its iterative solver, many iterations)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    cv_back = cv2.undistortPoints(distorted, _K.numpy(), np.array(_DIST), R=None, P=_K.numpy(), criteria=crit).reshape(-1, 2)
    np.testing.assert_allclose(undistort_points(uv, _K, _DIST).numpy(), cv_back, atol=1e-5)
    assert undistort_points(uv.float(), _K, _DIST).dtype == torch.float32


# --------------------------------------------------------------------------- build.json is indented
def test_build_builtin_backbone_writes_indented_json(tmp_path, monkeypatch):
    from controlgs_adapter.scene import build_builtin_backbone

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = build_builtin_backbone("ar", out=tmp_path / "bb", resolution=16, iterations=1, max_anchors=20, n_offsets=2,
                                 feat_dim=4, point_spacing=0.4, seed=0, progress=False)
    text = (out / "build.json").read_text()
    info = json.loads(text)
    assert text == json.dumps(info, indent=1)  # one key per line, one space of indent: meant to be read
    assert text.splitlines()[1].startswith(' "variant": "ar"')



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


def test_as_param_default_frozen_float32():
    from controlgs_adapter.backends.models.anchor_model import as_param

    p = as_param(np.arange(3, dtype=np.float64))
    assert p.dtype == torch.float32 and p.requires_grad is False and p.tolist() == [0.0, 1.0, 2.0]
    assert as_param(np.zeros(2), requires_grad=True).requires_grad is True
    src = torch.ones(2)
    q = as_param(src)
    src[0] = 5.0
    assert q.tolist() == [1.0, 1.0]  # a copy


def _octree(seed: int):
    from torch import nn

    from controlgs_adapter.backends.octree_gs import OctreeGSModel

    rng = np.random.default_rng(seed)
    a, k, f = 40, 2, 8
    arr = {"anchor": rng.normal(size=(a, 3)), "level": rng.integers(0, 4, a), "extra": rng.uniform(-0.4, 0.4, a)}
    torch.manual_seed(seed)
    model = OctreeGSModel(  # fork, levels, dist2level, voxel_centre left at their defaults
        anchor=torch.tensor(arr["anchor"], dtype=torch.float32), offset=torch.zeros(a, k, 3),
        anchor_feat=torch.zeros(a, f), scaling=torch.full((a, 6), -2.0), level=torch.tensor(arr["level"])[:, None],
        extra_level=torch.tensor(arr["extra"], dtype=torch.float32),
        mlp_opacity=nn.Sequential(nn.Linear(f + 3, k), nn.Tanh()), mlp_cov=nn.Sequential(nn.Linear(f + 3, 7 * k)),
        mlp_color=nn.Sequential(nn.Linear(f + 3, 3 * k), nn.Sigmoid()), voxel_size=0.1, standard_dist=3.0)
    return model, arr


def _lod_reference(arr, cam: np.ndarray, scale: float) -> list[bool]:
    """Octree-GS set_anchor_mask in float64 with fork 2, 'round', voxel centres, levels = 0..max level."""
    levels = int(arr["level"].max()) + 1
    out = []
    for pos, lv, extra in zip(arr["anchor"], arr["level"], arr["extra"]):
        centre = pos.astype(np.float64) + (0.1 / 2) / 2 ** int(lv)
        d = float(np.linalg.norm(centre - cam)) * scale
        pred = math.log2(3.0 / d) / math.log2(2) + float(np.float32(extra))
        out.append(int(lv) <= min(max(int(np.round(pred)), 0), levels - 1))
    return out


def test_octree_lod_defaults_fork_2_round_voxel_centre_and_resolution_scale_1():
    model, arr = _octree(4)
    cam = np.array([0.2, -0.1, 3.0])
    model.set_anchor_mask(torch.tensor(cam, dtype=torch.float32))  # iteration, resolution_scale defaults
    want = _lod_reference(arr, cam, 1.0)
    assert model._anchor_mask.tolist() == want and 0 < sum(want) < len(want)
    want2 = _lod_reference(arr, cam, 0.25)
    assert want2 != want  # resolution_scale matters for this view
    model.set_anchor_mask(torch.tensor(cam, dtype=torch.float32), -1, 0.25)
    assert model._anchor_mask.tolist() == want2


def test_save_scaffold_dir_default_mlp_mode_is_split(tmp_path):
    from controlgs_adapter.backends.scaffold_io import save_scaffold_dir

    model = NeuralGaussianModel(3, feat_dim=8, n_offsets=2)
    folder = save_scaffold_dir(model, tmp_path / "a", 10)
    assert folder == tmp_path / "a" / "point_cloud" / "iteration_10"
    # Scaffold-GS's save_mlp_checkpoints(mode="split"): one TorchScript file per decoder next to the PLY
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["color_mlp.pt", "cov_mlp.pt", "opacity_mlp.pt", "point_cloud.ply"]
    unite = save_scaffold_dir(model, tmp_path / "b", 10, mlp_mode="unite")
    assert sorted(p.name for p in unite.iterdir()) == ["checkpoints.pth", "point_cloud.ply"]


def test_build_builtin_backbone_cheap_defaults_recorded(tmp_path, monkeypatch, capfd):
    from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
    from controlgs_adapter.scene import build_builtin_backbone

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    # resolution / iterations / max_anchors are cut down; variant, n_offsets, feat_dim, point_spacing, seed and
    # progress keep their documented defaults ("ar", 5, 32, 0.04, 0, a progress bar)
    out = build_builtin_backbone(out=tmp_path / "bb", resolution=16, iterations=1, max_anchors=20)
    info = json.loads((out / "build.json").read_text())
    assert {k: info[k] for k in ("variant", "n_offsets", "feat_dim", "point_spacing", "seed")} == \
        {"variant": "ar", "n_offsets": 5, "feat_dim": 32, "point_spacing": 0.04, "seed": 0}
    model = load_scaffold_dir(out)
    assert (model.n_offsets, model.feat_dim) == (5, 32)
    assert "training backbone" in capfd.readouterr().err  # the tqdm bar is on by default
