"""ControlGS, the wrapper: a wrapped backbone is bit-identical to itself until the adapter moves, the
injection matches Eq. 9 in float64, gradients reach only the adapter, ``unwrap`` restores everything,
refusals come before any change; files round-trip exactly and named adapters switch. Also the
adapter as evaluation, the command line and the backbone families use it."""

from __future__ import annotations

import math
import re
import warnings

import pytest
import torch
from helpers.adapter_files import saved_adapter, trained
from helpers.banks import affine_bank
from helpers.rawfiles import write_raw
from helpers.scaffold_standin import ScaffoldStandIn, make_camera, script_decoders
from helpers.wrapping import (
    DECODERS,
    FULL,
    assert_same_outputs,
    assert_unchanged,
    conditioned_decode,
    decode,
    model_record,
    refusing_stand_in,
    stand_in,
)
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState, __version__
from controlgs_adapter.backend import get_attr_path, set_attr_path
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND, DEFAULT_ADAPTER, DEFAULT_MODULES, _backbone_tensors
from controlgs_adapter.errors import (
    FileFormatError,
    FileWriteError,
    InjectionMissedError,
    InputValueError,
    LifecycleError,
    NoMatchingBackendError,
    NonFiniteError,
    ShapeError,
    TargetError,
)
from controlgs_adapter.formats.safetensors import load_tensors, read_header
from controlgs_adapter.rendering.protocol import FunctionRenderer, render_view
from controlgs_adapter.state import Camera

#: a state in the middle of every shared schedule
STATE = RuntimeState(downsample=5.0, power_saving=0.55)


# ------------------------------------------------------------------------------ the injection
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bit_identical_at_init_inside_and_outside_the_block(kind):
    model, cam = stand_in(kind), make_camera()
    x = model.decoder_input(cam.center)
    ref = decode(model, x)
    cgs = ControlGS.wrap(model)
    assert_same_outputs(ref, decode(model, x))
    assert_same_outputs(ref, conditioned_decode(cgs, model, x, FULL, camera=cam))


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bit_identical_when_every_strength_is_zero(kind):
    model, cam = stand_in(kind), make_camera()
    x = model.decoder_input(cam.center)
    ref = decode(model, x)
    # lens endpoints beyond every anchor's radius: lambda_lens = 0; d = 1, rho = 0: the others are 0
    cgs = trained(model, 1, endpoints={"lens": (5.0, 6.0)})
    with cgs.conditioned(RuntimeState(downsample=1.0, power_saving=0.0), camera=cam):
        # shared strengths of zero are not computed; a per-anchor one stays (testing it would sync the device)
        assert list(cgs.injector.context.strengths) == ["lens"]
        assert not bool(cgs.injector.context.strengths["lens"].any())
        assert_same_outputs(ref, decode(model, x))
    assert_same_outputs(ref, decode(model, x))  # outside the block, with a non-zero adapter


def test_only_rows_with_positive_strength_change():
    model, cam = stand_in(num_anchors=60), make_camera()
    x = model.decoder_input(cam.center)
    ref = decode(model, x)
    cgs = trained(model, 1, modules=("lens",), endpoints={"lens": (0.3, 1.0)})
    lam = cgs.strengths(FULL, cam)["lens"]
    on = lam > 0
    assert 0 < int(on.sum()) < on.numel()
    out = conditioned_decode(cgs, model, x, FULL, camera=cam)
    for k in out:
        assert torch.equal(out[k][~on], ref[k][~on]), k
        # every changed row differs somewhere (tanh/sigmoid outputs are not saturated here)
        assert bool((out[k][on] != ref[k][on]).any(dim=1).all()), k


def _pinhole_screen(points: torch.Tensor, cam: Camera) -> torch.Tensor:
    """Independent float64 projection to normalised screen coordinates."""
    p = points.double() @ cam.world_to_camera[:3, :3].double().T + cam.world_to_camera[:3, 3].double()
    k = cam.intrinsics.double()
    u = k[0, 0] * p[:, 0] / p[:, 2] + k[0, 2]
    v = k[1, 1] * p[:, 1] / p[:, 2] + k[1, 2]
    return torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], dim=1)


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_injection_matches_eq9_in_float64(kind):
    """FC1 output + sum_m lambda_m * A_m(C_m) through the rest of the decoder, computed module by module."""
    model, cam = stand_in(kind, num_anchors=30, dtype=torch.float64), make_camera(dtype=torch.float64)
    visible = torch.arange(30) % 3 != 1
    x = model.decoder_input(cam.center, visible)
    state = RuntimeState(downsample=2.5, power_saving=0.3)
    cgs = trained(model, 1, endpoints={"lens": (0.1, 1.2)})
    eager = {d: getattr(model, d) for d in DECODERS}  # the wrapped (for TorchScript: rebuilt) decoders
    ids = visible.nonzero().squeeze(1)
    on_display = torch.tensor([1.0, cam.height / cam.width], dtype=torch.float64)  # "fit" placement, landscape
    r = torch.linalg.vector_norm(_pinhole_screen(model._anchor.detach()[ids], cam) * on_display, dim=1)
    lam = {"lens": ((r - 0.1) / 1.1).clamp(0, 1), "resample": torch.full_like(r, math.log2(2.5) / 3),
           "display": torch.full_like(r, 0.3 / 0.8)}
    got = conditioned_decode(cgs, model, x, state, camera=cam, anchor_ids=visible)
    with torch.no_grad():
        for d, name in zip(DECODERS, ("opacity", "cov", "color")):
            seq = eager[d]
            h = x @ seq[0].weight.T + seq[0].bias
            for m, lm in lam.items():
                c = cgs.injector.condition(m).detach()[ids]
                a = cgs.injector.projections[m]["d32"].weight.detach()
                h = h + lm[:, None] * (c @ a.T)
            want = seq[1:](h)
            assert torch.allclose(got[name], want, rtol=0, atol=1e-12), d


def test_rows_per_anchor_groups_rows_by_anchor():
    class KRows(ScaffoldGSBackend):
        """Scaffold layout with 3 decoder rows per anchor (CompGS-like)."""

        name = "k_rows_test"

        def rows_per_anchor(self, model):
            return 3

    model, cam = stand_in(num_anchors=12), make_camera()
    ids = torch.tensor([7, 2, 9, 0])
    x = model.decoder_input(cam.center)[ids].repeat_interleave(3, dim=0)  # [12, 35]
    x = x + 0.01 * torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    cgs = trained(model, 1, backend=KRows(), modules=("resample", "lens"))
    with cgs.conditioned(FULL, camera=cam, anchor_ids=ids):
        got = model.mlp_cov[0](x)
        with pytest.raises(ShapeError, match="4 anchor ids x 3 rows"):
            model.mlp_cov[0](x[:4])
    lam = cgs.strengths(FULL, cam, ids)
    inj = sum(lam[m][:, None] * (cgs.injector.condition(m)[ids] @ cgs.injector.projections[m]["d32"].weight.T)
              for m in ("resample", "lens"))
    want = nn.functional.linear(x, model.mlp_cov[0].weight, model.mlp_cov[0].bias) + inj.repeat_interleave(3, dim=0)
    assert torch.allclose(got, want.detach(), atol=1e-6)


def test_modules_switched_off_in_a_block_are_not_injected():
    """A block restricted to ``display`` gives what a wrapper of that module alone gives."""
    model, cam = stand_in(), make_camera()
    x = model.decoder_input(cam.center)
    full = trained(model, 1)
    with full.conditioned(FULL, camera=cam, modules=("display",)):
        assert list(full.injector.context.strengths) == ["display"]
        only_display = decode(model, x)
    state = {k: v.detach().clone() for k, v in full.injector.state_dict().items()}
    full.unwrap()
    single = ControlGS.wrap(model, modules=("display",))
    single.injector.load_state_dict({"conditions": state["conditions"][:, 2:3],
                                     "projections.display.d32.weight": state["projections.display.d32.weight"]})
    assert_same_outputs(only_display, conditioned_decode(single, model, x, FULL, camera=cam))


def test_gradients_reach_only_the_adapter_and_the_backbone_does_not_move():
    model, cam = stand_in(), make_camera()
    x = model.decoder_input(cam.center).detach()
    before = {d: {k: v.clone() for k, v in getattr(model, d).state_dict().items()} for d in DECODERS}
    anchors_before = model._anchor.detach().clone()
    cgs = ControlGS.wrap(model)
    with torch.no_grad():  # non-zero conditions so that projections get non-zero gradients too
        cgs.injector.conditions.normal_()
    opt = torch.optim.Adam(cgs.trainable_parameters(), lr=1e-2)
    with cgs.conditioned(FULL, camera=cam):
        loss = sum(v.square().mean() for v in model.decode(x).values())
    loss.backward()
    adapter = list(cgs.trainable_parameters())
    assert len(adapter) == 1 + 3  # the conditions [A, 3, N], three projections (one width)
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in adapter)
    backbone = [p for d in DECODERS for p in getattr(model, d).parameters()] + [model._anchor, model._anchor_feat]
    assert all(p.grad is None and not p.requires_grad for p in backbone)
    opt.step()
    for d in DECODERS:
        assert all(torch.equal(v, before[d][k]) for k, v in getattr(model, d).state_dict().items())
    assert torch.equal(model._anchor.detach(), anchors_before)


def test_adapter_gradients_match_finite_differences_float64():
    model, cam = stand_in(num_anchors=6, feat_dim=4, dtype=torch.float64), make_camera(dtype=torch.float64)
    x = model.decoder_input(cam.center).detach()
    cgs = trained(model, 1, cond_dim=2, endpoints={"lens": (0.0, 1.0)})
    state = RuntimeState(downsample=3.0, power_saving=0.5)
    w = torch.randn(6, 30, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def loss():
        with cgs.conditioned(state, camera=cam):
            return (model.mlp_color(x) * w).sum()

    loss().backward()
    checked = 0
    for p in cgs.trainable_parameters():
        for i in torch.randperm(p.numel(), generator=torch.Generator().manual_seed(checked))[:4].tolist():
            flat = p.data.view(-1)
            old = float(flat[i])
            with torch.no_grad():
                flat[i] = old + 1e-6
                up = float(loss())
                flat[i] = old - 1e-6
                down = float(loss())
            flat[i] = old
            assert math.isclose(float(p.grad.view(-1)[i]), (up - down) / 2e-6, rel_tol=1e-5, abs_tol=1e-8)
            checked += 1
    assert checked == 4 * 4  # conditions + three projections


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_unwrap_restores_objects_flags_and_outputs(kind):
    model, cam = stand_in(kind, use_feat_bank=True), make_camera()
    x = model.decoder_input(cam.center)
    ref = decode(model, x)
    model._anchor_feat.requires_grad_(False)  # a mix of flags, restored as they were
    before = model_record(model)
    objects = {d: getattr(model, d) for d in (*DECODERS, "mlp_feature_bank")}
    cgs = trained(model, 1)
    if kind == "script":
        assert all(getattr(model, d) is not objects[d] for d in DECODERS)
    assert getattr(model, "mlp_feature_bank") is objects["mlp_feature_bank"]  # not a default target
    fc1s = [getattr(model, d)[0] for d in DECODERS]
    assert cgs.unwrap() is model
    assert_unchanged(before, model)
    assert all(not f._forward_hooks for f in fc1s)
    assert_same_outputs(ref, decode(model, x))
    with pytest.raises(LifecycleError, match="unwrapped"):
        with cgs.conditioned(FULL, camera=cam):
            pass
    ControlGS.wrap(model).unwrap()  # can be wrapped again


def test_backbone_tensors_are_frozen_and_restored_and_an_unwrapped_wrapper_refuses_every_call():
    class Holder:
        pass

    h = Holder()
    h.net = nn.Linear(2, 2)
    h.leaf = torch.zeros(3, requires_grad=True)
    h.derived = h.leaf * 2  # not a leaf: not trainable, not listed
    h.other = 3
    found = _backbone_tensors(h)
    assert {id(t) for t in found} == {id(h.net.weight), id(h.net.bias), id(h.leaf)} and len(found) == 3
    mod = nn.Sequential(nn.Linear(2, 2))
    assert [id(p) for p in _backbone_tensors(mod)] == [id(p) for p in mod.parameters()]
    model = ScaffoldStandIn(10, seed=1)
    model._offset.requires_grad_(False)  # a flag that must come back as it was, not as True
    cgs = ControlGS.wrap(model)
    tensors = [model._anchor, model._anchor_feat, model._offset, *model.mlp_cov.parameters()]
    assert not any(t.requires_grad for t in tensors)
    assert all(p.requires_grad for p in cgs.trainable_parameters())
    cgs.unwrap()
    assert [t.requires_grad for t in tensors[:3]] == [True, True, False] and all(t.requires_grad for t in tensors[3:])
    for call in (cgs.unwrap, lambda: cgs.strengths(RuntimeState()), lambda: cgs.save("x.safetensors"),
                 lambda: cgs.set_adapter("default"), lambda: cgs.conditioned(RuntimeState()).__enter__()):
        with pytest.raises(LifecycleError, match="unwrapped"):
            call()


@pytest.mark.parametrize("dtype, want", [(torch.float64, torch.float64), (torch.float16, torch.float32)])
def test_injector_dtype_follows_fc1_when_float32_or_float64(dtype, want):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1, dtype=dtype)
    cgs = ControlGS.wrap(model, modules=("display",))
    assert cgs.injector.dtype == want and cgs.strengths(RuntimeState(power_saving=0.4))["display"].dtype == want
    cgs.unwrap()


def test_defaults_of_wrap():
    model = ScaffoldStandIn(12, seed=2)
    cgs = ControlGS.wrap(model)
    try:
        assert DEFAULT_MODULES == ("lens", "resample", "display") and DEFAULT_ADAPTER == "default"
        assert cgs.modules == DEFAULT_MODULES and cgs.injector.cond_dim == 8 and cgs.adapters == ("default",)
        assert cgs.active_adapter == "default" and cgs.state_blind is False and cgs.placement == "fit"
        assert cgs.backend.name == "scaffold_gs" and cgs.num_anchors == 12 and cgs.rows_per_anchor == 1
        assert [t.decoder for t in cgs.targets] == list(DECODERS)
        assert all((t.in_features, t.out_features, t.from_torchscript) == (35, 32, False) for t in cgs.targets)
        assert cgs.targets[0].as_header() == {"decoder": "mlp_opacity", "fc1": "mlp_opacity.0", "in_features": 35,
                                              "out_features": 32}
        assert {m: (s.lo, s.hi) for m, s in cgs.schedules.items()} == {"lens": (0.0, math.sqrt(2.0)),
                                                                       "resample": (0.0, 3.0), "display": (0.0, 0.8)}
        assert cgs.skipped == [] and cgs.injector.dtype == torch.float32
        assert cgs.fingerprint == ScaffoldGSBackend().fingerprint(model)
    finally:
        cgs.unwrap()


def test_summary_counts_and_repr():
    """The summary's numbers: anchors, rows per anchor, fingerprint, modules, N, each target's widths and
    the parameter counts (conditions A * M * N, one projection [D1, N] per module and width)."""
    # A = 7 anchors, 2 modules, N = 3: conditions 42; one FC1 width (D1 = F = 8): projections 2 * 8 * 3 = 48
    cgs = ControlGS.wrap(NeuralGaussianModel(7, feat_dim=8, n_offsets=2), modules=("display", "resample"), cond_dim=3)
    assert re.search(r"trainable: 90 parameters \(conditions 42, projections 48\)", cgs.summary())
    assert sum(p.numel() for p in cgs.trainable_parameters()) == 90
    cgs.unwrap()

    model = script_decoders(ScaffoldStandIn(12, feat_dim=4, n_offsets=2, seed=2))
    cgs = ControlGS.wrap(model, modules=("resample", "display"), cond_dim=3, targets=["mlp_cov"], state_blind=True)
    lines = cgs.summary().splitlines()
    # conditions 12 * 2 * 3 = 72; projections 2 modules x [4, 3] = 24
    for line, pattern in zip(lines, [r"ScaffoldStandIn.*'scaffold_gs'$", rf"anchors: 12 \(1 decoder row.*{cgs.fingerprint}$",
                                     r"modules: resample, display; N = 3.*state-blind", "targets:",
                                     r"mlp_cov\.0: Linear\(7 -> 4\).*TorchScript", "schedules:",
                                     r"resample: ResampleSchedule\(log2\(d\): 0 -> 0, 3 -> 1\)$",
                                     r"display: DisplaySchedule\(rho: 0 -> 0, 0\.8 -> 1\)$",
                                     r"trainable: 96 parameters \(conditions 72, projections 24\)$"], strict=True):
        assert re.search(pattern, line), (pattern, line)
    assert repr(cgs) == ("ControlGS(backend='scaffold_gs', anchors=12, modules=['resample', 'display'], cond_dim=3, "
                         "targets=['mlp_cov.0'], state_blind=True)")
    cgs.unwrap()
    assert repr(cgs).endswith("state_blind=True, unwrapped)")
    assert cgs.summary().splitlines()[0].endswith("(unwrapped)")
    assert isinstance(model.mlp_cov, torch.jit.ScriptModule)  # the original TorchScript decoder is back


def test_torchscript_decoders_are_replaced_on_the_users_object():
    """A plain-Python model with TorchScript decoders (a Scaffold-GS checkpoint): wrap puts hooked
    eager copies ON that object, so code holding the object (its renderer) sees the injection."""
    model = script_decoders(ScaffoldStandIn(num_anchors=30))
    originals = {k: getattr(model, k) for k in DECODERS}
    cam = make_camera()
    x = model.decoder_input(cam.center)
    before = decode(model, x)
    cgs = ControlGS.wrap(model, modules=("display",))
    with torch.no_grad():
        cgs.injector.conditions.normal_(generator=torch.Generator().manual_seed(0))
    for k, scripted in originals.items():
        assert isinstance(scripted, torch.jit.ScriptModule) and not isinstance(getattr(model, k), torch.jit.ScriptModule)
    renderer = FunctionRenderer(lambda m, c, v, bg: m.decode(m.decoder_input(c.center))["color"][:, :3].T.reshape(3, 3, 10))
    state = RuntimeState(downsample=2, power_saving=0.4)
    with torch.no_grad(), cgs.conditioned(state, cam):
        after = model.decode(x)
        assert cgs.injector.context.calls == {"mlp_opacity": 1, "mlp_cov": 1, "mlp_color": 1}
    assert not torch.equal(after["color"], before["color"])
    with torch.no_grad():
        image = render_view(cgs, model, make_camera(width=10, height=3), state, renderer=renderer)
    assert image.shape == (3, 3, 10)
    cgs.unwrap()
    assert all(getattr(model, k) is v for k, v in originals.items())


# ------------------------------------------------------------------------------ refusals
def test_wrong_row_counts_nested_blocks_and_bad_block_arguments_are_refused():
    model, cam = stand_in(num_anchors=20), make_camera()
    x = model.decoder_input(cam.center)
    cgs = ControlGS.wrap(model)
    mask = torch.zeros(20, dtype=torch.bool)
    mask[:5] = True
    with cgs.conditioned(FULL, camera=cam, anchor_ids=mask):
        model.decode(x[:5])  # the block's rows: the mask's 5 anchors
        with pytest.raises(ShapeError, match=r"20 rows.*5 rows"):
            model.decode(x)
        with pytest.raises(LifecycleError, match="nested"):
            with cgs.conditioned(FULL, camera=cam):
                pass
    with pytest.raises(ShapeError, match=r"anchor_ids mask.*20.*\[19\]"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.ones(19, dtype=torch.bool)):
            pass
    with pytest.raises(InputValueError, match="'lens'.*camera"):
        with cgs.conditioned(FULL, anchor_ids=mask):  # lens needs the camera
            pass
    with pytest.raises(InputValueError, match="state.*RuntimeState.*dict"):
        with cgs.conditioned({"downsample": 2}, camera=cam):
            pass
    assert cgs.injector.context is None  # failed entries leave nothing active
    model.decode(x)  # and outside a block any row count is fine


def test_anchor_ids_forms_and_refusals():
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("display",))
    assert cgs.anchor_ids(None).tolist() == [0, 1, 2, 3, 4, 5]
    for dt in (torch.int64, torch.int32, torch.int16, torch.uint8, torch.int8):
        got = cgs.anchor_ids(torch.tensor([5, 0, 0], dtype=dt))
        assert got.dtype == torch.int64 and got.tolist() == [5, 0, 0]
    assert cgs.anchor_ids(torch.tensor([], dtype=torch.int64)).tolist() == []
    assert cgs.anchor_ids(torch.tensor([0, 1, 0, 0, 1, 1], dtype=torch.bool)).tolist() == [1, 4, 5]  # ascending
    for bad, error, pattern in [([1, 2], InputValueError, r"anchor_ids.*BoolTensor\[6\].*got list"),
                                (torch.tensor([[1]]), ShapeError, r"anchor_ids.*\[R\].*got \[1, 1\]"),
                                (torch.tensor([-1, 3]), InputValueError, r"anchor_ids.*\[0, 6\).*\[-1, 3\]"),
                                (torch.tensor([6]), InputValueError, r"anchor_ids.*\[0, 6\).*\[6, 6\]"),
                                (torch.tensor([1.0]), InputValueError, r"anchor_ids.*torch\.float32"),
                                (torch.ones(5, dtype=torch.bool), ShapeError, r"anchor_ids mask.*6.*\[5\]")]:
        with pytest.raises(error, match=pattern):
            cgs.anchor_ids(bad)
    cgs.unwrap()


def test_conditioned_on_miss_branches_and_zero_row_blocks():
    model = script_decoders(ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1))
    cgs = ControlGS.wrap(model, modules=("display",))
    state = RuntimeState(power_saving=0.4)
    with pytest.warns(RuntimeWarning) as rec:
        with cgs.conditioned(state):
            pass
    msg = str(rec[0].message)
    # names the injected layers, the model object and the TorchScript decoders replaced on it
    assert re.search(rf"\(mlp_opacity\.0, mlp_cov\.0, mlp_color\.0\) of ScaffoldStandIn object at {id(model):#x}", msg)
    assert re.search(r"TorchScript decoders \['mlp_opacity', 'mlp_cov', 'mlp_color'\]", msg)
    assert rec[0].filename == __file__  # stacklevel: the warning points at the user's with-statement
    with pytest.raises(InjectionMissedError, match="no wrapped decoder ran"):
        with cgs.conditioned(state, on_miss="raise"):
            pass
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with cgs.conditioned(state, on_miss="ignore"):
            pass
        with cgs.conditioned(state, anchor_ids=torch.zeros(6, dtype=torch.bool), on_miss="raise"):
            pass  # no visible anchor: nothing to render, nothing missed
        x = torch.randn(6, 7)
        with cgs.conditioned(state, on_miss="raise"):
            model.mlp_cov(x)  # one decoder ran: not a miss
    with pytest.raises(InputValueError, match="on_miss.*got 'loud'"):
        with cgs.conditioned(state, on_miss="loud"):
            pass
    with pytest.raises(InputValueError, match=r"modules \['lens'\].*not wrapped.*\['display'\]"):
        with cgs.conditioned(state, modules=["lens"]):
            pass
    with pytest.raises(InputValueError, match=r"modules.*got \[1\]"):
        with cgs.conditioned(state, modules=[1]):
            pass
    # a shared strength of zero is left out of the context; a block with modules=() injects nothing;
    # a single name is one module (not its letters)
    with cgs.conditioned(RuntimeState(), on_miss="ignore"):
        assert cgs.injector.context.strengths == {}
    with cgs.conditioned(state, modules=(), on_miss="ignore"):
        assert cgs.injector.context.strengths == {}
    with cgs.conditioned(state, modules="display", on_miss="ignore"):
        assert cgs.injector.context.strengths == {"display": 0.5}
    cgs.unwrap()


@pytest.fixture
def cgs():
    c = ControlGS.wrap(ScaffoldStandIn(30, seed=0))
    yield c
    if c._wrapped:
        c.unwrap()


def _nan_conditions(c: ControlGS) -> None:
    with torch.no_grad():
        c.injector.conditions[0, 0, 0] = math.nan


def _huge_conditions(c: ControlGS) -> None:
    with torch.no_grad():
        c.injector.conditions[0, 0, 0] = 1e6


CALL_CASES = [
    ("save None", lambda c, d: c.save(None), InputValueError, "path.*None"),
    ("save 123", lambda c, d: c.save(123), InputValueError, "path.*123"),
    ("save onto a folder", lambda c, d: c.save(d), InputValueError, "{d}: is a folder"),
    ("save under a file", lambda c, d: c.save(d / "f.txt" / "a.safetensors"), FileWriteError, "{d}/f.txt/a.safetensors"),
    ("save dtype", lambda c, d: c.save(d / "a.safetensors", dtype=torch.int8), InputValueError, r"dtype.*torch\.int8"),
    ("save NaN", lambda c, d: (_nan_conditions(c), c.save(d / "a.safetensors")), NonFiniteError,
     "{d}/a.safetensors.*'conditions'.*1 NaN"),
    ("save fp16 overflow", lambda c, d: (_huge_conditions(c), c.save(d / "a.safetensors", dtype=torch.float16)),
     NonFiniteError, r"{d}/a.safetensors.*1e\+06.*float16.*65504"),
    ("load None", lambda c, d: ControlGS.load(None, ScaffoldStandIn(30, seed=0)), InputValueError, "path.*None"),
    ("load a folder", lambda c, d: ControlGS.load(d, ScaffoldStandIn(30, seed=0)), FileFormatError, "{d}: no such file"),
    ("load missing", lambda c, d: ControlGS.load(d / "none.safetensors", ScaffoldStandIn(30, seed=0)), FileFormatError,
     "{d}/none.safetensors: no such file"),
    ("conditioned modules=5", lambda c, d: c.conditioned(RuntimeState(), modules=5).__enter__(), InputValueError,
     "modules.*got 5"),
    ("conditioned modules=['nope']", lambda c, d: c.conditioned(RuntimeState(), modules=["nope"]).__enter__(),
     InputValueError, r"\['nope'\].*not wrapped"),
    ("conditioned modules='lns'", lambda c, d: c.conditioned(RuntimeState(), modules="lns").__enter__(),
     InputValueError, r"\['lns'\].*not wrapped"),
    ("conditioned state=None", lambda c, d: c.conditioned(None).__enter__(), InputValueError, "state.*NoneType"),
]


@pytest.mark.parametrize("call, error, pattern", [c[1:] for c in CALL_CASES], ids=[c[0] for c in CALL_CASES])
def test_bad_arguments_of_save_load_and_conditioned_are_refused(cgs, tmp_path, call, error, pattern):
    (tmp_path / "f.txt").write_text("x")
    with pytest.raises(error, match=pattern.replace("{d}", re.escape(str(tmp_path)))):
        call(cgs, tmp_path)


@pytest.mark.parametrize("kw, error, pattern", [
    (dict(modules="lens"), InputValueError, "modules.*got 'lens'"),
    (dict(name=""), InputValueError, "adapter name.*got ''"),
    (dict(name=3), InputValueError, "adapter name.*got 3"),
    (dict(backend=5), NoMatchingBackendError, "(?s)backend 5 is not registered.*scaffold_gs"),
    (dict(backend="octree_family_that_is_not_there"), NoMatchingBackendError,
     "(?s)'octree_family_that_is_not_there' is not registered.*scaffold_gs"),
], ids=["modules a string", "empty name", "name 3", "backend 5", "unknown backend"])
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bad_names_and_backends_are_refused_before_the_model_changes(kind, kw, error, pattern):
    model = refusing_stand_in(kind)
    before = model_record(model)
    with pytest.raises(error, match=pattern):
        ControlGS.wrap(model, **kw)
    assert_unchanged(before, model)
    assert ControlGS.attached(model) is None


class _Picky(ScaffoldGSBackend):
    """Picky test backend: Scaffold layout with settable anchors and rows."""

    name = "picky"

    def __init__(self, rows=1, anchors=None):
        self.rows, self.anchors = rows, anchors

    def rows_per_anchor(self, model):
        return self.rows

    def num_anchors(self, model):
        return super().num_anchors(model) if self.anchors is None else self.anchors


def test_a_backends_anchor_and_row_counts_are_checked():
    model = ScaffoldStandIn(10, seed=1)
    for backend, error, pattern in [(_Picky(rows=0), TargetError, "picky: rows_per_anchor.*got 0"),
                                    (_Picky(rows=2.0), TargetError, r"rows_per_anchor.*got 2\.0"),
                                    (_Picky(anchors=0), ShapeError, r"picky: .*0 anchors.*\[10, 3\]"),
                                    (_Picky(anchors=9), ShapeError, r"9 anchors.*\[10, 3\]")]:
        with pytest.raises(error, match=pattern):
            ControlGS.wrap(model, backend=backend)
        assert ControlGS.attached(model) is None and not model.mlp_cov[0]._forward_hooks
    cgs = ControlGS.wrap(model, backend=_Picky(rows=2))  # an instance is used as given
    assert cgs.backend.name == "picky" and cgs.rows_per_anchor == 2
    cgs.unwrap()
    cgs = ControlGS.wrap(model, backend="scaffold_gs")  # or a registered one by name
    assert cgs.backend.name == "scaffold_gs"
    cgs.unwrap()


class _FailingHook(ScaffoldGSBackend):
    """Failing-hook test backend: the second make_hookable fails."""

    name = "failing_hook"

    def __init__(self):
        self.calls = 0

    def make_hookable(self, model, decoder_path):
        self.calls += 1
        if self.calls == 2:
            raise RuntimeError("hook failed")
        return super().make_hookable(model, decoder_path)


class _BadHookable(ScaffoldGSBackend):
    """Bad-hookable test backend: make_hookable installs another first layer."""

    name = "bad_hookable"

    def __init__(self, layer):
        self.layer = layer

    def make_hookable(self, model, decoder_path):
        original = get_attr_path(model, decoder_path)
        set_attr_path(model, decoder_path, nn.Sequential(self.layer))
        return original


@pytest.mark.parametrize("backend, error, pattern", [
    (_FailingHook(), RuntimeError, "hook failed"),
    (_BadHookable(nn.Linear(7, 5)), TargetError, r"bad_hookable: .*'mlp_opacity\.0'.*Linear\(in_features=7, out_features=5"),
    (_BadHookable(nn.ReLU()), TargetError, r"bad_hookable: .*'mlp_opacity\.0'.*ReLU\(\)"),
], ids=["a failing hook", "another Linear", "not a Linear"])
def test_a_backend_failing_to_make_the_decoders_hookable_is_rolled_back(backend, error, pattern):
    """The decoders already replaced (TorchScript ones by eager copies) are put back; nothing is attached
    and the backbone is not frozen; the model wraps normally afterwards."""
    model = script_decoders(ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1))
    before = model_record(model)
    with pytest.raises(error, match=pattern):
        ControlGS.wrap(model, backend=backend)
    assert_unchanged(before, model)
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model)
    assert ControlGS.attached(model) is cgs and all(t.from_torchscript for t in cgs.targets)
    assert all(isinstance(getattr(model, d), nn.Sequential) for d in DECODERS)
    cgs.unwrap()
    assert_unchanged(before, model)
    assert ControlGS.attached(nn.Linear(2, 2)) is None  # no backend recognises it


# ------------------------------------------------------------------------------ files and named adapters
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_round_trip_reproduces_outputs_exactly(tmp_path, kind):
    model, cam = stand_in(kind, num_anchors=30), make_camera()
    x = model.decoder_input(cam.center)
    cgs = trained(model, modules=("lens", "display", "foveation"), cond_dim=4, endpoints={"lens": (0.2, 1.1)})
    want = conditioned_decode(cgs, model, x, STATE, camera=cam)
    path = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    loaded = ControlGS.load(path, model)
    assert_same_outputs(want, conditioned_decode(loaded, model, x, STATE, camera=cam))
    assert loaded.modules == ("lens", "display", "foveation") and loaded.injector.cond_dim == 4
    assert (loaded.schedules["lens"].lo, loaded.schedules["lens"].hi) == (0.2, 1.1)
    assert [t.from_torchscript for t in loaded.targets] == [kind == "script"] * 3


def test_header_describes_the_adapter(tmp_path):
    model = ScaffoldStandIn(30)
    cgs = trained(model, state_blind=True)
    path = cgs.save(tmp_path / "a.safetensors")
    h = read_header(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    # a centred radius lens condition records no frame: format 1, which readers of format 1 read as meant
    assert h["format_version"] == 1 and "lens_frame" not in h and h["library_version"] == __version__
    assert h["backend"] == "scaffold_gs" and h["modules"] == ["lens", "resample", "display"] and h["cond_dim"] == 8
    assert h["schedules"]["resample"] == {"class": "ResampleSchedule", "per_anchor": False, "lo": 0.0, "hi": 3.0}
    assert h["state_blind"] is True and h["num_anchors"] == 30 and h["rows_per_anchor"] == 1
    assert h["targets"][0] == {"decoder": "mlp_opacity", "fc1": "mlp_opacity.0", "in_features": 35, "out_features": 32}
    assert h["fingerprint"] == cgs.backend.fingerprint(model) and h["condition_dtype"] == "float32"
    cgs.unwrap()
    assert ControlGS.load(path, model).state_blind


#: a gaze in the field of both the Cardboard lens and :func:`_fov_bank`'s
GAZE_STATE = RuntimeState(power_saving=0.3, gaze=(4.0, -3.0))


def _fov_bank():
    """A decentred, sheared lens (affine green chief rays: bilinear maps of it are exact) seen 40 deg wide."""
    bank = affine_bank([[1.1, 0.2], [-0.1, 0.9]], [0.05, -0.03], axis=(0.1, -0.05))
    bank.meta["lens"]["half_fov_deg"] = 40.0
    return bank


def test_a_foveation_adapter_loads_measuring_through_its_lens(tmp_path):
    model, cam = ScaffoldStandIn(30), make_camera()
    cgs = trained(model, modules=("display", "foveation"), lens=_fov_bank())
    want = cgs.strengths(GAZE_STATE, cam)["foveation"]
    path = cgs.save(tmp_path / "a.safetensors")
    h = read_header(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    assert h["format_version"] == 3 and "lens_frame" not in h
    assert (len(h["visual_angles"]["tangents"]), len(h["visual_angles"]["tangents"][0])) == (9, 9)  # the bank's grid
    cgs.unwrap()
    cardboard = ControlGS.wrap(model, modules=("display", "foveation"))
    other = cardboard.strengths(GAZE_STATE, cam)["foveation"]
    cardboard.unwrap()
    assert (want - other).abs().max() > 0.05  # the lens matters at this gaze
    loaded = ControlGS.load(path, model)
    assert torch.equal(loaded.strengths(GAZE_STATE, cam)["foveation"], want)  # the bank's own grid: exact
    assert loaded.header() == cgs.header()


def test_a_file_without_visual_angles_measures_through_cardboard(tmp_path):
    """Files before format 3 record no visual-angle map: the foveation module sees through the Cardboard lens."""
    model, cam = ScaffoldStandIn(30), make_camera()
    cgs = trained(model, modules=("display", "foveation"), lens=_fov_bank())
    path = cgs.save(tmp_path / "a.safetensors")
    cgs.unwrap()
    h = read_header(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    header = {k: v for k, v in h.items() if k not in ("kind", "format_version", "library_version", "visual_angles")}
    tensors = load_tensors(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)[0]
    write_raw(path, tensors, header, kind=ADAPTER_KIND, format_version=1)
    loaded = ControlGS.load(path, model)
    assert loaded.schedules["foveation"].lens_angles is None
    cardboard = ControlGS.wrap(ScaffoldStandIn(30), modules=("display", "foveation"))
    assert torch.equal(loaded.strengths(GAZE_STATE, cam)["foveation"], cardboard.strengths(GAZE_STATE, cam)["foveation"])


@pytest.mark.parametrize("modules, lens", [(("display", "foveation"), None), (("display",), _fov_bank),
                                           (("display", "foveation"), PSFBank.default)])
def test_no_visual_angles_without_a_foveation_lens(tmp_path, modules, lens):
    """Without the foveation module, or with the Cardboard lens, the file is format 1 as before the field existed."""
    path = saved_adapter(tmp_path, modules=modules, lens=lens and lens())
    h = read_header(path, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    assert h["format_version"] == 1 and "visual_angles" not in h


def test_named_adapters_keep_their_own_foveation_lens(tmp_path):
    model, cam = ScaffoldStandIn(30, seed=0), make_camera()
    lens_path = saved_adapter(tmp_path, file="lens.safetensors", modules=("display", "foveation"), lens=_fov_bank())
    plain_path = saved_adapter(tmp_path, file="plain.safetensors", modules=("display", "foveation"))
    lensed = ControlGS.load(lens_path, model)
    want = lensed.strengths(GAZE_STATE, cam)["foveation"]
    lensed.load_adapter(plain_path, "plain")
    lensed.set_adapter("plain")
    plain = lensed.strengths(GAZE_STATE, cam)["foveation"]
    assert lensed.schedules["foveation"].lens_angles is None and (plain - want).abs().max() > 0.05
    lensed.set_adapter(DEFAULT_ADAPTER)
    assert torch.equal(lensed.strengths(GAZE_STATE, cam)["foveation"], want)
    other = ControlGS.load(plain_path, lensed.unwrap())
    other.load_adapter(lens_path, "lens")
    other.set_adapter("lens")
    assert torch.equal(other.strengths(GAZE_STATE, cam)["foveation"], want)


def test_fp16_storage_halves_conditions_and_stays_close(tmp_path):
    model, cam = ScaffoldStandIn(200), make_camera()
    x = model.decoder_input(cam.center)
    cgs = trained(model)
    with torch.no_grad():  # trained conditions are small: keep them in a realistic range
        cgs.injector.conditions.mul_(0.1)
    want = conditioned_decode(cgs, model, x, STATE, camera=cam)
    full = cgs.save(tmp_path / "f32.safetensors")
    half = cgs.save(tmp_path / "f16.safetensors", dtype=torch.float16)
    tensors, header = load_tensors(half, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    assert header["condition_dtype"] == "float16" and tensors["conditions"].dtype == torch.float16
    assert tensors["projections.lens.d32.weight"].dtype == torch.float32
    saved_bytes = 3 * 200 * 8 * 2
    assert abs(full.stat().st_size - half.stat().st_size - saved_bytes) <= 16  # header padding
    expected_conditions = cgs.injector.conditions.detach().half().float()
    cgs.unwrap()
    loaded = ControlGS.load(half, model)
    assert torch.equal(loaded.injector.conditions.detach(), expected_conditions)
    assert loaded.injector.dtype == torch.float32
    got = conditioned_decode(loaded, model, x, STATE, camera=cam)
    err = max(float((want[k] - got[k]).abs().max()) for k in want)
    assert 0 < err < 1e-3


def test_named_adapters_switch_and_each_equals_a_model_with_only_that_adapter(tmp_path):
    cam = make_camera()
    path_a = saved_adapter(tmp_path, 7, "a.safetensors")
    path_b = saved_adapter(tmp_path, 8, "b.safetensors", modules=("lens", "display"), cond_dim=4, state_blind=True)
    model = ScaffoldStandIn(30, seed=0)
    x = model.decoder_input(cam.center)
    cgs = ControlGS.load(path_a, model, name="a")
    assert cgs.load_adapter(path_b, name="b") == []
    assert cgs.adapters == ("a", "b") and cgs.active_adapter == "a"
    out_a = conditioned_decode(cgs, model, x, STATE, camera=cam)
    cgs.set_adapter("b")
    assert cgs.modules == ("lens", "display") and cgs.state_blind
    out_b = conditioned_decode(cgs, model, x, STATE, camera=cam)
    assert not torch.equal(out_a["color"], out_b["color"])
    cgs.set_adapter("a")
    assert_same_outputs(out_a, conditioned_decode(cgs, model, x, STATE, camera=cam))
    cgs.set_adapter("b")
    resaved = cgs.save(tmp_path / "b2.safetensors")  # save() writes the active adapter
    assert_same_outputs(decode(ScaffoldStandIn(30, seed=0), x), decode(model, x))  # outside a block: the backbone
    cgs.unwrap()

    for path, want in ((path_a, out_a), (path_b, out_b), (resaved, out_b)):
        alone_model = ScaffoldStandIn(30, seed=0)
        alone = ControlGS.load(path, alone_model)
        assert_same_outputs(want, conditioned_decode(alone, alone_model, x, STATE, camera=cam))


def test_adapter_names_are_checked_and_switching_moves_the_hooks(tmp_path):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("display",))
    with torch.no_grad():
        cgs.injector.conditions.fill_(0.5)
    path = cgs.save(tmp_path / "a.safetensors")
    assert cgs.load_adapter(path, "second") == []
    assert cgs.adapters == ("default", "second") and cgs.active_adapter == "default"
    with pytest.raises(InputValueError, match=r"'second' is already loaded.*\['default', 'second'\]"):
        cgs.load_adapter(path, "second")
    with pytest.raises(InputValueError, match="adapter name.*got ''"):
        cgs.load_adapter(path, "")
    with pytest.raises(InputValueError, match=r"unknown adapter 'third'.*\['default', 'second'\]"):
        cgs.set_adapter("third")
    first = cgs.injector
    with cgs.conditioned(RuntimeState(), on_miss="ignore"):
        with pytest.raises(LifecycleError, match="set_adapter inside a conditioned block"):
            cgs.set_adapter("second")
    cgs.set_adapter("default")  # already active: nothing changes
    assert cgs.injector is first and len(first._handles) == 3
    cgs.set_adapter("second")
    assert cgs.injector is not first and cgs.active_adapter == "second" and not first._handles
    assert len(cgs.injector._handles) == 3 and torch.equal(cgs.injector.conditions.detach(), first.conditions.detach())
    x = torch.randn(6, 7)
    ref = model.mlp_cov(x).detach()
    with torch.no_grad():
        cgs.injector.conditions.fill_(1.0)
    with cgs.conditioned(RuntimeState(power_saving=0.4), modules="display"):
        out = model.mlp_cov(x).detach()
    assert not torch.equal(out, ref)  # the second adapter's hooks are live
    cgs.set_adapter("default")
    assert cgs.injector is first
    cgs.unwrap()
