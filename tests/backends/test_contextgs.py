"""ContextGS: its backend (16-bit quantised anchor positions in the bound), its model's decoding and
prefilter against float64 references, and its loader for decoded and raw folders with every refusal."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import contextgs_files
from helpers.anchor_oracle import D, assert_gaussians, camera_centre, gaussian64, mlp, mlp64, oblique_camera, visible64
from helpers.contextgs_files import HI, LO, PAD, A, _arrays, _decoders, _model, _write_dir
from helpers.family_checks import make_camera, outputs, write_cfg_args
from helpers.family_checks import outputs as decoder_outputs
from torch import nn

from controlgs_adapter import RuntimeState
from controlgs_adapter.backends.compgs import CompGSBackend
from controlgs_adapter.backends.contextgs import ContextGSBackend, ContextGSModel, load_contextgs_dir, quantize_anchor
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.models.anchor_model import anchor_visibility
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.errors import FileFormatError, IncompatibleAdapterError, InputValueError
from controlgs_adapter.formats.backbone import read_ply, write_ply

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _kwargs(arr) -> dict:
    """ContextGSModel's per-anchor arguments from the arrays of ``helpers.contextgs_files``."""
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    return dict(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                scaling=t["scale"], hyper_latent=t["hyper"])


# ------------------------------------------------------------------------------------------ backend
def test_backend_recognises_contextgs_and_sees_the_quantised_positions():
    arr = _arrays(0, decoded=False)
    model = _model(arr, _decoders(0), decoded=False)
    b = ContextGSBackend()
    assert b.matches(model) and not any(o.matches(model) for o in (HACBackend(), OctreeGSBackend(), CompGSBackend()))
    assert ScaffoldGSBackend().matches(model)  # generic; ContextGS is registered before it
    assert b.input_layout(model, "mlp_color") == [("feat", 50), ("view", 3), ("dist", 1)]
    # a raw model: the decoder sees the anchors quantised in the bound, at most one step away
    got = b.anchor_positions(model)
    assert torch.equal(got, model.get_anchor) and not torch.equal(got, model._anchor)
    step = (HI.double() - LO.double()) / 65535 + 1e-6
    assert bool(((got.double() - torch.from_numpy(arr["anchor"]).double()).abs() <= step + 1e-6).all())
    model.decoded_version = True
    assert torch.equal(b.anchor_positions(model), model._anchor)


def test_quantize_anchor_by_hand():
    # lo = 0, hi = 65.535 on every axis: step = 65.535 / 65535 + 1e-6 = 0.001001;
    # 0.0025 / 0.001001 = 2.497 -> q = 2 -> 0.002002; below lo -> q = 0 -> lo; far above hi -> q = 65535
    lo, hi = torch.zeros(3, dtype=torch.float64), torch.full((3,), 65.535, dtype=torch.float64)
    a = torch.tensor([[0.0025, -1.0, 100.0]], dtype=torch.float64)
    got = quantize_anchor(a, lo, hi)
    assert torch.allclose(got, torch.tensor([[0.002002, 0.0, 65535 * 0.001001]], dtype=torch.float64), atol=1e-12)
    # a lower bound of -1 shifts everything: (0.0025 + 1) / 0.001001 = 1001.5 -> 1001 -> 1001 * 0.001001 - 1
    got = quantize_anchor(torch.tensor([[0.0025, 0.0025, 0.0025]], dtype=torch.float64), lo - 1.0, hi)
    step = 66.535 / 65535 + 1e-6
    assert torch.allclose(got, torch.full((1, 3), math.floor(1.0025 / step) * step - 1.0, dtype=torch.float64), atol=1e-12)


def test_lens_strength_uses_quantised_positions():
    """The lens strength is computed at the anchor position the decoder sees (quantised, not raw)."""
    arr = _arrays(6, decoded=False)
    arr["anchor"][:, :2] *= 3.0  # spread over the image so the radii differ
    lo, hi = torch.full((1, 3), -900.0), torch.full((1, 3), 1100.0)  # a wide bound: 0.03-unit quantisation steps
    model = ContextGSModel(**_kwargs(arr), x_bound_min=lo, x_bound_max=hi, decoded_version=False, **_decoders(6))
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("lens",), cond_dim=4)
    lam = cgs.strengths(RuntimeState(), cam, torch.arange(A))["lens"].double()

    def radius(pos: torch.Tensor) -> torch.Tensor:  # float64 pinhole projection of make_camera()
        uv = pos[:, :2] / (pos[:, 2:] + 5.0) * 40.0 + torch.tensor([32.0, 24.0], dtype=torch.float64)
        p = 2 * uv / torch.tensor([64.0, 48.0], dtype=torch.float64) - 1
        p = p * torch.tensor([1.0, 48 / 64], dtype=torch.float64)  # on the display ("fit": the longer axis spans it)
        return (p.norm(dim=1) / 2 ** 0.5).clamp(0, 1)

    q = quantize_anchor(torch.from_numpy(arr["anchor"]).double(), lo.double(), hi.double())
    assert torch.allclose(lam, radius(q), atol=1e-5)
    assert (lam - radius(torch.from_numpy(arr["anchor"]).double())).abs().max() > 1e-3  # raw positions: other strengths
    cgs.unwrap()


# ----------------------------------------------------------------------------- decoding, prefilter
def test_raw_model_decodes_by_hand_with_quantised_anchors_and_mask_logits():
    """A not-decoded ContextGS model: anchors quantised to 16 bits in the bound (floor, 2^16 - 1 levels,
    step + 1e-6), masks sigmoid(logit) > 0.01, log scales; every decoded Gaussian by hand."""
    a, k, f = 80, 3, 8
    rng = np.random.default_rng(4)
    lo, hi = torch.tensor([-7.5, -5.0, -1.0]), torch.tensor([7.3, 5.1, 1.6])
    anchor = torch.from_numpy(rng.uniform((-7.4, -4.9, -0.9), (7.2, 5.0, 1.5), (a, 3))).float()
    offset, feat = torch.randn(a, k, 3), torch.randn(a, f)
    mask = torch.from_numpy(rng.normal(-3.0, 3.0, (a, k, 1))).float()
    scaling = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    torch.manual_seed(6)
    decs = {"mlp_opacity": mlp(f + 4, f, k, nn.Tanh()), "mlp_cov": mlp(f + 4, f, 7 * k, None),
            "mlp_color": mlp(f + 4, f, 3 * k, nn.Sigmoid())}
    model = ContextGSModel(anchor=anchor, offset=offset, mask=mask, anchor_feat=feat, scaling=scaling,
                           hyper_latent=torch.randn(a, 2), x_bound_min=lo, x_bound_max=hi, decoded_version=False, **decs)
    cam = oblique_camera()
    centre = camera_centre(cam)
    step = (hi.to(D) - lo.to(D)) / 65535 + 1e-6
    q = torch.floor((anchor.to(D) - lo.to(D)) / step).clamp(0, 65535)
    pos = q * step + lo.to(D)
    torch.testing.assert_close(model.get_anchor.to(D), pos, rtol=0, atol=1e-6)
    on = 1.0 / (1.0 + torch.exp(-mask.to(D)[:, :, 0])) > 0.01
    with torch.no_grad():
        got = model.decode(cam, None)
    expected = {}
    for i in range(a):
        d = pos[i] - centre
        x = torch.cat([feat[i].to(D), d / d.norm(), d.norm()[None]])[None]
        op = mlp64(decs["mlp_opacity"], x)[0]
        cov = mlp64(decs["mlp_cov"], x)[0].reshape(k, 7)
        col = mlp64(decs["mlp_color"], x)[0].reshape(k, 3)
        s = torch.exp(scaling[i].to(D))
        for j in range(k):
            if op[j] > 0 and on[i, j]:
                expected[(i, j)] = gaussian64(pos[i], offset[i, j].to(D), s, op[j], col[j], cov[j])
    assert 0 < len(expected) < a * k
    assert_gaussians(got, expected)


def test_decoded_model_keeps_masked_offsets_out():
    arr = _arrays(5, decoded=True)
    model = _model(arr, _decoders(5), decoded=True)
    with torch.no_grad():
        g = model.decode(make_camera(), torch.arange(A) < A - PAD)
    mask = torch.from_numpy(arr["mask"])
    assert len(g.means) > 0 and bool((mask[g.anchor_of, g.offset_of] == 1).all())
    # every kept Gaussian: mean = anchor + offset * scale[:, :3] (linear scales of the decoded model)
    want = torch.from_numpy(arr["anchor"])[g.anchor_of] + torch.from_numpy(arr["offset"])[g.anchor_of, g.offset_of] * \
        torch.from_numpy(arr["scale"])[g.anchor_of, :3]
    assert torch.allclose(g.means, want, atol=1e-6)


def test_prefilter_takes_anchor_zeros_rotation_for_every_anchor():
    """ContextGS's prefilter_voxel passes rotations[[0]] for every anchor. A raw model of needle-like anchors
    near the image border, by hand with a float64 EWA projection; and a decoded model whose anchor 0 is
    upright while the others lie along the line of sight: all are kept, as anchor 0's footprint says."""
    a, k, f = 80, 3, 8
    rng = np.random.default_rng(4)
    lo, hi = torch.tensor([-7.5, -5.0, -1.0]), torch.tensor([7.3, 5.1, 1.6])
    anchor = torch.from_numpy(rng.uniform((-7.4, -4.9, -0.9), (7.2, 5.0, 1.5), (a, 3))).float()
    mask = torch.from_numpy(rng.normal(-3.0, 3.0, (a, k, 1))).float()
    scaling = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    scaling[:, 0] += 2.5  # needle-like anchors: their footprint depends on the rotation
    rotation = torch.nn.functional.normalize(torch.randn(a, 4, generator=torch.Generator().manual_seed(4)), dim=1)
    torch.manual_seed(6)
    decs = {"mlp_opacity": mlp(f + 4, f, k, nn.Tanh()), "mlp_cov": mlp(f + 4, f, 7 * k, None),
            "mlp_color": mlp(f + 4, f, 3 * k, nn.Sigmoid())}
    model = ContextGSModel(anchor=anchor, offset=torch.randn(a, k, 3), mask=mask, anchor_feat=torch.randn(a, f),
                           scaling=scaling, rotation=rotation, hyper_latent=torch.randn(a, 2), x_bound_min=lo,
                           x_bound_max=hi, decoded_version=False, **decs)
    cam = oblique_camera()
    pos = model.get_anchor.to(D)
    want = visible64(cam, pos, torch.exp(scaling.to(D)[:, :3]), rotation.to(D)[0].expand(a, 4))
    assert 0 < int(want.sum()) < a
    assert not torch.equal(want, visible64(cam, pos, torch.exp(scaling.to(D)[:, :3]), rotation.to(D)))
    assert torch.equal(model.visible_anchors(cam), want)

    arr = _arrays(9, decoded=True)
    n = A - PAD
    arr["anchor"][:n] = np.array([[0.5, 0.0, 0.0]], np.float32) + np.arange(n, dtype=np.float32)[:, None] * \
        np.array([[0.01, 0.0, 0.0]], np.float32)  # centres 8-15 px beyond the right edge of the image
    arr["scale"][:n] = np.array([0.01, 0.2, 0.01, 0.1, 0.1, 0.1], np.float32)  # long along y
    half = 2 ** -0.5
    rot = torch.tensor([[half, half, 0.0, 0.0]]).repeat(A, 1)  # 90 degrees about x: long along the view axis
    rot[0] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    model = ContextGSModel(**_kwargs(arr), rotation=rot, decoded_version=True, **_decoders(9))
    cam = make_camera()
    cam.intrinsics[0, 0] = cam.intrinsics[1, 1] = 400.0  # narrow: a long axis along the view projects short
    got = model.visible_anchors(cam)
    own = anchor_visibility(cam, model.get_anchor, model.get_scaling[:, :3], rot)
    first = anchor_visibility(cam, model.get_anchor, model.get_scaling[:, :3], rot[:1].expand(A, 4))
    assert torch.equal(got, first) and not torch.equal(got, own)
    assert got[1:n].all() and not own[1:n].any()  # anchor 0's footprint reaches into the image


# ------------------------------------------------------------------------------------------- loader
def test_decoded_folder_loads_without_its_zero_padding(tmp_path):
    arr, decs = _arrays(1, decoded=True), _decoders(1)
    root = _write_dir(tmp_path / "scene", arr, decs)
    model = load_contextgs_dir(root)
    n = A - PAD
    assert model.decoded_version and model.source_index.tolist() == list(range(n))
    assert torch.equal(model.get_anchor, torch.from_numpy(arr["anchor"][:n]))
    assert torch.equal(model._hyper_latent, torch.from_numpy(arr["hyper"][:n]))
    assert torch.equal(model.x_bound_min, LO) and model.latent_codec is None
    assert ContextGSBackend().matches(model) and ContextGSBackend().valid_anchors(model).all()
    cam = torch.tensor([0.0, 0.5, -6.0])
    ids = torch.tensor([0, 1, 4, 6, 9])
    ref = _model({k: v[:n] for k, v in arr.items()}, decs, decoded=True)
    want = outputs(ref, ref.decoder_inputs(cam, ids))
    for p, y in outputs(model, model.decoder_inputs(cam, ids)).items():
        assert torch.equal(y, want[p]), p


def test_raw_folder_needs_allow_unquantized_and_its_bound(tmp_path):
    arr = _arrays(2, decoded=False)
    root = _write_dir(tmp_path / "raw", arr, _decoders(2))
    with pytest.raises(FileFormatError, match="raw .*ContextGS.*allow_unquantized"):
        load_contextgs_dir(root)
    model = load_contextgs_dir(root, allow_unquantized=True)
    keep = model.source_index
    assert torch.equal(model.get_anchor, quantize_anchor(torch.from_numpy(arr["anchor"])[keep], LO, HI))
    root2 = _write_dir(tmp_path / "nobound", arr, _decoders(2), bound=False)
    with pytest.raises(FileFormatError, match="checkpoint.pth.*bound"):
        load_contextgs_dir(root2, allow_unquantized=True)


def test_loader_refusals_name_the_missing_field_or_file(tmp_path):
    root = _write_dir(tmp_path / "s", _arrays(3, decoded=True), _decoders(3))
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {k: v for k, v in fields.items() if not k.startswith("f_hyper_latent_")})
    with pytest.raises(FileFormatError, match="f_hyper_latent_0"):
        load_contextgs_dir(root)
    (root / "cfg_args").unlink()
    with pytest.raises(FileFormatError, match="cfg_args"):
        load_contextgs_dir(root)


def test_the_bound_is_needed_by_raw_models_and_must_be_a_pair(tmp_path):
    arr = _arrays(0, decoded=False)
    kw = dict(**_kwargs(arr), **_decoders(0))
    with pytest.raises(FileFormatError, match="x_bound_min and x_bound_max must be given together"):
        ContextGSModel(x_bound_min=LO, decoded_version=False, **kw)
    with pytest.raises(FileFormatError, match="x_bound_min and x_bound_max must be given together"):
        ContextGSModel(x_bound_max=HI, decoded_version=True, **kw)
    with pytest.raises(FileFormatError, match="not-decoded .*x_bound_min/x_bound_max"):
        ContextGSModel(decoded_version=False, **kw)
    decoded = ContextGSModel(decoded_version=True, **kw)  # a decoded model needs no bound: positions as stored
    assert torch.equal(decoded.get_anchor, kw["anchor"])
    # marked raw afterwards, it cannot quantise its anchors: named, not an AttributeError
    decoded.decoded_version = False
    with pytest.raises(InputValueError, match="x_bound_min/x_bound_max"):
        decoded.get_anchor  # noqa: B018 - the property is what is tested
    # checkpoint.pth entry 'bound' malformed
    root = _write_dir(tmp_path / "c", arr, _decoders(0))
    ckpt = root / "point_cloud" / "iteration_30000" / "checkpoint.pth"
    sd = torch.load(ckpt, weights_only=True)
    for bad in ([LO], [LO, torch.zeros(2)], (LO, [0.0, 0.0, 0.0])):
        torch.save({**sd, "bound": bad}, ckpt)
        with pytest.raises(FileFormatError, match=r"checkpoint.pth: entry 'bound' must be \[x_bound_min, x_bound_max\]"):
            load_contextgs_dir(root, allow_unquantized=True)
    torch.save({**sd, "bound": (LO, HI)}, ckpt)  # a tuple is as good as a list
    m = load_contextgs_dir(root, allow_unquantized=True)
    assert torch.equal(m.x_bound_min, LO) and torch.equal(m.x_bound_max, HI)


def test_cfg_args_without_widths_takes_feat_dim_50_and_n_offsets_10(tmp_path):
    # ContextGS ModelParams: feat_dim 50, n_offsets 10: a cfg_args without them reads the test folder (F 50, K 10)
    root = _write_dir(tmp_path / "c", _arrays(1, decoded=True), _decoders(1))
    write_cfg_args(root / "cfg_args", hyper_divisor=4, use_feat_bank=False)
    m = load_contextgs_dir(root)
    assert (m.feat_dim, m.n_offsets) == (50, 10)


# ------------------------------------------------------------------------------ the adapter on the backbone families
def test_adapter_maps_between_live_padded_model_and_loaded_folder(tmp_path):
    """An adapter trained on the live (zero-padded) decoded ContextGS model loads onto the stand-in of
    its folder (which drops invalid anchors; source_index maps the rows) and back, with equal outputs."""
    a, pad = contextgs_files.A, contextgs_files.PAD
    arr, decs = contextgs_files._arrays(7, decoded=True), contextgs_files._decoders(7)
    arr["mask"][3] = 0.0  # an invalid anchor among the valid ones
    root = contextgs_files._write_dir(tmp_path / "scene", arr, decs)
    live, loaded = contextgs_files._model(arr, decs, decoded=True), load_contextgs_dir(root)
    rows = [i for i in range(a - pad) if i != 3]
    assert loaded.source_index.tolist() == rows
    cam, state = torch.tensor([0.0, 0.5, -6.0]), RuntimeState(downsample=4, power_saving=0.4)
    cgs = ControlGS.wrap(live, modules=("resample", "display"), cond_dim=4)
    with torch.no_grad():
        cgs.injector.conditions.normal_(generator=torch.Generator().manual_seed(0))
    cgs.save(tmp_path / "live.safetensors")
    pick = torch.arange(0, len(rows), 2)
    with cgs.conditioned(state, anchor_ids=loaded.source_index[pick]):
        want = decoder_outputs(live, live.decoder_inputs(cam, loaded.source_index[pick]))
    conditions = cgs.injector.conditions.detach().clone()
    cgs.unwrap()
    on_loaded = ControlGS.load(tmp_path / "live.safetensors", loaded)
    assert torch.equal(on_loaded.injector.conditions.detach(), conditions[loaded.source_index])
    with on_loaded.conditioned(state, anchor_ids=pick):
        got = decoder_outputs(loaded, loaded.decoder_inputs(cam, pick))
    for p in want:
        assert torch.equal(got[p], want[p]), p
    on_loaded.save(tmp_path / "loaded.safetensors")
    on_loaded.unwrap()
    back = ControlGS.load(tmp_path / "loaded.safetensors", live)
    assert torch.equal(back.injector.conditions.detach()[rows], conditions[rows])
    assert not back.injector.conditions.detach()[[3, *range(a - pad, a)]].any()  # invalid rows stay at zero
    back.unwrap()
    other = load_contextgs_dir(contextgs_files._write_dir(tmp_path / "other", contextgs_files._arrays(8, decoded=True), decs))
    with pytest.raises(IncompatibleAdapterError, match="anchor count"):
        ControlGS.load(tmp_path / "live.safetensors", other)
    # another scene with the same counts (valid anchors included) is no reason to scatter the rows onto it
    arr8 = contextgs_files._arrays(8, decoded=True)
    arr8["mask"][3] = 0.0
    live8 = contextgs_files._model(arr8, decs, decoded=True)
    assert int(ContextGSBackend().valid_anchors(live8).sum()) == len(rows)
    with pytest.raises(IncompatibleAdapterError, match="anchor count"):
        ControlGS.load(tmp_path / "loaded.safetensors", live8)
