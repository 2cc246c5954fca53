"""The end-to-end XR operator E_s of paper Eq. 9 (Sec. 3, "Problem Formulation"), composed from stages.

    I_eye = O_phys(D_phys(P_disp(P_res(P_lens(I; s_lens); s_res); s_disp)))

Built-in stages, their default order and colour domain (every built-in works in linear light,
so the pipeline decodes the sRGB render once before the first stage that runs and encodes the
result once at the end):

    order  name       paper            resolution           domain
      5    foveation  (gaze, degrees)  keep                 linear   (identity without a gaze)
     10    lens       P_lens           keep (S)             linear
     20    resample   P_res            S -> round(S/d)      linear
     30    display    P_disp           keep (S/d)           linear
     40    oled       D_phys           S/d -> S             linear
     50    optics     O_phys           keep (S)             linear   (plug-in "optics", optional)

Stages before the first physical stage (``oled`` or ``optics``) are post-processing; their
output is the "post" intermediate. A stage that is the identity at the current state is skipped
without any work (no call, no domain conversion). A third-party stage sets ``after``/``before``
to the name of a stage to be inserted right after/before it.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping, Sequence, cast

import torch
from torch import nn

from controlgs_adapter import plugins
from controlgs_adapter.checks import check_finite, check_image, check_same_device
from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.state import RuntimeState

from .color import convert_domain
from .lens import LensPrewarp
from .optics.lenses import LENS_FOR_OPTICS
from .stage import Domain, Stage, StageContext

__all__ = ["Pipeline", "PHYSICAL_STAGES"]

#: Names of the stages that model the physical display-optics path (paper Eq. 5); everything
#: ordered before the first of them is post-processing.
PHYSICAL_STAGES: tuple[str, ...] = ("oled", "optics")


def _registered_stages() -> dict[str, type[Stage]]:
    return {name: info.obj for name, info in plugins.stages().items()}


def _resolve_order(stages: Sequence[Stage]) -> list[Stage]:
    """Sort by ``order`` (then name); then insert the stages with ``after``/``before`` next to
    their anchor (in their own ``(order, name)`` order). An anchor that is not in the pipeline
    is placed where its registered ``order`` would put it."""
    by_name = {s.name: s for s in stages}
    anchors: dict[str, str] = {}  # stage name -> the name it goes after/before
    for s in stages:
        anchor = s.after or s.before
        if anchor:
            anchors[s.name] = anchor
    plain = sorted((s for s in stages if s.name not in anchors), key=lambda s: (s.order, s.name))
    pending = sorted((s for s in stages if s.name in anchors), key=lambda s: (s.order, s.name))
    result: list[Stage] = list(plain)
    following: dict[str, list[Stage]] = {}  # stages inserted right after an anchor
    visiting: set[str] = set()

    def anchor_order(name: str, who: Stage) -> float:
        registered = _registered_stages()
        if name not in registered:
            raise InputValueError(
                f"stage {who.name!r} wants to go next to {name!r}, which is neither in the pipeline nor registered "
                f"(registered: {sorted(registered)})"
            )
        return float(registered[name].order)

    def insert(s: Stage) -> None:
        if s in result:
            return
        if s.name in visiting:
            raise InputValueError(f"stage placement constraints form a cycle through {s.name!r}")
        visiting.add(s.name)
        anchor = anchors[s.name]
        if anchor in by_name and by_name[anchor] not in result:
            insert(by_name[anchor])
        if anchor in by_name:
            if s.after:
                chain = [by_name[anchor], *following.get(anchor, [])]
                pos = result.index(chain[-1]) + 1
                following.setdefault(anchor, []).append(s)
            else:
                pos = result.index(by_name[anchor])
        else:
            a = anchor_order(anchor, s)
            plain_before = [i for i, t in enumerate(result) if t in plain and (t.order <= a if s.after else t.order < a)]
            pos = plain_before[-1] + 1 if plain_before else 0
        result.insert(pos, s)
        if s.after and s.before and s.before in by_name and by_name[s.before] in result:
            if result.index(by_name[s.before]) < pos:
                raise InputValueError(f"stage {s.name!r}: after={s.after!r} and before={s.before!r} contradict")
        visiting.discard(s.name)

    for s in pending:
        insert(s)
    return result


class Pipeline(nn.Module):
    """The downstream operator E_s: renderer output (sRGB, native S) -> eye-space sRGB image.

    Args:
        stages: stage instances (unique names); their order is resolved from ``order`` and
            ``after``/``before``, not from the sequence.
    """

    def __init__(self, stages: Sequence[Stage] = ()) -> None:
        super().__init__()
        names: list[str] = []
        for i, s in enumerate(stages):
            if not isinstance(s, Stage):
                raise InputValueError(f"stages[{i}] must be a Stage instance, got {type(s).__name__}")
            if not s.name:
                raise InputValueError(f"stages[{i}] ({type(s).__name__}) has no name")
            if s.domain not in ("srgb", "linear"):
                raise InputValueError(f"stage {s.name!r} has domain {s.domain!r}; expected 'srgb' or 'linear'")
            names.append(s.name)
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputValueError(f"stage names must be unique, got duplicates {dup}")
        self.stages = nn.ModuleList(_resolve_order(list(stages)))

    @classmethod
    def from_config(cls, effects: Mapping[str, Any] | Iterable[str]) -> "Pipeline":
        """Build the pipeline a scene calls for.

        Args:
            effects: stage names -> spec, where spec is False/None (absent), True (defaults), a dict
                of constructor keyword arguments (e.g. ``{"resample": {"max_factor": 8}}``,
                ``{"lens": {"coefficients": [[0.1], [0.1], [0.1]]}}``) or a ready Stage instance;
                or an iterable of names (all with defaults). Names are those of registered stages
                (:func:`controlgs_adapter.plugins.stages`), e.g. ``lens``, ``resample``,
                ``display`` (power saving), ``foveation``, ``optics`` (needs the optics plug-in).
                The physical display ``oled`` is always included unless set to False. With
                ``"lens": True`` and an optics stage, the lens pre-warp compensates that optics
                (:meth:`LensPrewarp.for_optics`): the map and gain fitted through it, per display
                primary, shipped for the Cardboard bank (:func:`.prewarp_fit.fit_bank_prewarp`),
                following the optics' mode; ``"lens": {"lut": path}`` reads a LUT fitted for another
                bank, ``{"source": "chief_rays"}`` uses the bank's chief rays, ``{"basis": "rgb"}``
                warps the RGB channels (the paper's per-channel warp). Without optics the lens is
                the analytic Cardboard radial map.
        """
        spec: dict[str, Any] = dict(effects) if isinstance(effects, Mapping) else {n: True for n in effects}
        spec.setdefault("oled", True)
        registered = _registered_stages()
        stages: list[Stage] = []
        # the default lens correction compensates the configured optics (fitted through it)
        lens_spec = spec.get("lens")
        lens_from_optics = spec.get("optics") not in (None, False) and (
            lens_spec is True or (isinstance(lens_spec, Mapping) and set(lens_spec) <= LENS_FOR_OPTICS))
        for name, value in sorted(spec.items(), key=lambda kv: kv[0] == "lens"):  # lens last: it may need the optics
            if name == "lens" and lens_from_optics:
                optics = next(s for s in stages if s.name == "optics")
                bank = getattr(optics, "bank", None)
                if bank is not None and hasattr(bank, "chief"):
                    options = dict(value) if isinstance(value, Mapping) else {}  # keys within LENS_FOR_OPTICS
                    stages.append(LensPrewarp.for_optics(optics, **options))
                    continue
            if value is None or value is False:
                continue
            if isinstance(value, Stage):
                if value.name != name:
                    raise InputValueError(f"effects[{name!r}] is a stage named {value.name!r}")
                stages.append(value)
                continue
            if name not in registered:
                raise InputValueError(
                    f"effects names unknown stage {name!r}; registered stages: {sorted(registered)}"
                    + (" (the optics stage comes from the optics plug-in)" if name == "optics" else "")
                )
            if value is True:
                stages.append(registered[name]())
            elif isinstance(value, Mapping):
                try:
                    stages.append(registered[name](**value))
                except TypeError as e:  # an unknown or missing option
                    raise InputValueError(f"effects[{name!r}]: {e}") from None
            else:
                raise InputValueError(f"effects[{name!r}] must be a bool, a dict of options or a Stage, got {type(value).__name__}")
        return cls(stages)

    def _ordered(self) -> list[Stage]:
        """The stages in execution order."""
        # nn.ModuleList's stubs type its items as Module; __init__ puts only Stage instances in it
        return cast("list[Stage]", list(self.stages))

    @property
    def names(self) -> list[str]:
        """Stage names in execution order."""
        return [s.name for s in self._ordered()]

    def __getitem__(self, name: str) -> Stage:
        for s in self._ordered():
            if s.name == name:
                return s
        raise KeyError(f"no stage {name!r} in this pipeline (stages: {self.names})")

    def __contains__(self, name: object) -> bool:
        return any(s.name == name for s in self._ordered())

    def active(self, state: RuntimeState, reference: torch.Tensor | None = None,
               native_size: tuple[int, int] | None = None) -> list[str]:
        """Names of the stages that run at ``state`` for a call with (or without) a ``reference``
        (the others are the identity there; e.g. ``display`` runs at rho = 0 with a reference)."""
        size = native_size or ((int(reference.shape[-2]), int(reference.shape[-1])) if reference is not None else (0, 0))
        ctx = StageContext(native_size=size, reference=reference)
        return [s.name for s in self._ordered() if not s.is_identity(state, ctx)]

    @staticmethod
    def _displayed_reference(ran: Sequence[Stage], state: RuntimeState, reference: torch.Tensor,
                             native_size: tuple[int, int], domain: Domain) -> torch.Tensor:
        """The ground truth ``reference`` (sRGB, at ``native_size``) through the stages that ran so
        far (no gradient, nothing recorded), in ``domain``: the frame the display would show for it
        (the display's P_ref)."""
        quiet = StageContext(native_size=native_size, reference=reference)
        with torch.no_grad():
            r = reference.detach()
            dom: Domain = "srgb"
            for stage in ran:
                r = stage(convert_domain(r, dom, stage.domain), state, quiet)
                dom = stage.domain
            return convert_domain(r, dom, domain)

    def forward(
        self,
        image: torch.Tensor,
        state: RuntimeState | None = None,
        reference: torch.Tensor | None = None,
        native_size: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        """Run E_s.

        Args:
            image: ``[..., 3, H, W]`` rendered image, sRGB-encoded, at the native size S (or already
                at the display size round(S/d) for the no-supersampling baseline).
            state: the run-time state (downsample d, power saving rho, gaze); None: the default.
            reference: ``[..., 3, S_h, S_w]`` ground truth (sRGB) at S; gives the display's P_ref
                and the native size.
            native_size: ``(S_h, S_w)``; default: the reference's size, else the image's.
        Returns:
            ``[..., 3, S_h, S_w]`` eye-space sRGB image.
        """
        return self._run(image, state, reference, native_size, record=False)[0]

    def run_recorded(
        self,
        image: torch.Tensor,
        state: RuntimeState | None = None,
        reference: torch.Tensor | None = None,
        native_size: tuple[int, int] | None = None,
    ) -> tuple[torch.Tensor, dict[str, Any]]:
        """:meth:`forward` that also returns the intermediates: ``(eye, intermediates)`` with the
        sRGB images ``rendered``, ``post`` (after post-processing, display size), ``displayed``
        (emitted by the display, at S), ``eye`` (detached copies), the list ``stages_run`` and
        ``diagnostics`` (what stages recorded, e.g. ``display.clipped_fraction``)."""
        eye, intermediates = self._run(image, state, reference, native_size, record=True)
        assert intermediates is not None
        return eye, intermediates

    def _run(self, image: torch.Tensor, state: RuntimeState | None, reference: torch.Tensor | None,
             native_size: tuple[int, int] | None, record: bool) -> tuple[torch.Tensor, dict[str, Any] | None]:
        if state is None:
            state = RuntimeState()
        check_image("image", image)
        if not isinstance(state, RuntimeState):
            raise InputValueError(f"state must be a RuntimeState, got {type(state).__name__}")
        if reference is not None:
            check_image("reference", reference, finite=False)
            check_same_device(image=image, reference=reference)
            check_finite("reference", reference)
        native: tuple[int, int]
        if native_size is None:
            src = reference if reference is not None else image
            native = (int(src.shape[-2]), int(src.shape[-1]))
        else:
            native = (int(native_size[0]), int(native_size[1]))
            if reference is not None and tuple(reference.shape[-2:]) != native:
                raise ShapeError(f"reference must be at native_size {native}, got {list(reference.shape)}")
        if image.shape[-2] > native[0] or image.shape[-1] > native[1]:
            raise ShapeError(f"image {list(image.shape)} is larger than the native size {native}")
        ctx = StageContext(native_size=native, reference=reference, record={} if record else None)
        x = image
        domain: Domain = "srgb"
        post_image: torch.Tensor | None = None
        displayed: torch.Tensor | None = None
        ran: list[str] = []
        ran_stages: list[Stage] = []
        for stage in self._ordered():
            if record and post_image is None and stage.name in PHYSICAL_STAGES:
                post_image = convert_domain(x, domain, "srgb").detach()
            if stage.is_identity(state, ctx):
                continue
            if reference is not None and getattr(stage, "wants_displayed_reference", False):
                ctx.displayed_reference = self._displayed_reference(ran_stages, state, reference, native, stage.domain)
            x = stage(convert_domain(x, domain, stage.domain), state, ctx)
            domain = stage.domain
            ran.append(stage.name)
            ran_stages.append(stage)
            if record and stage.name == "oled":
                displayed = convert_domain(x, domain, "srgb").detach()
        eye = convert_domain(x, domain, "srgb")
        if not record:
            return eye, None
        post = eye.detach() if post_image is None else post_image
        intermediates = {
            "rendered": image.detach(), "post": post, "displayed": post if displayed is None else displayed,
            "eye": eye.detach(), "stages_run": ran, "diagnostics": ctx.record,
        }
        return eye, intermediates
