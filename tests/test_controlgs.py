"""ControlGS.wrap / conditioned / unwrap on a Scaffold-structured stand-in (eager and TorchScript decoders)."""

from __future__ import annotations

import math
import warnings

import pytest
import torch
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.errors import (InputValueError, LifecycleError, NoMatchingBackendError, ShapeError, StateError,
                                      StateRangeError, TargetError)

from scaffold_standin import ScaffoldStandIn, script_decoders, make_camera

DECODERS = ("mlp_opacity", "mlp_cov", "mlp_color")
FULL = RuntimeState(downsample=8.0, power_saving=0.8 - 1e-9)


def make_model(kind: str, **kw) -> ScaffoldStandIn:
    model = ScaffoldStandIn(**kw)
    return script_decoders(model) if kind == "script" else model


def randomise(cgs: ControlGS, seed: int = 1) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in cgs.trainable_parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype))


def outputs(model, x):
    with torch.no_grad():
        return model.decode(x)


def assert_equal_outputs(a, b):
    for k in a:
        assert torch.equal(a[k], b[k]), k


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bit_identical_at_init_inside_and_outside_the_block(kind):
    model, cam = make_model(kind), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs(model, x)
    cgs = ControlGS.wrap(model)
    assert_equal_outputs(ref, outputs(model, x))
    with cgs.conditioned(FULL, camera=cam):
        assert_equal_outputs(ref, outputs(model, x))


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_bit_identical_when_every_strength_is_zero(kind):
    model, cam = make_model(kind), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs(model, x)
    # lens endpoints beyond every anchor's radius: lambda_lens = 0; d = 1, rho = 0: the others are 0
    cgs = ControlGS.wrap(model, endpoints={"lens": (5.0, 6.0)})
    randomise(cgs)
    with cgs.conditioned(RuntimeState(downsample=1.0, power_saving=0.0), camera=cam):
        # shared strengths of zero are not computed; a per-anchor one stays (testing it would sync the device)
        assert list(cgs.injector.context.strengths) == ["lens"]
        assert not bool(cgs.injector.context.strengths["lens"].any())
        assert_equal_outputs(ref, outputs(model, x))
    assert_equal_outputs(ref, outputs(model, x))  # outside the block after a randomised adapter


def test_only_rows_with_positive_strength_change():
    model, cam = make_model("eager", num_anchors=60), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs(model, x)
    cgs = ControlGS.wrap(model, modules=("lens",), endpoints={"lens": (0.3, 1.0)})
    randomise(cgs)
    lam = cgs.strengths(FULL, cam)["lens"]
    on = lam > 0
    assert 0 < int(on.sum()) < on.numel()
    with cgs.conditioned(FULL, camera=cam):
        out = outputs(model, x)
    for k in out:
        assert torch.equal(out[k][~on], ref[k][~on]), k
        # every changed row differs somewhere (tanh/sigmoid outputs are not saturated here)
        assert bool((out[k][on] != ref[k][on]).any(dim=1).all()), k


def _pinhole_screen(points: torch.Tensor, cam) -> torch.Tensor:
    """Independent float64 projection to normalised screen coordinates."""
    p = points.double() @ cam.world_to_camera[:3, :3].double().T + cam.world_to_camera[:3, 3].double()
    k = cam.intrinsics.double()
    u = k[0, 0] * p[:, 0] / p[:, 2] + k[0, 2]
    v = k[1, 1] * p[:, 1] / p[:, 2] + k[1, 2]
    return torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], dim=1)


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_injection_matches_eq9_in_float64(kind):
    """FC1 output + sum_m lambda_m * A_m(C_m) through the rest of the decoder, computed by hand."""
    model, cam = make_model(kind, num_anchors=30, dtype=torch.float64), make_camera(dtype=torch.float64)
    eager = {d: (getattr(model, d) if kind == "eager" else None) for d in DECODERS}
    visible = torch.arange(30) % 3 != 1
    x = model.decoder_input(cam.center, visible)
    state = RuntimeState(downsample=2.5, power_saving=0.3)
    cgs = ControlGS.wrap(model, endpoints={"lens": (0.1, 1.2)})
    randomise(cgs)
    eager = {d: getattr(model, d) for d in DECODERS}  # rebuilt eager decoders for the script variant
    ids = visible.nonzero().squeeze(1)
    on_display = torch.tensor([1.0, cam.height / cam.width], dtype=torch.float64)  # "fit" placement, landscape
    r = torch.linalg.vector_norm(_pinhole_screen(model._anchor.detach()[ids], cam) * on_display, dim=1)
    lam = {"lens": ((r - 0.1) / 1.1).clamp(0, 1), "resample": torch.full_like(r, math.log2(2.5) / 3),
           "display": torch.full_like(r, 0.3 / 0.8)}
    with cgs.conditioned(state, camera=cam, anchor_ids=visible):
        got = outputs(model, x)
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

    model, cam = make_model("eager", num_anchors=12), make_camera()
    ids = torch.tensor([7, 2, 9, 0])
    x = model.decoder_input(cam.center)[ids].repeat_interleave(3, dim=0)  # [12, 35]
    x = x + 0.01 * torch.randn_like(x)
    cgs = ControlGS.wrap(model, backend=KRows(), modules=("resample", "lens"))
    randomise(cgs)
    with cgs.conditioned(FULL, camera=cam, anchor_ids=ids):
        got = model.mlp_cov[0](x)
        with pytest.raises(ShapeError, match="4 anchor ids x 3 rows"):
            model.mlp_cov[0](x[:4])
    lam = cgs.strengths(FULL, cam, ids)
    inj = sum(lam[m][:, None] * (cgs.injector.condition(m)[ids] @ cgs.injector.projections[m]["d32"].weight.T)
              for m in ("resample", "lens"))
    want = nn.functional.linear(x, model.mlp_cov[0].weight, model.mlp_cov[0].bias) + inj.repeat_interleave(3, dim=0)
    assert torch.allclose(got, want.detach(), atol=1e-6)


def test_state_blind_injects_fully_at_the_neutral_state():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs(model, x)
    cgs = ControlGS.wrap(model, state_blind=True)
    randomise(cgs)
    neutral = RuntimeState(downsample=1.0, power_saving=0.0)
    assert all(torch.equal(v, torch.ones_like(v)) for v in cgs.strengths(neutral, cam).values())
    with cgs.conditioned(neutral):  # no camera needed: the strength does not depend on the state
        blind = outputs(model, x)
    assert not torch.equal(blind["color"], ref["color"])


def test_modules_switched_off_in_a_block_are_not_injected():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center)
    full = ControlGS.wrap(model)
    randomise(full)
    with full.conditioned(FULL, camera=cam, modules=("display",)):
        assert list(full.injector.context.strengths) == ["display"]
        only_display = outputs(model, x)
    state = {k: v.detach().clone() for k, v in full.injector.state_dict().items()}
    full.unwrap()
    single = ControlGS.wrap(model, modules=("display",))
    single.injector.load_state_dict({"conditions": state["conditions"][:, 2:3],
                                     "projections.display.d32.weight": state["projections.display.d32.weight"]})
    with single.conditioned(FULL, camera=cam):
        assert_equal_outputs(only_display, outputs(model, x))
    with pytest.raises(InputValueError, match="not wrapped"):
        with single.conditioned(FULL, camera=cam, modules=("lens",)):
            pass


def test_gradients_reach_only_the_adapter_and_the_backbone_does_not_move():
    model, cam = make_model("eager"), make_camera()
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
    model, cam = make_model("eager", num_anchors=6, feat_dim=4, dtype=torch.float64), make_camera(dtype=torch.float64)
    x = model.decoder_input(cam.center).detach()
    cgs = ControlGS.wrap(model, cond_dim=2, endpoints={"lens": (0.0, 1.0)})
    randomise(cgs)
    state = RuntimeState(downsample=3.0, power_saving=0.5)
    w = torch.randn(6, 30, dtype=torch.float64)

    def loss():
        with cgs.conditioned(state, camera=cam):
            return (model.mlp_color(x) * w).sum()

    loss().backward()
    checked = 0
    for p in cgs.trainable_parameters():
        for i in torch.randperm(p.numel())[:4].tolist():
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


def test_an_optimizer_step_inside_one_block_is_seen_by_the_next_decode():
    model, cam = make_model("eager"), make_camera()
    x = model.decoder_input(cam.center).detach()
    cgs = ControlGS.wrap(model)
    randomise(cgs)
    opt = torch.optim.SGD(cgs.trainable_parameters(), lr=0.5)
    with cgs.conditioned(FULL, camera=cam):
        model.mlp_color(x).sum().backward()
        opt.step()
        after = model.mlp_color(x).detach()
    with cgs.conditioned(FULL, camera=cam):
        fresh = model.mlp_color(x).detach()
    assert torch.equal(after, fresh)


@pytest.mark.parametrize("kind", ["eager", "script"])
def test_unwrap_restores_objects_flags_and_outputs(kind):
    model, cam = make_model(kind, use_feat_bank=True), make_camera()
    x = model.decoder_input(cam.center)
    ref = outputs(model, x)
    objects = {d: getattr(model, d) for d in (*DECODERS, "mlp_feature_bank")}
    model._anchor_feat.requires_grad_(False)  # a mix of flags, restored as they were
    flags = {id(t): t.requires_grad for t in (model._anchor, model._anchor_feat, model._offset)}
    cgs = ControlGS.wrap(model)
    if kind == "script":
        assert all(getattr(model, d) is not objects[d] for d in DECODERS)
    assert getattr(model, "mlp_feature_bank") is objects["mlp_feature_bank"]  # not a default target
    randomise(cgs)
    fc1s = [getattr(model, d)[0] for d in DECODERS]
    assert cgs.unwrap() is model
    assert all(getattr(model, d) is objects[d] for d in objects)
    assert all(not f._forward_hooks for f in fc1s)
    assert {id(t): t.requires_grad for t in (model._anchor, model._anchor_feat, model._offset)} == flags
    assert_equal_outputs(ref, outputs(model, x))
    with pytest.raises(LifecycleError, match="unwrapped"):
        with cgs.conditioned(FULL, camera=cam):
            pass
    ControlGS.wrap(model).unwrap()  # can be wrapped again


def test_wrong_rows_ids_and_masks_raise():
    model, cam = make_model("eager", num_anchors=20), make_camera()
    x = model.decoder_input(cam.center)
    cgs = ControlGS.wrap(model)
    mask = torch.zeros(20, dtype=torch.bool)
    mask[:5] = True
    assert cgs.anchor_ids(torch.arange(20) % 3 == 1).tolist() == list(range(1, 20, 3))  # a mask's anchors, ascending
    with cgs.conditioned(FULL, camera=cam, anchor_ids=mask):
        model.decode(x[:5])
        with pytest.raises(ShapeError, match="called with 20 rows .* expects 5 rows"):
            model.decode(x)
        with pytest.raises(LifecycleError, match="nested"):
            with cgs.conditioned(FULL, camera=cam):
                pass
    with pytest.raises(ShapeError, match=r"anchor_ids mask must have size 20 .*got \[19\]"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.ones(19, dtype=torch.bool)):
            pass
    with pytest.raises(InputValueError, match=r"\[0, 20\)"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.tensor([3, 20])):
            pass
    with pytest.raises(InputValueError, match="integer or bool"):
        with cgs.conditioned(FULL, camera=cam, anchor_ids=torch.tensor([1.0])):
            pass
    with pytest.raises(InputValueError, match="camera"):
        with cgs.conditioned(FULL, anchor_ids=mask):  # lens needs the camera
            pass
    with pytest.raises(InputValueError, match="RuntimeState"):
        with cgs.conditioned({"downsample": 2}, camera=cam):
            pass
    assert cgs.injector.context is None  # failed entries leave nothing active
    model.decode(x)  # and outside a block any row count is fine


def _snapshot(model):
    return {d: (getattr(model, d), [p.requires_grad for p in getattr(model, d).parameters()]) for d in DECODERS}


@pytest.mark.parametrize("kwargs, error, words", [
    (dict(targets=["mlp_opacity", "mlp_nope"]), TargetError, ["mlp_nope", "mlp_color"]),
    (dict(targets=["mlp_opacity", "mlp_opacity"]), TargetError, ["more than once"]),
    (dict(modules=("lens", "vignetting")), InputValueError, ["vignetting", "resample"]),
    (dict(modules=()), InputValueError, ["at least one"]),
    (dict(cond_dim=0), InputValueError, ["cond_dim"]),
    (dict(endpoints={"lens": (1.0, 1.0)}), InputValueError, ["lens", "differ"]),
    (dict(endpoints={"display": (0, 1)}, modules=("lens",)), InputValueError, ["display"]),
    (dict(backend="octree_family_that_is_not_there"), NoMatchingBackendError, ["scaffold_gs", "not registered"]),
])
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_wrap_validates_everything_before_changing_the_model(kind, kwargs, error, words):
    model = make_model(kind)
    before = _snapshot(model)
    with pytest.raises(error) as e:
        ControlGS.wrap(model, **kwargs)
    for w in words:
        assert w in str(e.value)
    after = _snapshot(model)
    assert all(after[d][0] is before[d][0] and after[d][1] == before[d][1] for d in DECODERS)
    if kind == "eager":
        assert not any(getattr(model, d)[0]._forward_hooks for d in DECODERS)


def test_unsupported_torchscript_layer_in_the_last_target_leaves_the_others_untouched():
    model = make_model("script")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        model.mlp_color = torch.jit.trace(nn.Sequential(nn.Linear(35, 32), nn.GELU(), nn.Linear(32, 30)), torch.randn(2, 35))
    before = _snapshot(model)
    with pytest.raises(TargetError) as e:
        ControlGS.wrap(model)
    assert "mlp_color" in str(e.value) and "GELU" in str(e.value)
    after = _snapshot(model)
    assert all(after[d][0] is before[d][0] for d in DECODERS)


def test_no_matching_backend_lists_what_each_backend_looks_for():
    class NotAModel:
        mlp_opacity = nn.Linear(3, 3)

    with pytest.raises(NoMatchingBackendError) as e:
        ControlGS.wrap(NotAModel())
    msg = str(e.value)
    assert "NotAModel" in msg and "scaffold_gs" in msg and "mlp_color" in msg


def test_wrapping_twice_is_refused_and_feature_bank_is_targetable():
    model = make_model("eager", use_feat_bank=True)
    cgs = ControlGS.wrap(model)
    with pytest.raises(LifecycleError, match=r"already carries an injector \(ControlGS\(backend='scaffold_gs'"):
        ControlGS.wrap(model)
    assert ControlGS.attached(model) is cgs
    ControlGS.attached(model).unwrap()
    assert ControlGS.attached(model) is None
    cgs = ControlGS.wrap(model, targets=["mlp_feature_bank", "mlp_color"])
    assert [(t.decoder, t.in_features, t.out_features) for t in cgs.targets] == [("mlp_feature_bank", 4, 32),
                                                                                ("mlp_color", 35, 32)]
    assert "mlp_feature_bank.0: Linear(4 -> 32)" in cgs.summary()
    cgs.unwrap()


def test_backend_positions_and_visible_rows():
    model = make_model("eager", num_anchors=8)
    backend = ScaffoldGSBackend()
    assert backend.matches(model) and backend.anchor_positions(model) is model._anchor
    mask = torch.tensor([0, 1, 1, 0, 0, 1, 0, 1], dtype=torch.bool)
    assert backend.visible_rows_to_anchor_ids(mask).tolist() == [1, 2, 5, 7]
    with pytest.raises(InputValueError, match="bool"):
        backend.visible_rows_to_anchor_ids(mask.long())


def test_lifecycle_and_state_range_errors_are_distinct():
    from controlgs_adapter import RuntimeState

    with pytest.raises(StateRangeError) as e:
        RuntimeState(downsample=0.5)
    assert isinstance(e.value, StateError) and isinstance(e.value, ValueError)
    assert not issubclass(LifecycleError, StateError) and issubclass(LifecycleError, RuntimeError)
