"""ContextGS backend: recognition, 16-bit anchor quantisation, zero padding, decoded-vs-raw loading of
an output directory written in ContextGS's layout, wrap/identity/injection/save-load, errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from _family_checks import check_wrap_identity_and_rows, outputs, write_cfg_args
from controlgs_adapter.backends.contextgs import ContextGSBackend, ContextGSModel, load_contextgs_dir, quantize_anchor
from controlgs_adapter.formats.backbone import read_ply, write_ply
from controlgs_adapter.backends.compgs import CompGSBackend
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import FileFormatError, InputValueError

A, K, F, PAD = 14, 10, 50, 4
H = F // 4  # hyper_divisor 4
LO, HI = torch.tensor([[-2.4, -2.0, -3.0]]), torch.tensor([[2.0, 2.6, 1.5]])


def _decoders(seed: int) -> dict[str, nn.Sequential]:
    torch.manual_seed(seed)
    return {"mlp_opacity": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, K), nn.Tanh()),
            "mlp_cov": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 7 * K)),
            "mlp_color": nn.Sequential(nn.Linear(F + 4, F), nn.ReLU(), nn.Linear(F, 3 * K), nn.Sigmoid())}


def _arrays(seed: int, *, decoded: bool) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    arr = {"anchor": rng.uniform(-1.8, 1.4, (A, 3)).astype(np.float32), "offset": rng.normal(size=(A, K, 3)).astype(np.float32),
           "feat": rng.normal(size=(A, F)).astype(np.float32), "hyper": rng.normal(size=(A, H)).astype(np.float32)}
    if decoded:
        arr["mask"] = (rng.random((A, K)) < 0.5).astype(np.float32)
        arr["mask"][:, 1] = 1.0
        arr["scale"] = rng.uniform(0.01, 0.3, (A, 6)).astype(np.float32)
        for v in arr.values():  # decoded arrays are zero-padded from the valid count to the full count
            v[A - PAD:] = 0.0
    else:
        arr["mask"] = rng.normal(0, 3, (A, K)).astype(np.float32)
        arr["scale"] = rng.normal(-3, 0.5, (A, 6)).astype(np.float32)
    return arr


def _model(arr, decs, *, decoded: bool) -> ContextGSModel:
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    return ContextGSModel(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                          scaling=t["scale"], hyper_latent=t["hyper"], x_bound_min=LO, x_bound_max=HI,
                          decoded_version=decoded, **decs)


def _write_dir(root, arr, decs, *, bound=True):
    root.mkdir(parents=True)
    write_cfg_args(root / "cfg_args", feat_dim=F, n_offsets=K, hyper_divisor=4, use_feat_bank=False, voxel_size=0.01)
    it = root / "point_cloud" / "iteration_30000"
    it.mkdir(parents=True)
    fields = {"x": arr["anchor"][:, 0], "y": arr["anchor"][:, 1], "z": arr["anchor"][:, 2]}
    fields.update({f"n{c}": np.zeros(A, np.float32) for c in "xyz"})
    flat = arr["offset"].transpose(0, 2, 1).reshape(A, 3 * K)
    fields.update({f"f_offset_{i}": flat[:, i] for i in range(3 * K)})
    fields.update({f"f_mask_{i}": arr["mask"][:, i] for i in range(K)})
    fields.update({f"f_anchor_feat_{i}": arr["feat"][:, i] for i in range(F)})
    fields.update({f"f_hyper_latent_{i}": arr["hyper"][:, i] for i in range(H)})
    fields["opacity"] = np.zeros(A, np.float32)
    fields.update({f"scale_{i}": arr["scale"][:, i] for i in range(6)})
    fields.update({f"rot_{i}": np.full(A, 1.0 if i == 0 else 0.0, np.float32) for i in range(4)})
    write_ply(it / "point_cloud.ply", fields)
    ckpt = {"opacity_mlp": decs["mlp_opacity"].state_dict(), "cov_mlp": decs["mlp_cov"].state_dict(),
            "color_mlp": decs["mlp_color"].state_dict(), "latent_codec": {"quantiles": torch.zeros(H, 1, 3)},
            "grid_mlp": {"0.0.weight": torch.zeros(4, 4)}, "level_scale": torch.ones(3)}
    if bound:
        ckpt["bound"] = [LO, HI]
    torch.save(ckpt, it / "checkpoint.pth")
    return root


def test_recognition_and_quantised_positions():
    arr = _arrays(0, decoded=False)
    model = _model(arr, _decoders(0), decoded=False)
    b = ContextGSBackend()
    assert b.matches(model) and not any(o.matches(model) for o in (HACBackend(), OctreeGSBackend(), CompGSBackend()))
    assert ScaffoldGSBackend().matches(model)  # generic; ContextGS is registered before it
    assert b.input_layout(model, "mlp_color") == [("feat", 50), ("view", 3), ("dist", 1)]
    got = b.anchor_positions(model).double()
    # float64 reference of the 16-bit quantisation inside the bound
    lo, hi = LO.double(), HI.double()
    step = (hi - lo) / 65535 + 1e-6
    q = torch.clamp(torch.floor((torch.from_numpy(arr["anchor"]).double() - lo) / step), 0, 65535)
    want = q * step + lo
    assert torch.allclose(got, want, atol=float(step.max()) + 1e-6, rtol=0)  # a floor boundary may tip one step
    assert (torch.isclose(got, want, atol=1e-5, rtol=0).double().mean() > 0.95)
    err = (got - torch.from_numpy(arr["anchor"]).double()).abs()
    assert bool((err <= step + 1e-6).all()) and not torch.equal(b.anchor_positions(model), model._anchor)
    outside = quantize_anchor(torch.tensor([[-9.0, 9.0, 0.0]]), LO, HI)  # clamped to the bound's grid
    assert torch.allclose(outside[0, :2], torch.tensor([LO[0, 0], LO[0, 1] + 65535 * float(step[0, 1])]).float(), atol=1e-4)
    model.decoded_version = True
    assert torch.equal(b.anchor_positions(model), model._anchor)


def test_load_decoded_dir_drops_padding_and_wraps(tmp_path):
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
    inputs = model.decoder_inputs(cam, ids)
    ref = _model({k: v[:n] for k, v in arr.items()}, decs, decoded=True)
    want = outputs(ref, ref.decoder_inputs(cam, ids))
    for p, y in outputs(model, inputs).items():
        assert torch.equal(y, want[p]), p
    check_wrap_identity_and_rows(model, inputs, ids, "contextgs", 1, tmp_path, lambda: load_contextgs_dir(root))


def test_raw_dir(tmp_path):
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


def test_loading_errors(tmp_path):
    root = _write_dir(tmp_path / "s", _arrays(3, decoded=True), _decoders(3))
    ply = root / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    fields, _ = read_ply(ply)
    write_ply(ply, {k: v for k, v in fields.items() if not k.startswith("f_hyper_latent_")})
    with pytest.raises(FileFormatError, match="f_hyper_latent_0"):
        load_contextgs_dir(root)
    (root / "cfg_args").unlink()
    with pytest.raises(FileFormatError, match="cfg_args"):
        load_contextgs_dir(root)


def test_raw_positions_need_the_bound():
    """A model built decoded without the bound cannot quantise its anchors once marked raw: named, not an AttributeError."""
    arr = _arrays(3, decoded=True)
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    model = ContextGSModel(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                           scaling=t["scale"], hyper_latent=t["hyper"], decoded_version=True, **_decoders(3))
    assert torch.equal(model.get_anchor, t["anchor"])
    model.decoded_version = False
    with pytest.raises(InputValueError, match="x_bound_min/x_bound_max"):
        model.get_anchor


def test_decode_keeps_masked_offsets_out():
    from _family_checks import make_camera

    arr = _arrays(5, decoded=True)
    model = _model(arr, _decoders(5), decoded=True)
    cam = make_camera()
    with torch.no_grad():
        g = model.decode(cam, torch.arange(A) < A - PAD)
    mask = torch.from_numpy(arr["mask"])
    assert len(g.means) > 0 and bool((mask[g.anchor_of, g.offset_of] == 1).all())
    # every kept Gaussian: mean = anchor + offset * scale[:, :3] (linear scales of the decoded model)
    want = torch.from_numpy(arr["anchor"])[g.anchor_of] + torch.from_numpy(arr["offset"])[g.anchor_of, g.offset_of] * \
        torch.from_numpy(arr["scale"])[g.anchor_of, :3]
    assert torch.allclose(g.means, want, atol=1e-6)


def test_lens_strength_uses_quantised_positions():
    """The lens strength is computed at the anchor position the decoder sees (quantised, not raw)."""
    from _family_checks import make_camera
    from controlgs_adapter import RuntimeState
    from controlgs_adapter.controlgs import ControlGS

    arr = _arrays(6, decoded=False)
    arr["anchor"][:, :2] *= 3.0  # spread over the image so the radii differ
    lo, hi = torch.full((1, 3), -900.0), torch.full((1, 3), 1100.0)  # a wide bound: 0.03-unit quantisation steps
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    model = ContextGSModel(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                           scaling=t["scale"], hyper_latent=t["hyper"], x_bound_min=lo, x_bound_max=hi,
                           decoded_version=False, **_decoders(6))
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("lens",), cond_dim=4)
    lam = cgs.strengths(RuntimeState(), cam, torch.arange(A))["lens"].double()

    def radius(pos: torch.Tensor) -> torch.Tensor:  # float64 pinhole projection of make_camera()
        uv = pos[:, :2] / (pos[:, 2:] + 5.0) * 40.0 + torch.tensor([32.0, 24.0], dtype=torch.float64)
        p = 2 * uv / torch.tensor([64.0, 48.0], dtype=torch.float64) - 1
        p = p * torch.tensor([1.0, 48 / 64], dtype=torch.float64)  # on the display ("fit": the longer axis spans it)
        return (p.norm(dim=1) / 2 ** 0.5).clamp(0, 1)

    q = quantize_anchor(t["anchor"].double(), lo.double(), hi.double())
    assert torch.allclose(lam, radius(q), atol=1e-5)
    assert (lam - radius(t["anchor"].double())).abs().max() > 1e-3  # the raw positions would give other strengths
    cgs.unwrap()


def test_adapter_maps_between_live_padded_model_and_loaded_folder(tmp_path):
    """An adapter trained on the live (zero-padded) decoded model loads onto the stand-in of its
    folder (which drops invalid anchors; source_index maps the rows) and back, with equal outputs."""
    from controlgs_adapter import RuntimeState
    from controlgs_adapter.controlgs import ControlGS
    from controlgs_adapter.errors import IncompatibleAdapterError

    arr, decs = _arrays(7, decoded=True), _decoders(7)
    arr["mask"][3] = 0.0  # an invalid anchor among the valid ones
    root = _write_dir(tmp_path / "scene", arr, decs)
    live, loaded = _model(arr, decs, decoded=True), load_contextgs_dir(root)
    rows = [i for i in range(A - PAD) if i != 3]
    assert loaded.source_index.tolist() == rows
    cam, state = torch.tensor([0.0, 0.5, -6.0]), RuntimeState(downsample=4, power_saving=0.4)
    cgs = ControlGS.wrap(live, modules=("resample", "display"), cond_dim=4)
    with torch.no_grad():
        cgs.injector.conditions.normal_(generator=torch.Generator().manual_seed(0))
    cgs.save(tmp_path / "live.safetensors")
    pick = torch.arange(0, len(rows), 2)
    with cgs.conditioned(state, anchor_ids=loaded.source_index[pick]):
        want = outputs(live, live.decoder_inputs(cam, loaded.source_index[pick]))
    trained = cgs.injector.conditions.detach().clone()
    cgs.unwrap()
    on_loaded = ControlGS.load(tmp_path / "live.safetensors", loaded)
    assert torch.equal(on_loaded.injector.conditions.detach(), trained[loaded.source_index])
    with on_loaded.conditioned(state, anchor_ids=pick):
        got = outputs(loaded, loaded.decoder_inputs(cam, pick))
    for p in want:
        assert torch.equal(got[p], want[p]), p
    on_loaded.save(tmp_path / "loaded.safetensors")
    on_loaded.unwrap()
    back = ControlGS.load(tmp_path / "loaded.safetensors", live)
    assert torch.equal(back.injector.conditions.detach()[rows], trained[rows])
    assert not back.injector.conditions.detach()[[3, *range(A - PAD, A)]].any()  # invalid rows stay at zero
    back.unwrap()
    other = load_contextgs_dir(_write_dir(tmp_path / "other", _arrays(8, decoded=True), decs))
    with pytest.raises(IncompatibleAdapterError, match="anchor count"):
        ControlGS.load(tmp_path / "live.safetensors", other)
    # another scene with the same counts (valid anchors included) is no reason to scatter the rows onto it
    arr8 = _arrays(8, decoded=True)
    arr8["mask"][3] = 0.0
    live8 = _model(arr8, decs, decoded=True)
    assert int(ContextGSBackend().valid_anchors(live8).sum()) == len(rows)
    with pytest.raises(IncompatibleAdapterError, match="anchor count"):
        ControlGS.load(tmp_path / "loaded.safetensors", live8)


def test_prefilter_uses_anchor_zero_rotation():
    """ContextGS's prefilter_voxel passes rotations[[0]] for every anchor; the stand-in does the same
    (kept from the file's row 0 even when that anchor is dropped)."""
    from _family_checks import make_camera
    from controlgs_adapter.backends.models.anchor_model import anchor_visibility

    arr = _arrays(9, decoded=True)
    arr["anchor"][: A - PAD] = np.array([[0.5, 0.0, 0.0]], np.float32) + np.arange(A - PAD, dtype=np.float32)[:, None] * \
        np.array([[0.01, 0.0, 0.0]], np.float32)  # centres 8-15 px beyond the right edge of the image
    arr["scale"][: A - PAD] = np.array([0.01, 0.2, 0.01, 0.1, 0.1, 0.1], np.float32)  # long along y
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    half = 2 ** -0.5
    rot = torch.tensor([[half, half, 0.0, 0.0]]).repeat(A, 1)  # 90 degrees about x: long along the view axis
    rot[0] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    model = ContextGSModel(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"],
                           scaling=t["scale"], hyper_latent=t["hyper"], rotation=rot, decoded_version=True, **_decoders(9))
    cam = make_camera()
    cam.intrinsics[0, 0] = cam.intrinsics[1, 1] = 400.0  # narrow: a long axis along the view projects short
    got = model.visible_anchors(cam)
    own = anchor_visibility(cam, model.get_anchor, model.get_scaling[:, :3], rot)
    first = anchor_visibility(cam, model.get_anchor, model.get_scaling[:, :3], rot[:1].expand(A, 4))
    assert torch.equal(got, first) and not torch.equal(got, own)
    assert got[1 : A - PAD].all() and not own[1 : A - PAD].any()  # anchor 0's footprint reaches into the image
