"""The condition injector (Eq. 9): its parameter layout and initialisation, the injected sum
against a float64 computation module by module, the cache of one conditioned block, and the FC1
hooks (rows per anchor, row-count and lifecycle refusals)."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.scaffold_standin import ScaffoldStandIn, make_camera
from helpers.wrapping import FULL
from torch import nn

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.errors import InputValueError, LifecycleError, ShapeError
from controlgs_adapter.injector import ConditionInjector, InjectionContext


def _injector(widths=None, modules=("lens", "resample", "display"), n=3, a=5, seed=0):
    inj = ConditionInjector(a, modules, n, widths or {"t": 4}, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in inj.parameters():
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype))
    return inj


def _float64_injection(inj, ids, strengths, width):
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
    assert repr(inj).splitlines()[1].strip() == "anchors=6, modules=['lens', 'display'], cond_dim=8, widths=[32, 64]"
    assert inj.dtype == torch.float32
    # nn.Linear's own init: Kaiming uniform with a = sqrt(5) -> U(-1/sqrt(N), 1/sqrt(N)) (bound 0.3536 for N = 8)
    big = ConditionInjector(1, ("lens",), 8, {"a": 4096})
    w = big.projections["lens"]["d4096"].weight.detach()
    assert float(w.abs().max()) <= 1 / math.sqrt(8) and float(w.abs().max()) > 0.99 / math.sqrt(8)
    assert big.condition("lens").shape == (1, 8)


def test_injection_in_float64_with_shared_per_anchor_and_subset_strengths():
    inj = _injector()
    ids = torch.tensor([4, 0, 0, 2])
    per = torch.tensor([0.0, 0.25, 1.0, 0.5], dtype=torch.float64)
    for strengths in ({"lens": per, "resample": 0.5, "display": 1.0},  # all columns, every kind of strength
                      {"display": 0.3},  # one column, shared strength folded into the projection
                      {"display": 1.0, "lens": per},  # a subset in another order than the modules
                      {"resample": 2.0}):
        ctx = InjectionContext(ids, dict(strengths))
        got = inj.injection(ctx, 4)
        assert torch.allclose(got, _float64_injection(inj, ids, strengths, 4), rtol=0, atol=1e-13), strengths
    assert inj.injection(InjectionContext(ids, {}), 4) is None
    assert torch.equal(per, torch.tensor([0.0, 0.25, 1.0, 0.5], dtype=torch.float64))  # not scaled in place
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
    assert again is not first and torch.allclose(again, _float64_injection(inj, ids, {"resample": 0.5}, 4), atol=1e-13)


def test_wrapped_decoders_see_a_fresh_injection_after_no_grad_and_after_an_optimizer_step():
    """Within one conditioned block, a decode with grad enabled after one under ``no_grad`` gets a graph
    (the cached no-grad injection is not reused), and an optimizer step taken inside the block is seen
    by the next decode exactly as by a fresh block."""
    torch.manual_seed(0)
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model, modules=("resample",), cond_dim=4)
    with torch.no_grad():
        cgs.injector.conditions.normal_()
    x = model.decoder_input(cam.center)
    with cgs.conditioned(RuntimeState(downsample=4.0), camera=cam):
        with torch.no_grad():
            model.decode(x)
        loss = sum(y.sum() for y in model.decode(x).values())
    assert loss.requires_grad
    loss.backward()
    assert cgs.injector.conditions.grad is not None and cgs.injector.conditions.grad.abs().sum() > 0
    cgs.unwrap()

    cgs = ControlGS.wrap(model)
    with torch.no_grad():
        for p in cgs.trainable_parameters():
            p.normal_()
    opt = torch.optim.SGD(cgs.trainable_parameters(), lr=0.5)
    x = x.detach()
    with cgs.conditioned(FULL, camera=cam):
        before = model.mlp_color(x)
        before.sum().backward()
        opt.step()
        after = model.mlp_color(x).detach()
    with cgs.conditioned(FULL, camera=cam):
        fresh = model.mlp_color(x).detach()
    assert torch.equal(after, fresh) and not torch.equal(after, before.detach())
    cgs.unwrap()


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
    want = ref + _float64_injection(inj, ids, strengths, 4).repeat_interleave(2, dim=0)  # rows 2i, 2i+1 = anchor ids[i]
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


def test_xy_strength_pairs_scale_the_two_halves_of_the_condition():
    """A ``[R, 2]`` strength (the lens in its xy frame): lambda_x A(C_first) + lambda_y A(C_second), C_first and
    C_second the first and second halves of the N condition columns, in float64 by hand; with the
    other modules' strengths added as usual; through the hook as well."""
    inj = _injector(n=4, widths={"t": 5})
    ids = torch.tensor([3, 0, 3, 1])
    pair = torch.tensor([[0.5, -1.0], [0.0, 0.25], [-0.75, 1.0], [1.0, 0.0]], dtype=torch.float64)
    got = inj.injection(InjectionContext(ids, {"lens": pair, "display": 0.5}), 5)
    c = inj.conditions.detach()[ids, 0]  # [R, 4]
    a = inj.projections["lens"]["d5"].weight.detach()  # [5, 4]
    want = pair[:, :1] * (c[:, :2] @ a[:, :2].T) + pair[:, 1:] * (c[:, 2:] @ a[:, 2:].T)
    want += _float64_injection(inj, ids, {"display": 0.5}, 5)
    assert torch.allclose(got, want, rtol=0, atol=1e-13)
    same = pair.new_tensor([0.3, 0.3, 0.3, 0.3])  # equal halves: the scalar strength
    assert torch.allclose(inj.injection(InjectionContext(ids, {"lens": same[:, None].expand(4, 2)}), 5),
                          inj.injection(InjectionContext(ids, {"lens": same}), 5), rtol=0, atol=1e-14)
    fc1 = nn.Linear(3, 5, dtype=torch.float64)
    inj.attach("t", fc1)
    x = torch.randn(4, 3, dtype=torch.float64)
    ref = fc1(x).detach()
    inj.activate(InjectionContext(ids, {"lens": pair}))
    hooked = fc1(x).detach()
    inj.deactivate()
    lens_only = pair[:, :1] * (c[:, :2] @ a[:, :2].T) + pair[:, 1:] * (c[:, 2:] @ a[:, 2:].T)
    assert torch.allclose(hooked, ref + lens_only, rtol=0, atol=1e-13)
    with pytest.raises(ShapeError, match=r"strengths\['lens'\]: 3 strengths per anchor do not split the 4 condition columns"):
        inj.activate(InjectionContext(ids, {"lens": torch.zeros(4, 3, dtype=torch.float64)}))
    assert inj.context is None


def test_xy_injection_gradcheck():
    """Gradients of the xy injection w.r.t. the conditions, the projection and the strength pair."""
    inj = _injector(n=4, modules=("lens", "display"), a=3)
    ids = torch.tensor([2, 0, 2])
    pair = torch.tensor([[0.5, -0.25], [1.0, 0.75], [-0.5, 0.0]], dtype=torch.float64, requires_grad=True)
    weight = inj.projections["lens"]["d4"].weight

    def f(conditions, w, lam):
        with torch.no_grad():
            inj.conditions.copy_(conditions)
            weight.copy_(w)
        z = conditions.index_select(0, ids)[:, 0]  # the injector's own path, with the inputs as leaves
        scaled = z * lam.repeat_interleave(2, dim=1)
        return scaled @ w.T

    c = inj.conditions.detach().clone().requires_grad_(True)
    w = weight.detach().clone().requires_grad_(True)
    assert torch.allclose(f(c, w, pair), inj.injection(InjectionContext(ids, {"lens": pair.detach()}), 4), atol=1e-13)
    assert torch.autograd.gradcheck(f, (c, w, pair))

    def through_injector(lam):
        return inj.injection(InjectionContext(ids, {"lens": lam}), 4)

    assert torch.autograd.gradcheck(through_injector, (pair,))
    out = through_injector(pair.detach())
    out.sum().backward()
    g = inj.conditions.grad[:, 0]
    want = torch.zeros(3, 4, dtype=torch.float64)  # d/dC of sum(lam * C @ A^T): lam-scaled column sums of A
    for r, i in enumerate(ids.tolist()):
        want[i] += pair.detach()[r].repeat_interleave(2) * weight.detach().sum(0)
    assert torch.allclose(g, want, atol=1e-13) and not bool(inj.conditions.grad[:, 1].any())
