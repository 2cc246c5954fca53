"""The contract of a downstream stage, as one reusable check: :func:`check_stage`.

A stage (:class:`controlgs_adapter.downstream.Stage`) is a differentiable module with a functional
twin; the pipeline calls it on ``[..., 3, H, W]`` float32/float64 images and skips it where it is the
identity. :func:`check_stage` checks one configured stage against that contract; the built-in stages
and colour conversions pass it in ``tests/downstream/test_stage_contract.py``, and a plug-in author
reuses it for a stage of their own (copy this file into the plug-in's tests, or put the library's
``tests/`` on ``sys.path``)::

    from helpers.stage_contract import check_stage

    def test_vignette_keeps_the_stage_contract():
        stage = Vignette(strength=0.3)
        check_stage(stage, lambda image, state, ctx: vignette(image, 0.3, state.power_saving),
                    state=RuntimeState(power_saving=0.5),    # a state where the stage works
                    off_state=RuntimeState())                # a state where it is the identity

``functional`` is the twin called as ``functional(image, state, ctx)`` (bind the stage's own settings
in a lambda, as above). What is checked, each failure naming the check:

- ``interface``: a non-empty ``name``, ``domain`` ``"srgb"`` or ``"linear"``, a numeric ``order``,
  ``is_identity`` answers a bool with and without a context, and ``stage(image)`` runs with the
  defaults (default state, the image's size as the native size);
- ``twin``: the module's output equals the functional twin's, and so do their gradients;
- ``shapes``: ``[3, H, W]`` -> ``[3, H', W']`` (``out_size`` if given) and batched ``[*batch, 3, H, W]``
  -> ``[*batch, 3, H', W']``, every item equal to the stage applied to it alone;
- ``dtypes``: float32 and float64 are kept, and the float32 result is the float64 one to ``float32_atol``;
- ``devices``: the output is on the input's device: CPU; ``meta`` (shapes only) unless ``meta=False``;
  CUDA when available, equal to the CPU result;
- ``gradcheck``: ``torch.autograd.gradcheck`` of the stage on a float64 input of ``size``;
- ``off`` (with ``off_state``): ``is_identity`` holds there, a pipeline skips the stage without calling
  it and hands back its input object, and the stage and its twin return their input (the object or
  equal values) for an image at its native size;
- ``pipeline``: ``Pipeline([stage])`` on an sRGB image (with the context's reference) equals the stage between the domain conversions
  it asks for (its input object where the stage is the identity at ``state``).

A plain ``nn.Module`` (e.g. a colour conversion, called as ``module(image)``) gets the checks that make
sense without a state: twin, shapes, dtypes, devices and gradcheck.
"""

from __future__ import annotations

import copy
from collections import Counter
from typing import Callable

import torch
from torch import nn

from controlgs_adapter.downstream.color import convert_domain
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.state import RuntimeState

__all__ = ["check_stage", "StageCalls", "contract_image"]

Functional = Callable[[torch.Tensor, RuntimeState, StageContext], torch.Tensor]


class StageCalls:
    """Counts the calls of each stage of ``pipeline`` by name (forward pre-hooks: the real stages run)."""

    def __init__(self, pipeline: Pipeline) -> None:
        self.calls: Counter[str] = Counter()
        for s in pipeline.stages:
            s.register_forward_pre_hook(lambda mod, args: self.calls.update([mod.name]))


def contract_image(shape: tuple[int, ...], dtype: torch.dtype = torch.float64, device: str | torch.device = "cpu",
                   seed: int = 0) -> torch.Tensor:
    """A reproducible image with values in [0.2, 0.8] (away from the sRGB threshold, clipping and 0)."""
    g = torch.Generator().manual_seed(seed)
    return (0.2 + 0.6 * torch.rand(shape, generator=g, dtype=torch.float64)).to(dtype=dtype, device=device)


def _run(stage: nn.Module, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
    return stage(image, state, ctx) if isinstance(stage, Stage) else stage(image)


def _on(ctx: StageContext, device: str) -> StageContext:
    """``ctx`` with its reference on ``device``."""
    reference = None if ctx.reference is None else ctx.reference.to(device)
    return StageContext(native_size=ctx.native_size, reference=reference)


def _same_or_equal(what: str, out: torch.Tensor, image: torch.Tensor) -> None:
    if out is not image:
        torch.testing.assert_close(out, image, msg=lambda m: f"off: {what} changes its input: {m}")


def check_stage(
    stage: nn.Module,
    functional: Functional,
    *,
    state: RuntimeState | None = None,
    off_state: RuntimeState | None = None,
    size: tuple[int, int] = (4, 6),
    native_size: tuple[int, int] | None = None,
    out_size: tuple[int, int] | None = None,
    reference: bool = False,
    batch: tuple[int, ...] = (2,),
    meta: bool = True,
    float32_atol: float = 1e-5,
) -> None:
    """Check ``stage`` and its twin ``functional`` against the stage contract (module docstring).

    Args:
        stage: the configured stage (a :class:`Stage`, or a plain module called as ``module(image)``).
        functional: its functional twin, ``functional(image, state, ctx) -> image``.
        state: the run-time state the stage works at (default: the default state).
        off_state: a state where the stage is the identity (a stage that is never off: None).
        size: ``(H, W)`` of the input images (small: gradcheck runs on it).
        native_size: the context's native size (default ``size``), e.g. larger for the display emission.
        out_size: the expected output ``(H', W')``, if known.
        reference: whether the context carries a ground truth (sRGB, at the native size), as in training.
        batch: the leading dims of the batched check.
        meta: whether the stage runs on the ``meta`` device (shape propagation without data).
        float32_atol: how close the float32 result must be to the float64 one.
    """
    state = RuntimeState() if state is None else state
    native = native_size or size
    ctx = StageContext(native_size=native, reference=contract_image((3, *native), seed=3) if reference else None)
    is_stage = isinstance(stage, Stage)
    x = contract_image((3, *size))

    # interface
    if is_stage:
        assert isinstance(stage.name, str) and stage.name, "interface: a stage needs a non-empty name"
        assert stage.domain in ("srgb", "linear"), f"interface: domain {stage.domain!r}"
        float(stage.order)
        assert isinstance(stage.is_identity(state), bool) and isinstance(stage.is_identity(state, ctx), bool), \
            "interface: is_identity must answer a bool"
        plain = stage(x)
        assert isinstance(plain, torch.Tensor) and plain.shape[-3] == 3, "interface: stage(image) with the defaults"

    # twin: values and gradients
    out = _run(stage, x, state, ctx)
    torch.testing.assert_close(out, functional(x, state, ctx), msg=lambda m: f"twin: module != functional: {m}")
    w = contract_image(tuple(out.shape), seed=1)
    grads = []
    for f in (lambda t: _run(stage, t, state, ctx), lambda t: functional(t, state, ctx)):
        xr = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad((f(xr) * w).sum(), xr)
        grads.append(g)
    torch.testing.assert_close(grads[0], grads[1], msg=lambda m: f"twin: gradients differ: {m}")

    # shapes
    assert out.shape[:-2] == (3,), f"shapes: [3, H, W] gave {list(out.shape)}"
    if out_size is not None:
        assert tuple(out.shape[-2:]) == tuple(out_size), f"shapes: output {list(out.shape)}, expected size {out_size}"
    for lead in (batch, (*batch, 1)):
        xb = contract_image((*lead, 3, *size), seed=2)
        ob = _run(stage, xb, state, ctx)
        assert ob.shape == (*lead, *out.shape), f"shapes: {list(xb.shape)} gave {list(ob.shape)}"
        flat_in, flat_out = xb.reshape(-1, 3, *size), ob.reshape(-1, *out.shape)
        for i in range(flat_in.shape[0]):
            torch.testing.assert_close(flat_out[i], _run(stage, flat_in[i], state, ctx),
                                       msg=lambda m: f"shapes: a batch item differs from the item alone: {m}")

    # dtypes
    out32 = _run(stage, x.float(), state, ctx)
    assert out.dtype == torch.float64 and out32.dtype == torch.float32, f"dtypes: {out.dtype}, {out32.dtype}"
    torch.testing.assert_close(out32.double(), out, rtol=0, atol=float32_atol,
                               msg=lambda m: f"dtypes: float32 result far from float64: {m}")

    # devices
    assert out.device == x.device, f"devices: {x.device} in, {out.device} out"
    if meta:
        om = _run(copy.deepcopy(stage).to("meta"), x.to("meta"), state, _on(ctx, "meta"))
        assert om.device.type == "meta" and om.shape == out.shape and om.dtype == out.dtype, \
            f"devices: on meta {om.device} {list(om.shape)} {om.dtype}"
    if torch.cuda.is_available():
        oc = _run(copy.deepcopy(stage).to("cuda"), x.cuda(), state, _on(ctx, "cuda"))
        assert oc.device.type == "cuda", f"devices: cuda in, {oc.device} out"
        torch.testing.assert_close(oc.cpu(), out, msg=lambda m: f"devices: CUDA differs from CPU: {m}")

    # gradcheck
    xg = x.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: _run(stage, t, state, ctx), (xg,)), "gradcheck"

    if not is_stage:
        return

    # off: skipped at no cost, the identity
    if off_state is not None:
        at_native = StageContext(native_size=size)
        assert stage.is_identity(off_state) and stage.is_identity(off_state, at_native), "off: is_identity is False"
        pipe = Pipeline([stage])
        counter = StageCalls(pipe)
        assert pipe(x, off_state) is x, "off: the pipeline does not hand back its input"
        assert counter.calls[stage.name] == 0, "off: the pipeline called the stage"
        _same_or_equal("the stage", _run(stage, x, off_state, at_native), x)
        _same_or_equal("the functional twin", functional(x, off_state, at_native), x)

    # pipeline: the stage between the domain conversions it asks for
    pipe = Pipeline([stage])
    eye, rec = pipe.run_recorded(x, state, reference=ctx.reference, native_size=native)
    if stage.is_identity(state, ctx):
        assert eye is x and rec["stages_run"] == [], "pipeline: an identity stage was run"
    else:
        want = convert_domain(_run(stage, convert_domain(x, "srgb", stage.domain), state, ctx), stage.domain, "srgb")
        torch.testing.assert_close(eye, want, msg=lambda m: f"pipeline: {m}")
        assert rec["stages_run"] == [stage.name], f"pipeline: ran {rec['stages_run']}"
