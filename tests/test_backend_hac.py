"""HAC++ / HAC backend: recognition, snapped anchors, invalid anchors, decoded-vs-raw loading of an
output directory written in HAC++'s / HAC's layout, wrap/identity/injection/save-load, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from _family_checks import check_wrap_identity_and_rows, outputs, write_cfg_args
from controlgs_adapter.backends.compgs import CompGSBackend
from controlgs_adapter.backends.contextgs import ContextGSBackend
from controlgs_adapter.formats.backbone import write_ply
from controlgs_adapter.backends.hac import HACBackend, HACModel, load_hac_dir
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.errors import FileFormatError

A, K, F, VOXEL = 16, 10, 50, 0.01  # HAC++ defaults: feat_dim 50, n_offsets 10


def _decoders(seed: int) -> dict[str, nn.Sequential]:
    torch.manual_seed(seed)
    return {  # HAC++: every decoder takes [feat, view, dist] = F + 4 -> F
        "mlp_opacity": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
        "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
        "mlp_color": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid()),
    }


def _arrays(seed: int, *, decoded: bool, mask_cols: int, n: int = A, invalid=()) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    if decoded:
        mask = (rng.random((n, mask_cols)) < 0.6).astype(np.float32)
        if mask_cols == K + 1:
            mask[:, K] = 0.0
        mask[:, 0] = 1.0
        scale = rng.uniform(0.01, 0.2, (n, 6)).astype(np.float32)  # linear
        anchor = (np.round(rng.normal(size=(n, 3)) / VOXEL) * VOXEL).astype(np.float32)
    else:
        mask = rng.normal(0, 3, (n, mask_cols)).astype(np.float32)  # logits
        scale = rng.normal(-3, 0.5, (n, 6)).astype(np.float32)  # log
        anchor = rng.normal(size=(n, 3)).astype(np.float32)
    for i in invalid:
        mask[i, :K] = 0.0 if decoded else -20.0
    return {"anchor": anchor, "offset": rng.normal(size=(n, K, 3)).astype(np.float32), "mask": mask,
            "feat": rng.normal(size=(n, F)).astype(np.float32), "scale": scale}


def _model(arr, decs, *, decoded: bool, variant: str = "hac++") -> HACModel:
    return HACModel(voxel_size=VOXEL, variant=variant, decoded_version=decoded, anchor=torch.from_numpy(arr["anchor"]),
                    offset=torch.from_numpy(arr["offset"]), mask=torch.from_numpy(arr["mask"])[:, :, None],
                    anchor_feat=torch.from_numpy(arr["feat"]), scaling=torch.from_numpy(arr["scale"]), **decs)


def _write_dir(root, arr, decs, *, voxel_size=VOXEL):
    """HAC++'s layout: cfg_args, point_cloud/iteration_N/{point_cloud.ply, checkpoint.pth}."""
    root.mkdir(parents=True)
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, voxel_size=voxel_size, use_feat_bank=False,
                   lmbda=0.004, model_path=str(root))
    it = root / "point_cloud" / "iteration_30000"
    it.mkdir(parents=True)
    n = arr["anchor"].shape[0]
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2]}
    fields.update({f"n{c}": np.zeros(n, np.float32) for c in "xyz"})
    flat = arr["offset"].transpose(0, 2, 1).reshape(n, 3 * K)  # f_offset_{c*K + k}
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_mask_{i}": arr["mask"][:, i] for i in range(arr["mask"].shape[1])})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields["opacity"] = np.zeros(n, np.float32)
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(n, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    grid = nn.Sequential(nn.Linear(8, 2 * F), nn.ReLU(), nn.Linear(2 * F, 4))
    torch.save({"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
                "color_mlp": decs["mlp_color"].state_dict(), "encoding_xyz": {"params": torch.zeros(32)},
                "grid_mlp": grid.state_dict(), "deform_mlp": {"w": torch.zeros(3)}}, it / "checkpoint.pth")
    return root


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
    from _family_checks import assert_same_gaussians, make_camera, reference_scaffold

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


def test_invalid_anchor_condition_rows_get_no_gradient():
    """An anchor with every offset masked off reaches the decoders but emits no Gaussian, so its
    condition row receives no gradient (it stays inert at zero), while valid anchors' rows do."""
    from _family_checks import STATE, make_camera
    from controlgs_adapter.controlgs import ControlGS

    arr = _arrays(6, decoded=False, mask_cols=K + 1, invalid=(2,))
    model = _model(arr, _decoders(6), decoded=False)
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=4)
    ids = torch.tensor([0, 1, 2, 3])
    with cgs.conditioned(STATE, anchor_ids=ids):
        g = model.decode(cam, torch.isin(torch.arange(A), ids))
    (g.colors.sum() + g.opacities.sum() + g.scales.sum()).backward()
    grad = cgs.injector.conditions.grad[:, 0]  # [A, N] of the display module
    assert bool((grad[2] == 0).all()) and 2 not in g.anchor_of.tolist()
    assert all(bool(grad[a].abs().sum() > 0) for a in (0, 1, 3))
    assert bool((grad[4:] == 0).all())  # anchors not in the view
    cgs.unwrap()


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
    from controlgs_adapter.backends import load_model_dir

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
    from _family_checks import make_camera

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
