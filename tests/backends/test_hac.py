"""HAC++ and HAC: the backend (voxel-snapped positions of raw models, validity from the offset masks), the
model's decoding against a float64 reference, telling decoded from raw files, and the loader with every
refusal."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import hac_files
from helpers.anchor_oracle import D, assert_gaussians, gaussian64, mlp64, visible64
from helpers.scaffold_standin import make_camera as standin_camera
from helpers.family_checks import STATE as DISPLAY_STATE
from helpers.family_checks import check_wrap_identity_and_rows, make_camera, outputs, write_cfg_args
from helpers.family_dirs import rewrite_ply
from helpers.family_models import hac_kwargs
from helpers.hac_files import VOXEL, A, F, K, _arrays, _decoders, _write_dir
from torch import nn

from controlgs_adapter import ControlGS
from controlgs_adapter.backends import load_model_dir
from controlgs_adapter.backends.compgs import CompGSBackend
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.backends.hac import (
    HACBackend,
    HACModel,
    decoders_from_checkpoint,
    drop_invalid,
    infer_decoded,
    load_hac_dir,
    voxel_snap,
)
from controlgs_adapter.backends.models.anchor_model import feature_bank
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.errors import FileFormatError, InputValueError

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _model(arr, decs, *, decoded: bool, variant: str = "hac++") -> HACModel:
    return HACModel(voxel_size=VOXEL, variant=variant, decoded_version=decoded, anchor=torch.from_numpy(arr["anchor"]),
                    offset=torch.from_numpy(arr["offset"]), mask=torch.from_numpy(arr["mask"])[:, :, None],
                    anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]), **decs)


def _decoders_of_width(f: int) -> dict[str, nn.Sequential]:
    return {"mlp_opacity": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(f + 4, f), nn.ReLU(), nn.Linear(f, 3 * K), nn.Sigmoid())}


def _dir_with_feature_bank(root, f: int):
    """HAC++'s layout with use_feat_bank=True and feat_dim f: the decoders take f + 4, the bank 4 -> f -> 3."""
    arr = _arrays(6, decoded=True, mask_cols=K + 1)
    arr["feat"] = arr["feat"][:, :f]
    torch.manual_seed(6)
    decs = _decoders_of_width(f)
    bank = nn.Sequential(nn.Linear(4, f), nn.ReLU(), nn.Linear(f, 3), nn.Softmax(dim=1))
    _write_dir(root, {**arr, "feat": np.zeros((A, F), np.float32)}, _decoders(6))
    it = root / "point_cloud" / "iteration_30000"
    rewrite_ply(it / "point_cloud.ply", **{f"f_anchor_feat_{i}": None for i in range(f, F)},
                **{f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(f)})
    torch.save({"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
                "color_mlp": decs["mlp_color"].state_dict(), "mlp_feature_bank": bank.state_dict()}, it / "checkpoint.pth")
    write_cfg_args(root / "cfg_args", feat_dim=f, n_offsets=K, voxel_size=VOXEL, use_feat_bank=True)
    return arr, bank


# ------------------------------------------------------------------------------------------ backend
def test_backend_recognises_hac_snaps_raw_positions_and_reads_validity_from_the_masks():
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


def test_voxel_snap_by_hand():
    # round(0.026 / 0.01) = 3 -> 0.03; round(-0.014 / 0.01) = -1 -> -0.01; round(0.004 / 0.01) = 0
    got = voxel_snap(torch.tensor([[0.026, -0.014, 0.004]], dtype=torch.float64), 0.01)
    assert torch.allclose(got, torch.tensor([[0.03, -0.01, 0.0]], dtype=torch.float64), atol=1e-15)


def test_live_model_keeps_a_condition_row_for_every_anchor_invalid_ones_included(tmp_path):
    arr = _arrays(1, decoded=False, mask_cols=K + 1, invalid=(2,))
    model = _model(arr, _decoders(1), decoded=False)
    ids = torch.tensor([0, 2, 5, 6, 9])
    inputs = model.decoder_inputs(torch.tensor([0.0, 0.0, -4.0]), ids)
    check_wrap_identity_and_rows(model, inputs, ids, "hac", 1, tmp_path,
                                 lambda: _model(arr, _decoders(1), decoded=False))


# ------------------------------------------------------------------------------------------- masks
def test_raw_mask_is_the_sigmoid_of_the_logits_above_0_01():
    """A raw (not decoded) model holds mask logits: HAC++'s ``get_mask`` switches an offset on where
    sigmoid(logit) > 0.01 (logit > -4.595; sigmoid(-4.0) = 0.018, sigmoid(-4.7) = 0.009), by hand here;
    HAC++'s extra K+1-th column is not an offset."""
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


def test_an_anchor_with_a_single_offset_on_is_valid_and_kept():
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


def test_infer_decoded_by_hand():
    """0/1 masks with non-negative scales: decoded (True); a mask value that is not 0/1: raw logits (False);
    0/1 masks with a negative scale: the file does not tell (None). HAC++'s extra column is 0 in a decoded
    file; all-zero rows (padding) are left out."""
    s = np.array([[0.1] * 6, [0.0] * 6, [0.2] * 6])
    m = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]])
    assert infer_decoded(s, m, extra_mask_column=True) is True
    one_off = m.copy()
    one_off[2, 1] = 0.5  # a single mask value that is not 0/1: a raw model's logits
    assert infer_decoded(s, one_off, extra_mask_column=False) is False
    neg = s.copy()
    neg[1, 3] = -0.1  # 0/1 masks but a negative scale: the file does not tell
    assert infer_decoded(neg, m, extra_mask_column=False) is None
    # HAC++'s extra column: a 1 there is not a decoded HAC++ file, but is for HAC (no extra column)
    extra = np.zeros((4, 4))
    extra[:, 0] = 1.0
    extra[2, -1] = 1.0
    assert infer_decoded(np.full((4, 6), 0.01), extra, extra_mask_column=True) is False
    assert infer_decoded(np.full((4, 6), 0.01), extra, extra_mask_column=False) is True
    # an all-zero row (zero padding) is left out: without it, a raw model's logits decide
    raw = np.array([[0.3, -2.0, 1.5], [0.0, 0.0, 0.0]])
    raw_s = np.array([[-3.0] * 6, [0.0] * 6])
    assert infer_decoded(raw_s, raw, extra_mask_column=False) is False
    pad = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert infer_decoded(np.array([[0.1] * 6, [0.0] * 6]), pad, extra_mask_column=True) is True
    # zero masks with a negative scale are not padding: that row makes the file undecidable
    assert infer_decoded(np.array([[0.1] * 6, [-0.5] + [0.0] * 5]), pad, extra_mask_column=True) is None


# ------------------------------------------------------------------------------ decoding, prefilter
def test_decoded_model_decodes_by_hand_without_its_masked_offsets():
    """Every Gaussian of a decoded HAC++ model, from the raw arrays and decoder weights in float64 (HAC++'s
    generate_neural_gaussians, linear scales s): x = [feat, view, dist]; mean = anchor + offset * s[:3],
    scale = s[3:] * sigmoid(cov[:3]), rotation = normalize(cov[3:7]); kept where opacity > 0 and the offset's
    mask is on. The prefilter is 3DGS's on the anchors' first three scales."""
    arr = _arrays(5, decoded=True, mask_cols=K + 1)
    decs = _decoders(5)
    model = _model(arr, decs, decoded=True)
    cam = make_camera()
    t = {k: torch.from_numpy(v).to(D) for k, v in arr.items()}
    visible = model.visible_anchors(cam)
    assert bool(visible.any())
    assert torch.equal(visible, visible64(cam, t["anchor"], t["scale"][:, :3], torch.tensor([[1.0, 0, 0, 0]]).expand(A, 4)))
    with torch.no_grad():
        got = model.decode(cam, None)
    centre = cam.center.to(D)
    expected, masked = {}, 0
    for i in range(A):
        d = t["anchor"][i] - centre
        x = torch.cat([t["feat"][i], d / d.norm(), d.norm()[None]])[None]
        op = mlp64(decs["mlp_opacity"], x)[0]
        cov = mlp64(decs["mlp_cov"], x)[0].reshape(K, 7)
        col = mlp64(decs["mlp_color"], x)[0].reshape(K, 3)
        for j in range(K):
            if op[j] > 0 and t["mask"][i, j] > 0:
                expected[(i, j)] = gaussian64(t["anchor"][i], t["offset"][i, j], t["scale"][i], op[j], col[j], cov[j])
            masked += int(op[j] > 0 and t["mask"][i, j] == 0)
    assert len(expected) > A and masked > 0  # several Gaussians per anchor; some are masked off
    assert_gaussians(got, expected)


def test_feature_bank_reweights_the_features_by_hand():
    # HAC++'s renderer: feat re-weighted by mlp_feature_bank([view, dist]) before [feat, view, dist]
    torch.manual_seed(2)
    kw = hac_kwargs(K + 1, seed=2)
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


def test_model_refuses_an_unknown_variant_and_a_mask_of_the_other_variant():
    with pytest.raises(InputValueError, match=r"variant must be 'hac\+\+' or 'hac', got 'hac\+'"):
        HACModel(voxel_size=0.01, variant="hac+", **hac_kwargs(K + 1))
    with pytest.raises(InputValueError, match=rf"hac\+\+: mask must have {K + 1} columns \(n_offsets={K}\), got {K}"):
        HACModel(voxel_size=0.01, variant="hac++", **hac_kwargs(K))
    with pytest.raises(InputValueError, match=rf"hac: mask must have {K} columns \(n_offsets={K}\), got {K + 1}"):
        HACModel(voxel_size=0.01, variant="hac", **hac_kwargs(K + 1))
    assert HACModel(voxel_size=0.01, **hac_kwargs(K + 1)).variant == "hac++"  # the default variant


# ------------------------------------------------------------------------------------------- loader
@pytest.mark.parametrize("variant", ["hac++", "hac"])
def test_decoded_folder_loads_linear_scales_without_zero_padding(tmp_path, variant):
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
    ref = _model({k: v[:n_valid] for k, v in arr.items()}, decs, decoded=True, variant=variant)
    want = outputs(ref, ref.decoder_inputs(cam, ids))
    for p, y in outputs(model, model.decoder_inputs(cam, ids)).items():
        assert torch.equal(y, want[p]), p


@pytest.mark.parametrize("variant", ["hac++", "hac"])
def test_decoded_folder_with_scales_rounded_to_zero(tmp_path, variant):
    """The codecs store round(s / Q) * Q (Q about 1e-3): small scales are exactly 0, still decoded."""
    arr = _arrays(7, decoded=True, mask_cols=K + 1 if variant == "hac++" else K)
    arr["scale"][1:6, 2] = 0.0
    arr["scale"][9, :3] = 0.0
    root = _write_dir(tmp_path / "scene", arr, _decoders(7))
    model = load_hac_dir(root)
    assert model.decoded_version and torch.equal(model.get_scaling, torch.from_numpy(arr["scale"]))  # linear, no exp


def test_raw_folder_is_refused_unless_allowed(tmp_path):
    arr = _arrays(3, decoded=False, mask_cols=K + 1, invalid=(4,))
    root = _write_dir(tmp_path / "raw", arr, _decoders(3))
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: .*raw \(not decoded\).*allow_unquantized=True"):
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
    # a raw model without voxel_size in cfg_args cannot be snapped: refused
    write_cfg_args(root / "cfg_args", feat_dim=50, n_offsets=K)
    with pytest.raises(FileFormatError, match=r"voxel_size=0.0"):
        load_hac_dir(root, allow_unquantized=True)


def test_undecidable_folder_is_refused_even_with_allow_unquantized(tmp_path):
    """0/1 masks with negative scales: the loader asks for decoded= rather than guessing (reading linear
    scales as log scales, or the reverse, would be silently wrong); it counts only the negative scales
    (here 3 negative, 6 exactly zero)."""
    arr = _arrays(8, decoded=True, mask_cols=K + 1)
    arr["scale"][2, 0] = -0.5
    root = _write_dir(tmp_path / "scene", arr, _decoders(8))
    for kw in ({}, {"allow_unquantized": True}):
        with pytest.raises(FileFormatError, match=r"cannot tell .*1 scale_\* value.*decoded=True.*decoded=False"):
            load_hac_dir(root, **kw)
    assert load_hac_dir(root, decoded=True).decoded_version
    arr = _arrays(5, decoded=True, mask_cols=K + 1)
    arr["scale"][0, :3] = -0.1
    arr["scale"][1] = 0.0
    root = _write_dir(tmp_path / "counted", arr, _decoders(5))
    with pytest.raises(FileFormatError, match=r"but 3 scale_\* value\(s\) are negative"):
        load_hac_dir(root)


def test_loader_keeps_the_ply_rotations_and_refuses_a_truncated_set(tmp_path):
    """HAC's PLY carries rot_0..rot_3 per anchor (the prefilter's rotations): they are read as stored."""
    root = _write_dir(tmp_path / "h", _arrays(4, decoded=True, mask_cols=K + 1), _decoders(4))
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    q = np.random.default_rng(5).normal(size=(A, 4)).astype(np.float32)
    rewrite_ply(ply, **{f"rot_{i}": q[:, i] for i in range(4)})
    model = load_hac_dir(root)
    assert torch.equal(model._rotation, torch.from_numpy(q)[model.source_index])
    rewrite_ply(ply, rot_3=None)
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: missing PLY field\(s\) \['rot_3'\]"):
        load_hac_dir(root)


def test_feature_bank_folder_loads_with_its_bank_when_feat_dim_is_divisible_by_4(tmp_path):
    arr, bank = _dir_with_feature_bank(tmp_path / "h", 48)
    model = load_hac_dir(tmp_path / "h")
    assert model.use_feat_bank and model.feat_dim == 48
    assert torch.equal(model.mlp_feature_bank[0].weight, bank[0].weight)
    b = HACBackend()
    assert b.decoder_paths(model) == ["mlp_opacity", "mlp_cov", "mlp_color", "mlp_feature_bank"]
    assert b.input_layout(model, "mlp_feature_bank") is None  # not a target: no FC1 layout
    assert b.input_layout(model, "mlp_color") == [("feat", 48), ("view", 3), ("dist", 1)]
    plain = load_hac_dir(_write_dir(tmp_path / "p", _arrays(6, decoded=True, mask_cols=K + 1), _decoders(6)))
    assert not plain.use_feat_bank


def test_cfg_args_without_widths_takes_hac_plus_plus_defaults(tmp_path):
    # HAC++ ModelParams defaults feat_dim 50, n_offsets 10: a cfg_args without them reads the folder
    root = _write_dir(tmp_path / "h", _arrays(0, decoded=True, mask_cols=K + 1), _decoders(0))
    write_cfg_args(root / "cfg_args", voxel_size=0.01)
    m = load_hac_dir(root)
    assert (m.feat_dim, m.n_offsets, m.variant, m.voxel_size) == (50, 10, "hac++", 0.01)


def test_loader_refusals_name_the_file_and_what_is_wrong(tmp_path):
    arr = _arrays(4, decoded=True, mask_cols=K + 1)
    root = _write_dir(tmp_path / "s", arr, _decoders(4))
    write_cfg_args(root / "cfg_args", feat_dim=48, n_offsets=K, voxel_size=0.01, use_feat_bank=False)
    with pytest.raises(FileFormatError, match=r"point_cloud.ply: 50 f_anchor_feat_\* fields, the configuration says feat_dim=48"):
        load_hac_dir(root)
    write_cfg_args(root / "cfg_args", feat_dim=50, n_offsets=9, voxel_size=0.01, use_feat_bank=False)
    with pytest.raises(FileFormatError, match=r"11 f_mask_\* fields, expected 9 or 10 for n_offsets=9"):
        load_hac_dir(root)
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=VOXEL, use_feat_bank=True)
    with pytest.raises(FileFormatError, match=r"use_feat_bank=True with feat_dim=50.*divisible by 4 \(50 channels give 52\)"):
        load_hac_dir(root)
    with pytest.raises(FileFormatError, match=r"ck.pth: missing entry 'mlp_feature_bank' \(cfg_args has use_feat_bank=True\)"):
        decoders_from_checkpoint({"opacity_mlp": {}, "cov_mlp": {}, "color_mlp": {}}, tmp_path / "ck.pth", feature_bank=True)
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=VOXEL, use_feat_bank=False)
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


def test_bitstreams_only_folder_is_refused_by_both_loaders(tmp_path):
    root = tmp_path / "compressed"
    (root / "bitstreams").mkdir(parents=True)
    (root / "bitstreams" / "hash.b").write_bytes(b"\0")
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=VOXEL, use_feat_bank=False)
    for load in (load_hac_dir, load_model_dir):
        with pytest.raises(FileFormatError, match="bitstreams/ was found, but it cannot be decoded"):
            load(root)


def test_invalid_hac_anchor_condition_rows_get_no_gradient():
    """An HAC++ anchor with every offset masked off reaches the decoders but emits no Gaussian, so its
    condition row receives no gradient (it stays inert at zero), while valid anchors' rows do."""
    arr = hac_files._arrays(6, decoded=False, mask_cols=hac_files.K + 1, invalid=(2,))
    model = HACModel(voxel_size=hac_files.VOXEL, variant="hac++", decoded_version=False,
                     anchor=torch.from_numpy(arr["anchor"]), offset=torch.from_numpy(arr["offset"]),
                     mask=torch.from_numpy(arr["mask"])[:, :, None], anchor_feat=torch.from_numpy(arr["feat"]),
                     scaling=torch.from_numpy(arr["scale"]), **hac_files._decoders(6))
    cam = standin_camera()
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=4)
    ids = torch.tensor([0, 1, 2, 3])
    with cgs.conditioned(DISPLAY_STATE, anchor_ids=ids):
        g = model.decode(cam, torch.isin(torch.arange(hac_files.A), ids))
    (g.colors.sum() + g.opacities.sum() + g.scales.sum()).backward()
    grad = cgs.injector.conditions.grad[:, 0]  # [A, N] of the display module
    assert bool((grad[2] == 0).all()) and 2 not in g.anchor_of.tolist()
    assert all(bool(grad[a].abs().sum() > 0) for a in (0, 1, 3))
    assert bool((grad[4:] == 0).all())  # anchors not in the view
    cgs.unwrap()
