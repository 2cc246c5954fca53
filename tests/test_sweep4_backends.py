"""Backbone-family backends and loaders (facts in /work/shared/notes/backbones.md): behaviours a line-by-line
mutation audit of backends/{scaffold_gs, scaffold_io, model_dir, octree_gs, hac, contextgs, compgs}.py found
unobserved, each checked through the public functions against the family's published layout or a value worked
out by hand (how is said next to each literal)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

import test_backend_compgs as compgs_t
import test_backend_contextgs as contextgs_t
import test_backend_hac as hac_t
import test_backend_octree_gs as octree_t
from _family_checks import make_camera, write_cfg_args
from controlgs_adapter import Camera
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.backends.compgs import CompGSModel, load_compgs_dir
from controlgs_adapter.backends.contextgs import ContextGSModel
from controlgs_adapter.backends.hac import HACBackend, HACModel, load_hac_dir
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel, load_octree_gs_dir, lod_anchor_ids
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir, save_scaffold_dir
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.backbone import read_ply, write_ply
from scaffold_oracle import make_raw_model, write_scaffold_dir_by_hand

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace: the format under test


# ---------------------------------------------------------------- Scaffold-GS backend

def test_scaffold_layout_keeps_a_one_wide_appearance_code():
    """Scaffold-GS appends the appearance code (appearance_dim wide, any size > 0) last to the colour
    decoder's input; a 1-wide code is still an input column."""
    m = NeuralGaussianModel(2, feat_dim=4, n_offsets=2, appearance_dim=1, num_cameras=3)
    layout = ScaffoldGSBackend().input_layout(m, "mlp_color")
    assert layout == [("feat", 4), ("view", 3), ("appearance", 1)]
    assert sum(w for _, w in layout) == m.mlp_color[0].in_features  # the decoder's own FC1 width: 4 + 3 + 1


def test_scaffold_anchor_positions_refuse_a_non_tensor_attribute():
    """A ``get_anchor`` that is neither a tensor nor callable (here an array) is refused as not a tensor,
    not called."""
    decs = dict(mlp_opacity=nn.Linear(1, 1), mlp_cov=nn.Linear(1, 1), mlp_color=nn.Linear(1, 1))
    model = SimpleNamespace(get_anchor=np.zeros((2, 3), np.float32), **decs)
    with pytest.raises(InputValueError, match="get_anchor must be a torch.Tensor, got ndarray"):
        ScaffoldGSBackend().anchor_positions(model)


# ---------------------------------------------------------------- model folders

def test_load_model_dir_with_an_iteration_ignores_a_half_written_later_one(tmp_path):
    """``iteration=N`` reads ``point_cloud/iteration_N`` for detection too: a later iteration folder that
    a crashed save left without its PLY does not stop the asked one from loading."""
    raw = make_raw_model(5, 4, 2, seed=3)
    root = tmp_path / "m"
    write_scaffold_dir_by_hand(root, raw, iteration=100)
    (root / "point_cloud" / "iteration_200").mkdir()
    model = load_model_dir(root, iteration=100)
    assert torch.equal(model._anchor, raw["anchor"])


# ---------------------------------------------------------------- stand-ins without stored rotations

def _cameras() -> tuple[Camera, Camera]:
    """Two cameras at the origin, f = 40, 64 x 48, principal point (-6, 24): a point on the optical axis
    projects 6 px left of the image. A looks along world +z; B along world +y (camera axes: x = world x,
    y = -world z, z = world y)."""
    k = torch.tensor([[40.0, 0.0, -6.0], [0.0, 40.0, 24.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    w2c[1:3, 1:3] = torch.tensor([[0.0, -1.0], [1.0, 0.0]])
    return Camera(torch.eye(4), k, 64, 48), Camera(w2c, k, 64, 48)


#: anchors 0-1 on camera A's optical axis (depth 5), 2-4 on camera B's; each has one scale 0.5 and two 0.01
_POS = torch.tensor([[0.0, 0, 5], [0, 0, 5], [0, 5, 0], [0, 5, 0], [0, 5, 0]])
_LIN = torch.tensor([[0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.5, 0.01, 0.01], [0.01, 0.01, 0.5], [0.01, 0.5, 0.01]])
#: With the identity rotation (what a family's file without rot_* means: CompGS's decoder resets rotations to
#: identity) the long axis of anchors 0, 2 (world x) and 3 (world z) is across the line of sight: footprint
#: sigma 40 / 5 * 0.5 = 4 px, radius ceil(3 sqrt(16.3)) = 13 px > 6 px: the anchor touches the image. Along
#: the line of sight (anchor 1: world z for A, anchor 4: world y for B) it projects to a point: sigma 0.08 px,
#: radius ceil(3 sqrt(0.0064 + 0.3)) = 2 px < 6 px: not visible. Anchors of the other camera are at depth 0.
_WANT_A, _WANT_B = [True, False, False, False, False], [False, False, True, True, False]


def _stand_ins_without_rotation() -> dict[str, object]:
    n, lin = len(_POS), torch.cat([_LIN, torch.full((len(_POS), 3), 0.02)], dim=1)
    ca = compgs_t._arrays(0)
    comp = CompGSModel(means=_POS, scales_before_exp=lin.log(), ref_feats=torch.from_numpy(ca["ref"][:n]),
                       res_feats=torch.from_numpy(ca["res"][:n]))
    ha = hac_t._arrays(0, decoded=True, mask_cols=hac_t.K + 1, n=n)
    hac = HACModel(voxel_size=0.001, decoded_version=True, anchor=_POS, offset=torch.from_numpy(ha["offset"]),
                   mask=torch.ones(n, hac_t.K + 1, 1), anchor_feat=torch.from_numpy(ha["feat"]), scaling=lin,
                   **hac_t._decoders(0))
    xa = {k: torch.from_numpy(v[:n]) for k, v in contextgs_t._arrays(0, decoded=True).items()}
    ctx = ContextGSModel(anchor=_POS, offset=xa["offset"], mask=torch.ones(n, contextgs_t.K, 1), anchor_feat=xa["feat"],
                         scaling=lin, hyper_latent=xa["hyper"], decoded_version=True, **contextgs_t._decoders(0))
    oa = octree_t._arrays(0)
    octo = OctreeGSModel(anchor=_POS, offset=torch.from_numpy(oa["offset"][:n]), anchor_feat=torch.from_numpy(oa["feat"][:n]),
                         scaling=lin.log(), level=torch.zeros(n, 1, dtype=torch.int32), extra_level=torch.zeros(n),
                         voxel_size=0.1, standard_dist=3.0, **octree_t._decoders(torch.Generator().manual_seed(0)))
    return {"compgs": comp, "hac": hac, "contextgs": ctx, "octree_gs": octo}


def test_stand_ins_without_rotations_prefilter_with_the_identity_rotation():
    cam_a, cam_b = _cameras()
    for name, model in _stand_ins_without_rotation().items():
        assert model.visible_anchors(cam_a).tolist() == _WANT_A, name
        assert model.visible_anchors(cam_b).tolist() == _WANT_B, name
    # the same anchors turned 90 degrees about x (y -> z): the verdicts follow the turned axes
    from controlgs_adapter.backends.models.anchor_model import anchor_visibility

    turned = torch.tensor([[1.0, 1.0, 0.0, 0.0]]).repeat(len(_POS), 1)
    assert anchor_visibility(cam_a, _POS, _LIN, turned).tolist() == [True, True, False, False, False]


def test_stand_ins_default_anchor_opacity_is_one_column():
    """Scaffold-GS's anchor ``_opacity`` is ``[A, 1]`` (one PLY ``opacity`` column per anchor)."""
    for name, model in _stand_ins_without_rotation().items():
        if name != "compgs":  # CompGS keeps no anchor opacity
            assert model._opacity.shape == (len(_POS), 1), name


# ---------------------------------------------------------------- HAC / HAC++ / ContextGS loaders

def _rewrite_ply(ply, **changes):
    fields, _ = read_ply(ply)
    for name, value in changes.items():
        if value is None:
            fields.pop(name)
        else:
            fields[name] = np.asarray(value, np.float32)
    write_ply(ply, fields)


def _quaternions(n: int) -> np.ndarray:
    return np.random.default_rng(5).normal(size=(n, 4)).astype(np.float32)


def test_hac_loader_keeps_the_ply_rotations_and_refuses_a_truncated_set(tmp_path):
    """HAC's PLY carries rot_0..rot_3 per anchor (the prefilter's rotations): they are read as stored."""
    arr = hac_t._arrays(4, decoded=True, mask_cols=hac_t.K + 1)
    root = hac_t._write_dir(tmp_path / "h", arr, hac_t._decoders(4))
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    q = _quaternions(hac_t.A)
    _rewrite_ply(ply, **{f"rot_{i}": q[:, i] for i in range(4)})
    model = load_hac_dir(root)
    assert torch.equal(model._rotation, torch.from_numpy(q)[model.source_index])
    _rewrite_ply(ply, rot_3=None)
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_hac_dir(root)


def test_hac_undecidable_file_counts_only_negative_scales(tmp_path):
    """The refusal of a file that does not tell decoded from raw reports how many scales are negative
    (here 3 negative, 6 exactly zero)."""
    arr = hac_t._arrays(5, decoded=True, mask_cols=hac_t.K + 1)
    arr["scale"][0, :3] = -0.1
    arr["scale"][1] = 0.0
    root = hac_t._write_dir(tmp_path / "h", arr, hac_t._decoders(5))
    with pytest.raises(FileFormatError, match=r"but 3 scale_\* value\(s\) are negative"):
        load_hac_dir(root)


def test_hac_mask_threshold_is_sigmoid_above_one_percent():
    """HAC++'s get_mask of a raw model: an offset is on where sigmoid(_mask) > 0.01 (module docstring).
    sigmoid(-4.0) = 0.0180 (on), sigmoid(-4.7) = 0.0090 (off)."""
    kw = dict(anchor=torch.zeros(1, 3), offset=torch.zeros(1, 2, 3), mask=torch.tensor([[[-4.0], [-4.7], [0.0]]]),
              anchor_feat=torch.zeros(1, 4), scaling=torch.zeros(1, 6), mlp_opacity=nn.Linear(8, 2),
              mlp_cov=nn.Linear(8, 14), mlp_color=nn.Linear(8, 6))
    model = HACModel(voxel_size=0.01, decoded_version=False, **kw)
    assert model.get_mask[0, :, 0].tolist() == [1.0, 0.0]


def _hac_dir_with_feature_bank(root, f: int):
    """HAC++'s layout with use_feat_bank=True and feat_dim f: the decoders take f + 4, the bank 4 -> f -> 3."""
    k = hac_t.K
    arr = hac_t._arrays(6, decoded=True, mask_cols=k + 1)
    arr["feat"] = arr["feat"][:, :f]
    torch.manual_seed(6)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, 7 * k)),
            "mlp_color": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid())}
    bank = nn.Sequential(nn.Linear(4, f), nn.ReLU(), nn.Linear(f, 3), nn.Softmax(dim=1))
    hac_t._write_dir(root, {**arr, "feat": np.zeros((hac_t.A, hac_t.F), np.float32)}, hac_t._decoders(6))
    it = root / "point_cloud" / "iteration_30000"
    _rewrite_ply(it / "point_cloud.ply", **{f"f_anchor_feat_{i}": None for i in range(f, hac_t.F)},
                 **{f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(f)})
    torch.save({"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
                "color_mlp": decs["mlp_color"].state_dict(), "mlp_feature_bank": bank.state_dict()}, it / "checkpoint.pth")
    write_cfg_args(root / "cfg_args", feat_dim=f, n_offsets=k, voxel_size=hac_t.VOXEL, use_feat_bank=True)
    return arr, bank


def test_hac_feature_bank_with_feat_dim_divisible_by_4_loads(tmp_path):
    """The feature bank needs feat_dim divisible by 4 (48 is): such a folder loads with its bank."""
    arr, bank = _hac_dir_with_feature_bank(tmp_path / "h", 48)
    model = load_hac_dir(tmp_path / "h")
    assert model.use_feat_bank and model.feat_dim == 48
    assert torch.equal(model.mlp_feature_bank[0].weight, bank[0].weight)
    b = HACBackend()
    assert b.decoder_paths(model) == ["mlp_opacity", "mlp_cov", "mlp_color", "mlp_feature_bank"]
    assert b.input_layout(model, "mlp_feature_bank") is None  # not a target: no FC1 layout
    assert b.input_layout(model, "mlp_color") == [("feat", 48), ("view", 3), ("dist", 1)]
    plain = load_hac_dir(hac_t._write_dir(tmp_path / "p", hac_t._arrays(6, decoded=True, mask_cols=hac_t.K + 1),
                                          hac_t._decoders(6)))
    assert not plain.use_feat_bank


# ---------------------------------------------------------------- CompGS loader

def _compgs_dir(root, g: int, *, rot: np.ndarray | None = None):
    """CompGS's training checkpoint with res_feats_dim g (f_res_feat_{k*g + j}, k-major)."""
    a, k, c = 4, 3, 5
    rng = np.random.default_rng(g)
    means, scales = rng.normal(size=(a, 3)).astype(np.float32), rng.normal(-3, 0.4, (a, 6)).astype(np.float32)
    ref, res = rng.normal(size=(a, c)).astype(np.float32), rng.normal(size=(a, k, g)).astype(np.float32)
    torch.manual_seed(g)
    model = CompGSModel(means=torch.from_numpy(means), scales_before_exp=torch.from_numpy(scales),
                        ref_feats=torch.from_numpy(ref), res_feats=torch.from_numpy(res))
    it = root / "point_cloud" / "iteration_100"
    it.mkdir(parents=True)
    fields = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    flat = res.reshape(a, k * g)
    fields.update({f"f_res_feat_{i}": flat[:, i] for i in range(k * g)})
    fields.update({f"f_ref_feat_{i}": ref[:, i] for i in range(c)})
    fields.update({f"scale_{i}": scales[:, i] for i in range(6)})
    if rot is not None:
        fields.update({f"rot_{i}": rot[:a, i] for i in range(rot.shape[1])})
    write_ply(it / "point_cloud.ply", fields)
    torch.save({f"prediction_net.{n}": v for n, v in model.network.prediction_net.state_dict().items()}, it / "weights.pth")
    return model, res


def test_compgs_loads_a_one_channel_residual_feature(tmp_path):
    """G = res_feats_dim is C_in - C - 4 of color_pred_mlp.net.0; G = 1 is a valid width."""
    model, res = _compgs_dir(tmp_path / "e", 1)
    got = load_compgs_dir(tmp_path / "e", allow_unquantized=True)
    assert got.gaussian_params.res_feats.shape == (4, 3, 1) and torch.equal(got.gaussian_params.res_feats, torch.from_numpy(res))
    w = "color_pred_mlp.net.0.weight"
    assert torch.equal(got.network.prediction_net.state_dict()[w], model.network.prediction_net.state_dict()[w])


def test_compgs_training_checkpoint_loads_beside_the_final_bitstreams(tmp_path):
    """CompGS's trainer writes point_cloud/bitstreams.npz at the end next to the iteration folders: only a
    folder with nothing but the bitstreams is refused."""
    _compgs_dir(tmp_path / "e", 2)
    (tmp_path / "e" / "point_cloud" / "bitstreams.npz").write_bytes(b"")
    assert load_compgs_dir(tmp_path / "e", allow_unquantized=True).gaussian_params.means.shape == (4, 3)


def test_compgs_loader_keeps_the_ply_rotations_and_refuses_a_truncated_set(tmp_path):
    q = _quaternions(4)
    _compgs_dir(tmp_path / "e", 2, rot=q)
    got = load_compgs_dir(tmp_path / "e", allow_unquantized=True)
    assert torch.equal(got.gaussian_params.rotations_before_norm, torch.from_numpy(q))
    _compgs_dir(tmp_path / "t", 2, rot=q[:, :3])
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_compgs_dir(tmp_path / "t", allow_unquantized=True)


def test_stand_ins_are_frozen():
    """The stand-ins are for evaluation: every parameter is frozen (load_model_dir: "eval mode, frozen")."""
    for name, model in _stand_ins_without_rotation().items():
        assert not any(p.requires_grad for p in model.parameters()), name
        assert not model.training, name


# ---------------------------------------------------------------- Octree-GS

def _octree(anchor, level, *, fork=2, voxel_size=0.0, standard_dist=16.0, dist2level="round", f=4, k=2, **kw):
    n = anchor.shape[0]
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 7 * k)),
            "mlp_color": nn.Sequential(nn.Linear(f + 3 + kw.pop("app", 0), f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid())}
    return OctreeGSModel(anchor=anchor, offset=torch.randn(n, k, 3, generator=g), anchor_feat=torch.randn(n, f, generator=g),
                         scaling=torch.full((n, 6), -2.0), level=torch.tensor(level, dtype=torch.int32)[:, None],
                         extra_level=torch.zeros(n), voxel_size=voxel_size, standard_dist=standard_dist, fork=fork,
                         dist2level=dist2level, **decs, **kw)


def test_octree_map_to_int_level_by_hand():
    """Octree-GS's map_to_int_level: round/floor/ceil then clamp to [0, cur_level]; 'progressive' takes
    floor(clamp(pred + 1, 0.9999, cur_level + 0.9999)) and keeps the fraction as the opacity ratio."""
    m = _octree(torch.zeros(4, 3), [0, 1, 2, 2])
    pred = torch.tensor([-1.2, 0.6, 1.4, 7.0])
    for mode, want in (("round", [0, 1, 1, 2]), ("floor", [0, 0, 1, 2]), ("ceil", [0, 1, 2, 2])):
        m.dist2level = mode
        assert m.map_to_int_level(pred, 2).tolist() == want, mode
    m.dist2level = "progressive"
    # pred + 1 = [-2, 1.25, 2.5, 8] -> clamped to [0.9999, 1.25, 2.5, 2.9999] -> floor [0, 1, 2, 2]
    assert m.map_to_int_level(torch.tensor([-3.0, 0.25, 1.5, 7.0]), 2).tolist() == [0, 1, 2, 2]
    assert torch.allclose(m._prog_ratio[:, 0], torch.tensor([0.9999, 0.25, 0.5, 0.9999]), atol=1e-5)
    assert m.transition_mask.tolist() == [True, True, True, True]  # each anchor's level is its predicted level


def test_octree_lod_level_divides_by_log2_of_the_fork():
    """level(d) = log2(standard_dist / d) / log2(fork): standard_dist 16, fork 4, camera at the origin,
    anchors on +z (voxel_size 0: no centre shift). d = 1 -> 2, d = 4 -> 1, d = 16 -> 0."""
    z = torch.tensor([1.0, 4.0, 4.0, 16.0, 16.0])
    m = _octree(torch.stack([torch.zeros(5), torch.zeros(5), z], dim=1), [2, 2, 1, 1, 0], fork=4)
    m.set_anchor_mask(torch.zeros(3))
    assert m._anchor_mask.tolist() == [True, False, True, False, True]


def test_octree_levels_count_from_the_lowest_stored_level():
    """Octree-GS's loader: levels = max(level) - min(level) + 1, and the predicted level is clamped to
    levels - 1. Stored levels {1, 2}: 2 levels, so a close camera (level log2(16 / 1) = 4) selects up to
    level 1 only, as Octree-GS does."""
    m = _octree(torch.tensor([[0.0, 0, 1], [0, 0, 1]]), [2, 1])
    assert m.levels == 2
    m.set_anchor_mask(torch.zeros(3))
    assert m._anchor_mask.tolist() == [False, True]


def test_octree_fresh_model_selects_every_anchor_and_lod_masks_must_be_bool():
    m = _octree(torch.zeros(3, 3), [0, 1, 0])
    assert m._anchor_mask.dtype == torch.bool and m._anchor_mask.tolist() == [True, True, True]
    b = OctreeGSBackend()
    assert b.anchor_ids(m, torch.tensor([True, False, True])).tolist() == [0, 2]
    with pytest.raises(InputValueError, match="anchor_mask must have dtype"):
        lod_anchor_ids(torch.tensor([1, 0, 1]), torch.tensor([True, True, True]))
    with pytest.raises(InputValueError, match="frustum_mask must have dtype"):
        lod_anchor_ids(torch.tensor([True, False, True]), torch.tensor([1, 1, 1]))


def test_octree_progressive_model_decodes_without_a_ratio_before_any_lod_selection():
    """Before set_anchor_mask there is no transition ratio: the progressive model decodes as the rounding one."""
    pos = torch.tensor([[0.0, 0, 0], [0.3, -0.2, 0.5]])
    cam = make_camera()
    prog = _octree(pos, [0, 1], dist2level="progressive").decode(cam)
    rnd = _octree(pos, [0, 1]).decode(cam)
    assert torch.equal(prog.opacities, rnd.opacities)


def test_octree_layout_without_add_level_attribute_has_no_level():
    """Octree-AnyGS's model has no add_level option: its decoders take [feat, view] (+ appearance)."""
    decs = dict(mlp_opacity=nn.Linear(7, 2), mlp_cov=nn.Linear(7, 2), mlp_color=nn.Linear(7, 2))
    model = SimpleNamespace(feat_dim=4, _anchor=torch.zeros(2, 3), _level=torch.zeros(2, 1), _extra_level=torch.zeros(2),
                            set_anchor_mask=lambda *a: None, **decs)
    b = OctreeGSBackend()
    assert b.matches(model)
    assert b.input_layout(model, "mlp_cov") == [("feat", 4), ("view", 3)]


def test_octree_decode_uses_appearance_code_zero_without_a_camera_uid():
    m = _octree(torch.tensor([[0.0, 0, 0], [0.3, -0.2, 0.5]]), [0, 0], app=2, embedding_appearance=nn.Embedding(3, 2))
    with torch.no_grad():
        m.mlp_opacity[2].bias.fill_(5.0)  # every Gaussian kept
    cam = make_camera()
    assert "uid" not in cam.extra
    assert torch.equal(m.decode(cam).colors, m.decode(cam, appearance_id=0).colors)
    assert not torch.equal(m.decode(cam).colors, m.decode(cam, appearance_id=1).colors)


def _octree_dir_with_defaults(root):
    """Octree-GS's layout at its ModelParams defaults (feat_dim 32, n_offsets 10, no dist/level inputs) and a
    cfg_args that names none of them."""
    a, f, k = 3, 32, 10
    rng = np.random.default_rng(1)
    it = root / "point_cloud" / "iteration_10"
    it.mkdir(parents=True)
    write_cfg_args(root / "cfg_args", model_path=str(root))
    info = np.zeros(a, np.float32)
    info[:2] = 0.01, 3.0
    fields = {c: rng.normal(size=a).astype(np.float32) for c in "xyz"}
    fields.update(level=np.array([0, 1, 1], np.float32), extra_level=np.zeros(a, np.float32), info=info)
    fields.update({f"f_offset_{i}": rng.normal(size=a).astype(np.float32) for i in range(3 * k)})
    fields.update({f"f_anchor_feat_{i}": rng.normal(size=a).astype(np.float32) for i in range(f)})
    fields.update({f"scale_{i}": np.full(a, -2.0, np.float32) for i in range(6)})
    fields.update({f"rot_{i}": np.full(a, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    torch.manual_seed(1)
    torch.save({"opacity_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()).state_dict(),
                "cov_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 7 * k)).state_dict(),
                "color_mlp": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid()).state_dict()},
               it / "checkpoints.pth")
    return it / "point_cloud.ply"


def test_octree_cfg_args_without_widths_or_options_takes_octree_gs_defaults(tmp_path):
    """Octree-GS's ModelParams (arguments/__init__.py): feat_dim 32, n_offsets 10, fork 2, add_*_dist and
    add_level False, dist2level 'round'."""
    _octree_dir_with_defaults(tmp_path / "o")
    m = load_octree_gs_dir(tmp_path / "o")
    assert (m.feat_dim, m.n_offsets, m.fork, m.dist2level) == (32, 10, 2, "round")
    assert not (m.add_level or m.add_opacity_dist or m.add_cov_dist or m.add_color_dist)
    assert OctreeGSBackend().input_layout(m, "mlp_opacity") == [("feat", 32), ("view", 3)]


def test_octree_loader_refuses_a_truncated_rotation_set(tmp_path):
    ply = _octree_dir_with_defaults(tmp_path / "o")
    _rewrite_ply(ply, rot_3=None)
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_octree_gs_dir(tmp_path / "o")


# ---------------------------------------------------------------- Scaffold-GS folders

def test_scaffold_loader_refuses_an_octree_anygs_folder_by_its_config_yaml(tmp_path):
    """Octree-AnyGS writes config.yaml (no cfg_args) next to Scaffold-GS-like files: load_scaffold_dir
    names it and points to the Octree-GS loader instead of decoding every level at once."""
    write_scaffold_dir_by_hand(tmp_path / "m", make_raw_model(5, 4, 2, seed=2), iteration=3)
    (tmp_path / "m" / "config.yaml").write_text("model_params: {\n  feat_dim: 4,\n}\n")
    with pytest.raises(FileFormatError, match=r"m: an Octree-GS / Octree-AnyGS output folder \(config.yaml\), not a flat"):
        load_scaffold_dir(tmp_path / "m")


def test_save_scaffold_dir_traces_a_colour_decoder_with_the_distance_input(tmp_path):
    """add_color_dist: the colour decoder takes [feat, view, dist] (F + 4); 'split' mode traces and reloads it."""
    torch.manual_seed(3)
    m = NeuralGaussianModel(3, feat_dim=4, n_offsets=2, add_color_dist=True)
    save_scaffold_dir(m, tmp_path / "s", 1)
    got = load_scaffold_dir(tmp_path / "s")
    assert got.add_color_dist and got.mlp_color[0].in_features == 4 + 3 + 1
    assert torch.equal(got.mlp_color[0].weight, m.mlp_color[0].weight)


def test_scaffold_loader_refuses_a_decoder_state_missing_a_parameter(tmp_path):
    """A 'unite' checkpoints.pth whose colour decoder lacks its last bias does not fit the decoder: refused
    (not loaded with that bias left at its random initial value)."""
    write_scaffold_dir_by_hand(tmp_path / "m", make_raw_model(5, 4, 2, seed=1), iteration=3, mode="unite")
    ck = tmp_path / "m" / "point_cloud" / "iteration_3" / "checkpoints.pth"
    sd = torch.load(ck, weights_only=True)
    del sd["color_mlp"]["2.bias"]
    torch.save(sd, ck)
    with pytest.raises(FileFormatError, match=r"decoder 'mlp_color' does not fit: .*Missing key\(s\) in state_dict: \"2.bias\""):
        load_scaffold_dir(tmp_path / "m")
