"""Scaffold-GS's output folder: loading folders laid out as Scaffold-GS writes them (decoded against a
float64 reference), saving the reference model in that layout and back exactly, and every refusal, named by
file and field or decoder; TorchScript decoders are read as data unless trusted."""

from __future__ import annotations

import ast
import os
import pickle
import re
import shutil
import subprocess
import tempfile
import warnings

import numpy as np
import pytest
import torch
from helpers.hostile_modules import SetState, Writer
from helpers.octree_files import _arrays, _decoders, _write_dir
from helpers.scaffold_oracle import (
    camera_looking_down_z,
    decode_by_hand,
    make_raw_model,
    write_ply_by_hand,
    write_scaffold_dir_by_hand,
)
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import latest_iteration, load_scaffold_dir, save_scaffold_dir
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.backbone import read_cfg_args, read_ply, write_ply

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

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


def _good(tmp_path, mode="split"):
    raw = make_raw_model(8, 8, 3, seed=9)
    return raw, write_scaffold_dir_by_hand(tmp_path, raw, mode=mode)


def _random_model(seed: int = 0, **opts) -> NeuralGaussianModel:
    torch.manual_seed(seed)
    m = NeuralGaussianModel(6, feat_dim=8, n_offsets=3, **opts)
    with torch.no_grad():
        for p in (m._anchor, m._offset, m._anchor_feat, m._scaling):
            p.normal_()
    return m.eval()


def _unite_folder(tmp_path):
    raw = make_raw_model(5, 8, 2, seed=4)
    return write_scaffold_dir_by_hand(tmp_path / "s", raw, mode="unite"), raw


# ------------------------------------------------------------------------------------------ loading

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


@pytest.mark.parametrize("given", [0.0, -1.0, None])
def test_voxel_size_not_given_is_the_median_anchor_spacing(tmp_path, given):
    # Scaffold-GS estimates the voxel from the point cloud when the argument is <= 0; it is not saved
    raw = make_raw_model(9, 8, 2, seed=8)
    over = {"voxel_size": given} if given is not None else {}
    write_scaffold_dir_by_hand(tmp_path / "s", raw, cfg_overrides=over)
    if given is None:  # no key at all
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


def test_octree_folders_are_refused_naming_the_octree_loader(tmp_path):
    """load_scaffold_dir would decode every level of detail at once: an Octree-GS folder (its PLY's level
    field) and an Octree-AnyGS folder (config.yaml, no cfg_args, Scaffold-GS-like files) name the Octree-GS
    loader instead."""
    root = _write_dir(tmp_path / "s", _arrays(4), _decoders(torch.Generator().manual_seed(4)))
    with pytest.raises(FileFormatError, match=r"level, .*load_octree_gs_dir.*load_model_dir"):
        load_scaffold_dir(root)
    write_scaffold_dir_by_hand(tmp_path / "m", make_raw_model(5, 4, 2, seed=2), iteration=3)
    (tmp_path / "m" / "config.yaml").write_text("model_params: {\n  feat_dim: 4,\n}\n")
    with pytest.raises(FileFormatError, match=r"m: .*Octree-AnyGS.*\(config.yaml\)"):
        load_scaffold_dir(tmp_path / "m")


# ------------------------------------------------------------------------------------- refusals

def test_not_a_scaffold_directory(tmp_path):
    with pytest.raises(FileFormatError, match="iteration"):
        load_scaffold_dir(tmp_path)


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


def test_non_finite_ply_value_names_the_field(tmp_path):
    raw, folder = _good(tmp_path)
    raw["feat"][3, 5] = float("nan")
    write_ply_by_hand(folder / "point_cloud.ply", raw)
    with pytest.raises(FileFormatError, match=r"point_cloud\.ply.*f_anchor_feat_5.*non-finite"):
        load_scaffold_dir(tmp_path)


@pytest.mark.parametrize("drop", ["scale_5", "f_offset_4", "rot_0", "y"])
def test_missing_ply_field_names_it(tmp_path, drop):
    raw, folder = _good(tmp_path)
    ply = folder / "point_cloud.ply"
    fields, _ = read_ply(ply)
    del fields[drop]
    write_ply(ply, fields)
    with pytest.raises(FileFormatError, match=rf"point_cloud\.ply.*{drop}"):
        load_scaffold_dir(tmp_path)


def test_ply_refusals_name_the_field(tmp_path):
    folder, _ = _unite_folder(tmp_path)
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
    # offset fields not numbered 0..3K-1
    write_ply(ply, {("f_offset_99" if n == "f_offset_2" else n): v for n, v in fields.items()})
    with pytest.raises(FileFormatError, match=r"point_cloud\.ply.*f_offset_2"):
        load_scaffold_dir(tmp_path / "s")


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


def test_decoder_state_refusals_name_the_decoder(tmp_path):
    folder, raw = _unite_folder(tmp_path)
    ck = folder / "checkpoints.pth"
    sd = torch.load(ck, weights_only=True)
    torch.save({**sd, "opacity_mlp": {**sd["opacity_mlp"], "0.weight": torch.zeros(11)}}, ck)
    with pytest.raises(FileFormatError, match=r"decoder 'mlp_opacity' layer 0 weight must be 2-D, got \[11\]"):
        load_scaffold_dir(tmp_path / "s")
    # widths right, but a bias of the wrong size: refused when the weights are loaded
    torch.save({**sd, "cov_mlp": {**sd["cov_mlp"], "0.bias": torch.zeros(9)}}, ck)
    with pytest.raises(FileFormatError, match=r"checkpoints.pth \['cov_mlp'\]: decoder 'mlp_cov' does not fit"):
        load_scaffold_dir(tmp_path / "s")
    # a missing parameter does not fit either (not loaded with that bias left at its random initial value)
    torch.save({**sd, "color_mlp": {k: v for k, v in sd["color_mlp"].items() if k != "2.bias"}}, ck)
    with pytest.raises(FileFormatError, match=r"decoder 'mlp_color' does not fit: .*Missing key\(s\) in state_dict: \"2.bias\""):
        load_scaffold_dir(tmp_path / "s")
    torch.save(sd, ck)
    m = load_scaffold_dir(tmp_path / "s")
    assert torch.equal(m.mlp_color[0].bias, raw["mlp_color"][0].bias.detach())


class _OddEmbedding(nn.Module):
    """Scaffold-GS's appearance embedding wrapper with one exported method besides ``forward``: outside the
    subset the data reader takes (a class with methods besides ``forward``), harmless."""

    def __init__(self, weight: torch.Tensor) -> None:
        super().__init__()
        self.embedding = nn.Embedding.from_pretrained(weight.clone(), freeze=False)

    def forward(self, idx: torch.Tensor) -> torch.Tensor:
        return self.embedding(idx)

    @torch.jit.export
    def extra(self) -> int:
        return 1


def test_trust_code_reaches_the_appearance_embedding_of_a_split_scaffold_folder(tmp_path):
    """``load_scaffold_dir(..., trust_code=True)`` docstring: TorchScript files outside the supported subset
    are read with ``torch.jit.load``; by default they are refused. That holds for ``embedding_appearance.pt``
    as for the decoders: the trusted load returns the weights this test wrote."""
    torch.manual_seed(0)
    model = NeuralGaussianModel(12, feat_dim=8, n_offsets=3, appearance_dim=4, num_cameras=5)
    it = save_scaffold_dir(model, tmp_path / "m", iteration=2)
    weight = torch.randn(5, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.jit.script(_OddEmbedding(weight)).save(str(it / "embedding_appearance.pt"))
    with pytest.raises(FileFormatError, match="embedding_appearance.pt"):
        load_scaffold_dir(tmp_path / "m")  # read as data by default: refused, nothing run
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        trusted = load_scaffold_dir(tmp_path / "m", trust_code=True)
    assert torch.equal(trusted.embedding_appearance.embedding.weight.detach(), weight)


def test_a_folder_with_a_malicious_decoder_fails_cleanly(tmp_path):
    torch.manual_seed(0)
    folder = tmp_path / "model"
    save_scaffold_dir(NeuralGaussianModel(20, feat_dim=8, n_offsets=3), folder, iteration=7)
    loaded = load_scaffold_dir(folder)  # the clean folder loads, nothing run
    assert isinstance(loaded.mlp_opacity, nn.Sequential)
    target = tmp_path / "victim"
    evil = folder / "point_cloud" / "iteration_7" / "opacity_mlp.pt"
    torch.jit.script(Writer(str(target))).save(str(evil))
    with pytest.raises(FileFormatError, match=r"iteration_7.opacity_mlp\.pt.*refused"):
        load_scaffold_dir(folder)
    torch.jit.script(SetState(str(target))).save(str(evil))
    with pytest.raises(FileFormatError, match=r"opacity_mlp\.pt.*__setstate__"):
        load_scaffold_dir(folder)
    assert not target.exists()


# ------------------------------------------------------------------------------------------- saving

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
    assert (loaded.use_feat_bank, loaded.appearance_dim, loaded.add_opacity_dist) == (True, 2, False)
    assert loaded.embedding_appearance.embedding.weight.shape == (4, 2)
    for (name, a), (name2, b) in zip(model.state_dict().items(), loaded.state_dict().items()):
        assert name == name2 and torch.equal(a, b), name
    cam = camera_looking_down_z()
    cam.extra["uid"] = 3
    g, h = model.decode(cam), loaded.decode(cam)
    for name in ("means", "scales", "rotations", "opacities", "colors", "anchor_of"):
        assert torch.equal(getattr(g, name), getattr(h, name)), name


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


def test_save_scaffold_dir_default_mlp_mode_is_split(tmp_path):
    model = NeuralGaussianModel(3, feat_dim=8, n_offsets=2)
    folder = save_scaffold_dir(model, tmp_path / "a", 10)
    assert folder == tmp_path / "a" / "point_cloud" / "iteration_10"
    # Scaffold-GS's save_mlp_checkpoints(mode="split"): one TorchScript file per decoder next to the PLY
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["color_mlp.pt", "cov_mlp.pt", "opacity_mlp.pt", "point_cloud.ply"]
    unite = save_scaffold_dir(model, tmp_path / "b", 10, mlp_mode="unite")
    assert sorted(p.name for p in unite.iterdir()) == ["checkpoints.pth", "point_cloud.ply"]


def test_save_scaffold_dir_traces_a_colour_decoder_with_the_distance_input(tmp_path):
    """add_color_dist: the colour decoder takes [feat, view, dist] (F + 4); 'split' mode traces and reloads it."""
    torch.manual_seed(3)
    m = NeuralGaussianModel(3, feat_dim=4, n_offsets=2, add_color_dist=True)
    save_scaffold_dir(m, tmp_path / "s", 1)
    got = load_scaffold_dir(tmp_path / "s")
    assert got.add_color_dist and got.mlp_color[0].in_features == 4 + 3 + 1
    assert torch.equal(got.mlp_color[0].weight, m.mlp_color[0].weight)


def test_saved_cfg_args_holds_scaffold_gs_model_params(tmp_path):
    """cfg_args as Scaffold-GS's train.py writes it: str(Namespace(**vars(args))) of its ModelParams
    (arguments/__init__.py: sh_degree 3, update_depth 3, update_init_factor 16, update_hierachy_factor 4,
    images 'images', resolution -1, white_background False, data_device 'cuda', eval True, lod 0, undistorted
    False: the images were not undistorted by it) with the model's own widths and options."""
    m = _random_model(9, use_feat_bank=True, appearance_dim=2, num_cameras=3, add_opacity_dist=True)
    save_scaffold_dir(m, tmp_path / "s", 1)
    text = (tmp_path / "s" / "cfg_args").read_text()
    assert text.startswith("Namespace(") and text.endswith(")")
    call = ast.parse(text, mode="eval").body
    cfg = {kw.arg: ast.literal_eval(kw.value) for kw in call.keywords}
    want = {"sh_degree": 3, "feat_dim": 8, "n_offsets": 3, "voxel_size": 0.01, "update_depth": 3, "update_init_factor": 16,
            "update_hierachy_factor": 4, "use_feat_bank": True, "source_path": "", "model_path": str(tmp_path / "s"),
            "images": "images", "resolution": -1, "white_background": False, "data_device": "cuda", "eval": True,
            "lod": 0, "undistorted": False, "appearance_dim": 2, "add_opacity_dist": True, "add_cov_dist": False, "add_color_dist": False}
    assert {k: cfg[k] for k in want} == want
    assert read_cfg_args(tmp_path / "s" / "cfg_args")["undistorted"] is False
    back = load_scaffold_dir(tmp_path / "s")  # and the loader reads its options back from it
    assert (back.voxel_size, back.add_opacity_dist, back.appearance_dim) == (0.01, True, 2)


def test_save_refusals_overwrite_and_cleanup(tmp_path):
    m = _random_model()
    with pytest.raises(InputValueError, match="mlp_mode must be 'split' or 'unite', got 'both'"):
        save_scaffold_dir(m, tmp_path / "a", 10, mlp_mode="both")
    with pytest.raises(InputValueError, match="iteration must be >= 0, got -1"):
        save_scaffold_dir(m, tmp_path / "a", -1)
    save_scaffold_dir(m, tmp_path / "a", 0)  # iteration 0 is allowed
    # writing the same iteration again replaces it, leaving no temporary folder behind
    m2 = _random_model(1)
    save_scaffold_dir(m2, tmp_path / "a", 0, mlp_mode="unite")
    assert sorted(p.name for p in (tmp_path / "a" / "point_cloud").iterdir()) == ["iteration_0"]
    back = load_scaffold_dir(tmp_path / "a")
    assert torch.equal(back._anchor_feat, m2._anchor_feat) and torch.equal(back.mlp_cov[2].weight, m2.mlp_cov[2].weight)

    class Broken(nn.Module):
        def forward(self, x):
            raise RuntimeError("cannot trace")

    m3 = _random_model(2)
    m3.mlp_cov = Broken()
    with pytest.raises(RuntimeError, match="cannot trace"):
        save_scaffold_dir(m3, tmp_path / "a", 5)
    assert sorted(p.name for p in (tmp_path / "a" / "point_cloud").iterdir()) == ["iteration_0"]


def test_save_stages_the_folder_beside_its_destination(tmp_path, monkeypatch):
    """The iteration folder is written under a temporary name next to where it ends (one filesystem, so
    the final rename is atomic), never in the system's temp folder: pointing that at a missing path
    changes nothing."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "no-such-folder"))
    model = NeuralGaussianModel(4, feat_dim=8, n_offsets=2).eval()
    save_scaffold_dir(model, tmp_path / "out", 7)
    assert (tmp_path / "out" / "point_cloud" / "iteration_7" / "point_cloud.ply").is_file()
    assert sorted(p.name for p in (tmp_path / "out" / "point_cloud").iterdir()) == ["iteration_7"]


def test_saving_over_a_model_succeeds_when_the_old_folder_cannot_be_removed(tmp_path):
    """Saving over an existing iteration folder renames the old one aside, moves the new one into place, then
    removes the old one as a best effort: a file there that cannot be deleted (here an immutable one, which
    root cannot delete either) leaves the old copy behind but does not turn the finished save into an error."""
    if shutil.which("chattr") is None:
        pytest.skip("needs chattr to make an undeletable file")
    torch.manual_seed(0)
    old = NeuralGaussianModel(5, feat_dim=4, n_offsets=2, voxel_size=0.05)
    folder = save_scaffold_dir(old, tmp_path, 10, mlp_mode="unite")
    stuck = folder / "notes.txt"
    stuck.write_text("kept by the user")
    if subprocess.run(["chattr", "+i", str(stuck)], capture_output=True).returncode != 0:
        pytest.skip("this filesystem cannot mark a file immutable")
    try:
        new = NeuralGaussianModel(7, feat_dim=4, n_offsets=2, voxel_size=0.05)
        assert save_scaffold_dir(new, tmp_path, 10, mlp_mode="unite") == folder
        assert load_scaffold_dir(tmp_path).num_anchors == 7
        left = [p for p in (tmp_path / "point_cloud").iterdir() if p.name.startswith(".iteration_10.old.")]
        assert len(left) == 1 and (left[0] / "iteration_10" / "notes.txt").is_file()
    finally:
        for p in tmp_path.rglob("notes.txt"):
            subprocess.run(["chattr", "-i", str(p)], capture_output=True)


def test_saved_folders_get_the_umask_mode(tmp_path):
    old = os.umask(0o022)
    try:
        model = NeuralGaussianModel.from_points(torch.rand(20, 3), torch.rand(20, 3), feat_dim=8, n_offsets=2,
                                                voxel_size=0.3, color_fit_steps=1)
        final = save_scaffold_dir(model, tmp_path / "m", iteration=1)
        assert final.stat().st_mode & 0o777 == 0o755
        assert all(p.stat().st_mode & 0o777 == 0o644 for p in final.iterdir())
    finally:
        os.umask(old)


def test_loaded_scaffold_folder_is_wrappable_and_rows_map_to_visible_anchors(tmp_path):
    raw = make_raw_model(30, 8, 3, seed=11)
    write_scaffold_dir_by_hand(tmp_path, raw)
    model = load_scaffold_dir(tmp_path)
    cam = camera_looking_down_z()
    visible = torch.arange(30) % 3 != 1
    before = model.decode(cam, visible)
    cgs = ControlGS.wrap(model, modules=("resample",))
    with torch.no_grad(), cgs.conditioned(RuntimeState(downsample=8.0), camera=cam, anchor_ids=visible):
        same = model.decode(cam, visible)  # conditions are zero at init: bit-identical
        cgs.injector.conditions[12].normal_(generator=torch.Generator().manual_seed(0))  # anchor 12 (visible) only
        moved = model.decode(cam, visible)
    for name in ("means", "scales", "rotations", "opacities", "colors"):
        assert torch.equal(getattr(same, name), getattr(before, name)), name
    # only anchor 12's rows change (the mask may drop/keep some of its Gaussians)
    keep_b, keep_m = before.anchor_of != 12, moved.anchor_of != 12
    assert torch.equal(before.colors[keep_b], moved.colors[keep_m])
    changed = (moved.neural_opacity - before.neural_opacity).reshape(-1, 3).abs().sum(1) > 0
    assert torch.equal(before.visible_ids[changed], torch.tensor([12]))
    cgs.unwrap()
