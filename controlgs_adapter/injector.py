"""The condition injector (paper Eq. 9): per-anchor conditions, shared projections, FC1 hooks.

For every target decoder with first linear layer ``FC1`` (output width ``D1``)::

    h = FC1(x) + sum_m lambda[v, m] * A_m(C[v, m])

A per-anchor strength may also be a pair ``[R_a, 2]`` (the lens in its ``"xy"`` frame,
:mod:`controlgs_adapter.lens_frame`): it scales the two halves of the module's N condition columns,
``lambda_x A_m([C_1, 0]) + lambda_y A_m([0, C_2])``.
``C`` is ``[A, M, N]`` (zero-initialised, so the wrapped model starts as the backbone) and
``A_m: R^N -> R^D1`` is a bias-free Linear shared by all anchors, one per module and distinct
``D1``. The sum is one gather and one matmul per :meth:`ConditionInjector.activate` context and
width, reused by every decoder of that width and added in place to FC1's output; modules whose
shared (not per-anchor) strength is zero are left out, and outside a context the hooks return at once
(outputs bit-identical to the backbone).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence, cast

import torch
from torch import nn

from .errors import InputValueError, LifecycleError, ShapeError

__all__ = ["ConditionInjector", "InjectionContext"]


@dataclass
class InjectionContext:
    """What one ``conditioned`` block injects.

    Attributes:
        anchor_ids: ``[R_a]`` long, the anchor of each group of ``rows_per_anchor`` decoder rows.
        strengths: module -> ``[R_a]`` per-anchor strength tensor, ``[R_a, k]`` (each of k equal
            slices of the N condition columns scaled by its own strength; k divides N), or a float
            shared by all rows; modules with a shared strength of zero are not listed.
        rows_per_anchor: decoder rows per anchor (row r belongs to ``anchor_ids[r // K]``).
        calls: target name -> how many times its hooked first layer ran in this context.
    """

    anchor_ids: torch.Tensor
    strengths: dict[str, torch.Tensor | float]
    rows_per_anchor: int = 1
    cache: dict[tuple[int, bool], tuple[tuple[int, ...], torch.Tensor]] = field(default_factory=dict)
    calls: dict[str, int] = field(default_factory=dict)

    @property
    def rows(self) -> int:
        return int(self.anchor_ids.shape[0]) * self.rows_per_anchor


class ConditionInjector(nn.Module):
    """Conditions and projections of one wrapped model, and the hooks that inject them.

    Args:
        num_anchors: A, rows of the condition table.
        modules: condition module names (``"lens"``, ``"resample"``, ...), M of them.
        cond_dim: N, size of one condition vector.
        widths: FC1 output width ``D1`` of each target (target name -> ``D1``).

    Parameters (state-dict keys): ``conditions`` ``[A, M, N]`` (module order = ``modules``);
    ``projections.<module>.d<D1>.weight`` ``[D1, N]``.
    """

    def __init__(self, num_anchors: int, modules: Sequence[str], cond_dim: int, widths: dict[str, int],
                 *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.num_anchors, self.cond_dim = int(num_anchors), int(cond_dim)
        self.module_names = tuple(modules)
        self.widths = dict(widths)
        self.conditions = nn.Parameter(torch.zeros(num_anchors, len(modules), cond_dim, device=device, dtype=dtype))
        self.projections = nn.ModuleDict()
        for m in modules:
            per_width = nn.ModuleDict()
            for d1 in sorted(set(widths.values())):
                proj = nn.Linear(cond_dim, d1, bias=False, device=device, dtype=dtype)
                nn.init.kaiming_uniform_(proj.weight, a=math.sqrt(5.0))  # nn.Linear's own (Kaiming) init
                per_width[f"d{d1}"] = proj
            self.projections[m] = per_width
        self._ctx: InjectionContext | None = None
        self._handles: list[torch.utils.hooks.RemovableHandle] = []

    @property
    def dtype(self) -> torch.dtype:
        return self.conditions.dtype

    def condition(self, module: str) -> torch.Tensor:
        """``[A, N]`` view of one module's conditions."""
        return self.conditions[:, self.module_names.index(module)]

    # -- attaching -------------------------------------------------------------------------------
    def attach(self, name: str, fc1: nn.Linear) -> None:
        """Register the injection hook on target ``name``'s first Linear."""
        if self.widths.get(name) != fc1.out_features:
            raise ShapeError(f"target {name!r}: FC1 width {fc1.out_features} != declared {self.widths.get(name)}")
        self._handles.append(fc1.register_forward_hook(self._make_hook(name, fc1.out_features)))

    def detach(self) -> None:
        """Remove every hook."""
        for h in self._handles:
            h.remove()
        self._handles.clear()
        self._ctx = None

    # -- contexts --------------------------------------------------------------------------------
    @property
    def context(self) -> InjectionContext | None:
        return self._ctx

    def activate(self, ctx: InjectionContext) -> None:
        if self._ctx is not None:
            raise LifecycleError("already inside a conditioned block: nested blocks are not supported")
        unknown = set(ctx.strengths) - set(self.module_names)
        if unknown:
            raise InputValueError(f"strengths for unknown module(s) {sorted(unknown)}; wrapped modules: {list(self.module_names)}")
        for m, lam in ctx.strengths.items():
            if isinstance(lam, torch.Tensor) and lam.dim() == 2 and (lam.shape[1] < 1 or self.cond_dim % lam.shape[1]):
                raise ShapeError(f"strengths[{m!r}]: {lam.shape[1]} strengths per anchor do not split the "
                                 f"{self.cond_dim} condition columns into equal slices")
        self._ctx = ctx

    def deactivate(self) -> None:
        self._ctx = None

    # -- the injection ---------------------------------------------------------------------------
    def _projection(self, module: str, width: int) -> nn.Linear:
        """``module``'s projection to FC1 width ``width`` (``projections.<module>.d<width>``)."""
        # nn.ModuleDict is not generic: its stubs type every item as Module, whatever __init__ put there
        per_width = cast(nn.ModuleDict, self.projections[module])
        return cast(nn.Linear, per_width[f"d{width}"])

    def injection(self, ctx: InjectionContext, width: int) -> torch.Tensor | None:
        """``[R_a, D1]`` sum of the active modules' scaled projected conditions, or None if no
        module is active. Cached per context, width and grad mode; recomputed if a parameter was
        changed in place since (e.g. an optimizer step inside one block)."""
        if not ctx.strengths:
            return None
        key = (width, torch.is_grad_enabled())
        projections = [self._projection(m, width).weight for m in ctx.strengths]  # [D1, N] each
        versions = (self.conditions._version, *(w._version for w in projections))
        hit = ctx.cache.get(key)
        if hit is not None and hit[0] == versions:
            return hit[1]
        cols = [self.module_names.index(m) for m in ctx.strengths]
        z = self.conditions.index_select(0, ctx.anchor_ids)  # [R_a, M, N]
        if cols != list(range(len(self.module_names))):
            z = z[:, cols]
        ws = []
        for j, (lam, w) in enumerate(zip(ctx.strengths.values(), projections)):
            if isinstance(lam, torch.Tensor):  # per-anchor strength scales the (few) condition columns
                lam = lam.to(z.dtype)
                z[:, j] *= lam.repeat_interleave(z.shape[-1] // lam.shape[1], dim=1) if lam.dim() == 2 else lam.unsqueeze(-1)
            elif lam != 1.0:  # a strength shared by all rows folds into the (tiny) projection
                w = w * lam
            ws.append(w)
        w = ws[0] if len(ws) == 1 else torch.cat(ws, dim=1)  # [D1, M'*N]
        inj = z.flatten(1) @ w.transpose(0, 1)  # [R_a, D1]
        ctx.cache[key] = (versions, inj)
        return inj

    def _make_hook(self, name: str, width: int):
        def hook(module: nn.Module, inputs: tuple, out: torch.Tensor) -> None:
            ctx = self._ctx
            if ctx is None:
                return
            ctx.calls[name] = ctx.calls.get(name, 0) + 1
            if out.dim() != 2 or out.shape[0] != ctx.rows:
                raise ShapeError(
                    f"decoder {name!r} was called with {out.shape[0] if out.dim() else 0} rows "
                    f"(FC1 output {list(out.shape)}) but the conditioned block expects {ctx.rows} rows "
                    f"= {ctx.anchor_ids.shape[0]} anchor ids x {ctx.rows_per_anchor} rows per anchor; "
                    "pass the ids of exactly the anchors whose rows the decoder sees"
                )
            inj = self.injection(ctx, width)
            if inj is None:
                return
            # in place: FC1's output is a fresh tensor that autograd does not save (Linear saves its
            # input and weight), so this avoids one [rows, D1] allocation per decoder
            k = ctx.rows_per_anchor
            if k == 1:
                out.add_(inj.to(out.dtype))
            else:
                out.view(-1, k, out.shape[1]).add_(inj.to(out.dtype).unsqueeze(1))

        return hook

    def extra_repr(self) -> str:
        return (f"anchors={self.num_anchors}, modules={list(self.module_names)}, cond_dim={self.cond_dim}, "
                f"widths={sorted(set(self.widths.values()))}")
