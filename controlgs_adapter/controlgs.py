"""``ControlGS``: wrap a trained neural-Gaussian backbone with a condition injector.

    cgs = ControlGS.wrap(model)                                   # model code unchanged
    with cgs.conditioned(RuntimeState(downsample=4, power_saving=0.4), camera=cam, anchor_ids=ids):
        image = render(...)                                       # decoders see the injection
    cgs.save("scene.controlgs.safetensors")
    cgs = ControlGS.load("scene.controlgs.safetensors", model)

``wrap`` follows PEFT's rule: it checks everything (backend, targets, widths, modules, endpoints)
before it changes anything on the model, and ``unwrap`` puts back exactly what was there.
"""

from __future__ import annotations

import contextlib
import weakref
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import torch
from torch import nn

from . import plugins
from .plugins import select_backend
from .backend import Backend, anchor_ids_from_mask, get_attr_path, set_attr_path
from .errors import (IncompatibleAdapterError, InjectionMissedError, InputValueError, NoMatchingBackendError,
                     LifecycleError, ShapeError, TargetError, warn_user)
from .injector import ConditionInjector, InjectionContext
from controlgs_adapter.formats.adapter import (ADAPTER_FORMAT_VERSION, ADAPTER_KIND, AdapterSpec, Problem, build_header, fingerprint_mismatch,
                           map_conditions, read_spec, read_tensors, row_map, tensor_mismatches, valid_fingerprint,
                           write_adapter)
from .schedules import StrengthSchedule
from .state import Camera, RuntimeState
from controlgs_adapter.formats.torchscript_live import eager_from_script
from .downstream.placement import Placement, to_display

__all__ = ["ControlGS", "Target", "ADAPTER_KIND", "ADAPTER_FORMAT_VERSION", "DEFAULT_ADAPTER"]

DEFAULT_MODULES = ("lens", "resample", "display")
DEFAULT_ADAPTER = "default"

# FC1 modules that carry a live injector hook -> the ControlGS that owns it (wrapping twice is an error)
_ATTACHED: "weakref.WeakKeyDictionary[nn.Module, ControlGS]" = weakref.WeakKeyDictionary()


@dataclass(frozen=True)
class Target:
    """One decoder that receives the injection.

    Attributes:
        decoder: dotted path of the decoder on the model (``"mlp_opacity"``).
        fc1: dotted path of its first Linear (``"mlp_opacity.0"``).
        in_features, out_features: FC1's widths (``out_features`` = D1).
        from_torchscript: the decoder was a TorchScript module, rebuilt as an eager one.
    """

    decoder: str
    fc1: str
    in_features: int
    out_features: int
    from_torchscript: bool

    def as_header(self) -> dict[str, Any]:
        return {"decoder": self.decoder, "fc1": self.fc1, "in_features": self.in_features, "out_features": self.out_features}


@dataclass
class _Adapter:
    """One named parameter set of a wrapped model: its injector, schedules and what its load skipped."""

    injector: ConditionInjector
    schedules: dict[str, StrengthSchedule]
    state_blind: bool
    skipped: list[str]


@dataclass
class _Plan:
    target: Target
    eager: nn.Module | None  # the eager rebuild of a TorchScript decoder (dry run), else None
    layer: nn.Module | None = None  # the model's own FC1 object (eager decoders): two targets must not share it


def _inspect_target(model: Any, backend: Backend, path: str) -> _Plan:
    """Resolve one target without changing the model; raise TargetError saying what is wrong."""
    try:
        decoder = get_attr_path(model, path)
    except (AttributeError, IndexError, KeyError, TypeError):
        raise TargetError(
            f"{backend.name}: the model has no decoder {path!r}; its decoders: {backend.decoder_paths(model)}"
        ) from None
    fc1_path = backend.first_linear_path(model, path)
    eager = None
    if isinstance(decoder, torch.jit.ScriptModule):
        eager = eager_from_script(decoder, name=path)
    fc1 = backend.check_decoder(model, path, eager)  # one check for eager and TorchScript decoders
    if not isinstance(fc1, nn.Linear):
        raise TargetError(f"{backend.name}: first layer {fc1_path!r} of {path!r} must be an eager nn.Linear, got {type(fc1).__name__}")
    if fc1 in _ATTACHED:
        raise LifecycleError(f"{fc1_path!r} already carries an injector ({_ATTACHED[fc1]!r}): unwrap it first, "
                          "e.g. ControlGS.attached(model).unwrap()")
    target = Target(path, fc1_path, fc1.in_features, fc1.out_features, eager is not None)
    return _Plan(target, eager, fc1 if eager is None else None)


def _check_shared_layers(backend: Backend, plans: Sequence[_Plan]) -> None:
    """Raise TargetError when two targets' first layers are one module object (``mlp_cov[0] is
    mlp_opacity[0]``, or one decoder under two names): a hook per target would inject into it twice."""
    seen: dict[int, Target] = {}
    for plan in plans:
        if plan.layer is None:  # a TorchScript decoder: each target gets its own eager rebuild
            continue
        first = seen.setdefault(id(plan.layer), plan.target)
        if first is not plan.target:
            raise TargetError(
                f"{backend.name}: targets {first.decoder!r} and {plan.target.decoder!r} share one first layer "
                f"({first.fc1!r} is {plan.target.fc1!r}): its output would get the injection twice; wrap one of "
                f"them (targets=[{first.decoder!r}, ...] without {plan.target.decoder!r}) or give each decoder its own layer")


def _check_modules(modules: Sequence[str], cond_dim: int,
                   endpoints: Mapping[str, Sequence[float] | Mapping[str, Any]] | None) -> dict[str, StrengthSchedule]:
    """The schedules of ``modules``: the registered ones, with ``endpoints[m]`` (``(lo, hi)`` or a
    header's ``{"lo", "hi", ...}``) where given."""
    if isinstance(modules, str) or not isinstance(modules, Sequence):
        raise InputValueError(f"modules must be a sequence of module names, got {modules!r}")
    registered = {name: info.obj for name, info in plugins.schedules().items()}
    if not modules:
        raise InputValueError(f"modules must name at least one condition module; registered: {sorted(registered)}")
    dupes = sorted({m for m in modules if list(modules).count(m) > 1})
    if dupes:
        raise InputValueError(f"modules lists {dupes} more than once")
    unknown = [m for m in modules if m not in registered]
    if unknown:
        raise InputValueError(f"unknown condition module(s) {unknown}; registered schedules: {sorted(registered)}")
    if isinstance(cond_dim, bool) or not isinstance(cond_dim, int) or cond_dim <= 0:
        raise InputValueError(f"cond_dim must be a positive int, got {cond_dim!r}")
    endpoints = dict(endpoints or {})
    stray = sorted(set(endpoints) - set(modules))
    if stray:
        raise InputValueError(f"endpoints given for {stray}, which are not among modules {list(modules)}")
    schedules = {}
    for m in modules:
        lo_hi = endpoints.get(m)
        if lo_hi is None:
            schedules[m] = registered[m]
            continue
        pair = (lo_hi.get("lo"), lo_hi.get("hi")) if isinstance(lo_hi, Mapping) else lo_hi
        if len(pair) != 2:
            raise InputValueError(f"endpoints[{m!r}] must be (lo, hi), got {lo_hi!r}")
        schedules[m] = registered[m].with_endpoints(*pair)
    return schedules


def _backbone_tensors(model: Any) -> list[torch.Tensor]:
    """Every parameter/tensor of the backbone that autograd could train: the model's parameters if
    it is an ``nn.Module``, else those of its module attributes and its tensor attributes."""
    if isinstance(model, nn.Module):
        return list(model.parameters())
    found: dict[int, torch.Tensor] = {}
    for value in vars(model).values():
        if isinstance(value, nn.Module):
            found.update((id(p), p) for p in value.parameters())
        elif isinstance(value, torch.Tensor) and value.is_leaf:
            found[id(value)] = value
    return list(found.values())


class ControlGS:
    """A backbone wrapped with a :class:`~controlgs_adapter.injector.ConditionInjector`.

    Build with :meth:`wrap` or :meth:`load`. Attributes: ``model``, ``backend``, ``injector``,
    ``targets`` (what it attached to), ``modules``, ``schedules``, ``state_blind``,
    ``num_anchors``, ``rows_per_anchor``, ``fingerprint`` (of the backbone), ``placement``,
    ``adapters`` (names of the loaded parameter sets), ``active_adapter`` (the injected one; ``injector``,
    ``schedules`` and ``state_blind`` are its), ``skipped`` (what a non-strict load of it left out).
    """

    #: where the image sits on the headset display for the per-anchor strengths (``"fit"`` or
    #: ``"stretch"``, :mod:`controlgs_adapter.downstream.placement`); set it as the optics stage's
    #: ``placement`` when that is not the default. A run-time setting, not saved with the adapter.
    placement: Placement = "fit"

    def __init__(self, model: Any, backend: Backend, injector: ConditionInjector, targets: list[Target],
                 schedules: dict[str, StrengthSchedule], state_blind: bool, fingerprint: str,
                 originals: dict[str, nn.Module], grad_flags: list[tuple[torch.Tensor, bool]],
                 name: str = DEFAULT_ADAPTER) -> None:
        self.model, self.backend, self.injector = model, backend, injector
        self.targets = tuple(targets)
        self.schedules = dict(schedules)
        self.state_blind = bool(state_blind)
        self._adapters = {name: _Adapter(injector, self.schedules, self.state_blind, [])}
        self.active_adapter = name
        self.num_anchors = injector.num_anchors
        self.rows_per_anchor = backend.rows_per_anchor(model)
        self.fingerprint = fingerprint
        self._originals = originals
        self._grad_flags = grad_flags
        self._wrapped = True

    # ------------------------------------------------------------------ wrap / unwrap
    @classmethod
    def wrap(cls, model: Any, modules: Sequence[str] = DEFAULT_MODULES, cond_dim: int = 8,
             backend: str | Backend | None = None, targets: Sequence[str] | None = None,
             endpoints: Mapping[str, Sequence[float]] | None = None, state_blind: bool = False,
             name: str = DEFAULT_ADAPTER) -> "ControlGS":
        """Attach a condition injector to every target decoder of ``model``.

        Args:
            model: a trained backbone (e.g. Scaffold-GS's ``GaussianModel``); its code is not changed.
            modules: condition modules (registered schedules: ``lens``, ``resample``, ``display``,
                ``foveation``, plug-ins').
            cond_dim: N, size of each per-anchor condition.
            backend: backend name (or instance) to use; None picks the first registered backend
                that recognises the model.
            targets: decoder paths to inject into; None = the backend's defaults.
            endpoints: ``{module: (lo, hi)}`` control values of zero and full strength.
            state_blind: ablation: strength 1 for every module, whatever the state.
            name: name of this parameter set (more are added with :meth:`load_adapter`).

        Raises:
            NoMatchingBackendError, TargetError, InputValueError, ShapeError: before anything on the
            model has changed.
        """
        _check_name(name)
        chosen = select_backend(model, backend)
        schedules = _check_modules(modules, cond_dim, endpoints)
        if targets is None:
            targets = chosen.default_targets(model)
        if isinstance(targets, str) or not isinstance(targets, Sequence) or not targets:
            raise TargetError(f"targets must be a non-empty sequence of decoder paths, got {targets!r}")
        if len(set(targets)) != len(targets):
            raise TargetError(f"targets lists a decoder more than once: {list(targets)}")
        plans = [_inspect_target(model, chosen, t) for t in targets]
        _check_shared_layers(chosen, plans)
        positions = chosen.anchor_positions(model)
        num_anchors = chosen.num_anchors(model)
        if num_anchors < 1 or positions.shape[0] != num_anchors:
            raise ShapeError(f"{chosen.name}: the model has {num_anchors} anchors and positions {list(positions.shape)}")
        rpa = chosen.rows_per_anchor(model)
        if not isinstance(rpa, int) or rpa < 1:
            raise TargetError(f"{chosen.name}: rows_per_anchor must be an int >= 1, got {rpa!r}")
        fingerprint = chosen.fingerprint(model)

        # -- every check passed: now change the model (rolled back if a backend hook still fails)
        originals: dict[str, nn.Module] = {}
        try:
            for plan in plans:
                original = chosen.make_hookable(model, plan.target.decoder)
                if original is not None:
                    originals[plan.target.decoder] = original
            fc1s = [get_attr_path(model, p.target.fc1) for p in plans]
            for p, fc1 in zip(plans, fc1s):
                if not isinstance(fc1, nn.Linear) or fc1.out_features != p.target.out_features:
                    raise TargetError(f"{chosen.name}: make_hookable left {p.target.fc1!r} as {fc1!r}")
        except BaseException:
            for path, original in originals.items():
                set_attr_path(model, path, original)
            raise
        weight = fc1s[0].weight
        dtype = weight.dtype if weight.dtype in (torch.float32, torch.float64) else torch.float32
        injector = ConditionInjector(num_anchors, list(schedules), cond_dim,
                                     {p.target.decoder: p.target.out_features for p in plans},
                                     device=weight.device, dtype=dtype)
        grad_flags = [(t, t.requires_grad) for t in _backbone_tensors(model)]
        for t, _ in grad_flags:
            t.requires_grad_(False)
        cgs = cls(model, chosen, injector, [p.target for p in plans], schedules, state_blind, fingerprint,
                  originals, grad_flags, name)
        for p, fc1 in zip(plans, fc1s):
            injector.attach(p.target.decoder, fc1)
            _ATTACHED[fc1] = cgs
        return cgs

    def unwrap(self) -> Any:
        """Remove the hooks, put back the original (TorchScript) decoders and the backbone's
        ``requires_grad`` flags. Returns the model; this wrapper cannot be used afterwards."""
        self._check_live()
        for t in self.targets:
            _ATTACHED.pop(get_attr_path(self.model, t.fc1), None)
        self.injector.detach()
        for path, original in self._originals.items():
            set_attr_path(self.model, path, original)
        for tensor, flag in self._grad_flags:
            tensor.requires_grad_(flag)
        self._wrapped = False
        return self.model

    @staticmethod
    def attached(model: Any) -> "ControlGS | None":
        """The live wrapper whose injector sits on ``model``'s decoders, or None (e.g. to unwrap a
        model whose wrapper object was lost after an exception)."""
        for backend in (info.obj for info in plugins.backends().values()):
            if not backend.matches(model):
                continue
            for path in backend.decoder_paths(model):
                try:
                    fc1 = get_attr_path(model, backend.first_linear_path(model, path))
                except (AttributeError, IndexError, KeyError, TypeError):
                    continue
                if isinstance(fc1, nn.Module) and fc1 in _ATTACHED:
                    return _ATTACHED[fc1]
        return None

    def _check_live(self) -> None:
        if not self._wrapped:
            raise LifecycleError("this ControlGS was unwrapped; wrap the model again")

    # ------------------------------------------------------------------ run time
    @property
    def modules(self) -> tuple[str, ...]:
        """Names of the wrapped condition modules."""
        return self.injector.module_names

    def trainable_parameters(self) -> Iterator[nn.Parameter]:
        """The adapter's parameters (conditions and projections); the backbone stays frozen."""
        return self.injector.parameters()

    def anchor_ids(self, anchor_ids: torch.Tensor | None) -> torch.Tensor:
        """Normalise ``LongTensor[R]`` / ``BoolTensor[A]`` / None (all anchors) to ``LongTensor[R]``
        on the injector's device, checking range and shape."""
        device = next(self.injector.parameters()).device
        a = self.num_anchors
        if anchor_ids is None:
            return torch.arange(a, device=device)
        if not isinstance(anchor_ids, torch.Tensor):
            raise InputValueError(f"anchor_ids must be a LongTensor[R], a BoolTensor[{a}] or None, got {type(anchor_ids).__name__}")
        if anchor_ids.dtype == torch.bool:
            return anchor_ids_from_mask(anchor_ids.to(device), a, name="anchor_ids mask")
        if anchor_ids.dtype not in (torch.int64, torch.int32, torch.int16, torch.uint8, torch.int8):
            raise InputValueError(f"anchor_ids must be an integer or bool tensor, got {anchor_ids.dtype}")
        if anchor_ids.dim() != 1:
            raise ShapeError(f"anchor_ids must have shape [R], got {list(anchor_ids.shape)}")
        ids = anchor_ids.to(device=device, dtype=torch.int64)
        if ids.numel() and bool(((ids < 0) | (ids >= a)).any()):  # one device sync; min/max only on error
            raise InputValueError(f"anchor_ids must lie in [0, {a}), got values in [{int(ids.min())}, {int(ids.max())}]")
        return ids

    def strengths(self, state: RuntimeState, camera: Camera | None = None,
                  anchor_ids: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Injection strength of every wrapped module for the given anchors: ``{module: [R]}``."""
        self._check_live()
        ids = self.anchor_ids(anchor_ids)
        out = {}
        for m, lam in self._strengths(state, camera, ids, self.modules, skip_zero=False).items():
            out[m] = lam if isinstance(lam, torch.Tensor) else torch.full(ids.shape, lam, dtype=self.injector.dtype,
                                                                          device=ids.device)
        return out

    def _strengths(self, state: RuntimeState, camera: Camera | None, ids: torch.Tensor, modules: Sequence[str],
                   *, skip_zero: bool) -> dict[str, torch.Tensor | float]:
        if not isinstance(state, RuntimeState):
            raise InputValueError(f"state must be a RuntimeState, got {type(state).__name__}")
        if self.state_blind:
            return {m: 1.0 for m in modules}
        screen = None
        out: dict[str, torch.Tensor | float] = {}
        for m in modules:
            schedule = self.schedules[m]
            if not schedule.per_anchor:
                lam = schedule.scalar_strength(float(schedule.control(state, None)))
                if lam != 0.0 or not skip_zero:
                    out[m] = lam
                continue
            if screen is None:
                if not isinstance(camera, Camera):
                    raise InputValueError(
                        f"module {m!r} needs each anchor's screen position: pass camera=Camera(...) "
                        f"(Camera.from_scaffold converts a Scaffold-GS camera), got {type(camera).__name__}"
                    )
                positions = self.backend.anchor_positions(self.model).detach()
                screen, display_state = self._display_positions(
                    camera, camera.normalized_screen(positions.index_select(0, ids.to(positions.device))), state)
            # per-anchor strengths stay even where all zero (they add exact zeros): testing would sync the device
            out[m] = schedule.strength(display_state, screen, dtype=self.injector.dtype, device=ids.device)
        return out

    def _display_positions(self, camera: Camera, screen: torch.Tensor,
                           state: RuntimeState) -> tuple[torch.Tensor, RuntimeState]:
        """Image-normalised anchor positions ``[R, 2]`` and gaze -> display-normalised ones (p_v of the
        lens and foveation schedules): the image placed on the Cardboard display as the optics
        places it, so a strength follows the radial distance on the display (a square image: as is)."""
        h, w = camera.height, camera.width
        if state.gaze is not None:
            gaze = to_display(torch.tensor(state.gaze, dtype=torch.float64), h, w, self.placement)
            state = replace(state, gaze=tuple(gaze.tolist()))
        return to_display(screen, h, w, self.placement), state

    @contextlib.contextmanager
    def conditioned(self, state: RuntimeState, camera: Camera | None = None, anchor_ids: torch.Tensor | None = None,
                    *, modules: Sequence[str] | None = None, on_miss: str = "warn") -> Iterator["ControlGS"]:
        """Inject the conditions into every target decoder called inside the block.

        Args:
            state: the run-time state (downsample, power saving, gaze).
            camera: the view's camera; needed by per-anchor modules (lens, foveation).
            anchor_ids: which anchor each decoder row belongs to: ``LongTensor[R]`` (row i =
                anchor ``anchor_ids[i]``), ``BoolTensor[A]`` visibility mask (rows = visible anchors,
                ascending), or None (all anchors). With ``rows_per_anchor`` K > 1, row r belongs to
                ``anchor_ids[r // K]``. A decoder called with another row count raises ShapeError.
            modules: restrict the injection to these wrapped modules (others are off, not computed);
                a single name (``"lens"``) is one module.
            on_miss: what happens when the block ends without any wrapped decoder having run (the
                render used another object than the wrapped model, e.g. a copy or a forwarding
                wrapper holding the original decoders): ``"warn"`` (RuntimeWarning), ``"raise"``
                (:class:`InjectionMissedError`) or ``"ignore"``.
        """
        self._check_live()
        if on_miss not in ("warn", "raise", "ignore"):
            raise InputValueError(f"on_miss must be 'warn', 'raise' or 'ignore', got {on_miss!r}")
        ids = self.anchor_ids(anchor_ids)
        if modules is None:
            active = self.modules
        else:
            if isinstance(modules, str):
                modules = (modules,)
            if not isinstance(modules, Sequence) or not all(isinstance(m, str) for m in modules):
                raise InputValueError(f"modules must be a module name or a sequence of them, got {modules!r}")
            active = tuple(modules)
            unknown = [m for m in active if m not in self.modules]
            if unknown:
                raise InputValueError(f"modules {unknown} are not wrapped; wrapped modules: {list(self.modules)}")
        strengths = self._strengths(state, camera, ids, active, skip_zero=True)
        ctx = InjectionContext(ids, strengths, self.rows_per_anchor)
        self.injector.activate(ctx)
        try:
            yield self
        finally:
            self.injector.deactivate()
        if on_miss != "ignore" and not ctx.calls and ctx.rows:
            self._missed(on_miss)

    def _missed(self, on_miss: str) -> None:
        """Report a conditioned block in which no wrapped decoder ran."""
        fc1s = ", ".join(t.fc1 for t in self.targets)
        rebuilt = [t.decoder for t in self.targets if t.from_torchscript]
        msg = (f"no wrapped decoder ran inside this conditioned block: the injected first layers ({fc1s}) of "
               f"{type(self.model).__name__} object at {id(self.model):#x} were never called, so the render did not "
               "see the adapter. The renderer must call the decoders of that very object (ControlGS.wrap changed it in "
               "place), not of a copy, a forwarding wrapper or decoders fetched before wrapping"
               + (f"; the TorchScript decoders {rebuilt} were replaced there by eager copies" if rebuilt else ""))
        if on_miss == "raise":
            raise InjectionMissedError(msg)
        warn_user(msg, RuntimeWarning)

    # ------------------------------------------------------------------ files
    def adapter_spec(self) -> AdapterSpec:
        """The active adapter as plain data (backend, modules, schedules' endpoints, targets, anchors,
        backbone fingerprints): what its file header records."""
        return AdapterSpec(
            backend=self.backend.name,
            modules=list(self.modules),
            cond_dim=self.injector.cond_dim,
            schedules={m: {"class": type(s).__qualname__, "per_anchor": s.per_anchor, **s.endpoints()}
                       for m, s in self.schedules.items()},
            state_blind=self.state_blind,
            targets=[t.as_header() for t in self.targets if t.decoder in self.injector.widths],
            num_anchors=self.num_anchors,
            rows_per_anchor=self.rows_per_anchor,
            fingerprint=self.fingerprint,
            valid_fingerprint=valid_fingerprint(self.model, self.backend),
        )

    def header(self) -> dict[str, Any]:
        """The JSON header :meth:`save` writes (without the fields io adds)."""
        return build_header(self.adapter_spec())

    def save(self, path: str | Path, dtype: torch.dtype | None = None) -> Path:
        """Write the active adapter to one ``.safetensors`` file (atomically).

        Args:
            dtype: storage dtype of the conditions: None (as trained, float32) or
                ``torch.float16`` (half the size; see docs/reference/adapter.md for the effect on output).
                Projections are always stored as trained.
        """
        self._check_live()
        return write_adapter(path, dict(self.injector.state_dict()), self.header(), dtype)

    @classmethod
    def load(cls, path: str | Path, model: Any, *, strict: bool = True, name: str = DEFAULT_ADAPTER) -> "ControlGS":
        """Wrap ``model`` and load the adapter saved at ``path`` onto it (as adapter ``name``).

        Args:
            strict: True: any mismatch raises. False (PEFT's ``strict=False``): what does not fit is
                skipped and listed in ``cgs.skipped`` (a RuntimeWarning says so): file targets the
                model lacks or has with other widths, tensors missing from the file (left at their
                initial values; conditions start at zero, i.e. inert), unexpected ones, tensors of the
                wrong shape or with NaN/Inf, and the conditions on an anchor-count mismatch. Another
                backbone fingerprint or rows per anchor is only warned about. Another backend, or no
                target left, still raises.

        Raises:
            FileFormatError: the file is missing, truncated, foreign or of a newer format.
            IncompatibleAdapterError: listing every mismatch with the model (backend, anchor count,
                decoder widths, backbone fingerprint, tensors).
        """
        _check_name(name)
        plan = _read_adapter(path, model, strict=strict)
        spec = plan.spec
        cgs = cls.wrap(model, modules=spec["modules"], cond_dim=spec["cond_dim"], backend=plan.backend,
                       targets=plan.targets, endpoints=_spec_endpoints(spec), state_blind=spec["state_blind"],
                       name=name)
        _load_into(cgs.injector, plan.tensors)
        cgs._adapters[name].skipped = plan.skipped
        return cgs

    def load_adapter(self, path: str | Path, name: str, *, strict: bool = True) -> list[str]:
        """Load another adapter of this backbone as parameter set ``name`` (not activated: see
        :meth:`set_adapter`). Its targets must be among the wrapped ones; ``strict`` as in :meth:`load`.
        Returns what a non-strict load skipped (also ``skipped`` while it is active)."""
        self._check_live()
        _check_name(name)
        if name in self._adapters:
            raise InputValueError(f"an adapter named {name!r} is already loaded; loaded adapters: {list(self._adapters)}")
        plan = _read_adapter(path, self.model, strict=strict, wrapped=self)
        spec = plan.spec
        schedules = _check_modules(spec["modules"], spec["cond_dim"], _spec_endpoints(spec))
        widths = {t.decoder: t.out_features for t in self.targets if t.decoder in plan.targets}
        injector = ConditionInjector(self.num_anchors, spec["modules"], spec["cond_dim"], widths,
                                     device=self.injector.conditions.device, dtype=self.injector.dtype)
        _load_into(injector, plan.tensors)
        self._adapters[name] = _Adapter(injector, schedules, bool(spec["state_blind"]), plan.skipped)
        return list(plan.skipped)

    @property
    def adapters(self) -> tuple[str, ...]:
        """Names of the loaded parameter sets, in loading order."""
        return tuple(self._adapters)

    @property
    def skipped(self) -> list[str]:
        """What the non-strict load of the active adapter skipped (empty after a strict load or a wrap)."""
        return list(self._adapters[self.active_adapter].skipped)

    def set_adapter(self, name: str) -> None:
        """Inject parameter set ``name`` from now on (``injector``, ``schedules``, ``state_blind``,
        ``trainable_parameters()`` and :meth:`save` follow it). Not inside a ``conditioned`` block."""
        self._check_live()
        if name not in self._adapters:
            raise InputValueError(f"unknown adapter {name!r}; loaded adapters: {list(self._adapters)}")
        if self.injector.context is not None:
            raise LifecycleError("set_adapter inside a conditioned block: leave the block first")
        if name == self.active_adapter:
            return
        new = self._adapters[name]
        self.injector.detach()
        for t in self.targets:
            if t.decoder in new.injector.widths:
                new.injector.attach(t.decoder, get_attr_path(self.model, t.fc1))
        self.injector, self.schedules, self.state_blind = new.injector, new.schedules, new.state_blind
        self.active_adapter = name

    # ------------------------------------------------------------------ reporting
    def summary(self) -> str:
        """What is attached where, the schedules and the parameter counts."""
        n_cond = self.injector.conditions.numel()
        n_proj = sum(p.numel() for p in self.injector.projections.parameters())
        lines = [
            f"ControlGS on {type(self.model).__name__} via backend {self.backend.name!r}"
            + ("" if self._wrapped else " (unwrapped)"),
            f"  anchors: {self.num_anchors} ({self.rows_per_anchor} decoder row(s) per anchor), "
            f"backbone fingerprint {self.fingerprint}",
            f"  modules: {', '.join(self.modules)}; N = {self.injector.cond_dim} per module"
            + ("; state-blind (strength 1)" if self.state_blind else ""),
            "  targets:",
        ]
        for t in self.targets:
            note = "  (rebuilt from TorchScript)" if t.from_torchscript else ""
            lines.append(f"    {t.fc1}: Linear({t.in_features} -> {t.out_features}){note}")
        lines.append("  schedules:")
        lines += [f"    {m}: {s!r}" for m, s in self.schedules.items()]
        lines.append(f"  trainable: {n_cond + n_proj:,} parameters (conditions {n_cond:,}, projections {n_proj:,})")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"ControlGS(backend={self.backend.name!r}, anchors={self.num_anchors}, modules={list(self.modules)}, "
                f"cond_dim={self.injector.cond_dim}, targets={[t.fc1 for t in self.targets]}"
                + (", state_blind=True" if self.state_blind else "") + ("" if self._wrapped else ", unwrapped") + ")")


def _check_name(name: str) -> None:
    if not isinstance(name, str) or not name:
        raise InputValueError(f"an adapter name must be a non-empty str, got {name!r}")


def _spec_endpoints(spec: dict[str, Any]) -> dict[str, tuple[float, float]]:
    return {m: (s["lo"], s["hi"]) for m, s in spec["schedules"].items()}


@dataclass
class _LoadPlan:
    spec: dict[str, Any]
    backend: Backend
    targets: list[str]  # decoders that get this adapter
    tensors: dict[str, torch.Tensor]  # what loads (conditions already mapped onto the model's anchors)
    skipped: list[str]


def _read_adapter(path: str | Path, model: Any, *, strict: bool, wrapped: ControlGS | None = None) -> _LoadPlan:
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
                other = select_backend(model, None).name
            except NoMatchingBackendError:
                other = "no registered backend"
            problems.append((f"backend: the adapter was made for {spec['backend']!r}; this model is recognised by {other}",
                             "fatal"))
            backend = None
    rows = None
    if backend is not None:
        rows = row_map(model, backend, spec)
        problems += _model_mismatches(model, backend, spec, mapped=rows is not None, wrapped=wrapped)
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
    return _LoadPlan(spec, backend, targets, tensors, skipped)


def _load_into(injector: ConditionInjector, tensors: Mapping[str, torch.Tensor]) -> None:
    """Copy the loadable ``tensors`` into ``injector`` (the others keep their initial values)."""
    state = injector.state_dict()
    injector.load_state_dict({**state, **{k: v.to(state[k].dtype) for k, v in tensors.items() if k in state}})


def _model_mismatches(model: Any, backend: Backend, spec: dict[str, Any], *, mapped: bool = False,
                      wrapped: ControlGS | None = None) -> list[Problem]:
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
                got = _inspect_target(model, backend, t["decoder"]).target
            except TargetError as e:
                problems.append((f"target {t['decoder']!r}: {e}", skip))
                continue
        if (got.in_features, got.out_features) != (t["in_features"], t["out_features"]):
            problems.append((f"target {t['decoder']!r}: the adapter was made for Linear({t['in_features']} -> "
                             f"{t['out_features']}), the model has Linear({got.in_features} -> {got.out_features})", skip))
    if not mapped:
        problems += fingerprint_mismatch(spec, wrapped.fingerprint if wrapped is not None else backend.fingerprint(model))
    return problems
