"""Tests of ``controlgs_adapter.backends.octree_gs``."""

from __future__ import annotations

import math
from types import SimpleNamespace

import helpers.octree_files as octree_t
import numpy as np
import pytest
import torch
from helpers.family_checks import check_wrap_identity_and_rows, make_camera, outputs, write_cfg_args
from helpers.octree_files import CFG, FORK, STD_DIST, VOXEL, A, F, K, _arrays, _decoders, _model, _write_dir
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import CompGSBackend, ResidualBlock, ResidualMLP
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel, load_octree_gs_dir, lod_anchor_ids
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError, TargetError
from controlgs_adapter.formats.backbone import read_ply, write_ply

ANYGS_YAML = """# Model Parameters
model_params: {
    model_config: {
        name: "GaussianLoDModel",
        kwargs: {
            feat_dim: %d,
            view_dim: 3,
            appearance_dim: 0,
            n_offsets: %d,
            fork: 2,
            visible_threshold: 0.9,
            dist2level: 'round',
            progressive: True,
            use_feat_bank: False,
            levels: -1,
        }
    },
    base_model: "%s",
    resolution_scales: [1.0],
}
optim_params: {
    iterations: 40_000,
}
"""


class _Embedding(nn.Module):
    """Scaffold/Octree-GS's appearance embedding wrapper (``embedding = nn.Embedding``)."""

    def __init__(self, n: int, dim: int) -> None:
        super().__init__()
        self.embedding = nn.Embedding(n, dim)

    def forward(self, ids: torch.Tensor) -> torch.Tensor:
        return self.embedding(ids)


def test_recognition_and_targets():
    gen = torch.Generator().manual_seed(0)
    model = _model(_arrays(), _decoders(gen))
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


def test_lod_mask_matches_float64_reference():
    gen = torch.Generator().manual_seed(1)
    arr = _arrays(1)
    model = _model(arr, _decoders(gen))
    cam = torch.tensor([0.3, -0.2, 4.0])
    model.set_anchor_mask(cam, -1, 1.0)
    levels = int(arr["level"].max() - arr["level"].min() + 1)
    want = []
    for a in range(A):
        lv = int(arr["level"][a])
        pos = arr["anchor"][a].astype(np.float64) + (VOXEL / 2) / FORK ** lv
        d = float(np.linalg.norm(pos - cam.double().numpy()))
        pred = math.log2(STD_DIST / d) / math.log2(FORK) + float(arr["extra"][a])
        want.append(lv <= min(max(int(np.round(pred)), 0), levels - 1))
    assert model._anchor_mask.tolist() == want
    assert 0 < sum(want) < A  # the view selects a proper subset


def test_lod_anchor_ids_both_mask_forms():
    lod = torch.tensor([True, False, True, True, False, True])
    frustum_lod_only = torch.tensor([True, False, True, True])  # over anchors 0, 2, 3, 5
    assert lod_anchor_ids(lod, frustum_lod_only).tolist() == [0, 3, 5]
    full = torch.tensor([True, True, False, True, False, True])  # prefilter_voxel's full-length mask
    assert lod_anchor_ids(lod, full).tolist() == [0, 3, 5]
    with pytest.raises(ShapeError, match="frustum_mask"):
        lod_anchor_ids(lod, torch.ones(5, dtype=torch.bool))


@pytest.mark.parametrize("mode", ["split", "unite"])
def test_load_dir_and_wrap(tmp_path, mode):
    gen = torch.Generator().manual_seed(2)
    arr, decs = _arrays(2), _decoders(gen)
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
    inputs = model.decoder_inputs(cam, ids)
    want = outputs(ref, ref.decoder_inputs(cam, ids))
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, want[p]), p
    check_wrap_identity_and_rows(model, inputs, ids, "octree_gs", 1, tmp_path, lambda: load_octree_gs_dir(root))


def test_loading_errors(tmp_path):
    gen = torch.Generator().manual_seed(3)
    arr, decs = _arrays(3), _decoders(gen)
    root = _write_dir(tmp_path / "s", arr, decs)
    it = root / "point_cloud" / "iteration_30000"
    (it / "cov_mlp.pt").unlink()
    with pytest.raises(FileFormatError, match="cov_mlp.pt"):
        load_octree_gs_dir(root)
    with pytest.raises(FileFormatError, match="iteration_5"):
        load_octree_gs_dir(root, iteration=5)
    (root / "cfg_args").unlink()
    with pytest.raises(FileFormatError, match="cfg_args"):
        load_octree_gs_dir(root)
    root2 = _write_dir(tmp_path / "s2", arr, decs)
    write_cfg_args(root2 / "cfg_args", **{**CFG, "add_level": False})  # widths no longer fit the configuration
    with pytest.raises(FileFormatError, match="mlp_opacity takes 37 inputs"):
        load_octree_gs_dir(root2)


def test_decode_matches_reference_scaffold_and_renders():
    """Without the level input, Octree-GS decodes as Scaffold-GS: compare with the reference model."""
    from helpers.family_checks import assert_same_gaussians, make_camera, reference_scaffold

    arr = _arrays(5)
    torch.manual_seed(5)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    model = OctreeGSModel(anchor=t["anchor"], offset=t["offset"], anchor_feat=t["feat"], scaling=t["scale"],
                          level=t["level"][:, None], extra_level=t["extra"], voxel_size=VOXEL, standard_dist=STD_DIST,
                          add_opacity_dist=True, add_cov_dist=True, add_color_dist=True, **decs)
    ref = reference_scaffold(t["anchor"], t["offset"], t["feat"], t["scale"], decs, dist=True)
    cam = make_camera()
    visible = model.visible_anchors(cam)
    assert torch.equal(visible, model._anchor_mask & ref.visible_anchors(cam))  # LOD ∧ frustum
    with torch.no_grad():
        assert_same_gaussians(model.decode(cam, visible), ref.decode(cam, visible))
        out = model.render(cam)
    assert out.color.shape == (3, cam.height, cam.width) and bool(out.alpha.max() > 0)


def test_load_octree_anygs_dir(tmp_path):
    """Octree-AnyGS (Scaffold-GS base): config.yaml, PLY without info/opacity, LOD metadata in obj_info."""
    arr = _arrays(6)
    torch.manual_seed(6)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 3, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}
    root = tmp_path / "anygs"
    it = root / "point_cloud" / "iteration_40000"
    it.mkdir(parents=True)
    (root / "config.yaml").write_text(ANYGS_YAML % (F, K, "scaffoldgs"))
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2],
              "level": arr["level"].astype(np.float32), "extra_level": arr["extra"]}
    flat = arr["offset"].transpose(0, 2, 1).reshape(A, 3 * K)
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields, comments=[f"standard_dist {STD_DIST}", "levels 3"], comment_keyword="obj_info")
    for attr, fname in (("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")):
        torch.jit.trace(decs[attr], torch.randn(5, F + 3)).save(str(it / fname))
    model = load_octree_gs_dir(root)
    assert OctreeGSBackend().matches(model) and not model.voxel_centre and model.levels == 3
    assert [n for n, _ in OctreeGSBackend().input_layout(model, "mlp_color")] == ["feat", "view"]
    cam = torch.tensor([0.2, 0.4, 3.5])
    model.set_anchor_mask(cam)
    d = np.linalg.norm(arr["anchor"].astype(np.float64) - cam.double().numpy(), axis=1)  # raw anchor, no voxel centre
    pred = np.log2(STD_DIST / d) / math.log2(FORK) + arr["extra"]
    assert model._anchor_mask.tolist() == (arr["level"] <= np.clip(np.round(pred), 0, 2)).tolist()
    ids = model._anchor_mask.nonzero().squeeze(1)
    check_wrap_identity_and_rows(model, model.decoder_inputs(cam, ids), ids, "octree_gs", 1, tmp_path,
                                 lambda: load_octree_gs_dir(root))
    (root / "config.yaml").write_text(ANYGS_YAML % (F, K, "3dgs"))
    with pytest.raises(FileFormatError, match="config.yaml.*base_model '3dgs'"):
        load_octree_gs_dir(root)
    (root / "config.yaml").write_text(ANYGS_YAML % (F, K, "scaffoldgs"))
    write_ply(it / "point_cloud.ply", fields)  # LOD metadata lost
    with pytest.raises(FileFormatError, match="obj_info standard_dist"):
        load_octree_gs_dir(root)


def test_load_feature_bank_and_appearance(tmp_path):
    """use_feat_bank (input [view, level]) and appearance_dim > 0 (code appended last to colour)."""
    app_dim, n_cams = 4, 3
    arr = _arrays(7)
    torch.manual_seed(7)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(F + 5, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 4 + app_dim, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}
    bank = nn.Sequential(nn.Linear(3 + 1, F), nn.ReLU(), nn.Linear(F, 3), nn.Softmax(dim=1))
    emb = _Embedding(n_cams, app_dim)
    root = _write_dir(tmp_path / "s", arr, decs)
    write_cfg_args(root / "cfg_args", **{**CFG, "use_feat_bank": True, "appearance_dim": app_dim})
    it = root / "point_cloud" / "iteration_30000"
    torch.jit.trace(bank, torch.randn(5, 4)).save(str(it / "feature_bank_mlp.pt"))
    torch.jit.trace(emb, torch.zeros(5, dtype=torch.long)).save(str(it / "embedding_appearance.pt"))
    model = load_octree_gs_dir(root)
    assert model.use_feat_bank and model.appearance_dim == app_dim
    cam = torch.tensor([0.0, 0.3, 3.0])
    ids = torch.tensor([1, 4, 5, 9])
    x = model.decoder_inputs(cam, ids, appearance_id=2)
    # float64 reference of the view-adaptive feature and the colour input
    a = torch.from_numpy(arr["anchor"]).double()[ids]
    d = a - cam.double()
    dist = d.norm(dim=1, keepdim=True)
    lvl = torch.from_numpy(arr["level"]).double()[ids, None]
    w = bank.double()(torch.cat([d / dist, lvl], dim=1))
    f = torch.from_numpy(arr["feat"]).double()[ids]
    feat = f[:, ::4].repeat(1, 4) * w[:, :1] + f[:, ::2].repeat(1, 2) * w[:, 1:2] + f * w[:, 2:]
    want_color = torch.cat([feat, d / dist, lvl, emb.embedding.weight.double()[2].expand(4, -1)], dim=1)
    assert torch.allclose(x["mlp_color"].double(), want_color, atol=1e-5)
    assert torch.allclose(x["mlp_opacity"].double(), torch.cat([feat, d / dist, dist, lvl], dim=1), atol=1e-5)
    assert OctreeGSBackend().default_targets(model) == ["mlp_opacity", "mlp_cov", "mlp_color"]
    assert "mlp_feature_bank" in OctreeGSBackend().decoder_paths(model)


def test_decode_takes_appearance_id_and_names_other_options():
    """Octree-GS's one decode option, ``appearance_id``, reaches decode through render; any other is named."""
    model = _model(_arrays(9), _decoders(torch.Generator().manual_seed(9)))
    w2c = torch.eye(4)
    w2c[2, 3] = 2.5
    cam = Camera(w2c, torch.tensor([[30.0, 0, 16], [0, 30.0, 16], [0, 0, 1]]), 32, 32)
    with torch.no_grad():
        model.render(cam, appearance_id=None)
        with pytest.raises(InputValueError, match=r"OctreeGSModel\.decode got unknown option\(s\) \['appearance'\]"):
            model.render(cam, appearance=1)


def test_progressive_opacity_ratio():
    """dist2level='progressive': anchors at their transition level have their neural opacity scaled
    by the fractional level (float64 reference); the decoders' inputs are unchanged."""
    arr = _arrays(8)
    model = _model(arr, _decoders(torch.Generator().manual_seed(8)))
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


@pytest.mark.parametrize("rule", ["floor", "ceil"])
def test_lod_mask_floor_and_ceil_match_float64_reference(rule):
    """dist2level 'floor' / 'ceil' (Octree-GS's options besides 'round'): the level the view predicts
    is rounded down / up, checked against math.floor / math.ceil in float64."""
    arr = _arrays(2)
    model = OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                          anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                          level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                          voxel_size=VOXEL, standard_dist=STD_DIST, fork=FORK, dist2level=rule, add_level=True,
                          add_opacity_dist=True, **_decoders(torch.Generator().manual_seed(2)))
    cam = torch.tensor([0.1, 0.2, 2.5])
    model.set_anchor_mask(cam, -1, 1.0)
    levels = int(arr["level"].max() - arr["level"].min() + 1)
    rnd = {"floor": math.floor, "ceil": math.ceil}[rule]
    want, preds = [], []
    for a in range(A):
        lv = int(arr["level"][a])
        pos = arr["anchor"][a].astype(np.float64) + (VOXEL / 2) / FORK ** lv
        pred = math.log2(STD_DIST / float(np.linalg.norm(pos - cam.double().numpy()))) / math.log2(FORK) + float(arr["extra"][a])
        preds.append(pred)
        want.append(lv <= min(max(rnd(pred), 0), levels - 1))
    assert model._anchor_mask.tolist() == want
    # the rule matters here: some anchor's level lies between the clamped floor(pred) and ceil(pred)
    assert any(max(math.floor(p), 0) < int(lv) <= min(math.ceil(p), levels - 1) for p, lv in zip(preds, arr["level"]))


def test_unite_feature_bank_weights_are_a_softmax_over_three(tmp_path):
    """'unite' mode (checkpoints.pth of state dicts) with use_feat_bank: the rebuilt bank turns each row's
    3 logits into weights summing to 1 (Scaffold-GS's Softmax(dim=1)); float64 reference by hand."""
    arr = _arrays(8)
    torch.manual_seed(8)
    decs = {"mlp_opacity": nn.Sequential(nn.Linear(F + 5, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}
    bank = nn.Sequential(nn.Linear(3 + 1, F), nn.ReLU(), nn.Linear(F, 3), nn.Softmax(dim=1))
    root = _write_dir(tmp_path / "u", arr, decs, mode="unite")
    write_cfg_args(root / "cfg_args", **{**CFG, "use_feat_bank": True})
    it = root / "point_cloud" / "iteration_30000"
    torch.save({"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
                "color_mlp": decs["mlp_color"].state_dict(), "feature_bank_mlp": bank.state_dict()}, it / "checkpoints.pth")
    model = load_octree_gs_dir(root)
    cam = torch.tensor([0.2, -0.1, 3.0])
    ids = torch.tensor([0, 2, 3, 7, 11])
    x = model.decoder_inputs(cam, ids)
    a = torch.from_numpy(arr["anchor"]).double()[ids]
    d = a - cam.double()
    dist = d.norm(dim=1, keepdim=True)
    lvl = torch.from_numpy(arr["level"]).double()[ids, None]
    w0, b0, w2, b2 = (t.detach().double() for t in (bank[0].weight, bank[0].bias, bank[2].weight, bank[2].bias))
    logits = (torch.cat([d / dist, lvl], dim=1) @ w0.T + b0).clamp(min=0) @ w2.T + b2  # [R, 3]
    w = logits.exp() / logits.exp().sum(dim=1, keepdim=True)
    f = torch.from_numpy(arr["feat"]).double()[ids]
    feat = f[:, ::4].repeat(1, 4) * w[:, :1] + f[:, ::2].repeat(1, 2) * w[:, 1:2] + f * w[:, 2:]
    assert torch.allclose(x["mlp_cov"].double(), torch.cat([feat, d / dist, lvl], dim=1), atol=1e-5)


D = torch.float64


def _camera(uid: int | None = None) -> Camera:
    """Non-square camera about 5 units from the origin, turned 0.1 rad about y, principal point off centre."""
    c, s = math.cos(0.1), math.sin(0.1)
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])
    w2c[:3, 3] = torch.tensor([-0.3, 0.2, 5.0])
    k = torch.tensor([[52.0, 0.0, 37.0], [0.0, 47.0, 21.0], [0.0, 0.0, 1.0]])
    return Camera(w2c, k, 72, 40, {} if uid is None else {"uid": uid})


def _centre(cam: Camera) -> torch.Tensor:
    """Camera centre -R^T t in float64 from the world-to-camera matrix."""
    w2c = cam.world_to_camera.to(D)
    return -(w2c[:3, :3].T @ w2c[:3, 3])


def _mlp(mod: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """Evaluate ``mod`` layer by layer in float64 by hand (Linear, ReLU, LeakyReLU, Tanh, Sigmoid,
    Softmax over dim 1, Sequential, CompGS's ResidualBlock / ResidualMLP)."""
    if isinstance(mod, nn.Sequential):
        for layer in mod:
            x = _mlp(layer, x)
        return x
    if isinstance(mod, nn.Linear):
        return x @ mod.weight.detach().to(D).T + mod.bias.detach().to(D)
    if isinstance(mod, nn.ReLU):
        return torch.where(x > 0, x, torch.zeros_like(x))
    if isinstance(mod, nn.LeakyReLU):
        return torch.where(x > 0, x, 0.01 * x)
    if isinstance(mod, nn.Tanh):
        return (torch.exp(x) - torch.exp(-x)) / (torch.exp(x) + torch.exp(-x))
    if isinstance(mod, nn.Sigmoid):
        return 1.0 / (1.0 + torch.exp(-x))
    if isinstance(mod, nn.Softmax):
        e = torch.exp(x - x.max(dim=1, keepdim=True).values)
        return e / e.sum(dim=1, keepdim=True)
    if isinstance(mod, ResidualBlock):
        return x + _mlp(mod.net, x)
    if isinstance(mod, ResidualMLP):
        skip = x if isinstance(mod.skip, nn.Identity) else _mlp(mod.skip, x)
        return _mlp(mod.tail_activation, _mlp(mod.net, x) + skip)
    if isinstance(mod, nn.Identity):
        return x
    raise TypeError(type(mod))


def _bank(feat: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Scaffold-GS's feature bank for one anchor: channel c mixes feat[4*(c mod F/4)], feat[2*(c mod F/2)]
    and feat[c] with the softmax weights w[0], w[1], w[2]."""
    f = feat.shape[0]
    c = torch.arange(f)
    return feat[4 * (c % (f // 4))] * w[0] + feat[2 * (c % (f // 2))] * w[1] + feat * w[2]


def _check(got, expected: dict[tuple[int, int], dict[str, torch.Tensor]]) -> None:
    """``got`` (NeuralGaussians) holds exactly the (anchor, offset) pairs of ``expected``, with its values."""
    pairs = [(int(a), int(k)) for a, k in zip(got.anchor_of, got.offset_of)]
    assert sorted(pairs) == sorted(expected)
    for g, key in enumerate(pairs):
        e = expected[key]
        for name in ("means", "scales", "rotations", "colors"):
            torch.testing.assert_close(getattr(got, name)[g].to(D), e[name], rtol=1e-5, atol=1e-6, msg=f"{name} {key}")
        torch.testing.assert_close(got.opacities[g].to(D), e["opacity"], rtol=1e-5, atol=1e-6)


def _gaussian(anchor, offset, s, opacity, color, cov) -> dict[str, torch.Tensor]:
    """One Scaffold-family Gaussian: mean = anchor + offset * s[:3], scale = s[3:] * sigmoid(cov[:3]),
    rotation = cov[3:7] / |cov[3:7]|."""
    return {"means": anchor + offset * s[:3], "scales": s[3:] / (1.0 + torch.exp(-cov[:3])),
            "rotations": cov[3:7] / cov[3:7].norm(), "colors": color, "opacity": opacity}


def _seq(d_in: int, d_hidden: int, d_out: int, tail: nn.Module | None) -> nn.Sequential:
    return nn.Sequential(nn.Linear(d_in, d_hidden), nn.ReLU(), nn.Linear(d_hidden, d_out), *([tail] if tail else []))


# ----------------------------------------------------------------------------------------- Octree-GS
def test_octree_gs_by_hand_with_level_bank_appearance_and_lod():
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
    decs = {"mlp_opacity": _seq(f + 5, f, k, nn.Tanh()), "mlp_cov": _seq(f + 4, f, 7 * k, None),
            "mlp_color": _seq(f + 5 + 2, f, 3 * k, nn.Sigmoid()), "mlp_feature_bank": _seq(4, f, 3, nn.Softmax(dim=1)),
            "embedding_appearance": nn.Embedding(4, 2)}
    model = OctreeGSModel(anchor=anchor, offset=offset, anchor_feat=feat, scaling=scaling, level=level, extra_level=extra,
                          voxel_size=voxel, standard_dist=std, fork=fork, levels=3, add_level=True,
                          add_opacity_dist=True, add_color_dist=True, **decs)
    cam = _camera(uid=2)
    centre = _centre(cam)
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
        w = _mlp(decs["mlp_feature_bank"], torch.cat([view, lv])[None])[0]
        fb = _bank(feat[i].to(D), w)
        op = _mlp(decs["mlp_opacity"], torch.cat([fb, view, dist[None], lv])[None])[0]
        cov = _mlp(decs["mlp_cov"], torch.cat([fb, view, lv])[None])[0].reshape(k, 7)
        col = _mlp(decs["mlp_color"], torch.cat([fb, view, dist[None], lv, code])[None])[0].reshape(k, 3)
        s = torch.exp(scaling[i].to(D))
        for j in range(k):
            if op[j] > 0:
                expected[(i, j)] = _gaussian(anchor[i].to(D), offset[i, j].to(D), s, op[j], col[j], cov[j])
    assert expected
    _check(got, expected)


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


# ------------------------------------------------------------------------------ Octree-GS anchor opacity
def _octree_2(opacity: torch.Tensor | None, a: int = 6, k: int = 2, f: int = 4):
    from controlgs_adapter.backends.octree_gs import OctreeGSModel

    g = torch.Generator().manual_seed(3)
    return OctreeGSModel(
        anchor=torch.randn(a, 3, generator=g), offset=torch.zeros(a, k, 3), anchor_feat=torch.randn(a, f, generator=g),
        scaling=torch.full((a, 6), -2.0), level=torch.randint(0, 3, (a, 1), generator=g), extra_level=torch.zeros(a),
        mlp_opacity=nn.Sequential(nn.Linear(f + 3, k), nn.Tanh()), mlp_cov=nn.Sequential(nn.Linear(f + 3, 7 * k)),
        mlp_color=nn.Sequential(nn.Linear(f + 3, 3 * k), nn.Sigmoid()), voxel_size=0.1, standard_dist=3.0,
        opacity=opacity)


def test_octree_model_without_file_opacity_keeps_octree_gs_anchor_opacity_layout():
    """Octree-GS keeps one opacity per anchor (``_opacity [A, 1]``, class docstring); a model built without one
    (a ``point_cloud.ply`` with no ``opacity`` column) has the same layout, so parameters move between the two."""
    given = torch.linspace(-1.0, 1.0, 6)[:, None]
    with_file = _octree_2(given)
    without = _octree_2(None)
    assert without._opacity.shape == with_file._opacity.shape == (6, 1)
    without.load_state_dict(with_file.state_dict())  # strict: every tensor of one fits the other
    assert torch.equal(without._opacity, given)


def _rewrite_ply(ply, **changes):
    fields, _ = read_ply(ply)
    for name, value in changes.items():
        if value is None:
            fields.pop(name)
        else:
            fields[name] = np.asarray(value, np.float32)
    write_ply(ply, fields)


def _octree_3(anchor, level, *, fork=2, voxel_size=0.0, standard_dist=16.0, dist2level="round", f=4, k=2, **kw):
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


def test_octree_map_to_int_level_by_hand():
    """Octree-GS's map_to_int_level: round/floor/ceil then clamp to [0, cur_level]; 'progressive' takes
    floor(clamp(pred + 1, 0.9999, cur_level + 0.9999)) and keeps the fraction as the opacity ratio."""
    m = _octree_3(torch.zeros(4, 3), [0, 1, 2, 2])
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
    m = _octree_3(torch.stack([torch.zeros(5), torch.zeros(5), z], dim=1), [2, 2, 1, 1, 0], fork=4)
    m.set_anchor_mask(torch.zeros(3))
    assert m._anchor_mask.tolist() == [True, False, True, False, True]


def test_octree_levels_count_from_the_lowest_stored_level():
    """Octree-GS's loader: levels = max(level) - min(level) + 1, and the predicted level is clamped to
    levels - 1. Stored levels {1, 2}: 2 levels, so a close camera (level log2(16 / 1) = 4) selects up to
    level 1 only, as Octree-GS does."""
    m = _octree_3(torch.tensor([[0.0, 0, 1], [0, 0, 1]]), [2, 1])
    assert m.levels == 2
    m.set_anchor_mask(torch.zeros(3))
    assert m._anchor_mask.tolist() == [False, True]


def test_octree_fresh_model_selects_every_anchor_and_lod_masks_must_be_bool():
    m = _octree_3(torch.zeros(3, 3), [0, 1, 0])
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
    prog = _octree_3(pos, [0, 1], dist2level="progressive").decode(cam)
    rnd = _octree_3(pos, [0, 1]).decode(cam)
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
    m = _octree_3(torch.tensor([[0.0, 0, 0], [0.3, -0.2, 0.5]]), [0, 0], app=2, embedding_appearance=nn.Embedding(3, 2))
    with torch.no_grad():
        m.mlp_opacity[2].bias.fill_(5.0)  # every Gaussian kept
    cam = make_camera()
    assert "uid" not in cam.extra
    assert torch.equal(m.decode(cam).colors, m.decode(cam, appearance_id=0).colors)
    assert not torch.equal(m.decode(cam).colors, m.decode(cam, appearance_id=1).colors)


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


def test_octree_refusals_and_appearance_id():
    arr = octree_t._arrays(0)
    decs = octree_t._decoders(torch.Generator().manual_seed(0))

    class NoMask:
        pass

    with pytest.raises(InputValueError, match="model has no _anchor_mask: call model.set_anchor_mask"):
        OctreeGSBackend().anchor_ids(NoMask(), torch.ones(3, dtype=torch.bool))
    with pytest.raises(InputValueError, match="dist2level must be 'round', 'floor', 'ceil' or 'progressive', got 'nearest'"):
        OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                      anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                      level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                      voxel_size=0.1, standard_dist=3.0, dist2level="nearest", **decs)
    emb = nn.Embedding(3, 2)
    f, k = octree_t.F, octree_t.K
    decs["mlp_color"] = nn.Sequential(nn.Linear(f + 3 + 1 + 2, f), nn.ReLU(), nn.Linear(f, 3 * k), nn.Sigmoid())
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
    assert m.fork == 2 and m.dist2level == "round"  # Octree-GS defaults (arguments/__init__.py)
    # decode() takes camera.extra["uid"] (default 0) when no appearance_id is given
    cam = make_camera()
    g0 = m.decode(cam)
    g2 = m.decode(cam, appearance_id=2)
    cam.extra["uid"] = 2
    assert torch.equal(m.decode(cam).colors, g2.colors) and not torch.equal(g0.colors, g2.colors)


def test_octree_loader_refusals_and_cfg_defaults(tmp_path):
    arr = octree_t._arrays(1)
    decs = octree_t._decoders(torch.Generator().manual_seed(1))
    root = octree_t._write_dir(tmp_path / "o", arr, decs, mode="unite")
    cfg = dict(octree_t.CFG)
    write_cfg_args(root / "cfg_args", **{**cfg, "feat_dim": 16})
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: 32 f_anchor_feat_\* fields, .*cfg_args says feat_dim=16"):
        load_octree_gs_dir(root)
    # keys missing from cfg_args take Octree-GS's ModelParams defaults: fork 2, dist2level 'round', n_offsets 10
    # (the folder has 4 offsets, so n_offsets must be given), feat_dim 32
    write_cfg_args(root / "cfg_args", n_offsets=octree_t.K, add_opacity_dist=True, add_level=True)
    m = load_octree_gs_dir(root)
    assert (m.fork, m.dist2level, m.feat_dim, m.add_level, m.add_cov_dist, m.add_color_dist) == (2, "round", 32, True,
                                                                                             False, False)
    # one anchor: the 'info' column cannot hold voxel_size and standard_dist in rows 0 and 1
    from controlgs_adapter.formats.backbone import read_ply, write_ply

    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {n: c[:1] for n, c in fields.items()})
    with pytest.raises(FileFormatError, match=r"'info' column holds voxel_size and standard_dist in rows 0 and 1; the "
                                              r"file has 1 anchors"):
        load_octree_gs_dir(root)


def test_octree_anygs_yaml_key_with_two_values_is_refused(tmp_path):
    root = tmp_path / "anygs"
    (root / "point_cloud" / "iteration_1").mkdir(parents=True)
    (root / "config.yaml").write_text("a: {\n  feat_dim: 32,\n}\nb: {\n  feat_dim: 16,\n}\n")
    with pytest.raises(FileFormatError, match=r"config.yaml: key 'feat_dim' has several values \[32, 16\]"):
        load_octree_gs_dir(root)
    (root / "config.yaml").write_text("a: {\n  base_model: 'gaussians',\n}\n")
    with pytest.raises(FileFormatError, match="base_model 'gaussians': only Octree-AnyGS's Scaffold-GS base model"):
        load_octree_gs_dir(root)
    (root / "config.yaml").unlink()
    with pytest.raises(FileFormatError, match="neither 'cfg_args' \\(Octree-GS\\) nor 'config.yaml'"):
        load_octree_gs_dir(root)


def test_octree_lod_distance_is_scaled_by_the_resolution_scale():
    """Octree-GS's set_anchor_mask: dist = |voxel centre - camera| * resolution_scale; a float64 reference
    at resolution_scale 2 and 0.5 (a larger scale reads as farther: coarser levels)."""
    arr = octree_t._arrays(1)
    model = octree_t._model(arr, octree_t._decoders(torch.Generator().manual_seed(1)))
    cam = torch.tensor([0.3, -0.2, 4.0])
    levels = int(arr["level"].max() - arr["level"].min() + 1)
    masks = {}
    for scale in (2.0, 0.5):
        model.set_anchor_mask(cam, -1, scale)
        want = []
        for a in range(octree_t.A):
            lv = int(arr["level"][a])
            pos = arr["anchor"][a].astype(np.float64) + (octree_t.VOXEL / 2) / octree_t.FORK ** lv
            d = float(np.linalg.norm(pos - cam.double().numpy())) * scale
            pred = math.log2(octree_t.STD_DIST / d) / math.log2(octree_t.FORK) + float(arr["extra"][a])
            want.append(lv <= min(max(int(np.round(pred)), 0), levels - 1))
        assert model._anchor_mask.tolist() == want, scale
        masks[scale] = want
    assert sum(masks[2.0]) < sum(masks[0.5])  # the two scales select different sets
    # visible_anchors passes its resolution_scale on to the LOD selection
    c = make_camera()
    model.visible_anchors(c, resolution_scale=0.25)
    m2 = model._anchor_mask.clone()
    model.set_anchor_mask(c.center, -1, 0.25)
    assert torch.equal(m2, model._anchor_mask)
    model.set_anchor_mask(c.center, -1, 1.0)
    assert not torch.equal(m2, model._anchor_mask)  # for this camera, scales 1 and 0.25 select different sets


class SetState(nn.Module):
    """A scripted ``__setstate__`` (run by ``torch.jit.load`` itself) that writes ``target``."""

    def __init__(self, target: str) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(4, 4))
        self.target = target

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight

    @torch.jit.export
    def __getstate__(self) -> tuple[str, torch.Tensor, bool]:
        return (self.target, self.weight, self.training)

    @torch.jit.export
    def __setstate__(self, state: tuple[str, torch.Tensor, bool]) -> None:
        self.target = state[0]
        t = torch.from_file(self.target, True, 8, dtype=torch.uint8)
        self.weight = state[1] + t[:1].float().fill_(0)
        self.training = state[2]


def test_octree_folder_with_a_malicious_decoder_fails_cleanly(tmp_path):
    from helpers.octree_files import _arrays, _decoders, _write_dir  # noqa: PLC0415 - the family's folder writer

    folder = _write_dir(tmp_path / "scene", _arrays(2), _decoders(torch.Generator().manual_seed(2)))
    assert isinstance(load_octree_gs_dir(folder).mlp_cov, nn.Sequential)
    target = tmp_path / "victim"
    evil = folder / "point_cloud" / "iteration_30000" / "cov_mlp.pt"
    torch.jit.script(SetState(str(target))).save(str(evil))
    with pytest.raises(FileFormatError, match=r"cov_mlp\.pt.*__setstate__"):
        load_octree_gs_dir(folder)
    assert not target.exists()


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
