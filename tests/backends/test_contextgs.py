"""Tests of ``controlgs_adapter.backends.contextgs``."""

from __future__ import annotations

import math

import helpers.contextgs_files as contextgs_t
import numpy as np
import pytest
import torch
from helpers.contextgs_files import HI, LO, PAD, A, _arrays, _decoders, _model, _write_dir
from helpers.family_checks import check_wrap_identity_and_rows, make_camera, outputs, write_cfg_args
from torch import nn

from controlgs_adapter import Camera
from controlgs_adapter.backends.compgs import CompGSBackend, ResidualBlock, ResidualMLP
from controlgs_adapter.backends.contextgs import ContextGSBackend, ContextGSModel, load_contextgs_dir, quantize_anchor
from controlgs_adapter.backends.hac import HACBackend
from controlgs_adapter.backends.octree_gs import OctreeGSBackend
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.formats.backbone import read_ply, write_ply


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


def _visible_by_hand(cam: Camera, means: torch.Tensor, scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """3DGS's prefilter in float64: depth > 0.2 and the square of half-width ceil(3 sqrt(lambda_max)) about
    the projected centre overlaps [0, W] x [0, H]; 2D covariance J W R S^2 R^T W^T J^T + 0.3 I."""
    w2c = cam.world_to_camera.to(D)
    k = cam.intrinsics.to(D)
    out = torch.zeros(means.shape[0], dtype=torch.bool)
    for i in range(means.shape[0]):
        t = w2c[:3, :3] @ means[i] + w2c[:3, 3]
        if t[2] <= 0.2:
            continue
        w, x, y, z = (quats[i] / quats[i].norm()).tolist()
        r = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                          [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                          [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=D)
        cov3 = r @ torch.diag(scales[i] ** 2) @ r.T
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        # x/z, y/z clamped to the image widened by 15 % of its size on each side (3DGS's 1.3 x FoV)
        tx = min(max(float(t[0] / t[2]), -float(cx + 0.15 * cam.width) / fx), float(1.15 * cam.width - cx) / fx)
        ty = min(max(float(t[1] / t[2]), -float(cy + 0.15 * cam.height) / fy), float(1.15 * cam.height - cy) / fy)
        j = torch.tensor([[fx / t[2], 0, -fx * tx / t[2]], [0, fy / t[2], -fy * ty / t[2]]], dtype=D)
        m = j @ w2c[:3, :3]
        c2 = m @ cov3 @ m.T + 0.3 * torch.eye(2, dtype=D)
        det = c2[0, 0] * c2[1, 1] - c2[0, 1] ** 2
        mid = 0.5 * (c2[0, 0] + c2[1, 1])
        radius = math.ceil(3.0 * math.sqrt(mid + math.sqrt(max(float(mid * mid - det), 0.1))))
        u, v = fx * t[0] / t[2] + k[0, 2], fy * t[1] / t[2] + k[1, 2]
        out[i] = bool(det > 0 and u + radius > 0 and u - radius < cam.width and v + radius > 0 and v - radius < cam.height)
    return out


# ----------------------------------------------------------------------------------------- ContextGS
def test_contextgs_raw_model_by_hand_quantised_anchors_masks_and_anchor0_prefilter():
    """A not-decoded ContextGS model: anchors quantised to 16 bits in the bound (floor, 2^16 - 1 levels,
    step + 1e-6), masks sigmoid(logit) > 0.01, log scales; every decoded Gaussian by hand. The prefilter
    uses anchor 0's rotation for every anchor: by hand with a float64 EWA projection."""
    a, k, f = 80, 3, 8
    rng = np.random.default_rng(4)
    lo, hi = torch.tensor([-7.5, -5.0, -1.0]), torch.tensor([7.3, 5.1, 1.6])
    anchor = torch.from_numpy(rng.uniform((-7.4, -4.9, -0.9), (7.2, 5.0, 1.5), (a, 3))).float()
    offset, feat = torch.randn(a, k, 3), torch.randn(a, f)
    mask = torch.from_numpy(rng.normal(-3.0, 3.0, (a, k, 1))).float()
    scaling = torch.from_numpy(rng.normal(-2.5, 0.3, (a, 6))).float()
    scaling[:, 0] += 2.5  # needle-like anchors: their footprint depends on the rotation
    rotation = torch.nn.functional.normalize(torch.randn(a, 4), dim=1)
    torch.manual_seed(6)
    decs = {"mlp_opacity": _seq(f + 4, f, k, nn.Tanh()), "mlp_cov": _seq(f + 4, f, 7 * k, None),
            "mlp_color": _seq(f + 4, f, 3 * k, nn.Sigmoid())}
    model = ContextGSModel(anchor=anchor, offset=offset, mask=mask, anchor_feat=feat, scaling=scaling, rotation=rotation,
                           hyper_latent=torch.randn(a, 2), x_bound_min=lo, x_bound_max=hi, decoded_version=False, **decs)
    cam = _camera()
    centre = _centre(cam)
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
        op = _mlp(decs["mlp_opacity"], x)[0]
        cov = _mlp(decs["mlp_cov"], x)[0].reshape(k, 7)
        col = _mlp(decs["mlp_color"], x)[0].reshape(k, 3)
        s = torch.exp(scaling[i].to(D))
        for j in range(k):
            if op[j] > 0 and on[i, j]:
                expected[(i, j)] = _gaussian(pos[i], offset[i, j].to(D), s, op[j], col[j], cov[j])
    assert 0 < len(expected) < a * k
    _check(got, expected)
    # prefilter: anchors as Gaussians with anchor 0's rotation, near the image border so the rotation matters
    want = _visible_by_hand(cam, pos, torch.exp(scaling.to(D)[:, :3]), rotation.to(D)[0].expand(a, 4))
    assert 0 < int(want.sum()) < a
    assert not torch.equal(want, _visible_by_hand(cam, pos, torch.exp(scaling.to(D)[:, :3]), rotation.to(D)))
    assert torch.equal(model.visible_anchors(cam), want)


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


def test_contextgs_bound_refusals(tmp_path):
    arr = contextgs_t._arrays(0, decoded=False)
    t = {k: torch.from_numpy(v) for k, v in arr.items()}
    kw = dict(anchor=t["anchor"], offset=t["offset"], mask=t["mask"][:, :, None], anchor_feat=t["feat"], scaling=t["scale"],
              hyper_latent=t["hyper"], **contextgs_t._decoders(0))
    with pytest.raises(FileFormatError, match="x_bound_min and x_bound_max must be given together"):
        ContextGSModel(x_bound_min=contextgs_t.LO, decoded_version=False, **kw)
    with pytest.raises(FileFormatError, match="x_bound_min and x_bound_max must be given together"):
        ContextGSModel(x_bound_max=contextgs_t.HI, decoded_version=True, **kw)
    with pytest.raises(FileFormatError, match="a not-decoded ContextGS model needs x_bound_min/x_bound_max"):
        ContextGSModel(decoded_version=False, **kw)
    decoded = ContextGSModel(decoded_version=True, **kw)  # a decoded model needs no bound: positions as stored
    assert torch.equal(decoded.get_anchor, t["anchor"])
    # checkpoint.pth entry 'bound' malformed
    root = contextgs_t._write_dir(tmp_path / "c", arr, contextgs_t._decoders(0))
    ckpt = root / "point_cloud" / "iteration_30000" / "checkpoint.pth"
    sd = torch.load(ckpt, weights_only=True)
    for bad in ([contextgs_t.LO], [contextgs_t.LO, torch.zeros(2)], (contextgs_t.LO, [0.0, 0.0, 0.0])):
        torch.save({**sd, "bound": bad}, ckpt)
        with pytest.raises(FileFormatError, match=r"checkpoint.pth: entry 'bound' must be \[x_bound_min, x_bound_max\]"):
            load_contextgs_dir(root, allow_unquantized=True)
    torch.save({**sd, "bound": (contextgs_t.LO, contextgs_t.HI)}, ckpt)  # a tuple is as good as a list
    m = load_contextgs_dir(root, allow_unquantized=True)
    assert torch.equal(m.x_bound_min, contextgs_t.LO) and torch.equal(m.x_bound_max, contextgs_t.HI)


def test_contextgs_defaults_feat_dim_50_and_n_offsets_10(tmp_path):
    # ContextGS ModelParams: feat_dim 50, n_offsets 10: a cfg_args without them reads the test folder (F 50, K 10)
    root = contextgs_t._write_dir(tmp_path / "c", contextgs_t._arrays(1, decoded=True), contextgs_t._decoders(1))
    write_cfg_args(root / "cfg_args", hyper_divisor=4, use_feat_bank=False)
    m = load_contextgs_dir(root)
    assert (m.feat_dim, m.n_offsets) == (50, 10)


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
