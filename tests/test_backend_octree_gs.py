"""Octree-GS backend: recognition, LOD ∧ frustum row mapping, loading an output directory written
in Octree-GS's layout (TorchScript and 'unite' decoders), wrap/identity/injection/save-load, errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from _family_checks import check_wrap_identity_and_rows, outputs, write_cfg_args
from controlgs_adapter import Camera
from controlgs_adapter.formats.backbone import write_ply
from controlgs_adapter.backends.compgs import CompGSBackend
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel, load_octree_gs_dir, lod_anchor_ids
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
from controlgs_adapter.errors import FileFormatError, InputValueError, ShapeError, TargetError

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")  # torch.jit.trace/load: the format under test

A, K, F, FORK, VOXEL, STD_DIST = 14, 4, 32, 2, 0.1, 3.0
CFG = dict(feat_dim=F, n_offsets=K, fork=FORK, use_feat_bank=False, appearance_dim=0, add_opacity_dist=True,
           add_cov_dist=False, add_color_dist=False, add_level=True, dist2level="round", progressive=False,
           voxel_size=0.0, source_path="/data/scene", model_path="/out/scene")


def _decoders(gen: torch.Generator) -> dict[str, nn.Sequential]:
    torch.manual_seed(int(torch.randint(0, 10_000, (1,), generator=gen)))
    return {  # Octree-GS widths: [feat, view, (dist), (level)] -> F
        "mlp_opacity": nn.Sequential(nn.Linear(F + 3 + 1 + 1, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
        "mlp_cov": nn.Sequential(nn.Linear(F + 3 + 1, F), nn.ReLU(), nn.Linear(F, 7 * K)),
        "mlp_color": nn.Sequential(nn.Linear(F + 3 + 1, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid()),
    }


def _arrays(seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    level = rng.integers(0, 3, A)
    return {"anchor": rng.normal(size=(A, 3)).astype(np.float32), "offset": rng.normal(size=(A, K, 3)).astype(np.float32),
            "feat": rng.normal(size=(A, F)).astype(np.float32), "scale": rng.normal(-2, 0.3, size=(A, 6)).astype(np.float32),
            "level": level, "extra": rng.uniform(-0.4, 0.4, A).astype(np.float32)}


def _model(arr, decoders) -> OctreeGSModel:
    return OctreeGSModel(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                         anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]),
                         level=torch.from_numpy(arr["level"][:, None]), extra_level=torch.from_numpy(arr["extra"]),
                         voxel_size=VOXEL, standard_dist=STD_DIST, fork=FORK, add_level=True, add_opacity_dist=True,
                         **decoders)


def _write_dir(root, arr, decoders, *, mode="split", iteration=30000):
    """Octree-GS's on-disk layout, written independently of the loader."""
    root.mkdir(parents=True, exist_ok=True)
    write_cfg_args(root / "cfg_args", **CFG)
    it = root / "point_cloud" / f"iteration_{iteration}"
    it.mkdir(parents=True)
    info = np.zeros(A, np.float32)
    info[0], info[1] = VOXEL, STD_DIST
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2],
              "level": arr["level"].astype(np.float32), "extra_level": arr["extra"], "info": info}
    flat = arr["offset"].transpose(0, 2, 1).reshape(A, 3 * K)  # f_offset_{c*K + k}
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields["opacity"] = np.zeros(A, np.float32)
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    if mode == "split":
        for attr, fname in (("mlp_opacity", "opacity_mlp.pt"), ("mlp_cov", "cov_mlp.pt"), ("mlp_color", "color_mlp.pt")):
            dec = decoders[attr]
            torch.jit.trace(dec, torch.randn(5, dec[0].in_features)).save(str(it / fname))
    else:
        torch.save({"opacity_mlp": decoders["mlp_opacity"].state_dict(), "cov_mlp": decoders["mlp_cov"].state_dict(),
                    "color_mlp": decoders["mlp_color"].state_dict()}, it / "checkpoints.pth")
    return root


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


def test_scaffold_loader_refuses_an_octree_folder(tmp_path):
    """load_scaffold_dir would decode every level of detail at once: it names the Octree-GS loader."""
    gen = torch.Generator().manual_seed(4)
    root = _write_dir(tmp_path / "s", _arrays(4), _decoders(gen))
    with pytest.raises(FileFormatError, match=r"level, .*load_octree_gs_dir.*load_model_dir"):
        load_scaffold_dir(root)


def test_decode_matches_reference_scaffold_and_renders():
    """Without the level input, Octree-GS decodes as Scaffold-GS: compare with the reference model."""
    from _family_checks import assert_same_gaussians, make_camera, reference_scaffold

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


class _Embedding(nn.Module):
    """Scaffold/Octree-GS's appearance embedding wrapper (``embedding = nn.Embedding``)."""

    def __init__(self, n: int, dim: int) -> None:
        super().__init__()
        self.embedding = nn.Embedding(n, dim)

    def forward(self, ids: torch.Tensor) -> torch.Tensor:
        return self.embedding(ids)


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
