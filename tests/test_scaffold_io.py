"""Scaffold-GS output directories: read what the original code writes, write what it reads, refuse bad files."""

from __future__ import annotations

import pickle
import re

import numpy as np
import pytest
import torch

from controlgs_adapter.formats.backbone import read_ply
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import latest_iteration, load_scaffold_dir, save_scaffold_dir
from controlgs_adapter.errors import FileFormatError
from scaffold_oracle import camera_looking_down_z, decode_by_hand, make_raw_model, write_ply_by_hand, \
    write_scaffold_dir_by_hand

OPTIONS = [
    dict(),
    dict(feat_bank=True, appearance_dim=4, num_cameras=3, dists=(True, False, True)),
    dict(dists=(False, True, False)),
]


def _assert_matches_hand_decode(model, raw, cam, visible, uid=0):
    got = model.decode(cam, visible)
    want = decode_by_hand(raw, cam.center, visible, uid)
    assert got.means.shape[0] == want["means"].shape[0] > 0
    torch.testing.assert_close(got.anchor_of, want["anchor_of"], rtol=0, atol=0)
    for name in ("means", "scales", "rotations", "opacities", "colors"):
        torch.testing.assert_close(getattr(got, name).double(), want[name], rtol=1e-5, atol=2e-6, msg=name)


@pytest.mark.parametrize("mode", ["split", "unite"])
@pytest.mark.parametrize("opts", OPTIONS)
def test_loads_directory_laid_out_as_scaffold_gs_writes_it(tmp_path, mode, opts):
    raw = make_raw_model(40, 8, 4, seed=3, **opts)
    write_scaffold_dir_by_hand(tmp_path, raw, mode=mode)
    model = load_scaffold_dir(tmp_path)
    assert (model.feat_dim, model.n_offsets, model.num_anchors) == (8, 4, 40)
    assert model.use_feat_bank == bool(opts.get("feat_bank")) and model.appearance_dim == opts.get("appearance_dim", 0)
    cam = camera_looking_down_z()
    cam.extra["uid"] = 2 if opts.get("appearance_dim") else 0
    visible = torch.rand(40, generator=torch.Generator().manual_seed(1)) > 0.3
    _assert_matches_hand_decode(model, raw, cam, visible, uid=cam.extra["uid"])


def test_rebuilt_decoders_reproduce_the_traced_files_exactly(tmp_path):
    raw = make_raw_model(10, 8, 3, seed=5, feat_bank=True)
    folder = write_scaffold_dir_by_hand(tmp_path, raw)
    model = load_scaffold_dir(tmp_path)
    x = torch.randn(64, 11)
    for attr, file in (("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")):
        script = torch.jit.load(str(folder / file))
        assert not isinstance(getattr(model, attr), torch.jit.ScriptModule)
        assert torch.equal(getattr(model, attr)(x), script(x)), attr
    bank = torch.jit.load(str(folder / "feature_bank_mlp.pt"))
    assert torch.equal(model.mlp_feature_bank(x[:, :4]), bank(x[:, :4]))


@pytest.mark.parametrize("mode", ["split", "unite"])
def test_save_load_round_trip_is_exact(tmp_path, mode):
    torch.manual_seed(0)
    model = NeuralGaussianModel(30, feat_dim=8, n_offsets=3, voxel_size=0.05, use_feat_bank=True, appearance_dim=2,
                                num_cameras=4, add_cov_dist=True)
    with torch.no_grad():
        for p in (model._anchor, model._offset, model._anchor_feat, model._scaling, model._rotation, model._opacity):
            p.normal_()
        model._anchor[:, 2] += 5
    folder = save_scaffold_dir(model, tmp_path, 7000, mlp_mode=mode)
    assert folder == tmp_path / "point_cloud" / "iteration_7000"
    loaded = load_scaffold_dir(tmp_path)
    assert loaded.voxel_size == pytest.approx(0.05) and loaded.add_cov_dist and not loaded.add_color_dist
    for (name, a), (name2, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert name == name2 and torch.equal(a, b), name
    cam = camera_looking_down_z()
    cam.extra["uid"] = 3
    g, h = model.decode(cam), loaded.decode(cam)
    for name in ("means", "scales", "rotations", "opacities", "colors", "anchor_of"):
        assert torch.equal(getattr(g, name), getattr(h, name)), name
    # only the format's files are left behind (no temporaries), and saving again replaces the folder
    save_scaffold_dir(model, tmp_path, 7000, mlp_mode="unite" if mode == "split" else "split")
    assert sorted(p.name for p in (tmp_path / "point_cloud").iterdir()) == ["iteration_7000"]


def test_saved_ply_has_scaffold_gs_field_order_and_offset_layout(tmp_path):
    model = NeuralGaussianModel(5, feat_dim=4, n_offsets=2)
    with torch.no_grad():
        model._offset.copy_(torch.arange(30.0).reshape(5, 2, 3))
    save_scaffold_dir(model, tmp_path, 1)
    raw = (tmp_path / "point_cloud" / "iteration_1" / "point_cloud.ply").read_bytes()
    header = raw[: raw.index(b"end_header\n")].decode()
    names = re.findall(r"property float (\w+)", header)
    assert names == (["x", "y", "z", "nx", "ny", "nz"] + [f"f_offset_{i}" for i in range(6)]
                     + [f"f_anchor_feat_{i}" for i in range(4)] + ["opacity"] + [f"scale_{i}" for i in range(6)]
                     + [f"rot_{i}" for i in range(4)])
    fields, _ = read_ply(tmp_path / "point_cloud" / "iteration_1" / "point_cloud.ply")
    # anchor 1, offset k=1, coordinate c=2 is 6 + 3 + 2 = 11, stored in f_offset_{c*K+k} = f_offset_5
    assert fields["f_offset_5"][1] == 11.0 and fields["f_offset_1"][1] == 9.0


def test_latest_iteration_is_loaded_by_default(tmp_path):
    old, new = make_raw_model(6, 8, 2, seed=1), make_raw_model(9, 8, 2, seed=2)
    write_scaffold_dir_by_hand(tmp_path, old, iteration=7000)
    write_scaffold_dir_by_hand(tmp_path, new, iteration=30000)
    assert latest_iteration(tmp_path) == 30000
    assert load_scaffold_dir(tmp_path).num_anchors == 9
    assert load_scaffold_dir(tmp_path, iteration=7000).num_anchors == 6
    with pytest.raises(FileFormatError, match="iteration_5"):
        load_scaffold_dir(tmp_path, iteration=5)


def test_missing_cfg_args_is_inferred_from_the_files(tmp_path):
    raw = make_raw_model(12, 8, 3, seed=4, appearance_dim=2, dists=(True, True, False))
    write_scaffold_dir_by_hand(tmp_path, raw)
    (tmp_path / "cfg_args").unlink()
    model = load_scaffold_dir(tmp_path)
    assert (model.add_opacity_dist, model.add_cov_dist, model.add_color_dist, model.appearance_dim) == (True, True, False, 2)
    _assert_matches_hand_decode(model, raw, camera_looking_down_z(), torch.ones(12, dtype=torch.bool))


# ------------------------------------------------------------------------------------------ bad files

def _good(tmp_path, mode="split"):
    raw = make_raw_model(8, 8, 3, seed=9)
    return raw, write_scaffold_dir_by_hand(tmp_path, raw, mode=mode)


def test_missing_mlp_names_the_file(tmp_path):
    _, folder = _good(tmp_path)
    (folder / "cov_mlp.pt").unlink()
    with pytest.raises(FileFormatError, match=r"cov_mlp\.pt"):
        load_scaffold_dir(tmp_path)
    for p in folder.glob("*.pt"):
        p.unlink()
    with pytest.raises(FileFormatError, match=r"checkpoints\.pth"):
        load_scaffold_dir(tmp_path)


def test_unite_file_missing_entry_names_the_key(tmp_path):
    _, folder = _good(tmp_path, mode="unite")
    blob = torch.load(folder / "checkpoints.pth", weights_only=True)
    del blob["color_mlp"]
    torch.save(blob, folder / "checkpoints.pth")
    with pytest.raises(FileFormatError, match=r"checkpoints\.pth.*color_mlp"):
        load_scaffold_dir(tmp_path)


def test_unite_file_with_pickled_objects_is_refused(tmp_path):
    _, folder = _good(tmp_path, mode="unite")
    blob = torch.load(folder / "checkpoints.pth", weights_only=True)
    blob["opacity_mlp"] = {"0.weight": blob["opacity_mlp"]["0.weight"], "payload": pickle.loads(pickle.dumps(np.float64))}
    torch.save(blob, folder / "checkpoints.pth")
    with pytest.raises(FileFormatError, match=r"checkpoints\.pth.*weights-only"):
        load_scaffold_dir(tmp_path)


def test_truncated_ply_names_the_file(tmp_path):
    _, folder = _good(tmp_path)
    ply = folder / "point_cloud.ply"
    ply.write_bytes(ply.read_bytes()[:-10])
    with pytest.raises(FileFormatError, match=r"point_cloud\.ply.*truncated"):
        load_scaffold_dir(tmp_path)


@pytest.mark.parametrize("drop", ["scale_5", "f_offset_4", "rot_0", "y"])
def test_missing_ply_field_names_it(tmp_path, drop):
    raw, folder = _good(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    del fields[drop]
    from controlgs_adapter.formats.backbone import write_ply

    write_ply(ply, fields)
    with pytest.raises(FileFormatError, match=rf"point_cloud\.ply.*{drop}"):
        load_scaffold_dir(tmp_path)


def test_non_finite_ply_value_names_the_field(tmp_path):
    raw, folder = _good(tmp_path)
    raw["feat"][3, 5] = float("nan")
    write_ply_by_hand(folder / "point_cloud.ply", raw)
    with pytest.raises(FileFormatError, match=r"point_cloud\.ply.*f_anchor_feat_5.*non-finite"):
        load_scaffold_dir(tmp_path)


def test_feat_dim_in_cfg_args_disagreeing_with_ply_names_both(tmp_path):
    raw = make_raw_model(8, 8, 3, seed=9)
    write_scaffold_dir_by_hand(tmp_path, raw, cfg_overrides={"feat_dim": 16})
    with pytest.raises(FileFormatError, match=r"cfg_args.*feat_dim=16.*f_anchor_feat"):
        load_scaffold_dir(tmp_path)


def test_dist_option_disagreeing_with_mlp_width_names_it(tmp_path):
    raw = make_raw_model(8, 8, 3, seed=9, dists=(True, False, False))
    write_scaffold_dir_by_hand(tmp_path, raw, cfg_overrides={"add_opacity_dist": False})
    with pytest.raises(FileFormatError, match=r"cfg_args.*add_opacity_dist"):
        load_scaffold_dir(tmp_path)


@pytest.mark.parametrize("mode", ["split", "unite"])
def test_mlp_output_k_disagreeing_with_ply_offsets_names_the_decoder(tmp_path, mode):
    raw = make_raw_model(8, 8, 3, seed=9)
    raw["mlp_opacity"][2] = torch.nn.Linear(8, 4)  # K = 4 opacities, the PLY has 3 offsets per anchor
    write_scaffold_dir_by_hand(tmp_path, raw, mode=mode)
    name = "opacity_mlp.pt" if mode == "split" else r"checkpoints\.pth.*opacity_mlp"
    with pytest.raises(FileFormatError, match=rf"{name}.*mlp_opacity.*n_offsets=3"):
        load_scaffold_dir(tmp_path)


def test_wrong_hidden_width_names_the_decoder(tmp_path):
    raw = make_raw_model(8, 8, 3, seed=9)
    raw["mlp_cov"] = torch.nn.Sequential(torch.nn.Linear(11, 16), torch.nn.ReLU(), torch.nn.Linear(16, 21))
    write_scaffold_dir_by_hand(tmp_path, raw)
    with pytest.raises(FileFormatError, match=r"cov_mlp\.pt.*mlp_cov"):
        load_scaffold_dir(tmp_path)


def test_wrong_activation_names_the_decoder(tmp_path):
    raw = make_raw_model(8, 8, 3, seed=9)
    raw["mlp_opacity"][3] = torch.nn.Sigmoid()
    write_scaffold_dir_by_hand(tmp_path, raw)
    with pytest.raises(FileFormatError, match=r"opacity_mlp\.pt.*Sigmoid"):
        load_scaffold_dir(tmp_path)


def test_offset_fields_not_numbered_contiguously_are_refused(tmp_path):
    raw, folder = _good(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    fields = {("f_offset_99" if n == "f_offset_2" else n): v for n, v in fields.items()}
    from controlgs_adapter.formats.backbone import write_ply

    write_ply(ply, fields)
    with pytest.raises(FileFormatError, match=r"point_cloud\.ply.*f_offset_2"):
        load_scaffold_dir(tmp_path)


def test_not_a_scaffold_directory(tmp_path):
    with pytest.raises(FileFormatError, match="iteration"):
        load_scaffold_dir(tmp_path)


def test_loaded_directory_is_wrappable_and_rows_map_to_visible_anchors(tmp_path):
    from controlgs_adapter import ControlGS
    from controlgs_adapter.state import RuntimeState

    raw = make_raw_model(30, 8, 3, seed=11)
    write_scaffold_dir_by_hand(tmp_path, raw)
    model = load_scaffold_dir(tmp_path)
    cam = camera_looking_down_z()
    visible = torch.arange(30) % 3 != 1
    before = model.decode(cam, visible)
    cgs = ControlGS.wrap(model, modules=("resample",))
    state = RuntimeState(downsample=8.0)
    with torch.no_grad(), cgs.conditioned(state, camera=cam, anchor_ids=visible):
        same = model.decode(cam, visible)  # conditions are zero at init: bit-identical
        cgs.injector.conditions[12].normal_()  # anchor 12 (visible) only
        moved = model.decode(cam, visible)
    for name in ("means", "scales", "rotations", "opacities", "colors"):
        assert torch.equal(getattr(same, name), getattr(before, name)), name
    # only anchor 12's rows change (the mask may drop/keep some of its Gaussians)
    keep_b, keep_m = before.anchor_of != 12, moved.anchor_of != 12
    assert torch.equal(before.colors[keep_b], moved.colors[keep_m])
    changed = (moved.neural_opacity - before.neural_opacity).reshape(-1, 3).abs().sum(1) > 0
    assert torch.equal(before.visible_ids[changed], torch.tensor([12]))
    cgs.unwrap()
