"""Loading an adapter file onto a model: read it, check it against the model (or a live wrapper) and
decide what loads, before anything changes (:meth:`ControlGS.load
<controlgs_adapter.controlgs.ControlGS.load>`, :meth:`~controlgs_adapter.controlgs.ControlGS.load_adapter`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

import torch

from . import plugins
from .backend import Backend
from .errors import IncompatibleAdapterError, NoMatchingBackendError, TargetError, warn_user
from .formats.adapter import (Problem, fingerprint_mismatch, map_conditions, read_spec, read_tensors, row_map,
                              tensor_mismatches)
from .injector import ConditionInjector
from .plugins import select_backend
from .targets import Target, inspect_target

__all__ = ["LoadPlan", "Wrapped", "plan_load", "load_into", "model_mismatches", "spec_endpoints"]


class Wrapped(Protocol):
    """What loading another adapter checks of a live wrapper (a :class:`~controlgs_adapter.controlgs.ControlGS`)."""

    @property
    def backend(self) -> Backend: ...

    @property
    def targets(self) -> Sequence[Target]: ...

    @property
    def fingerprint(self) -> str: ...


def spec_endpoints(spec: dict[str, Any]) -> dict[str, tuple[float, float]]:
    return {m: (s["lo"], s["hi"]) for m, s in spec["schedules"].items()}


@dataclass
class LoadPlan:
    """What loading an adapter file onto a model does, decided before anything changes."""

    spec: dict[str, Any]
    backend: Backend
    targets: list[str]  # decoders that get this adapter
    tensors: dict[str, torch.Tensor]  # what loads (conditions already mapped onto the model's anchors)
    skipped: list[str]


def plan_load(path: str | Path, model: Any, *, strict: bool, wrapped: Wrapped | None = None) -> LoadPlan:
    """Read and check the adapter at ``path`` against ``model`` (or the live ``wrapped``) without
    changing anything; strict: raise on any mismatch, else say what is left out."""
    spec = read_spec(path)
    problems: list[Problem] = []
    registered = plugins.backends()
    backend = None
    if spec["backend"] not in registered:
        problems.append((f"backend: the adapter was made for {spec['backend']!r}, which is not registered "
                         f"(registered: {sorted(registered)})", "fatal"))
    else:
        backend = registered[spec["backend"]].obj
        if wrapped is not None and wrapped.backend.name != spec["backend"]:
            problems.append((f"backend: the adapter was made for {spec['backend']!r}; this model is wrapped with "
                             f"{wrapped.backend.name}", "fatal"))
            backend = None
        elif not backend.matches(model):
            try:
                other = select_backend(model).name
            except NoMatchingBackendError:
                other = "no registered backend"
            problems.append((f"backend: the adapter was made for {spec['backend']!r}; this model is recognised by {other}",
                             "fatal"))
            backend = None
    rows = None
    if backend is not None:
        rows = row_map(model, backend, spec)
        problems += model_mismatches(model, backend, spec, mapped=rows is not None, wrapped=wrapped)
    tensors = read_tensors(path)
    problems += tensor_mismatches(tensors, spec)
    skip_targets = {s[1] for _, s in problems if isinstance(s, tuple)}
    targets = [t["decoder"] for t in spec["targets"] if t["decoder"] not in skip_targets]
    if backend is not None and not targets:
        problems.append(("targets: none of the adapter's targets fits this model", "fatal"))
    if problems and (strict or any(s == "fatal" for _, s in problems)):
        raise IncompatibleAdapterError(f"{path}: the adapter does not fit this model:\n  - "
                                       + "\n  - ".join(m for m, _ in problems))
    assert backend is not None
    skipped = [m for m, s in problems if s is not None]
    if problems:
        warn_user(f"{path}: non-strict load skipped what does not fit this model:\n  - "
                  + "\n  - ".join(m if s is not None else m + " (loaded anyway)" for m, s in problems), RuntimeWarning)
    for _, s in problems:
        if isinstance(s, (set, frozenset)):
            for k in s:
                tensors.pop(k, None)
        elif s == "conditions":
            tensors.pop("conditions", None)
    if rows is not None and "conditions" in tensors:
        tensors["conditions"] = map_conditions(tensors["conditions"], rows, backend.num_anchors(model))
    return LoadPlan(spec, backend, targets, tensors, skipped)


def load_into(injector: ConditionInjector, tensors: Mapping[str, torch.Tensor]) -> None:
    """Copy the loadable ``tensors`` into ``injector`` (the others keep their initial values)."""
    state = injector.state_dict()
    injector.load_state_dict({**state, **{k: v.to(state[k].dtype) for k, v in tensors.items() if k in state}})


def model_mismatches(model: Any, backend: Backend, spec: dict[str, Any], *, mapped: bool = False,
                     wrapped: Wrapped | None = None) -> list[Problem]:
    """What does not fit, with what a non-strict load skips for each; ``mapped``: the anchors were
    matched by :func:`~controlgs_adapter.formats.adapter.row_map` (count and fingerprint already checked over the valid anchors);
    ``wrapped``: check against this live wrapper's targets (:meth:`ControlGS.load_adapter`)."""
    problems: list[Problem] = []
    a = backend.num_anchors(model)
    if a != spec["num_anchors"] and not mapped:
        problems.append((f"anchor count: the adapter has {spec['num_anchors']} anchors, the model {a}", "conditions"))
    rpa = backend.rows_per_anchor(model)
    if rpa != spec["rows_per_anchor"]:
        problems.append((f"rows per anchor: the adapter expects {spec['rows_per_anchor']}, the model has {rpa}", None))
    have = {t.decoder: t for t in wrapped.targets} if wrapped is not None else {}
    for t in spec["targets"]:
        skip = ("target", t["decoder"])
        if wrapped is not None:
            if t["decoder"] not in have:
                problems.append((f"target {t['decoder']!r}: not wrapped (wrapped: {list(have)})", skip))
                continue
            got = have[t["decoder"]]
        else:
            try:
                got = inspect_target(model, backend, t["decoder"]).target
            except TargetError as e:
                problems.append((f"target {t['decoder']!r}: {e}", skip))
                continue
        if (got.in_features, got.out_features) != (t["in_features"], t["out_features"]):
            problems.append((f"target {t['decoder']!r}: the adapter was made for Linear({t['in_features']} -> "
                             f"{t['out_features']}), the model has Linear({got.in_features} -> {got.out_features})", skip))
    if not mapped:
        problems += fingerprint_mismatch(spec, wrapped.fingerprint if wrapped is not None else backend.fingerprint(model))
    return problems
