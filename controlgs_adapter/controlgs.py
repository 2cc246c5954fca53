"""``ControlGS``: wrap a trained neural-Gaussian backbone with a condition injector.

    cgs = ControlGS.wrap(model)                                   # model code unchanged
    with cgs.conditioned(RuntimeState(downsample=4, power_saving=0.4), camera=cam, anchor_ids=ids):
        image = render(...)                                       # decoders see the injection
    cgs.save("scene.controlgs.safetensors")
    cgs = ControlGS.load("scene.controlgs.safetensors", model)

``wrap(model, lens=bank)`` conditions the lens module in the frame of the optics' lens
(:mod:`controlgs_adapter.lens_frame`: the radius for a centred, rotationally symmetric lens, the
position ``(x, y)`` in the lens's frame otherwise) and the foveation module's eccentricities through
that lens; the file records both.

``wrap`` follows PEFT's rule: it checks everything (backend, targets, widths, modules, endpoints)
before it changes anything on the model, and ``unwrap`` puts back exactly what was there.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

import torch
from torch import nn

from . import plugins
from .plugins import select_backend
from .backend import Backend, anchor_ids_from_mask, get_attr_path, set_attr_path
from .errors import InjectionMissedError, InputValueError, LifecycleError, ShapeError, TargetError, warn_user
from .injector import ConditionInjector, InjectionContext
from controlgs_adapter.formats.adapter import (ADAPTER_FORMAT_VERSION, ADAPTER_KIND, AdapterSpec, build_header,
                                               lens_frame_of, valid_fingerprint, visual_angles_of, write_adapter)
from .lens_frame import LensFrame
from .load_plan import load_into, plan_load, spec_endpoints
from .schedules import FoveationSchedule, LensSchedule, StrengthSchedule
from .state import Camera, RuntimeState
from .strengths import check_modules, module_strengths
from .targets import ATTACHED, Target, check_shared_layers, inspect_target
from .downstream.optics.bank import PSFBank
from .downstream.optics.visual_angles import VisualAngles
from .downstream.placement import Placement

__all__ = ["ControlGS", "Target", "ADAPTER_KIND", "ADAPTER_FORMAT_VERSION", "DEFAULT_ADAPTER"]

DEFAULT_MODULES = ("lens", "resample", "display")
DEFAULT_ADAPTER = "default"



@dataclass
class _Adapter:
    """One named parameter set of a wrapped model: its injector, schedules, lens frame and what its load skipped."""

    injector: ConditionInjector
    schedules: dict[str, StrengthSchedule]
    state_blind: bool
    skipped: list[str]
    lens_frame: LensFrame


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
    ``schedules``, ``state_blind`` and ``lens_frame`` are its), ``skipped`` (what a non-strict load of it
    left out), ``lens_frame`` (the :class:`~controlgs_adapter.lens_frame.LensFrame` of the lens condition).
    """

    #: where the image sits on the headset display for the per-anchor strengths (``"fit"`` or
    #: ``"stretch"``, :mod:`controlgs_adapter.downstream.placement`); set it as the optics stage's
    #: ``placement`` when that is not the default. A run-time setting, not saved with the adapter.
    placement: Placement = "fit"

    def __init__(self, model: Any, backend: Backend, injector: ConditionInjector, targets: list[Target],
                 schedules: dict[str, StrengthSchedule], state_blind: bool, fingerprint: str,
                 originals: dict[str, nn.Module], grad_flags: list[tuple[torch.Tensor, bool]],
                 name: str = DEFAULT_ADAPTER, lens_frame: LensFrame | None = None) -> None:
        self.model, self.backend, self.injector = model, backend, injector
        self.targets = tuple(targets)
        self.schedules = dict(schedules)
        self.state_blind = bool(state_blind)
        self.lens_frame = lens_frame or LensFrame()
        self._adapters = {name: _Adapter(injector, self.schedules, self.state_blind, [], self.lens_frame)}
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
             name: str = DEFAULT_ADAPTER, lens: PSFBank | LensFrame | None = None,
             lens_conditioning: str | None = None) -> "ControlGS":
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
            lens: the optics' lens, for the lens module's condition: a
                :class:`~controlgs_adapter.downstream.optics.bank.PSFBank`, a
                :class:`~controlgs_adapter.lens_frame.LensFrame`, or None (a centred radius frame); a bank
                also sets the lens the foveation module measures eccentricities through (otherwise Cardboard).
            lens_conditioning: ``"radius"`` (``||p - axis||``), ``"xy"`` (the position in the lens's
                frame: a signed strength pair scaling the two halves of the N condition columns, so
                ``cond_dim`` must be even), or None: ``"radius"`` for a rotationally symmetric, centred
                lens, ``"xy"`` otherwise.

        Raises:
            NoMatchingBackendError, TargetError, InputValueError, ShapeError: before anything on the
            model has changed.
        """
        _check_name(name)
        chosen = select_backend(model, backend)
        schedules = check_modules(modules, cond_dim, endpoints)
        lens_frame = _lens_frame(lens, lens_conditioning, schedules, cond_dim)
        fov = schedules.get("foveation")
        if isinstance(fov, FoveationSchedule) and isinstance(lens, PSFBank) and lens is not PSFBank.default():
            schedules["foveation"] = fov.for_lens(VisualAngles.of_bank(lens))  # eccentricities through this lens
        if targets is None:
            targets = chosen.default_targets(model)
        if isinstance(targets, str) or not isinstance(targets, Sequence) or not targets:
            raise TargetError(f"targets must be a non-empty sequence of decoder paths, got {targets!r}")
        if len(set(targets)) != len(targets):
            raise TargetError(f"targets lists a decoder more than once: {list(targets)}")
        plans = [inspect_target(model, chosen, t) for t in targets]
        check_shared_layers(chosen, plans)
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
                  originals, grad_flags, name, lens_frame)
        for p, fc1 in zip(plans, fc1s):
            injector.attach(p.target.decoder, fc1)
            ATTACHED[fc1] = cgs
        return cgs

    def unwrap(self) -> Any:
        """Remove the hooks, put back the original (TorchScript) decoders and the backbone's
        ``requires_grad`` flags. Returns the model; this wrapper cannot be used afterwards."""
        self._check_live()
        for t in self.targets:
            ATTACHED.pop(get_attr_path(self.model, t.fc1), None)
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
                if isinstance(fc1, nn.Module) and fc1 in ATTACHED:
                    return ATTACHED[fc1]
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
        """Injection strength of every wrapped module for the given anchors: ``{module: [R]}``, the lens
        ``[R, 2]`` ``(lambda_x, lambda_y)`` in an ``"xy"`` :attr:`lens_frame`."""
        self._check_live()
        ids = self.anchor_ids(anchor_ids)
        out = {}
        for m, lam in self._strengths(state, camera, ids, self.modules, skip_zero=False).items():
            out[m] = lam if isinstance(lam, torch.Tensor) else torch.full(ids.shape, lam, dtype=self.injector.dtype,
                                                                          device=ids.device)
        return out

    def _strengths(self, state: RuntimeState, camera: Camera | None, ids: torch.Tensor, modules: Sequence[str],
                   *, skip_zero: bool) -> dict[str, torch.Tensor | float]:
        return module_strengths(self.schedules, state, camera, ids, modules, state_blind=self.state_blind,
                                anchor_positions=lambda: self.backend.anchor_positions(self.model),
                                placement=self.placement, dtype=self.injector.dtype, skip_zero=skip_zero,
                                lens_frame=self.lens_frame)

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
        backbone fingerprints, the lens frame, the foveation module's lens): what its file header records."""
        fov = self.schedules.get("foveation")
        angles = fov.lens_angles if isinstance(fov, FoveationSchedule) else None
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
            lens_frame=None if self.lens_frame.is_default else self.lens_frame.header(),
            visual_angles=None if angles is None else angles.header(),
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
        plan = plan_load(path, model, strict=strict)
        spec = plan.spec
        cgs = cls.wrap(model, modules=spec["modules"], cond_dim=spec["cond_dim"], backend=plan.backend,
                       targets=plan.targets, endpoints=spec_endpoints(spec), state_blind=spec["state_blind"],
                       name=name, lens=lens_frame_of(path, spec))
        _foveation_through(cgs.schedules, visual_angles_of(path, spec))
        load_into(cgs.injector, plan.tensors)
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
        plan = plan_load(path, self.model, strict=strict, wrapped=self)
        spec = plan.spec
        schedules = check_modules(spec["modules"], spec["cond_dim"], spec_endpoints(spec))
        _foveation_through(schedules, visual_angles_of(path, spec))
        widths = {t.decoder: t.out_features for t in self.targets if t.decoder in plan.targets}
        injector = ConditionInjector(self.num_anchors, spec["modules"], spec["cond_dim"], widths,
                                     device=self.injector.conditions.device, dtype=self.injector.dtype)
        load_into(injector, plan.tensors)
        self._adapters[name] = _Adapter(injector, schedules, bool(spec["state_blind"]), plan.skipped,
                                        lens_frame_of(path, spec))
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
        ``lens_frame``, ``trainable_parameters()`` and :meth:`save` follow it). Not inside a ``conditioned`` block."""
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
        self.lens_frame = new.lens_frame
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
        if not self.lens_frame.is_default:
            lines.append(f"  lens condition: {self.lens_frame!r}")
        lines.append(f"  trainable: {n_cond + n_proj:,} parameters (conditions {n_cond:,}, projections {n_proj:,})")
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (f"ControlGS(backend={self.backend.name!r}, anchors={self.num_anchors}, modules={list(self.modules)}, "
                f"cond_dim={self.injector.cond_dim}, targets={[t.fc1 for t in self.targets]}"
                + (", state_blind=True" if self.state_blind else "") + ("" if self._wrapped else ", unwrapped") + ")")


def _lens_frame(lens: PSFBank | LensFrame | None, mode: str | None, schedules: Mapping[str, StrengthSchedule],
                cond_dim: int) -> LensFrame:
    """The frame of the lens condition (a centred radius frame when no lens module is wrapped and
    ``mode`` is not ``"xy"``); InputValueError where ``"xy"`` cannot split the condition in two."""
    frame = LensFrame.of(lens, mode)
    if frame.mode == "radius" and frame.axis == (0.0, 0.0):
        return frame
    if not any(isinstance(s, LensSchedule) for s in schedules.values()):
        if mode == "xy":
            raise InputValueError(f"lens_conditioning='xy' needs the 'lens' module, got modules {list(schedules)}")
        return LensFrame()
    if frame.mode == "xy" and cond_dim % 2:
        raise InputValueError(f"cond_dim must be even for lens_conditioning 'xy' (lambda_x and lambda_y scale its two "
                              f"halves), got {cond_dim}")
    return frame


def _foveation_through(schedules: dict[str, StrengthSchedule], angles: VisualAngles | None) -> None:
    """Measure the foveation module's eccentricities (where wrapped) through the lens of ``angles`` (None: as is)."""
    fov = schedules.get("foveation")
    if isinstance(fov, FoveationSchedule) and angles is not None:
        schedules["foveation"] = fov.for_lens(angles)


def _check_name(name: str) -> None:
    if not isinstance(name, str) or not name:
        raise InputValueError(f"an adapter name must be a non-empty str, got {name!r}")
