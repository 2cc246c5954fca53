"""Issue 15 s.5 sweep, core area: ConditionInjector and ControlGS pinned by hand (float64 sums of
Eq. 9, documented defaults, refusals with their messages, every option branch)."""

from __future__ import annotations

import math
import types
import warnings

import pytest
import torch
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.controlgs import DEFAULT_ADAPTER, DEFAULT_MODULES, _backbone_tensors
from controlgs_adapter.plugins import _describe
from controlgs_adapter.errors import (InjectionMissedError, InputValueError, LifecycleError, NoMatchingBackendError,
                                      ShapeError, TargetError)
from controlgs_adapter.injector import ConditionInjector, InjectionContext

from scaffold_standin import ScaffoldStandIn, make_camera, script_decoders

# ---------------------------------------------------------------------------------------------- injector


def _injector(widths=None, modules=("lens", "resample", "display"), n=3, a=5, seed=0):
    inj = ConditionInjector(a, modules, n, widths or {"t": 4}, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in inj.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype))
    return inj


def _by_hand(inj, ids, strengths, width):
    """sum_m lambda_m * C[ids, m] @ A_m^T in float64, module by module."""
    out = torch.zeros(len(ids), width, dtype=torch.float64)
    for m, lam in strengths.items():
        c = inj.conditions.detach()[ids, inj.module_names.index(m)]
        lam_t = lam if isinstance(lam, torch.Tensor) else torch.full((len(ids),), float(lam), dtype=torch.float64)
        out += lam_t[:, None] * (c @ inj.projections[m][f"d{width}"].weight.detach().T)
    return out


def test_injector_init_layout_and_repr():
    inj = ConditionInjector(6, ("lens", "display"), 8, {"a": 64, "b": 32, "c": 64})
    assert inj.conditions.shape == (6, 2, 8) and not bool(inj.conditions.any())  # zero: starts as the backbone
    assert sorted(k for k, _ in inj.named_parameters()) == [
        "conditions", "projections.display.d32.weight", "projections.display.d64.weight",
        "projections.lens.d32.weight", "projections.lens.d64.weight"]
    assert all(p.shape == (int(k.split(".")[2][1:]), 8) for k, p in inj.named_parameters() if k != "conditions")
    assert repr(inj).endswith("(anchors=6, modules=['lens', 'display'], cond_dim=8, widths=[32, 64])\n)") or \
        "anchors=6, modules=['lens', 'display'], cond_dim=8, widths=[32, 64]" in repr(inj)
    assert inj.dtype == torch.float32
    # nn.Linear's own init: Kaiming uniform with a = sqrt(5) -> U(-1/sqrt(N), 1/sqrt(N)) (bound 0.3536 for N = 8)
    big = ConditionInjector(1, ("lens",), 8, {"a": 4096})
    w = big.projections["lens"]["d4096"].weight.detach()
    assert float(w.abs().max()) <= 1 / math.sqrt(8) and float(w.abs().max()) > 0.99 / math.sqrt(8)
    assert big.condition("lens").shape == (1, 8)


def test_injection_by_hand_shared_per_anchor_and_subset_strengths():
    inj = _injector()
    ids = torch.tensor([4, 0, 0, 2])
    per = torch.tensor([0.0, 0.25, 1.0, 0.5], dtype=torch.float64)
    for strengths in ({"lens": per, "resample": 0.5, "display": 1.0},  # all columns, every kind of strength
                      {"display": 0.3},  # one column, shared strength folded into the projection
                      {"display": 1.0, "lens": per},  # a subset in another order than the modules
                      {"resample": 2.0}):
        ctx = InjectionContext(ids, dict(strengths))
        got = inj.injection(ctx, 4)
        assert torch.allclose(got, _by_hand(inj, ids, strengths, 4), rtol=0, atol=1e-13), strengths
    assert inj.injection(InjectionContext(ids, {}), 4) is None
    assert not bool(per.eq(torch.tensor([0.0, 0.25, 1.0, 0.5], dtype=torch.float64)).logical_not().any())  # not scaled in place
    before = inj.conditions.detach().clone()
    inj.injection(InjectionContext(ids, {"lens": per}), 4)
    assert torch.equal(inj.conditions.detach(), before)


def test_injection_cache_follows_versions_grad_mode_and_width():
    inj = _injector(widths={"t": 4, "u": 6})
    ids = torch.tensor([1, 3])
    ctx = InjectionContext(ids, {"resample": 0.5})
    first = inj.injection(ctx, 4)
    assert inj.injection(ctx, 4) is first  # cached within a context
    assert inj.injection(ctx, 6).shape == (2, 6) and set(ctx.cache) == {(4, True), (6, True)}
    with torch.no_grad():
        assert inj.injection(ctx, 4) is not first and (4, False) in ctx.cache
        inj.conditions[1, 1] += 1.0  # an in-place change (an optimizer step) invalidates the cache
        inj.projections["resample"]["d4"].weight[0, 0] += 1.0
    again = inj.injection(ctx, 4)
    assert again is not first and torch.allclose(again, _by_hand(inj, ids, {"resample": 0.5}, 4), atol=1e-13)


def test_hook_adds_rows_per_anchor_groups_and_checks_row_count():
    inj = _injector()
    fc1 = nn.Linear(2, 4, dtype=torch.float64)
    with pytest.raises(ShapeError, match="target 'u': FC1 width 4 != declared None"):
        inj.attach("u", fc1)  # the name must be declared
    with pytest.raises(ShapeError, match="target 't': FC1 width 5 != declared 4"):
        inj.attach("t", nn.Linear(2, 5))
    inj.attach("t", fc1)
    x = torch.randn(6, 2, dtype=torch.float64)
    ref = fc1(x).detach()
    ids = torch.tensor([2, 0, 3])
    strengths = {"lens": torch.tensor([1.0, 0.5, 0.0], dtype=torch.float64), "display": 0.75}
    ctx = InjectionContext(ids, strengths, rows_per_anchor=2)
    assert ctx.rows == 6 and InjectionContext(ids, {}).rows == 3
    inj.activate(ctx)
    got = fc1(x).detach()
    want = ref + _by_hand(inj, ids, strengths, 4).repeat_interleave(2, dim=0)  # rows 2i, 2i+1 = anchor ids[i]
    assert torch.allclose(got, want, rtol=0, atol=1e-13) and ctx.calls == {"t": 1}
    fc1(x)
    assert ctx.calls == {"t": 2}
    with pytest.raises(ShapeError, match=r"decoder 't' was called with 5 rows \(FC1 output \[5, 4\]\) but the conditioned "
                                         r"block expects 6 rows = 3 anchor ids x 2 rows per anchor"):
        fc1(x[:5])
    with pytest.raises(ShapeError, match=r"called with 4 rows \(FC1 output \[4\]\)"):
        fc1(x[0])  # a 1-d output
    with pytest.raises(LifecycleError, match="nested"):
        inj.activate(InjectionContext(ids, {}))
    inj.deactivate()
    assert torch.equal(fc1(x).detach(), ref) and inj.context is None
    with pytest.raises(InputValueError, match=r"strengths for unknown module\(s\) \['fov'\]; wrapped modules: "
                                              r"\['lens', 'resample', 'display'\]"):
        inj.activate(InjectionContext(ids, {"fov": 1.0, "lens": 1.0}))
    assert inj.context is None
    inj.activate(InjectionContext(ids, {}, rows_per_anchor=2))
    assert torch.equal(fc1(x).detach(), ref)  # no module active: FC1's output as is
    inj.detach()
    assert inj.context is None and not fc1._forward_hooks


# ---------------------------------------------------------------------------------------------- ControlGS


def test_defaults_of_wrap():
    model = ScaffoldStandIn(12, seed=2)
    cgs = ControlGS.wrap(model)
    try:
        assert DEFAULT_MODULES == ("lens", "resample", "display") and DEFAULT_ADAPTER == "default"
        assert cgs.modules == DEFAULT_MODULES and cgs.injector.cond_dim == 8 and cgs.adapters == ("default",)
        assert cgs.active_adapter == "default" and cgs.state_blind is False and cgs.placement == "fit"
        assert cgs.backend.name == "scaffold_gs" and cgs.num_anchors == 12 and cgs.rows_per_anchor == 1
        assert [t.decoder for t in cgs.targets] == ["mlp_opacity", "mlp_cov", "mlp_color"]
        assert all((t.in_features, t.out_features, t.from_torchscript) == (35, 32, False) for t in cgs.targets)
        assert cgs.targets[0].as_header() == {"decoder": "mlp_opacity", "fc1": "mlp_opacity.0", "in_features": 35,
                                              "out_features": 32}
        assert {m: (s.lo, s.hi) for m, s in cgs.schedules.items()} == {"lens": (0.0, math.sqrt(2.0)),
                                                                       "resample": (0.0, 3.0), "display": (0.0, 0.8)}
        assert cgs.skipped == [] and cgs.injector.dtype == torch.float32
        assert cgs.fingerprint == ScaffoldGSBackend().fingerprint(model)
    finally:
        cgs.unwrap()


def test_summary_and_repr_text():
    model = script_decoders(ScaffoldStandIn(12, feat_dim=4, n_offsets=2, seed=2))
    cgs = ControlGS.wrap(model, modules=("resample", "display"), cond_dim=3, targets=["mlp_cov"], state_blind=True)
    # conditions 12 * 2 * 3 = 72; projections 2 modules x [4, 3] = 24
    fp = cgs.fingerprint
    assert cgs.summary() == "\n".join([
        "ControlGS on ScaffoldStandIn via backend 'scaffold_gs'",
        f"  anchors: 12 (1 decoder row(s) per anchor), backbone fingerprint {fp}",
        "  modules: resample, display; N = 3 per module; state-blind (strength 1)",
        "  targets:",
        "    mlp_cov.0: Linear(7 -> 4)  (rebuilt from TorchScript)",
        "  schedules:",
        "    resample: ResampleSchedule(log2(d): 0 -> 0, 3 -> 1)",
        "    display: DisplaySchedule(rho: 0 -> 0, 0.8 -> 1)",
        "  trainable: 96 parameters (conditions 72, projections 24)"])
    assert repr(cgs) == ("ControlGS(backend='scaffold_gs', anchors=12, modules=['resample', 'display'], cond_dim=3, "
                         "targets=['mlp_cov.0'], state_blind=True)")
    cgs.unwrap()
    assert repr(cgs).endswith("state_blind=True, unwrapped)")
    assert cgs.summary().splitlines()[0] == "ControlGS on ScaffoldStandIn via backend 'scaffold_gs' (unwrapped)"
    assert isinstance(model.mlp_cov, torch.jit.ScriptModule)  # the original TorchScript decoder is back


def test_module_and_target_refusals_name_the_argument():
    model = ScaffoldStandIn(10, seed=1)
    cases = [
        (dict(modules=("lens", "display", "lens")), InputValueError, "modules lists ['lens'] more than once"),
        (dict(modules=5), InputValueError, "modules must be a sequence of module names, got 5"),
        (dict(cond_dim=True), InputValueError, "cond_dim must be a positive int, got True"),
        (dict(cond_dim=-2), InputValueError, "cond_dim must be a positive int, got -2"),
        (dict(cond_dim=2.0), InputValueError, "cond_dim must be a positive int, got 2.0"),
        (dict(endpoints={"lens": (0.1, 0.5, 0.9)}), InputValueError, "endpoints['lens'] must be (lo, hi), got (0.1, 0.5, 0.9)"),
        (dict(targets="mlp_cov"), TargetError, "targets must be a non-empty sequence of decoder paths, got 'mlp_cov'"),
        (dict(targets=[]), TargetError, "targets must be a non-empty sequence"),
        (dict(name=""), InputValueError, "an adapter name must be a non-empty str, got ''"),
        (dict(name=3), InputValueError, "an adapter name must be a non-empty str, got 3"),
        (dict(backend=5), NoMatchingBackendError, "backend 5 is not registered"),
    ]
    for kw, error, words in cases:
        with pytest.raises(error) as e:
            ControlGS.wrap(model, **kw)
        assert words in str(e.value), kw
        assert ControlGS.attached(model) is None
    # a header's {"lo", "hi"} mapping is taken as the endpoints, and an explicit name
    cgs = ControlGS.wrap(model, modules=("lens",), endpoints={"lens": {"lo": 0.2, "hi": 0.9, "x": 1}}, name="mine")
    assert (cgs.schedules["lens"].lo, cgs.schedules["lens"].hi) == (0.2, 0.9) and cgs.adapters == ("mine",)
    cgs.unwrap()


class _Picky(ScaffoldGSBackend):
    """Picky test backend: Scaffold layout with settable anchors and rows."""

    name = "picky"

    def __init__(self, rows=1, anchors=None):
        self.rows, self.anchors = rows, anchors

    def rows_per_anchor(self, model):
        return self.rows

    def num_anchors(self, model):
        return super().num_anchors(model) if self.anchors is None else self.anchors


def test_backend_choice_and_backend_counts_are_checked():
    model = ScaffoldStandIn(10, seed=1)
    assert _describe(ScaffoldGSBackend()) == ("scaffold_gs: Scaffold-GS layout: any object with decoder modules "
                                              "``mlp_opacity``, ``mlp_cov``, ``mlp_color`` and anchors ``get_anchor`` "
                                              "or ``_anchor``")
    nodoc = type("NoDoc", (ScaffoldGSBackend,), {"name": "nodoc", "__doc__": None})
    assert _describe(nodoc()) == "nodoc: NoDoc"
    cgs = ControlGS.wrap(model, backend="scaffold_gs")
    assert cgs.backend.name == "scaffold_gs"
    cgs.unwrap()
    with pytest.raises(NoMatchingBackendError, match=r"backend scaffold_gs: Scaffold-GS layout.* does not recognise a "
                                                     r"SimpleNamespace"):
        ControlGS.wrap(types.SimpleNamespace(mlp_cov=nn.Linear(2, 2)), backend="scaffold_gs")
    with pytest.raises(NoMatchingBackendError, match="picky: Picky test backend.* does not recognise a Linear"):
        ControlGS.wrap(nn.Linear(2, 2), backend=_Picky())
    for backend, error, words in [(_Picky(rows=0), TargetError, "picky: rows_per_anchor must be an int >= 1, got 0"),
                                  (_Picky(rows=2.0), TargetError, "rows_per_anchor must be an int >= 1, got 2.0"),
                                  (_Picky(anchors=0), ShapeError, "picky: the model has 0 anchors and positions [10, 3]"),
                                  (_Picky(anchors=9), ShapeError, "the model has 9 anchors and positions [10, 3]")]:
        with pytest.raises(error) as e:
            ControlGS.wrap(model, backend=backend)
        assert words in str(e.value)
        assert ControlGS.attached(model) is None and not model.mlp_cov[0]._forward_hooks
    cgs = ControlGS.wrap(model, backend=_Picky(rows=2))  # an instance is used as given
    assert cgs.backend.name == "picky" and cgs.rows_per_anchor == 2
    cgs.unwrap()


def test_backbone_tensors_are_frozen_and_restored():
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
    with pytest.raises(LifecycleError, match="this ControlGS was unwrapped; wrap the model again"):
        cgs.unwrap()
    for call in (lambda: cgs.strengths(RuntimeState()), lambda: cgs.save("x.safetensors"),
                 lambda: cgs.set_adapter("default"), lambda: cgs.conditioned(RuntimeState()).__enter__()):
        with pytest.raises(LifecycleError):
            call()


@pytest.mark.parametrize("dtype, want", [(torch.float64, torch.float64), (torch.float16, torch.float32)])
def test_injector_dtype_follows_fc1_when_float32_or_float64(dtype, want):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1, dtype=dtype)
    cgs = ControlGS.wrap(model, modules=("display",))
    assert cgs.injector.dtype == want and cgs.strengths(RuntimeState(power_saving=0.4))["display"].dtype == want
    cgs.unwrap()


def test_anchor_ids_forms_and_refusals():
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("display",))
    assert cgs.anchor_ids(None).tolist() == [0, 1, 2, 3, 4, 5]
    for dt in (torch.int64, torch.int32, torch.int16, torch.uint8, torch.int8):
        got = cgs.anchor_ids(torch.tensor([5, 0, 0], dtype=dt))
        assert got.dtype == torch.int64 and got.tolist() == [5, 0, 0]
    assert cgs.anchor_ids(torch.tensor([], dtype=torch.int64)).tolist() == []
    assert cgs.anchor_ids(torch.tensor([0, 1, 0, 0, 1, 1], dtype=torch.bool)).tolist() == [1, 4, 5]
    for bad, error, words in [([1, 2], InputValueError, "anchor_ids must be a LongTensor[R], a BoolTensor[6] or None, got list"),
                              (torch.tensor([[1]]), ShapeError, "anchor_ids must have shape [R], got [1, 1]"),
                              (torch.tensor([-1, 3]), InputValueError, "anchor_ids must lie in [0, 6), got values in [-1, 3]"),
                              (torch.tensor([6]), InputValueError, "anchor_ids must lie in [0, 6), got values in [6, 6]"),
                              (torch.tensor([1.0]), InputValueError, "integer or bool tensor, got torch.float32")]:
        with pytest.raises(error) as e:
            cgs.anchor_ids(bad)
        assert words in str(e.value)
    cgs.unwrap()


def test_strengths_by_hand_state_blind_and_camera_refusal():
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("resample", "display", "lens"))
    state = RuntimeState(downsample=2.0, power_saving=0.2)
    got = cgs.strengths(state, make_camera(), torch.tensor([3, 1]))
    assert list(got) == ["resample", "display", "lens"]
    # log2(2) / 3 and 0.2 / 0.8, one per requested anchor
    assert got["resample"].tolist() == pytest.approx([1 / 3, 1 / 3], abs=1e-7) and got["display"].tolist() == [0.25, 0.25]
    assert got["lens"].shape == (2,)
    # strengths() lists every module, zeros included (a conditioned block leaves shared zeros out)
    got = cgs.strengths(RuntimeState(), make_camera(), torch.tensor([3, 1, 0]))
    assert got["resample"].tolist() == [0.0] * 3 and got["display"].tolist() == [0.0] * 3
    with pytest.raises(InputValueError, match=r"module 'lens' needs each anchor's screen position: pass "
                                              r"camera=Camera\(...\).*got NoneType"):
        cgs.strengths(state)
    with pytest.raises(InputValueError, match="state must be a RuntimeState, got dict"):
        cgs.strengths({"downsample": 2.0}, make_camera())
    cgs.unwrap()
    blind = ControlGS.wrap(model, modules=("resample", "lens"), state_blind=True)
    got = blind.strengths(RuntimeState(), anchor_ids=torch.tensor([0, 5, 2]))  # no camera needed: strength 1
    assert {m: v.tolist() for m, v in got.items()} == {"resample": [1.0] * 3, "lens": [1.0] * 3}
    assert got["lens"].dtype == torch.float32
    blind.unwrap()


def test_gaze_is_placed_on_the_display_like_the_anchors():
    # "fit" placement on a 64 x 48 image: y is scaled by 48 / 64 = 0.75; an anchor at the gaze has eccentricity 0
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("foveation",))
    screen = cam.normalized_screen(model._anchor.detach()[[2]])[0]
    gaze = (float(screen[0]), float(screen[1]))
    lam = cgs.strengths(RuntimeState(gaze=gaze), cam, torch.tensor([2]))["foveation"]
    assert float(lam[0]) < 1e-6
    # gaze at the image centre: eccentricity = |(x, 0.75 y)| / sqrt 2
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    want = math.hypot(gaze[0], 0.75 * gaze[1]) / math.sqrt(2.0)
    assert math.isclose(float(lam[0]), want, rel_tol=1e-5)
    cgs.placement = "stretch"  # stretched: display positions are the screen positions
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    assert math.isclose(float(lam[0]), math.hypot(*gaze) / math.sqrt(2.0), rel_tol=1e-5)
    cgs.unwrap()


def test_conditioned_on_miss_branches_and_zero_row_blocks():
    model = script_decoders(ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1))
    cgs = ControlGS.wrap(model, modules=("display",))
    state = RuntimeState(power_saving=0.4)
    with pytest.warns(RuntimeWarning) as rec:
        with cgs.conditioned(state):
            pass
    msg = str(rec[0].message)
    assert msg.startswith("no wrapped decoder ran inside this conditioned block: the injected first layers "
                          "(mlp_opacity.0, mlp_cov.0, mlp_color.0) of ScaffoldStandIn object at ")
    assert msg.endswith("; the TorchScript decoders ['mlp_opacity', 'mlp_cov', 'mlp_color'] were replaced there by "
                        "eager copies")
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
    with pytest.raises(InputValueError, match="on_miss must be 'warn', 'raise' or 'ignore', got 'loud'"):
        with cgs.conditioned(state, on_miss="loud"):
            pass
    with pytest.raises(InputValueError, match=r"modules \['lens'\] are not wrapped; wrapped modules: \['display'\]"):
        with cgs.conditioned(state, modules=["lens"]):
            pass
    with pytest.raises(InputValueError, match="modules must be a module name or a sequence of them, got"):
        with cgs.conditioned(state, modules=[1]):
            pass
    # a shared strength of zero is left out of the context; a block with modules=() injects nothing
    with cgs.conditioned(RuntimeState(), on_miss="ignore"):
        assert cgs.injector.context.strengths == {}
    with cgs.conditioned(state, modules=(), on_miss="ignore"):
        assert cgs.injector.context.strengths == {}
    with cgs.conditioned(state, modules="display", on_miss="ignore"):
        assert cgs.injector.context.strengths == {"display": 0.5}
    cgs.unwrap()


def test_adapters_are_named_switched_and_refused(tmp_path):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cgs = ControlGS.wrap(model, modules=("display",))
    with torch.no_grad():
        cgs.injector.conditions.fill_(0.5)
    path = cgs.save(tmp_path / "a.safetensors")
    assert cgs.load_adapter(path, "second") == []
    assert cgs.adapters == ("default", "second") and cgs.active_adapter == "default"
    with pytest.raises(InputValueError, match=r"an adapter named 'second' is already loaded; loaded adapters: "
                                              r"\['default', 'second'\]"):
        cgs.load_adapter(path, "second")
    with pytest.raises(InputValueError, match="an adapter name must be a non-empty str"):
        cgs.load_adapter(path, "")
    with pytest.raises(InputValueError, match=r"unknown adapter 'third'; loaded adapters: \['default', 'second'\]"):
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


class _FC1Elsewhere(ScaffoldGSBackend):
    """FC1-elsewhere test backend."""

    name = "fc1_elsewhere"

    def __init__(self, fc1):
        self.fc1 = fc1

    def first_linear_path(self, model, decoder_path):
        return self.fc1.format(decoder_path)


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


def test_torchscript_targets_and_rollback_of_a_failed_hook():
    model = script_decoders(ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1))
    originals = {d: getattr(model, d) for d in ("mlp_opacity", "mlp_cov", "mlp_color")}
    with pytest.raises(TargetError) as e:
        ControlGS.wrap(model, backend=_FC1Elsewhere("mlp_color.0"))
    assert str(e.value) == "fc1_elsewhere: FC1 path 'mlp_color.0' of TorchScript decoder 'mlp_opacity' is not inside it"
    with pytest.raises(TargetError, match="fc1_elsewhere: decoder 'mlp_opacity' has no first layer 'mlp_opacity.7'"):
        ControlGS.wrap(model, backend=_FC1Elsewhere("{}.7"))
    with pytest.raises(TargetError, match=r"fc1_elsewhere: first layer of 'mlp_opacity' must be a Linear, got ReLU"):
        ControlGS.wrap(model, backend=_FC1Elsewhere("{}.1"))
    with pytest.raises(RuntimeError, match="hook failed"):
        ControlGS.wrap(model, backend=_FailingHook())
    # the first decoder had been replaced by its eager copy: put back, nothing attached
    assert all(getattr(model, d) is m for d, m in originals.items())
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model)
    assert ControlGS.attached(model) is cgs and all(t.from_torchscript for t in cgs.targets)
    assert all(isinstance(getattr(model, d), nn.Sequential) for d in originals)
    cgs.unwrap()
    assert all(getattr(model, d) is m for d, m in originals.items())
    assert ControlGS.attached(nn.Linear(2, 2)) is None  # no backend recognises it


def test_load_adapter_mismatches_with_the_live_wrapper(tmp_path):
    from controlgs_adapter.errors import IncompatibleAdapterError

    from _adapter_files import rewrite, trained

    donor = trained(ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1), seed=3)  # all three targets
    path = donor.save(tmp_path / "all.safetensors")
    want = {k: v.clone() for k, v in donor.injector.state_dict().items()}
    donor.unwrap()
    model = ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)  # the same backbone
    cgs = ControlGS.wrap(model, targets=["mlp_cov"])
    with pytest.raises(IncompatibleAdapterError) as e:
        cgs.load_adapter(path, "b")
    assert "target 'mlp_opacity': not wrapped (wrapped: ['mlp_cov'])" in str(e.value)
    assert "target 'mlp_color': not wrapped (wrapped: ['mlp_cov'])" in str(e.value) and cgs.adapters == ("default",)
    with pytest.warns(RuntimeWarning, match="non-strict load skipped"):
        skipped = cgs.load_adapter(path, "b", strict=False)
    assert skipped == ["target 'mlp_opacity': not wrapped (wrapped: ['mlp_cov'])",
                       "target 'mlp_color': not wrapped (wrapped: ['mlp_cov'])"]
    cgs.set_adapter("b")
    assert cgs.skipped == skipped and cgs.injector.widths == {"mlp_cov": 4}
    assert all(torch.equal(v, want[k]) for k, v in cgs.injector.state_dict().items())  # what fits loads exactly
    # another rows-per-anchor is only warned about (loaded anyway, not listed as skipped)
    rewrite(path, {"rows_per_anchor": 2})
    with pytest.raises(IncompatibleAdapterError, match="rows per anchor: the adapter expects 2, the model has 1"):
        ControlGS.load(path, ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1))
    other = ScaffoldStandIn(8, feat_dim=4, n_offsets=2, seed=1)
    with pytest.warns(RuntimeWarning, match=r"rows per anchor: the adapter expects 2, the model has 1 \(loaded anyway\)"):
        loaded = ControlGS.load(path, other, strict=False, name="mine")
    assert loaded.adapters == ("mine",) and loaded.active_adapter == "mine" and loaded.skipped == [] and torch.equal(loaded.injector.conditions.detach(), want["conditions"])
    loaded.unwrap()
    # an adapter of another registered backend never loads onto this wrapper, not even non-strict
    rewrite(path, {"backend": "octree_gs", "rows_per_anchor": 1})
    with pytest.raises(IncompatibleAdapterError, match="backend: the adapter was made for 'octree_gs'; this model is "
                                                       "wrapped with scaffold_gs"):
        cgs.load_adapter(path, "c", strict=False)
    assert cgs.adapters == ("default", "b")
    cgs.unwrap()


class _BadHookable(ScaffoldGSBackend):
    """Bad-hookable test backend: make_hookable installs another first layer."""

    name = "bad_hookable"

    def __init__(self, layer):
        self.layer = layer

    def make_hookable(self, model, decoder_path):
        from controlgs_adapter.backend import get_attr_path, set_attr_path

        original = get_attr_path(model, decoder_path)
        set_attr_path(model, decoder_path, nn.Sequential(self.layer))
        return original


@pytest.mark.parametrize("layer, shown", [(nn.Linear(7, 5), "Linear(in_features=7, out_features=5, bias=True)"),
                                          (nn.ReLU(), "ReLU()")])
def test_a_backend_whose_make_hookable_breaks_fc1_is_refused_and_rolled_back(layer, shown):
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    originals = {d: getattr(model, d) for d in ("mlp_opacity", "mlp_cov", "mlp_color")}
    with pytest.raises(TargetError) as e:
        ControlGS.wrap(model, backend=_BadHookable(layer))
    assert str(e.value) == f"bad_hookable: make_hookable left 'mlp_opacity.0' as {shown}"
    assert all(getattr(model, d) is m for d, m in originals.items()) and ControlGS.attached(model) is None
    assert model._anchor.requires_grad  # the backbone was not frozen either
