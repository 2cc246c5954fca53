"""Octree-GS and Octree-AnyGS: the backend (level input, LOD ∧ frustum rows), the level-of-detail selection
and the decoding against float64 references, appearance codes, and the loader (cfg_args / config.yaml,
TorchScript or state-dict decoders) with its defaults and every refusal."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from helpers.anchor_oracle import D, assert_gaussians, camera_centre, feature_bank64, gaussian64, mlp, mlp64, oblique_camera
from helpers.family_checks import assert_same_gaussians, make_camera, outputs, reference_scaffold, write_cfg_args
from helpers.family_dirs import rewrite_ply
from helpers.hostile_modules import SetState
from helpers.octree_files import (
    ANYGS_YAML,
    CFG,
    FORK,
    STD_DIST,
    VOXEL,
    A,
    F,
    K,
    _arrays,
    _decoders,
    _model,
    _write_dir,
    anygs_decoders,
    anygs_fields,
    write_anygs_dir,
)
from helpers.scaffold_oracle import Embedding
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import CompGSBackend
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel, load_octree_gs_dir, lod_anchor_ids
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError, TargetError
from controlgs_adapter.formats.backbone import read_ply, write_ply

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _gen(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _lod64(arr, cam: torch.Tensor, *, rule: str = "round", scale: float = 1.0, voxel: float = VOXEL,
           std: float = STD_DIST, fork: int = FORK) -> list[bool]:
    """Octree-GS's set_anchor_mask in float64, anchor by anchor: dist = |voxel centre - camera| * scale
    (voxel centre = anchor + voxel / 2 / fork^level), predicted level log2(std / dist) / log2(fork) + extra,
    rounded by ``rule``, clamped to [0, levels - 1] with levels = max(level) - min(level) + 1."""
    levels = int(arr["level"].max() - arr["level"].min() + 1)
    rnd = {"round": lambda p: int(np.round(p)), "floor": math.floor, "ceil": math.ceil}[rule]
    c = cam.double().numpy()
    out = []
    for a in range(len(arr["level"])):
        lv = int(arr["level"][a])
        pos = arr["anchor"][a].astype(np.float64) + (voxel / 2) / fork ** lv
        pred = math.log2(std / (float(np.linalg.norm(pos - c)) * scale)) / math.log2(fork) + float(arr["extra"][a])
        out.append(lv <= min(max(rnd(pred), 0), levels - 1))
    return out


def _small(anchor, level, *, fork=2, voxel_size=0.0, standard_dist=16.0, dist2level="round", f=4, k=2, **kw):
    """An Octree-GS model of few anchors at ``anchor`` with ``level``; ``app``: appearance width."""
    n = anchor.shape[0]
    g = _gen(0)
    torch.manual_seed(0)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, k), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(f + 3, f), nn.ReLU(), nn.Linear(f, 7 * k)),
            "mlp_color": nn.Sequential(nn.Linear(f + 3 + kw.pop("app", 0), f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid())}
    return OctreeGSModel(anchor=anchor, offset=torch.randn(n, k, 3, generator=g), anchor_feat=torch.randn(n, f, generator=g),
                         scaling=torch.full((n, 6), -2.0), level=torch.tensor(level, dtype=torch.int32)[:, None],
                         extra_level=torch.zeros(n), voxel_size=voxel_size, standard_dist=standard_dist, fork=fork,
                         dist2level=dist2level, **decs, **kw)


def _defaults_dir(root):
    """Octree-GS's layout at its ModelParams defaults (feat_dim 32, n_offsets 10, no dist/level inputs) and a
    cfg_args that names none of them. Returns the PLY."""
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
    torch.save({"opacity_mlp": mlp(f + 3, f, k, nn.Tanh()).state_dict(), "cov_mlp": mlp(f + 3, f, 7 * k, None).state_dict(),
                "color_mlp": mlp(f + 3, f, 3 * k, nn.Sigmoid()).state_dict()}, it / "checkpoints.pth")
    return it / "point_cloud.ply"


# ------------------------------------------------------------------------------------------ backend
def test_backend_recognises_octree_gs_and_checks_the_level_input():
    model = _model(_arrays(), _decoders(_gen(0)))
    b = OctreeGSBackend()
    assert b.matches(model) and not any(o.matches(model) for o in (HACBackend(), ContextGSBackend(), CompGSBackend()))
    assert ScaffoldGSBackend().matches(model)  # generic; Octree-GS is registered before it
    assert b.default_targets(model) == ["mlp_opacity", "mlp_cov", "mlp_color"]
    assert [w for _, w in b.input_layout(model, "mlp_opacity")] == [F, 3, 1, 1]
    assert [n for n, _ in b.input_layout(model, "mlp_cov")] == ["feat", "view", "level"]
    assert torch.equal(b.anchor_positions(model), model._anchor)  # raw anchors, not voxel centres
    for d in b.default_targets(model):
        assert b.check_decoder(model, d).out_features == F
    model.add_level = False  # config and widths disagree -> named error
    with pytest.raises(TargetError, match="mlp_opacity"):
        b.check_decoder(model, "mlp_opacity")


def test_a_model_without_the_add_level_option_has_no_level_input():
    """Octree-AnyGS's model has no add_level option: its decoders take [feat, view] (+ appearance)."""
    decs = dict(mlp_opacity=nn.Linear(7, 2), mlp_cov=nn.Linear(7, 2), mlp_color=nn.Linear(7, 2))
    model = SimpleNamespace(feat_dim=4, _anchor=torch.zeros(2, 3), _level=torch.zeros(2, 1), _extra_level=torch.zeros(2),
                            set_anchor_mask=lambda *a: None, **decs)
    b = OctreeGSBackend()
    assert b.matches(model)
    assert b.input_layout(model, "mlp_cov") == [("feat", 4), ("view", 3)]


def test_rows_are_the_lod_anchors_the_visibility_mask_keeps():
    lod = torch.tensor([True, False, True, True, False, True])
    frustum_lod_only = torch.tensor([True, False, True, True])  # over anchors 0, 2, 3, 5
    assert lod_anchor_ids(lod, frustum_lod_only).tolist() == [0, 3, 5]
    full = torch.tensor([True, True, False, True, False, True])  # prefilter_voxel's full-length mask
    assert lod_anchor_ids(lod, full).tolist() == [0, 3, 5]
    with pytest.raises(ShapeError, match="frustum_mask"):
        lod_anchor_ids(lod, torch.ones(5, dtype=torch.bool))
    with pytest.raises(InputValueError, match="anchor_mask must have dtype"):
        lod_anchor_ids(torch.tensor([1, 0, 1]), torch.tensor([True, True, True]))
    with pytest.raises(InputValueError, match="frustum_mask must have dtype"):
        lod_anchor_ids(torch.tensor([True, False, True]), torch.tensor([1, 1, 1]))
    # a fresh model selects every anchor until set_anchor_mask
    m = _small(torch.zeros(3, 3), [0, 1, 0])
    assert m._anchor_mask.dtype == torch.bool and m._anchor_mask.tolist() == [True, True, True]
    assert OctreeGSBackend().anchor_ids(m, torch.tensor([True, False, True])).tolist() == [0, 2]

    class NoMask:
        pass

    with pytest.raises(InputValueError, match="model has no _anchor_mask: call model.set_anchor_mask"):
        OctreeGSBackend().anchor_ids(NoMask(), torch.ones(3, dtype=torch.bool))


# -------------------------------------------------------------------------------- level of detail
@pytest.mark.parametrize("rule", ["round", "floor", "ceil"])
def test_lod_mask_matches_a_float64_reference(rule):
    """Each dist2level rule against the float64 reference; for 'round' at resolution scales 1, 2 and 0.5 (a
    larger scale reads as farther: coarser levels), also through visible_anchors."""
    seed, cam = (1, torch.tensor([0.3, -0.2, 4.0])) if rule == "round" else (2, torch.tensor([0.1, 0.2, 2.5]))
    arr = _arrays(seed)
    model = _model(arr, _decoders(_gen(seed)))
    model.dist2level = rule
    model.set_anchor_mask(cam, -1, 1.0)
    want = _lod64(arr, cam, rule=rule)
    assert model._anchor_mask.tolist() == want
    assert 0 < sum(want) < A  # the view selects a proper subset
    if rule != "round":
        # the rule matters here: some anchor's level lies between the clamped floor(pred) and ceil(pred)
        assert want != _lod64(arr, cam, rule="floor" if rule == "ceil" else "ceil")
        return
    counts = {}
    for scale in (2.0, 0.5):
        model.set_anchor_mask(cam, -1, scale)
        assert model._anchor_mask.tolist() == _lod64(arr, cam, scale=scale), scale
        counts[scale] = int(model._anchor_mask.sum())
    assert counts[2.0] < counts[0.5]
    # visible_anchors passes its resolution_scale on to the LOD selection
    c = make_camera()
    model.visible_anchors(c, resolution_scale=0.25)
    m2 = model._anchor_mask.clone()
    model.set_anchor_mask(c.center, -1, 0.25)
    assert torch.equal(m2, model._anchor_mask)
    model.set_anchor_mask(c.center, -1, 1.0)
    assert not torch.equal(m2, model._anchor_mask)  # for this camera, scales 1 and 0.25 select different sets


def test_lod_defaults_are_fork_2_round_voxel_centre_and_resolution_scale_1():
    rng = np.random.default_rng(4)
    a, k, f = 40, 2, 8
    arr = {"anchor": rng.normal(size=(a, 3)).astype(np.float32), "level": rng.integers(0, 4, a),
           "extra": rng.uniform(-0.4, 0.4, a).astype(np.float32)}
    torch.manual_seed(4)
    model = OctreeGSModel(  # fork, levels, dist2level, voxel_centre left at their defaults
        anchor=torch.from_numpy(arr["anchor"]), offset=torch.zeros(a, k, 3), anchor_feat=torch.zeros(a, f),
        scaling=torch.full((a, 6), -2.0), level=torch.tensor(arr["level"])[:, None], extra_level=torch.from_numpy(arr["extra"]),
        mlp_opacity=nn.Sequential(nn.Linear(f + 3, k), nn.Tanh()), mlp_cov=nn.Sequential(nn.Linear(f + 3, 7 * k)),
        mlp_color=nn.Sequential(nn.Linear(f + 3, 3 * k), nn.Sigmoid()), voxel_size=0.1, standard_dist=3.0)
    assert model.fork == 2 and model.dist2level == "round"  # Octree-GS's defaults (arguments/__init__.py)
    cam = torch.tensor([0.2, -0.1, 3.0])
    model.set_anchor_mask(cam)  # iteration, resolution_scale defaults
    want = _lod64(arr, cam, voxel=0.1, std=3.0, fork=2)
    assert model._anchor_mask.tolist() == want and 0 < sum(want) < a
    want2 = _lod64(arr, cam, scale=0.25, voxel=0.1, std=3.0, fork=2)
    assert want2 != want  # resolution_scale matters for this view
    model.set_anchor_mask(cam, -1, 0.25)
    assert model._anchor_mask.tolist() == want2


def test_map_to_int_level_by_hand():
    """Octree-GS's map_to_int_level: round/floor/ceil then clamp to [0, cur_level]; 'progressive' takes
    floor(clamp(pred + 1, 0.9999, cur_level + 0.9999)) and keeps the fraction as the opacity ratio."""
    m = _small(torch.zeros(4, 3), [0, 1, 2, 2])
    pred = torch.tensor([-1.2, 0.6, 1.4, 7.0])
    for mode, want in (("round", [0, 1, 1, 2]), ("floor", [0, 0, 1, 2]), ("ceil", [0, 1, 2, 2])):
        m.dist2level = mode
        assert m.map_to_int_level(pred, 2).tolist() == want, mode
    m.dist2level = "progressive"
    # pred + 1 = [-2, 1.25, 2.5, 8] -> clamped to [0.9999, 1.25, 2.5, 2.9999] -> floor [0, 1, 2, 2]
    assert m.map_to_int_level(torch.tensor([-3.0, 0.25, 1.5, 7.0]), 2).tolist() == [0, 1, 2, 2]
    assert torch.allclose(m._prog_ratio[:, 0], torch.tensor([0.9999, 0.25, 0.5, 0.9999]), atol=1e-5)
    assert m.transition_mask.tolist() == [True, True, True, True]  # each anchor's level is its predicted level


def test_lod_level_divides_by_log2_of_the_fork():
    """level(d) = log2(standard_dist / d) / log2(fork): standard_dist 16, fork 4, camera at the origin,
    anchors on +z (voxel_size 0: no centre shift). d = 1 -> 2, d = 4 -> 1, d = 16 -> 0."""
    z = torch.tensor([1.0, 4.0, 4.0, 16.0, 16.0])
    m = _small(torch.stack([torch.zeros(5), torch.zeros(5), z], dim=1), [2, 2, 1, 1, 0], fork=4)
    m.set_anchor_mask(torch.zeros(3))
    assert m._anchor_mask.tolist() == [True, False, True, False, True]


def test_levels_count_from_the_lowest_stored_level():
    """Octree-GS's loader: levels = max(level) - min(level) + 1, and the predicted level is clamped to
    levels - 1. Stored levels {1, 2}: 2 levels, so a close camera (level log2(16 / 1) = 4) selects up to
    level 1 only, as Octree-GS does."""
    m = _small(torch.tensor([[0.0, 0, 1], [0, 0, 1]]), [2, 1])
    assert m.levels == 2
    m.set_anchor_mask(torch.zeros(3))
    assert m._anchor_mask.tolist() == [False, True]


def test_progressive_lod_scales_the_opacity_of_transition_anchors():
    """dist2level='progressive': anchors at their transition level have their neural opacity scaled
    by the fractional level (float64 reference); the decoders' inputs are unchanged."""
    arr = _arrays(8)
    model = _model(arr, _decoders(_gen(8)))
    model.dist2level = "progressive"
    cam = torch.tensor([0.1, 0.0, 2.5])
    model.set_anchor_mask(cam)
    levels = int(arr["level"].max() - arr["level"].min() + 1)
    pos = arr["anchor"].astype(np.float64) + (VOXEL / 2) / FORK ** arr["level"][:, None]
    pred = np.log2(STD_DIST / np.linalg.norm(pos - cam.double().numpy(), axis=1)) / math.log2(FORK) + arr["extra"]
    p = np.clip(pred + 1.0, 0.9999, levels - 1 + 0.9999)
    level = np.floor(p)
    assert model._anchor_mask.tolist() == (arr["level"] <= level).tolist()
    ratio = np.where(arr["level"] == level, p - level, 1.0)
    ids = model._anchor_mask.nonzero().squeeze(1)
    w2c = torch.eye(4)
    w2c[:3, 3] = -cam
    with torch.no_grad():
        g = model.decode(Camera(w2c, torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]]), 32, 32), model._anchor_mask)
        raw = model.mlp_opacity(model.decoder_inputs(cam, ids)["mlp_opacity"])  # [R, K]
    want = raw.double() * torch.from_numpy(ratio[ids.numpy()])[:, None]
    assert torch.allclose(g.neural_opacity.double(), want.reshape(-1), atol=1e-6)
    assert bool((torch.from_numpy(ratio[ids.numpy()]) < 1).any())


def test_progressive_model_decodes_without_a_ratio_before_any_lod_selection():
    """Before set_anchor_mask there is no transition ratio: the progressive model decodes as the rounding one."""
    pos = torch.tensor([[0.0, 0, 0], [0.3, -0.2, 0.5]])
    cam = make_camera()
    prog = _small(pos, [0, 1], dist2level="progressive").decode(cam)
    rnd = _small(pos, [0, 1]).decode(cam)
    assert torch.equal(prog.opacities, rnd.opacities)


def test_model_refuses_an_unknown_dist2level():
    arr = _arrays(0)
    with pytest.raises(InputValueError, match="dist2level must be 'round', 'floor', 'ceil' or 'progressive', got 'nearest'"):
        OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                      anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                      level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                      voxel_size=0.1, standard_dist=3.0, dist2level="nearest", **_decoders(_gen(0)))


# ----------------------------------------------------------------------------------------- decoding
def test_decode_by_hand_with_level_bank_appearance_and_lod():
    """Octree-GS with add_level, add_opacity/color_dist, the feature bank (input [view, level]) and an
    appearance code (camera uid 2): the LOD mask (voxel-centre distance, round, clamp to the levels) and
    every decoded Gaussian by hand."""
    a, k, f, fork, voxel, std = 40, 3, 8, 2, 0.2, 10.0
    rng = np.random.default_rng(3)
    anchor = torch.from_numpy(rng.uniform(-1.0, 1.0, (a, 3))).float()
    offset, feat = torch.randn(a, k, 3), torch.randn(a, f)
    scaling = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    level = torch.from_numpy(rng.integers(0, 3, (a, 1))).int()
    extra = torch.from_numpy(rng.uniform(-0.5, 0.5, a)).float()
    torch.manual_seed(5)
    decs = {"mlp_opacity": mlp(f + 5, f, k, nn.Tanh()), "mlp_cov": mlp(f + 4, f, 7 * k, None),
            "mlp_color": mlp(f + 5 + 2, f, 3 * k, nn.Sigmoid()), "mlp_feature_bank": mlp(4, f, 3, nn.Softmax(dim=1)),
            "embedding_appearance": nn.Embedding(4, 2)}
    model = OctreeGSModel(anchor=anchor, offset=offset, anchor_feat=feat, scaling=scaling, level=level, extra_level=extra,
                          voxel_size=voxel, standard_dist=std, fork=fork, levels=3, add_level=True,
                          add_opacity_dist=True, add_color_dist=True, **decs)
    cam = oblique_camera(uid=2)
    centre = camera_centre(cam)
    # LOD by hand: level(dist) = round(log2(std / dist) / log2(fork) + extra), clamped to [0, 2]
    pos = anchor.to(D) + (voxel / 2) / fork ** level.to(D)
    pred = torch.log2(std / (pos - centre).norm(dim=1)) / math.log2(fork) + extra.to(D)
    lod = level[:, 0] <= torch.round(pred).clamp(0, 2).int()
    assert 0 < int(lod.sum()) < a  # the LOD mask drops some anchors
    visible = model.visible_anchors(cam)
    assert torch.equal(visible, lod)  # every anchor is inside the frustum: visible = LOD
    with torch.no_grad():
        got = model.decode(cam, visible)
    code = decs["embedding_appearance"].weight.detach().to(D)[2]
    expected = {}
    for i in lod.nonzero()[:, 0].tolist():
        d = anchor[i].to(D) - centre
        dist, view, lv = d.norm(), d / d.norm(), level[i].to(D)
        w = mlp64(decs["mlp_feature_bank"], torch.cat([view, lv])[None])[0]
        fb = feature_bank64(feat[i].to(D), w)
        op = mlp64(decs["mlp_opacity"], torch.cat([fb, view, dist[None], lv])[None])[0]
        cov = mlp64(decs["mlp_cov"], torch.cat([fb, view, lv])[None])[0].reshape(k, 7)
        col = mlp64(decs["mlp_color"], torch.cat([fb, view, dist[None], lv, code])[None])[0].reshape(k, 3)
        s = torch.exp(scaling[i].to(D))
        for j in range(k):
            if op[j] > 0:
                expected[(i, j)] = gaussian64(anchor[i].to(D), offset[i, j].to(D), s, op[j], col[j], cov[j])
    assert expected
    assert_gaussians(got, expected)


def test_without_the_level_input_it_decodes_as_scaffold_gs_and_renders():
    """Without the level input, Octree-GS decodes as Scaffold-GS: compare with the reference model, whose
    prefilter is the frustum part of Octree-GS's (visible = LOD ∧ frustum)."""
    arr = _arrays(5)
    torch.manual_seed(5)
    decs = {"mlp_opacity": mlp(F + 4, F, K, nn.Tanh()), "mlp_cov": mlp(F + 4, F, 7 * K, None),
            "mlp_color": mlp(F + 4, F, 3 * K, nn.Sigmoid())}
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    model = OctreeGSModel(anchor=t["anchor"], offset=t["offset"], anchor_feat=t["feat"], scaling=t["scale"],
                          level=t["level"][:, None], extra_level=t["extra"], voxel_size=VOXEL, standard_dist=STD_DIST,
                          add_opacity_dist=True, add_cov_dist=True, add_color_dist=True, **decs)
    ref = reference_scaffold(t["anchor"], t["offset"], t["feat"], t["scale"], decs, dist=True)
    cam = make_camera()
    visible = model.visible_anchors(cam)
    assert torch.equal(visible, model._anchor_mask & ref.visible_anchors(cam))
    with torch.no_grad():
        assert_same_gaussians(model.decode(cam, visible), ref.decode(cam, visible))
        out = model.render(cam)
    assert out.color.shape == (3, cam.height, cam.width) and bool(out.alpha.max() > 0)


def _bank_folder(root, mode: str):
    """Octree-GS's folder with use_feat_bank (bank input [view, level]); 'split' also with an appearance
    code of width 4 for 3 cameras (appended last to the colour input). Returns arrays, bank, embedding."""
    app = 4 if mode == "split" else 0
    arr = _arrays(7)
    torch.manual_seed(7)
    decs = {"mlp_opacity": mlp(F + 5, F, K, nn.Tanh()), "mlp_cov": mlp(F + 4, F, 7 * K, None),
            "mlp_color": mlp(F + 4 + app, F, 3 * K, nn.Sigmoid())}
    bank = mlp(3 + 1, F, 3, nn.Softmax(dim=1))
    emb = Embedding(3, app) if app else None
    _write_dir(root, arr, decs, mode=mode)
    write_cfg_args(root / "cfg_args", **{**CFG, "use_feat_bank": True, "appearance_dim": app})
    it = root / "point_cloud" / "iteration_30000"
    if mode == "split":
        torch.jit.trace(bank, torch.randn(5, 4)).save(str(it / "feature_bank_mlp.pt"))
        torch.jit.trace(emb, torch.zeros(5, dtype=torch.long)).save(str(it / "embedding_appearance.pt"))
    else:
        torch.save({"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
                    "color_mlp": decs["mlp_color"].state_dict(), "feature_bank_mlp": bank.state_dict()},
                   it / "checkpoints.pth")
    return arr, bank, emb


@pytest.mark.parametrize("mode", ["split", "unite"])
def test_feature_bank_and_appearance_inputs_by_hand(tmp_path, mode):
    """The loaded bank turns [view, level] into three softmax weights that mix the feature channels
    (Scaffold-GS's bank); opacity takes [feat, view, dist, level], covariance [feat, view, level], colour
    [feat, view, level] then the camera's appearance code. Float64 from the raw weights."""
    arr, bank, emb = _bank_folder(tmp_path / mode, mode)
    model = load_octree_gs_dir(tmp_path / mode)
    assert model.use_feat_bank and model.appearance_dim == (4 if emb else 0)
    assert OctreeGSBackend().default_targets(model) == ["mlp_opacity", "mlp_cov", "mlp_color"]
    assert "mlp_feature_bank" in OctreeGSBackend().decoder_paths(model)
    cam = torch.tensor([0.2, -0.1, 3.0])
    ids = torch.tensor([0, 2, 3, 7, 11])
    x = model.decoder_inputs(cam, ids, **({"appearance_id": 2} if emb else {}))
    d = torch.from_numpy(arr["anchor"]).double()[ids] - cam.double()
    dist = d.norm(dim=1, keepdim=True)
    lvl = torch.from_numpy(arr["level"]).double()[ids, None]
    w = mlp64(bank, torch.cat([d / dist, lvl], dim=1))
    assert torch.allclose(w.sum(dim=1), torch.ones(len(ids), dtype=D))
    feat = torch.stack([feature_bank64(f, wi) for f, wi in zip(torch.from_numpy(arr["feat"]).double()[ids], w)])
    code = [emb.embedding.weight.detach().double()[2].expand(len(ids), -1)] if emb else []
    assert torch.allclose(x["mlp_opacity"].double(), torch.cat([feat, d / dist, dist, lvl], dim=1), atol=1e-5)
    assert torch.allclose(x["mlp_cov"].double(), torch.cat([feat, d / dist, lvl], dim=1), atol=1e-5)
    assert torch.allclose(x["mlp_color"].double(), torch.cat([feat, d / dist, lvl, *code], dim=1), atol=1e-5)


def test_appearance_code_comes_from_the_camera_uid_or_appearance_id():
    """The colour decoder takes the appearance code last: ``appearance_id`` when given (required by
    decoder_inputs), else the camera's ``extra["uid"]``, else camera 0; decode takes no other option."""
    arr = _arrays(0)
    decs = _decoders(_gen(0))
    emb = nn.Embedding(3, 2)
    decs["mlp_color"] = nn.Sequential(nn.Linear(F + 3 + 1 + 2, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())
    m = OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                      anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                      level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                      voxel_size=0.1, standard_dist=3.0, add_level=True, add_opacity_dist=True, embedding_appearance=emb,
                      **decs)
    ids = torch.tensor([0, 3])
    with pytest.raises(InputValueError, match="appearance_id is required"):
        m.decoder_inputs(torch.zeros(3), ids)
    x = m.decoder_inputs(torch.zeros(3), ids, appearance_id=2)["mlp_color"]
    assert torch.equal(x[:, -2:], emb.weight[2].detach().expand(2, 2))  # the code of camera 2, last
    cam = make_camera()
    assert "uid" not in cam.extra
    with torch.no_grad():
        g0, g1, g2 = (m.decode(cam, appearance_id=i) for i in range(3))
        assert torch.equal(m.decode(cam).colors, g0.colors)
        assert not torch.equal(g0.colors, g1.colors) and not torch.equal(g0.colors, g2.colors)
        cam.extra["uid"] = 2
        assert torch.equal(m.decode(cam).colors, g2.colors)
        m.render(cam, appearance_id=None)
        with pytest.raises(InputValueError, match=r"OctreeGSModel\.decode got unknown option\(s\) \['appearance'\]"):
            m.render(cam, appearance=1)


def test_a_model_built_without_anchor_opacity_keeps_the_opacity_layout():
    """Octree-GS keeps one opacity per anchor (``_opacity [A, 1]``, class docstring); a model built without one
    (a ``point_cloud.ply`` with no ``opacity`` column) has the same layout, so parameters move between the two."""

    def build(opacity):
        g = _gen(3)
        a, k, f = 6, 2, 4
        return OctreeGSModel(
            anchor=torch.randn(a, 3, generator=g), offset=torch.zeros(a, k, 3), anchor_feat=torch.randn(a, f, generator=g),
            scaling=torch.full((a, 6), -2.0), level=torch.randint(0, 3, (a, 1), generator=g), extra_level=torch.zeros(a),
            mlp_opacity=nn.Sequential(nn.Linear(f + 3, k), nn.Tanh()), mlp_cov=nn.Sequential(nn.Linear(f + 3, 7 * k)),
            mlp_color=nn.Sequential(nn.Linear(f + 3, 3 * k), nn.Sigmoid()), voxel_size=0.1, standard_dist=3.0,
            opacity=opacity)

    given = torch.linspace(-1.0, 1.0, 6)[:, None]
    with_file, without = build(given), build(None)
    assert without._opacity.shape == with_file._opacity.shape == (6, 1)
    without.load_state_dict(with_file.state_dict())  # strict: every tensor of one fits the other
    assert torch.equal(without._opacity, given)


# ------------------------------------------------------------------------------------------- loader
@pytest.mark.parametrize("mode", ["split", "unite"])
def test_folder_loads_the_newest_iteration_with_its_lod_metadata(tmp_path, mode):
    arr, decs = _arrays(2), _decoders(_gen(2))
    root = _write_dir(tmp_path / "scene", arr, decs, mode=mode)
    (root / "point_cloud" / "iteration_7000").mkdir()  # an older iteration: the highest is taken
    model = load_octree_gs_dir(root)
    assert torch.equal(model._anchor, torch.from_numpy(arr["anchor"]))
    assert torch.equal(model._offset, torch.from_numpy(arr["offset"]))
    assert model._level.squeeze(1).tolist() == arr["level"].tolist()
    assert (model.voxel_size, model.standard_dist, model.fork) == (pytest.approx(VOXEL), STD_DIST, FORK)
    ref = _model(arr, decs)
    cam = torch.tensor([0.5, 0.1, 3.0])
    model.set_anchor_mask(cam)
    ref.set_anchor_mask(cam)
    assert torch.equal(model._anchor_mask, ref._anchor_mask)
    frustum = torch.arange(int(model._anchor_mask.sum())) % 3 != 1  # the visibility filter's radii > 0 over LOD anchors
    ids = OctreeGSBackend().anchor_ids(model, frustum)
    assert torch.equal(ids, lod_anchor_ids(ref._anchor_mask, frustum)) and len(ids) >= 2
    want = outputs(ref, ref.decoder_inputs(cam, ids))
    for p, y in outputs(model, model.decoder_inputs(cam, ids)).items():
        assert torch.equal(y, want[p]), p


def test_two_anchors_hold_voxel_size_and_standard_dist_in_info(tmp_path):
    """Octree-GS keeps voxel_size and standard_dist in rows 0 and 1 of the 'info' column: a file with exactly
    two anchors holds both and loads, with those two values; one anchor cannot."""
    root = _write_dir(tmp_path / "o", _arrays(2), _decoders(_gen(2)), mode="unite")
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {n: np.ascontiguousarray(c[:2]) for n, c in fields.items()})
    m = load_octree_gs_dir(root)
    assert m.get_anchor.shape[0] == 2
    assert m.voxel_size == pytest.approx(VOXEL, rel=1e-6)
    assert m.standard_dist == pytest.approx(STD_DIST, rel=1e-6)
    write_ply(ply, {n: c[:1] for n, c in fields.items()})
    with pytest.raises(FileFormatError, match=r"'info'.*voxel_size and standard_dist in rows 0 and 1.*1 anchors"):
        load_octree_gs_dir(root)


def test_six_scales_are_read_when_another_tool_adds_scale_columns(tmp_path):
    """Octree-GS anchors have six scales (``scale_0..5``: offset extent and Gaussian size); a PLY carrying a
    further ``scale_6`` column (appended by another tool) still loads as ``[A, 6]`` from the first six."""
    arr = _arrays(1)
    _write_dir(tmp_path, arr, _decoders(_gen(1)))
    ply = tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    rewrite_ply(ply, scale_6=np.full(A, 9.0))
    assert torch.equal(load_octree_gs_dir(tmp_path)._scaling, torch.from_numpy(arr["scale"]))


def test_cfg_args_without_widths_or_options_takes_octree_gs_defaults(tmp_path):
    """Octree-GS's ModelParams (arguments/__init__.py): feat_dim 32, n_offsets 10, fork 2, add_*_dist and
    add_level False, dist2level 'round'."""
    _defaults_dir(tmp_path / "o")
    m = load_octree_gs_dir(tmp_path / "o")
    assert (m.feat_dim, m.n_offsets, m.fork, m.dist2level) == (32, 10, 2, "round")
    assert not (m.add_level or m.add_opacity_dist or m.add_cov_dist or m.add_color_dist)
    assert OctreeGSBackend().input_layout(m, "mlp_opacity") == [("feat", 32), ("view", 3)]
    # keys missing from cfg_args take those defaults next to the keys given (4 offsets need n_offsets)
    root = _write_dir(tmp_path / "u", _arrays(1), _decoders(_gen(1)), mode="unite")
    write_cfg_args(root / "cfg_args", n_offsets=K, add_opacity_dist=True, add_level=True)
    m = load_octree_gs_dir(root)
    assert (m.fork, m.dist2level, m.feat_dim, m.add_level, m.add_cov_dist, m.add_color_dist) == (2, "round", 32, True,
                                                                                             False, False)


def test_loader_refusals_name_the_file_and_what_is_wrong(tmp_path):
    arr, decs = _arrays(3), _decoders(_gen(3))
    root = _write_dir(tmp_path / "s", arr, decs)
    write_cfg_args(root / "cfg_args", **{**CFG, "add_level": False})  # widths no longer fit the configuration
    with pytest.raises(FileFormatError, match="mlp_opacity takes 37 inputs"):
        load_octree_gs_dir(root)
    write_cfg_args(root / "cfg_args", **{**CFG, "feat_dim": 16})
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: 32 f_anchor_feat_\* fields, .*cfg_args says feat_dim=16"):
        load_octree_gs_dir(root)
    write_cfg_args(root / "cfg_args", **CFG)
    it = root / "point_cloud" / "iteration_30000"
    (it / "cov_mlp.pt").unlink()
    with pytest.raises(FileFormatError, match="cov_mlp.pt"):
        load_octree_gs_dir(root)
    with pytest.raises(FileFormatError, match="iteration_5"):
        load_octree_gs_dir(root, iteration=5)
    (root / "cfg_args").unlink()
    with pytest.raises(FileFormatError, match="neither 'cfg_args' \\(Octree-GS\\) nor 'config.yaml'"):
        load_octree_gs_dir(root)
    ply = _defaults_dir(tmp_path / "r")
    rewrite_ply(ply, rot_3=None)
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_octree_gs_dir(tmp_path / "r")


def test_a_folder_with_a_malicious_decoder_fails_cleanly(tmp_path):
    folder = _write_dir(tmp_path / "scene", _arrays(2), _decoders(_gen(2)))
    assert isinstance(load_octree_gs_dir(folder).mlp_cov, nn.Sequential)
    target = tmp_path / "victim"
    torch.jit.script(SetState(str(target))).save(str(folder / "point_cloud" / "iteration_30000" / "cov_mlp.pt"))
    with pytest.raises(FileFormatError, match=r"cov_mlp\.pt.*__setstate__"):
        load_octree_gs_dir(folder)
    assert not target.exists()


# ------------------------------------------------------------------------------------ Octree-AnyGS
def test_anygs_folder_loads_with_its_lod_metadata_from_obj_info(tmp_path):
    """Octree-AnyGS (Scaffold-GS base): config.yaml, PLY without info/opacity, LOD metadata in obj_info,
    distances from the raw anchor (no voxel centre)."""
    arr = _arrays(6)
    root = tmp_path / "anygs"
    it = write_anygs_dir(root, arr, anygs_decoders(6))
    model = load_octree_gs_dir(root)
    assert OctreeGSBackend().matches(model) and not model.voxel_centre and model.levels == 3
    assert [n for n, _ in OctreeGSBackend().input_layout(model, "mlp_color")] == ["feat", "view"]
    cam = torch.tensor([0.2, 0.4, 3.5])
    model.set_anchor_mask(cam)
    d = np.linalg.norm(arr["anchor"].astype(np.float64) - cam.double().numpy(), axis=1)  # raw anchor, no voxel centre
    pred = np.log2(STD_DIST / d) / math.log2(FORK) + arr["extra"]
    assert model._anchor_mask.tolist() == (arr["level"] <= np.clip(np.round(pred), 0, 2)).tolist()
    (root / "config.yaml").write_text(ANYGS_YAML % (F, K, "3dgs"))
    with pytest.raises(FileFormatError, match="config.yaml.*base_model '3dgs'"):
        load_octree_gs_dir(root)
    (root / "config.yaml").write_text(ANYGS_YAML % (F, K, "scaffoldgs"))
    write_ply(it / "point_cloud.ply", anygs_fields(arr))  # LOD metadata lost
    with pytest.raises(FileFormatError, match="obj_info standard_dist"):
        load_octree_gs_dir(root)


def test_anygs_config_without_widths_takes_gaussian_lod_model_defaults(tmp_path):
    """Octree-AnyGS's GaussianLoDModel defaults: feat_dim 32, n_offsets 10, fork 2, dist2level 'round',
    base model Scaffold-GS: a config.yaml naming none of them reads a folder of those widths; both LOD
    header lines are required."""
    a, f, k = 6, 32, 10
    rng = np.random.default_rng(0)
    root = tmp_path / "anygs"
    it = root / "point_cloud" / "iteration_5"
    it.mkdir(parents=True)
    (root / "config.yaml").write_text("optim_params: {\n    iterations: 40_000,\n}\n")
    fields = {c: rng.normal(size=a).astype(np.float32) for c in "xyz"}
    fields.update(level=np.zeros(a, np.float32), extra_level=np.zeros(a, np.float32))
    fields.update({f"f_offset_{i}": rng.normal(size=a).astype(np.float32) for i in range(3 * k)})
    fields.update({f"f_anchor_feat_{i}": rng.normal(size=a).astype(np.float32) for i in range(f)})
    fields.update({f"scale_{i}": np.full(a, -2.0, np.float32) for i in range(6)})
    write_ply(it / "point_cloud.ply", fields, comments=["standard_dist 3.0", "levels 2"], comment_keyword="obj_info")
    torch.manual_seed(0)
    torch.save({"opacity_mlp": mlp(f + 3, f, k, nn.Tanh()).state_dict(), "cov_mlp": mlp(f + 3, f, 7 * k, None).state_dict(),
                "color_mlp": mlp(f + 3, f, 3 * k, nn.Sigmoid()).state_dict()}, it / "checkpoints.pth")
    m = load_octree_gs_dir(root)
    assert (m.feat_dim, m.n_offsets, m.fork, m.dist2level, m.levels, m.standard_dist) == (32, 10, 2, "round", 2, 3.0)
    assert not m.voxel_centre and m.voxel_size == 0.0
    write_ply(it / "point_cloud.ply", fields, comments=["standard_dist 3.0"], comment_keyword="obj_info")
    with pytest.raises(FileFormatError, match="must carry 'obj_info standard_dist <v>' and 'obj_info levels <v>'"):
        load_octree_gs_dir(root)


def test_anygs_config_refusals_name_the_key(tmp_path):
    root = tmp_path / "anygs"
    (root / "point_cloud" / "iteration_1").mkdir(parents=True)
    (root / "config.yaml").write_text("a: {\n  feat_dim: 32,\n}\nb: {\n  feat_dim: 16,\n}\n")
    with pytest.raises(FileFormatError, match=r"config.yaml: key 'feat_dim' has several values \[32, 16\]"):
        load_octree_gs_dir(root)
    (root / "config.yaml").write_text("a: {\n  base_model: 'gaussians',\n}\n")
    with pytest.raises(FileFormatError, match="config.yaml.*base_model 'gaussians'"):
        load_octree_gs_dir(root)
