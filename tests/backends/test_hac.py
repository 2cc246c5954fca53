"""Tests of ``controlgs_adapter.backends.hac``."""

from __future__ import annotations

import helpers.compgs_files as compgs_t
import helpers.contextgs_files as contextgs_t
import helpers.hac_files as hac_t
import helpers.octree_files as octree_t
import numpy as np
import pytest
import torch
from helpers.family_checks import check_wrap_identity_and_rows, make_camera, outputs, write_cfg_args
from helpers.hac_files import VOXEL, A, F, K, _arrays, _decoders, _write_dir
from torch import nn

from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.backends.compgs import CompGSBackend, CompGSModel
from controlgs_adapter.backends.contextgs import ContextGSBackend, ContextGSModel
from controlgs_adapter.backends.hac import HACBackend, HACModel, decoders_from_checkpoint, load_hac_dir, voxel_snap
from controlgs_adapter.backends.models.anchor_model import feature_bank
from controlgs_adapter.backends.octree_gs import OctreeGSBackend, OctreeGSModel
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.backbone import read_ply, write_ply


def _model(arr, decs, *, decoded: bool, variant: str = "hac++") -> HACModel:
    return HACModel(voxel_size=VOXEL, variant=variant, decoded_version=decoded, anchor=torch.from_numpy(arr["anchor"]),
                    offset=torch.from_numpy(arr["offset"]), mask=torch.from_numpy(arr["mask"])[:, :, None],
                    anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]), **decs)


def test_recognition_positions_and_validity():
    arr = _arrays(0, decoded=False, mask_cols=K + 1, invalid=(3, 7))
    model = _model(arr, _decoders(0), decoded=False)
    b = HACBackend()
    assert b.matches(model)
    assert not any(o.matches(model) for o in (ContextGSBackend(), OctreeGSBackend(), CompGSBackend()))
    assert b.default_targets(model) == ["mlp_opacity", "mlp_cov", "mlp_color"]
    assert b.input_layout(model, "mlp_cov") == [("feat", 50), ("view", 3), ("dist", 1)]
    # not decoded: the decoder sees voxel-snapped anchors (float64 reference)
    snapped = np.round(arr["anchor"].astype(np.float64) / VOXEL) * VOXEL
    assert np.allclose(b.anchor_positions(model).double().numpy(), snapped, atol=1e-6, rtol=0)
    assert not torch.equal(b.anchor_positions(model), model._anchor)
    # validity: some of the K offset masks on (sigmoid > 0.01); HAC++'s extra column does not count
    sig = 1 / (1 + np.exp(-arr["mask"][:, :K].astype(np.float64)))
    assert b.valid_anchors(model).tolist() == (sig > 0.01).any(axis=1).tolist()
    assert not b.valid_anchors(model)[[3, 7]].any()
    model.decoded_version = True  # decoded: positions as stored
    assert torch.equal(b.anchor_positions(model), model._anchor)


def test_live_model_keeps_invalid_anchor_rows(tmp_path):
    """On a live model, the condition table has one row per model anchor (invalid ones included)."""
    arr = _arrays(1, decoded=False, mask_cols=K + 1, invalid=(2,))
    model = _model(arr, _decoders(1), decoded=False)
    ids = torch.tensor([0, 2, 5, 6, 9])
    cam = torch.tensor([0.0, 0.0, -4.0])
    inputs = model.decoder_inputs(cam, ids)
    check_wrap_identity_and_rows(model, inputs, ids, "hac", 1, tmp_path,
                                 lambda: _model(arr, _decoders(1), decoded=False))


@pytest.mark.parametrize("variant", ["hac++", "hac"])
def test_load_decoded_dir_and_wrap(tmp_path, variant):
    cols = K + 1 if variant == "hac++" else K
    arr = _arrays(2, decoded=True, mask_cols=cols)
    if variant == "hac":  # HAC zero-pads the decoded arrays after the valid anchors
        for key in arr:
            arr[key][-3:] = 0.0
    decs = _decoders(2)
    root = _write_dir(tmp_path / "scene", arr, decs)
    model = load_hac_dir(root)
    assert model.variant == variant and model.decoded_version
    n_valid = A - (3 if variant == "hac" else 0)
    assert model.source_index.tolist() == list(range(n_valid))
    assert torch.equal(model.get_anchor, torch.from_numpy(arr["anchor"][:n_valid]))
    assert torch.equal(model.get_scaling, torch.from_numpy(arr["scale"][:n_valid]))  # linear, no exp
    assert torch.equal(model._offset, torch.from_numpy(arr["offset"][:n_valid]))
    assert model.encoding_xyz is None and model.mlp_grid is None
    cam = torch.tensor([0.2, 0.1, -5.0])
    ids = torch.arange(0, n_valid, 2)
    inputs = model.decoder_inputs(cam, ids)
    ref = _model({k: v[:n_valid] for k, v in arr.items()}, decs, decoded=True, variant=variant)
    want = outputs(ref, ref.decoder_inputs(cam, ids))
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, want[p]), p
    check_wrap_identity_and_rows(model, inputs, ids, "hac", 1, tmp_path, lambda: load_hac_dir(root))


def test_raw_dir_refused_unless_allowed(tmp_path):
    arr = _arrays(3, decoded=False, mask_cols=K + 1, invalid=(4,))
    root = _write_dir(tmp_path / "raw", arr, _decoders(3))
    with pytest.raises(FileFormatError, match="raw .*allow_unquantized"):
        load_hac_dir(root)
    model = load_hac_dir(root, allow_unquantized=True)
    assert not model.decoded_version and 4 not in model.source_index.tolist() and len(model.source_index) == A - 1
    keep = model.source_index.numpy()
    assert np.allclose(model.get_anchor.numpy(), np.round(arr["anchor"][keep] / VOXEL) * VOXEL, atol=1e-6)
    assert torch.allclose(model.get_scaling, torch.exp(torch.from_numpy(arr["scale"][keep])))
    with pytest.raises(FileFormatError, match="raw"):
        load_hac_dir(root, decoded=False)  # explicit flag, same refusal
    root0 = _write_dir(tmp_path / "raw0", arr, _decoders(3), voxel_size=0.0)
    with pytest.raises(FileFormatError, match="voxel_size"):
        load_hac_dir(root0, allow_unquantized=True)


def test_loading_errors(tmp_path):
    arr = _arrays(4, decoded=True, mask_cols=K + 1)
    root = _write_dir(tmp_path / "s", arr, _decoders(4))
    ckpt = root / "point_cloud" / "iteration_30000" / "checkpoint.pth"
    sd = torch.load(ckpt, weights_only=True)
    del sd["color_mlp"]
    torch.save(sd, ckpt)
    with pytest.raises(FileFormatError, match="checkpoint.pth.*color_mlp"):
        load_hac_dir(root)
    ckpt.unlink()
    with pytest.raises(FileFormatError, match="checkpoint.pth"):
        load_hac_dir(root)
    root2 = _write_dir(tmp_path / "s2", {**arr, "mask": arr["mask"][:, :4]}, _decoders(4))
    with pytest.raises(FileFormatError, match="f_mask_"):
        load_hac_dir(root2)


def test_decode_keeps_masked_offsets_out():
    """HAC++ decodes as Scaffold-GS with distance inputs, minus the Gaussians whose offset mask is off."""
    from helpers.family_checks import assert_same_gaussians, reference_scaffold

    arr = _arrays(5, decoded=True, mask_cols=K + 1)
    decs = _decoders(5)
    model = _model(arr, decs, decoded=True)
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    ref = reference_scaffold(t["anchor"], t["offset"], t["feat"], torch.log(t["scale"]), decs, dist=True)
    cam = make_camera()
    visible = model.visible_anchors(cam)
    assert torch.equal(visible, ref.visible_anchors(cam)) and bool(visible.any())
    with torch.no_grad():
        got, full = model.decode(cam, visible), ref.decode(cam, visible)
    on = t["mask"][full.anchor_of, full.offset_of] > 0
    assert bool((~on).any())  # some decoded Gaussians are masked off
    for f in ("means", "scales", "rotations", "opacities", "colors", "anchor_of", "offset_of"):
        setattr(full, f, getattr(full, f)[on])
    assert_same_gaussians(got, full, atol=1e-5)


@pytest.mark.parametrize("variant", ["hac++", "hac"])
def test_decoded_dir_with_scales_rounded_to_zero(tmp_path, variant):
    """The codecs store round(s / Q) * Q (Q about 1e-3): small scales are exactly 0, still decoded."""
    arr = _arrays(7, decoded=True, mask_cols=K + 1 if variant == "hac++" else K)
    arr["scale"][1:6, 2] = 0.0
    arr["scale"][9, :3] = 0.0
    root = _write_dir(tmp_path / "scene", arr, _decoders(7))
    model = load_hac_dir(root)
    assert model.decoded_version and torch.equal(model.get_scaling, torch.from_numpy(arr["scale"]))  # linear, no exp


def test_undecidable_dir_refused_even_with_allow_unquantized(tmp_path):
    """0/1 masks with negative scales: the loader asks for decoded= rather than guessing (reading
    linear scales as log scales, or the reverse, would be silently wrong)."""
    arr = _arrays(8, decoded=True, mask_cols=K + 1)
    arr["scale"][2, 0] = -0.5
    root = _write_dir(tmp_path / "scene", arr, _decoders(8))
    for kw in ({}, {"allow_unquantized": True}):
        with pytest.raises(FileFormatError, match=r"cannot tell .*1 scale_\* value.*decoded=True.*decoded=False"):
            load_hac_dir(root, **kw)
    assert load_hac_dir(root, decoded=True).decoded_version
    raw = _write_dir(tmp_path / "raw", _arrays(9, decoded=False, mask_cols=K + 1), _decoders(9))
    with pytest.raises(FileFormatError, match=r"mask logits and log scales.*allow_unquantized=True .*log scales exponentiated"):
        load_hac_dir(raw)


def test_feature_bank_at_width_50_refused(tmp_path):
    arr = _arrays(10, decoded=True, mask_cols=K + 1)
    root = _write_dir(tmp_path / "scene", arr, _decoders(10))
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=VOXEL, use_feat_bank=True)
    with pytest.raises(FileFormatError, match=r"use_feat_bank=True with feat_dim=50.*divisible by 4 \(50 channels give 52\)"):
        load_hac_dir(root)


def test_bitstreams_only_folder(tmp_path):

    root = tmp_path / "compressed"
    (root / "bitstreams").mkdir(parents=True)
    (root / "bitstreams" / "hash.b").write_bytes(b"\0")
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=VOXEL, use_feat_bank=False)
    for load in (load_hac_dir, load_model_dir):
        with pytest.raises(FileFormatError, match="bitstreams/ was found, but it cannot be decoded"):
            load(root)


def test_raw_mask_is_the_sigmoid_of_the_logits_above_0_01():
    """A raw (not decoded) model holds mask logits: HAC++'s ``get_mask`` switches an offset on where
    sigmoid(logit) > 0.01 (logit > -4.595), by hand here; HAC++'s extra K+1-th column is not an offset."""
    logits = [-6.0, -4.0, -2.0, 0.005, 0.5, -30.0, 3.0, -4.7, -4.5, 1.0]
    arr = _arrays(5, decoded=False, mask_cols=K + 1, n=2)
    arr["mask"][0, :K] = logits
    arr["mask"][0, K] = 9.0
    arr["mask"][1, :K] = -10.0
    model = _model(arr, _decoders(5), decoded=False)
    want = [1.0 if 1.0 / (1.0 + np.exp(-v)) > 0.01 else 0.0 for v in logits]
    assert want == [0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 1.0, 0.0, 1.0, 1.0]
    assert model.get_mask[0, :, 0].tolist() == want
    assert model.get_mask_anchor.tolist() == [True, False]


def test_decoded_gaussians_by_hand_in_float64():
    """Every kept Gaussian of a decoded HAC++ model, from the raw arrays and decoder weights in float64:
    mean = anchor + offset * s[:3], scale = s[3:] * sigmoid(cov[:3]), rotation = normalize(cov[3:7]) with
    cov = mlp_cov([feat, view, dist]) rows 7k..7k+6 (HAC++'s generate_neural_gaussians, linear scales s)."""

    arr = _arrays(6, decoded=True, mask_cols=K + 1)
    decs = _decoders(6)
    model = _model(arr, decs, decoded=True)
    cam = make_camera()
    with torch.no_grad():
        got = model.decode(cam, None)
    assert got.means.shape[0] > A  # several Gaussians per anchor
    lin = [(m.weight.detach().double(), m.bias.detach().double()) for m in (decs["mlp_cov"][0], decs["mlp_cov"][2])]
    centre = cam.center.double()
    for g in range(got.means.shape[0]):
        a, k = int(got.anchor_of[g]), int(got.offset_of[g])
        anchor, s = torch.from_numpy(arr["anchor"][a]).double(), torch.from_numpy(arr["scale"][a]).double()
        d = anchor - centre
        x = torch.cat([torch.from_numpy(arr["feat"][a]).double(), d / d.norm(), d.norm()[None]])
        cov = (lin[1][0] @ torch.clamp(lin[0][0] @ x + lin[0][1], min=0) + lin[1][1])[7 * k: 7 * k + 7]
        torch.testing.assert_close(got.means[g].double(), anchor + torch.from_numpy(arr["offset"][a, k]).double() * s[:3],
                                   rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(got.scales[g].double(), s[3:] * torch.sigmoid(cov[:3]), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(got.rotations[g].double(), cov[3:] / cov[3:].norm(), rtol=1e-5, atol=1e-6)


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


def _hac_kw(n_mask_cols: int, seed: int = 0) -> dict:
    arr = hac_t._arrays(seed, decoded=True, mask_cols=n_mask_cols)
    return dict(anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                scaling=torch.from_numpy(arr["scale"]), decoded_version=True, **hac_t._decoders(seed))


def _family_kwargs():
    """(class, kwargs, per-anchor tensor arguments) of every family stand-in."""

    h = _hac_kw(hac_t.K + 1)
    hac = (HACModel, {"voxel_size": 0.01, **h}, ["anchor", "offset", "mask", "anchor_feat", "scaling"])
    arr = contextgs_t._arrays(0, decoded=True)
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    ctx = (ContextGSModel, dict(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                                scaling=t["scale"], hyper_latent=t["hyper"], decoded_version=True, **contextgs_t._decoders(0)),
           ["anchor", "offset", "mask", "anchor_feat", "scaling", "hyper_latent"])
    oa = octree_t._arrays(0)
    octo = (OctreeGSModel, dict(anchor=torch.from_numpy(oa["anchor"]), offset=torch.from_numpy(oa["offset"]),
                                anchor_feat=torch.from_numpy(oa["feat"]), scaling=torch.from_numpy(oa["scale"]),
                                level=torch.from_numpy(oa["level"][:, None]), extra_level=torch.from_numpy(oa["extra"]),
                                voxel_size=0.1, standard_dist=3.0, **octree_t._decoders(torch.Generator().manual_seed(0))),
            ["anchor", "offset", "anchor_feat", "scaling", "level", "extra_level"])
    ca = compgs_t._arrays(0)
    comp = (CompGSModel, dict(means=torch.from_numpy(ca["means"]), scales_before_exp=torch.from_numpy(ca["scales"]),
                              ref_feats=torch.from_numpy(ca["ref"]), res_feats=torch.from_numpy(ca["res"])),
            ["means", "scales_before_exp", "ref_feats", "res_feats"])
    return [hac, ctx, octo, comp]


def test_hac_model_variant_and_mask_column_refusals():
    k = hac_t.K
    with pytest.raises(InputValueError, match=r"variant must be 'hac\+\+' or 'hac', got 'hac\+'"):
        HACModel(voxel_size=0.01, variant="hac+", **_hac_kw(k + 1))
    with pytest.raises(InputValueError, match=rf"hac\+\+: mask must have {k + 1} columns \(n_offsets={k}\), got {k}"):
        HACModel(voxel_size=0.01, variant="hac++", **_hac_kw(k))
    with pytest.raises(InputValueError, match=rf"hac: mask must have {k} columns \(n_offsets={k}\), got {k + 1}"):
        HACModel(voxel_size=0.01, variant="hac", **_hac_kw(k + 1))
    assert HACModel(voxel_size=0.01, **_hac_kw(k + 1)).variant == "hac++"  # the default variant


def test_hac_feature_bank_input_by_hand():
    # HAC++'s renderer: feat re-weighted by mlp_feature_bank([view, dist]) before [feat, view, dist]
    f = hac_t.F
    torch.manual_seed(2)
    bank = nn.Sequential(nn.Linear(4, f), nn.ReLU(), nn.Linear(f, 3), nn.Softmax(dim=1))
    kw = _hac_kw(hac_t.K + 1, seed=2)
    kw["anchor_feat"] = kw["anchor_feat"][:, :48]  # the bank needs F divisible by 4
    kw.update(mlp_opacity=nn.Linear(52, 2), mlp_cov=nn.Linear(52, 2), mlp_color=nn.Linear(52, 2))
    bank = nn.Sequential(nn.Linear(4, 48), nn.ReLU(), nn.Linear(48, 3), nn.Softmax(dim=1))
    model = HACModel(voxel_size=0.01, mlp_feature_bank=bank, **kw)
    cam = torch.tensor([0.3, -0.2, 4.0])
    ids = torch.tensor([5, 1, 9])
    x = model.decoder_inputs(cam, ids)["mlp_opacity"]
    anchor = kw["anchor"][ids].double()
    v = anchor - cam.double()
    dist = v.norm(dim=1, keepdim=True)
    view = v / dist
    w = bank.double()(torch.cat([view, dist], dim=1))
    feat = kw["anchor_feat"][ids].double()
    # every 4th channel repeated 4 times, every 2nd twice, all channels; mixed by the three weights
    mixed = feat[:, ::4].repeat(1, 4) * w[:, :1] + feat[:, ::2].repeat(1, 2) * w[:, 1:2] + feat * w[:, 2:]
    assert torch.allclose(x.double(), torch.cat([mixed, view, dist], dim=1), atol=1e-5)
    assert torch.allclose(feature_bank(feat, w), mixed)


def test_hac_checkpoint_and_ply_refusals(tmp_path):
    sd = {"opacity_mlp": {}, "cov_mlp": {}, "color_mlp": {}}
    with pytest.raises(FileFormatError, match=r"ck.pth: missing entry 'mlp_feature_bank' \(cfg_args has use_feat_bank=True\)"):
        decoders_from_checkpoint(sd, tmp_path / "ck.pth", feature_bank=True)
    root = hac_t._write_dir(tmp_path / "h", hac_t._arrays(0, decoded=True, mask_cols=hac_t.K + 1), hac_t._decoders(0))
    write_cfg_args(root / "cfg_args", feat_dim=48, n_offsets=hac_t.K, voxel_size=0.01, use_feat_bank=False)
    with pytest.raises(FileFormatError, match="point_cloud.ply: 50 f_anchor_feat_\\* fields, the configuration says feat_dim=48"):
        load_hac_dir(root)
    write_cfg_args(root / "cfg_args", feat_dim=50, n_offsets=9, voxel_size=0.01, use_feat_bank=False)
    with pytest.raises(FileFormatError, match=r"11 f_mask_\* fields, expected 9 or 10 for n_offsets=9"):
        load_hac_dir(root)
    # HAC++ ModelParams defaults feat_dim 50, n_offsets 10: a cfg_args without them reads the folder
    write_cfg_args(root / "cfg_args", voxel_size=0.01)
    m = load_hac_dir(root)
    assert (m.feat_dim, m.n_offsets, m.variant, m.voxel_size) == (50, 10, "hac++", 0.01)
    # a raw model without voxel_size in cfg_args cannot be snapped: refused
    raw = hac_t._write_dir(tmp_path / "raw", hac_t._arrays(1, decoded=False, mask_cols=hac_t.K + 1), hac_t._decoders(1))
    write_cfg_args(raw / "cfg_args", feat_dim=50, n_offsets=hac_t.K)
    with pytest.raises(FileFormatError, match=r"voxel_size=0.0: the raw model's anchors are snapped to a voxel grid"):
        load_hac_dir(raw, allow_unquantized=True)


def test_voxel_snap_by_hand():
    # round(0.026 / 0.01) = 3 -> 0.03; round(-0.014 / 0.01) = -1 -> -0.01; round(0.004 / 0.01) = 0
    got = voxel_snap(torch.tensor([[0.026, -0.014, 0.004]], dtype=torch.float64), 0.01)
    assert torch.allclose(got, torch.tensor([[0.03, -0.01, 0.0]], dtype=torch.float64), atol=1e-15)


def test_stand_in_constructors_refuse_a_tensor_with_another_anchor_count():
    from controlgs_adapter.errors import ShapeError

    for cls, kw, names in _family_kwargs():
        cls(**kw)  # as built: accepted
        for i, name in enumerate(names):
            short = {**kw, name: kw[name][:-1]}
            # the first tensor sets A: the next one is named as disagreeing with it
            with pytest.raises(ShapeError, match=names[1] if i == 0 else name):
                cls(**short)
    # the fixed trailing sizes: positions 3, scales 6, offsets [K, 3], mask [M, 1], level [A, 1]
    for cls, kw, _ in _family_kwargs():
        for name, bad in (("scaling", lambda x: x[:, :5]), ("scales_before_exp", lambda x: x[:, :5]),
                          ("anchor", lambda x: x[:, :2]), ("means", lambda x: x[:, :2]),
                          ("offset", lambda x: x[:, :, :2]), ("mask", lambda x: x[:, :, :1].repeat(1, 1, 2)),
                          ("level", lambda x: x.repeat(1, 2))):
            if name in kw:
                with pytest.raises(ShapeError, match=name):
                    cls(**{**kw, name: bad(kw[name])})


def test_infer_decoded_by_hand():
    from controlgs_adapter.backends.hac import infer_decoded

    s = np.array([[0.1] * 6, [0.0] * 6, [0.2] * 6])
    m = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    assert infer_decoded(s, m, extra_mask_column=True) is True
    one_off = m.copy()
    one_off[2, 1] = 0.5  # a single mask value that is not 0/1: a raw model's logits
    assert infer_decoded(s, one_off, extra_mask_column=False) is False
    neg = s.copy()
    neg[1, 3] = -0.1  # 0/1 masks but a negative scale: the file does not tell
    assert infer_decoded(neg, m, extra_mask_column=False) is None
    # an all-zero row (zero padding) is left out: without it, a raw model's logits decide
    raw = np.array([[0.3, -2.0, 1.5], [0.0, 0.0, 0.0]])
    raw_s = np.array([[-3.0] * 6, [0.0] * 6])
    assert infer_decoded(raw_s, raw, extra_mask_column=False) is False
    pad = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert infer_decoded(np.array([[0.1] * 6, [0.0] * 6]), pad, extra_mask_column=True) is True
    # zero masks with a negative scale are not padding: that row makes the file undecidable
    assert infer_decoded(np.array([[0.1] * 6, [-0.5] + [0.0] * 5]), pad, extra_mask_column=True) is None


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
