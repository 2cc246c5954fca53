"""Pieces the sixth and seventh mutation samples found unpinned, each against a reference written here:
numbers computed but compared with nothing (ring all-reduce bytes, the backbone's learning-rate schedule,
ControlGS.summary's parameter counts), error and edge paths (a module named twice, checkpoint tensors of
another shape, an instant-ngp size that is not one scale, a HAC anchor with one offset on, HAC++'s extra
mask column, iteration folder names), non-square layouts (the sanity check, Camera.scaled), plug-in stage
placement, data-parallel shards and the built-in scene (split, trilinear mip lookup)."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from controlgs_adapter.errors import FileFormatError, InputValueError


@pytest.mark.parametrize("world", [1, 2, 3, 4, 8])
def test_all_reduce_bytes_is_the_ring_volume(world):
    """A ring all-reduce sends 2 (W - 1) / W of the buffer per process (reduce-scatter + all-gather)."""
    from controlgs_adapter.distributed import _all_reduce_bytes

    for nbytes in (0, 4, 4096, 123_456):
        assert _all_reduce_bytes(nbytes, world) == (2 * (world - 1) * nbytes) // world
    assert _all_reduce_bytes(1200, world) == {1: 0, 2: 1200, 3: 1600, 4: 1800, 8: 2100}[world]


def test_backbone_learning_rate_is_log_linear_from_init_to_final():
    from controlgs_adapter.backends.models.train_backbone import _lr_at

    assert _lr_at(1e-2, 1e-4, 0.0) == pytest.approx(1e-2, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 1.0) == pytest.approx(1e-4, rel=1e-12)
    assert _lr_at(1e-2, 1e-4, 0.5) == pytest.approx(1e-3, rel=1e-12)  # geometric mean
    assert _lr_at(1e-2, 1e-4, 0.25) == pytest.approx(1e-2 * 10 ** -0.5, rel=1e-12)
    assert _lr_at(0.4, 0.0, 0.75) == pytest.approx(0.1, rel=1e-12)  # final 0: linear decay


def test_hac_anchor_with_a_single_offset_on_is_valid_and_kept():
    from controlgs_adapter.backends.hac import HACBackend, HACModel, drop_invalid

    a, k, f = 4, 3, 8
    mask = torch.zeros(a, k + 1, 1)
    mask[0, :k] = 1.0   # every offset on
    mask[1, 2] = 1.0    # exactly one offset on
    mask[3, 0] = 1.0    # exactly one, the first
    torch.manual_seed(0)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, 7 * k)),
            "mlp_color": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid())}
    model = HACModel(anchor=torch.randn(a, 3), offset=torch.randn(a, k, 3), mask=mask, anchor_feat=torch.randn(a, f),
                     scaling=torch.rand(a, 6) * 0.1 + 0.01, decoded_version=True, voxel_size=0.01, **decs)
    want = [True, True, False, True]  # anchor 2 has no offset on
    assert model.get_mask_anchor.tolist() == want
    assert HACBackend().valid_anchors(model).tolist() == want
    assert drop_invalid(model).source_index.tolist() == [0, 1, 3]


def test_a_module_named_twice_is_refused():
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.controlgs import ControlGS

    model = NeuralGaussianModel(5, feat_dim=8, n_offsets=2)
    with pytest.raises(InputValueError, match=r"\['display'\] more than once"):
        ControlGS.wrap(model, modules=("display", "resample", "display"), cond_dim=2)
    cgs = ControlGS.wrap(model, modules=("display", "resample"), cond_dim=2)  # each once: accepted
    cgs.unwrap()


def test_checkpoint_with_adapter_tensors_of_another_shape_is_refused():
    from controlgs_adapter.formats.checkpoint import _split_tensors

    own = {"conditions": torch.zeros(5, 2, 4), "proj.display.weight": torch.zeros(8, 4)}
    good = {"adapter.conditions": torch.ones(5, 2, 4), "adapter.proj.display.weight": torch.ones(8, 4)}
    adapter, _ = _split_tensors("ck.safetensors", good, own, [torch.Size([5, 2, 4]), torch.Size([8, 4])])
    assert set(adapter) == set(own)
    bad = {**good, "adapter.proj.display.weight": torch.ones(8, 3)}
    with pytest.raises(FileFormatError, match=r"ck.safetensors.*mis-shaped: \['proj.display.weight'\]"):
        _split_tensors("ck.safetensors", bad, own, [torch.Size([5, 2, 4]), torch.Size([8, 4])])


def test_plugin_stage_after_an_absent_anchor_follows_the_last_stage_ordered_before_it():
    """A stage ``after="resample"`` in a pipeline without resampling goes after the last built-in whose
    registered order is at most resample's (20): foveation (5), lens (10), then it, then display (30)."""
    from controlgs_adapter.downstream.display import DisplayMapping
    from controlgs_adapter.downstream.foveation import Foveation
    from controlgs_adapter.downstream.lens import LensPrewarp
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.downstream.stage import Stage

    class After(Stage):
        name = "after_resample"
        domain = "srgb"
        after = "resample"

        def forward(self, image, state, ctx):
            return image

    p = Pipeline([DisplayMapping(), After(), LensPrewarp(), Foveation()])
    assert p.names == ["foveation", "lens", "after_resample", "display"]


def test_ngp_portrait_file_size_that_is_not_one_scale_is_refused(tmp_path):
    """transforms.json says 25 x 100, the image is 26 x 102: x scale 1.04, y scale 1.02 (refused);
    the same file with a 50 x 200 image is one scale (2) and loads with the intrinsics doubled."""
    import numpy as np

    from _datasets_synth import marker_image, ring_poses, write_json, write_png
    from controlgs_adapter.datasets import read_instant_ngp

    def scene(root, size):
        write_png(root / "images" / "a.png", marker_image(size[0], size[1], [], rgba=False))
        write_json(root / "transforms.json", {"fl_x": 20.0, "fl_y": 21.0, "cx": 12.0, "cy": 50.0, "w": 25.0, "h": 100.0,
                                              "frames": [{"file_path": "images/a.png",
                                                          "transform_matrix": ring_poses(1)[0].tolist()}]})

    scene(tmp_path / "bad", (26, 102))
    with pytest.raises(FileFormatError, match=r"25 x 100.*26 x 102"):
        read_instant_ngp(tmp_path / "bad", holdout=0)
    scene(tmp_path / "ok", (50, 200))
    cam = read_instant_ngp(tmp_path / "ok", holdout=0).splits["train"][0].camera
    np.testing.assert_allclose(cam.intrinsics.numpy(), [[40.0, 0.0, 24.0], [0.0, 42.0, 100.0], [0.0, 0.0, 1.0]])


def test_sanity_check_counts_points_in_a_wide_image_by_its_width():
    """An 80 x 40 camera; every point projects to u in [44, 76], v in [4, 36]: inside the image (u < W),
    though u > H. The scene is seen, nothing is blind."""
    from controlgs_adapter import Camera
    from controlgs_adapter.datasets.base import Frame, SceneData
    from controlgs_adapter.datasets.sanity import check_scene

    cam = Camera(torch.eye(4), torch.tensor([[40.0, 0.0, 40.0], [0.0, 40.0, 20.0], [0.0, 0.0, 1.0]]), 80, 40)
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(50, 2, generator=g) * torch.tensor([32.0, 32.0]) + torch.tensor([44.0, 4.0])
    pts = torch.cat([(uv - torch.tensor([40.0, 20.0])) / 40.0 * 3.0, torch.full((50, 1), 3.0)], dim=1)  # depth 3
    data = SceneData({"train": [Frame("a", cam, torch.zeros(3, 40, 80))]}, points=pts, source="synthetic", format="builtin")
    report = check_scene(data)
    assert report["in_front"] == {"a": 1.0} and report["blind"] == []


def test_texture_lookup_is_trilinear_between_floor_and_next_mip_level():
    """At lod 0.7 the lookup is 0.3 level 0 + 0.7 level 1. At plane coordinates (-0.5, -0.5) of a 4 x 4
    texture, level 0 (bilinear) is the mean of texels [0:2, 0:2] and level 1 (2 x 2) is its texel (0, 0)."""
    from controlgs_adapter.scene.planes import TexturedPlane

    g = torch.Generator().manual_seed(1)
    tex = torch.rand(3, 4, 4, generator=g, dtype=torch.float64)
    plane = TexturedPlane("p", torch.zeros(3), torch.tensor([1.0, 0, 0]), torch.tensor([0, 1.0, 0]), tex)
    a = torch.tensor([-0.5, 0.5], dtype=torch.float64)
    b = torch.tensor([-0.5, -0.5], dtype=torch.float64)
    lvl1 = plane.levels[1]
    assert lvl1.shape == (3, 2, 2)
    for lod in (0.0, 0.3, 0.7, 1.0):
        got = plane.sample(a, b, torch.full((2,), lod, dtype=torch.float64))
        want0 = torch.stack([tex[:, 0:2, 0:2].mean(dim=(1, 2)), tex[:, 0:2, 2:4].mean(dim=(1, 2))])
        want1 = torch.stack([lvl1[:, 0, 0], lvl1[:, 0, 1]])
        torch.testing.assert_close(got, (1 - lod) * want0 + lod * want1, rtol=1e-12, atol=1e-12)


def test_summary_parameter_counts_by_hand():
    """A = 7 anchors, 2 modules, N = 3: conditions 7 * 2 * 3 = 42; one FC1 width (D1 = F = 8) shared by
    the three decoders: projections 2 modules * 8 * 3 = 48; 90 in all (numbers shown to users)."""
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.controlgs import ControlGS

    cgs = ControlGS.wrap(NeuralGaussianModel(7, feat_dim=8, n_offsets=2), modules=("display", "resample"), cond_dim=3)
    try:
        assert "  trainable: 90 parameters (conditions 42, projections 48)" in cgs.summary().splitlines()
        assert sum(p.numel() for p in cgs.trainable_parameters()) == 90
    finally:
        cgs.unwrap()


@pytest.mark.parametrize("world", [1, 2, 3, 5])
def test_shards_of_a_batch_and_of_scenes_partition_it_round_robin(world):
    """Rank r takes items r, r + W, r + 2W ...: every item on exactly one rank, in order."""
    from controlgs_adapter.distributed import DistContext, shard_scenes

    items = [f"s{i}" for i in range(7)]
    shards = [DistContext(rank=r, world_size=world).shard(items) for r in range(world)]
    assert shards == [[items[i] for i in range(r, 7, world)] for r in range(world)]
    assert sorted(x for s in shards for x in s) == sorted(items)
    assert [shard_scenes(items, DistContext(rank=r, world_size=world)) for r in range(world)] == shards
    with pytest.raises(InputValueError, match=r"\['s1'\] more than once"):
        shard_scenes(["s0", "s1", "s1"], DistContext(rank=0, world_size=world))


@pytest.mark.parametrize("size,factor,want", [((103, 77), 2.0, (52, 38)), ((100, 60), 1.5, (67, 40)),
                                              ((10, 7), 3.0, (3, 2)), ((5, 3), 8.0, (1, 1))])
def test_camera_scaled_rounds_each_side_to_the_nearest_pixel(size, factor, want):
    """round(W / f), round(H / f) (at least 1), intrinsics scaled by each axis's own ratio."""
    from controlgs_adapter import Camera

    w, h = size
    k = torch.tensor([[50.0, 0.0, w / 2], [0.0, 40.0, h / 2], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), k, w, h).scaled(factor)
    assert (cam.width, cam.height) == want
    torch.testing.assert_close(cam.intrinsics, torch.tensor([[50.0 * want[0] / w, 0.0, want[0] / 2],
                                                             [0.0, 40.0 * want[1] / h, want[1] / 2], [0.0, 0.0, 1.0]]))


def test_iteration_folders_are_named_exactly_iteration_n(tmp_path):
    """iteration_10 and iteration_7 count; iteration_20_old, iteration_x and a file iteration_30 do not."""
    from controlgs_adapter.formats.layout import iteration_dir, iteration_dirs

    pc = tmp_path / "point_cloud"
    for name in ("iteration_10", "iteration_7", "iteration_20_old", "iteration_x", "old_iteration_40"):
        (pc / name).mkdir(parents=True)
    (pc / "iteration_30").write_text("")
    assert iteration_dirs(tmp_path) == {10: pc / "iteration_10", 7: pc / "iteration_7"}
    assert iteration_dir(tmp_path, None, family="Scaffold-GS") == pc / "iteration_10"
    with pytest.raises(FileFormatError, match=r"no 'iteration_20' folder \(present: \[7, 10\]\)"):
        iteration_dir(tmp_path, 20, family="Scaffold-GS")


def test_builtin_scene_holds_out_every_test_every_th_arc_camera():
    """views=8, test_every=4: test = arc cameras 0 and 4, train = 1, 2, 3, 5, 6, 7 (disjoint, in order)."""
    pytest.importorskip("skimage")
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.scene.cameras import arc_cameras

    scene = load_builtin_scene("ar", 16, views=8, test_every=4, samples=1)
    arc = arc_cameras(8, size=16)
    for got, i in zip(scene.test_cameras, (0, 4), strict=True):
        torch.testing.assert_close(got.world_to_camera.double(), arc[i].world_to_camera.double())
    for got, i in zip(scene.train_cameras, (1, 2, 3, 5, 6, 7), strict=True):
        torch.testing.assert_close(got.world_to_camera.double(), arc[i].world_to_camera.double())


def test_hac_plus_plus_decoded_needs_its_extra_mask_column_zero():
    """HAC++'s codec fills the extra (K+1-th) mask column with 0: 0/1 masks with a 1 there are not a decoded
    HAC++ file (False), but are for HAC (no extra column) or with the column 0 (True)."""
    import numpy as np

    from controlgs_adapter.backends.hac import infer_decoded

    scales = np.full((4, 6), 0.01)
    masks = np.zeros((4, 4))
    masks[:, 0] = 1.0
    assert infer_decoded(scales, masks, extra_mask_column=True) is True
    masks[2, -1] = 1.0
    assert infer_decoded(scales, masks, extra_mask_column=True) is False
    assert infer_decoded(scales, masks, extra_mask_column=False) is True
