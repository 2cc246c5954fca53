"""The paper's evaluation (Sec. 4.1-4.2): end-to-end quality on the run-time grid.

For every test view and every setting of the 4 x 5 grid (d in {1, 2, 4, 8} x rho in {0, .2, .4,
.6, .8}) each method's render goes through the same downstream pipeline E_s and its eye image
is compared with the ground truth (PSNR, SSIM, LDR-FLIP; LPIPS given local weights; ColorVideoVDP
at the on-axis pixels per degree of the simulated lens, when installed). Methods:

- ``no_ss``: the backbone rendered directly at the display size round(S/d) (no supersampling);
- ``ss``: the SS-backbone: rendered at S, area-pooled to S/d by the pipeline's resampling;
- ``controlgs`` (and ablations): rendered at S through an adapter conditioned on the state;
- ``ideal``: the ideal-render bound, the ground truth itself through E_s (E_s(GT) vs GT): what the
  pipeline costs a perfect render; an adapter above it pre-compensates beyond it.

Eye images are clamped to [0, 1] (what a display-encoded image can hold) before the metrics.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from tqdm.auto import tqdm

from .controlgs import ControlGS
from .downstream.oled import oled_emission
from .downstream.optics.bank import PSFBank
from .downstream.optics.lenses import LensSpec, effects_for_lens
from .downstream.optics.stage import set_optics_mode
from .downstream.optics.visual_angles import VisualAngles
from .downstream.pipeline import Pipeline
from .downstream.placement import Placement
from .errors import InputValueError
from .metrics import CVVDP_DISPLAY, ColorVideoVDP, cvvdp_missing, optional_metrics, psnr, ssim
from .state import Camera, RuntimeState
from controlgs_adapter.rendering.protocol import Renderer, as_renderer, model_device, render_view
from .training import DEFAULT_EFFECTS, Views

__all__ = ["GRID_DOWNSAMPLE", "GRID_POWER_SAVING", "BASELINES", "IDEAL", "GridResult", "evaluate_grid", "make_pipeline",
           "side_by_side", "condition_response", "scores", "lens_ppd", "pipeline_lens"]

GRID_DOWNSAMPLE: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
GRID_POWER_SAVING: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6, 0.8)
#: the two backbone baselines, always evaluated
BASELINES: tuple[str, ...] = ("no_ss", "ss")
#: the ideal-render bound's method name: the ground truth through the pipeline
IDEAL = "ideal"


@dataclass(eq=False)
class GridResult:
    """Metrics of every method on the grid.

    Attributes:
        downsample, power_saving: the grid axes.
        per_view: ``{method: {metric: Tensor[D, P, V]}}`` (float64).
        optics_mode: the optics operator used.
        info: JSON-able facts about the run (test views, their sizes, ...), kept in ``results.json``.
    """

    downsample: tuple[float, ...]
    power_saving: tuple[float, ...]
    per_view: dict[str, dict[str, torch.Tensor]] = field(default_factory=dict)
    optics_mode: str = "fast"
    info: dict[str, Any] = field(default_factory=dict)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GridResult):
            return NotImplemented
        return (self.downsample == other.downsample and self.power_saving == other.power_saving
                and self.optics_mode == other.optics_mode and self.info == other.info
                and {m: list(v) for m, v in self.per_view.items()} == {m: list(v) for m, v in other.per_view.items()}
                and all(torch.equal(v, other.per_view[m][k]) for m, mv in self.per_view.items() for k, v in mv.items()))

    @property
    def methods(self) -> list[str]:
        return list(self.per_view)

    @property
    def metrics(self) -> list[str]:
        return list(next(iter(self.per_view.values()))) if self.per_view else []

    def grid(self, method: str, metric: str) -> torch.Tensor:
        """``[D, P]`` mean over the test views."""
        return self.per_view[method][metric].mean(dim=-1)

    def mean(self, method: str, metric: str) -> float:
        """Mean over views and the whole grid (the paper's Tbl. 1 entry)."""
        return float(self.per_view[method][metric].mean())

    def to_json(self) -> dict[str, Any]:
        """Every number: per-view values, grid means and overall means."""
        return {
            "info": dict(self.info),
            "downsample": list(self.downsample),
            "power_saving": list(self.power_saving),
            "optics_mode": self.optics_mode,
            "methods": {
                m: {k: {"mean": self.mean(m, k), "grid": self.grid(m, k).tolist(), "per_view": v.tolist()}
                    for k, v in metrics.items()}
                for m, metrics in self.per_view.items()
            },
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "GridResult":
        """Inverse of :meth:`to_json` (also reads a report's ``results.json``): exact, the per-view
        values being stored as JSON floats (``repr`` round trip)."""
        try:
            per_view = {m: {k: torch.tensor(v["per_view"], dtype=torch.float64) for k, v in metrics.items()}
                        for m, metrics in data["methods"].items()}
            result = cls(tuple(float(d) for d in data["downsample"]), tuple(float(p) for p in data["power_saving"]),
                         per_view, str(data.get("optics_mode", "fast")), dict(data.get("info", {})))
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise InputValueError(f"not a GridResult JSON ({type(e).__name__}: {e})") from None
        shape = (len(result.downsample), len(result.power_saving))
        bad = [f"{m}.{k}" for m, mv in per_view.items() for k, v in mv.items() if v.dim() != 3 or tuple(v.shape[:2]) != shape]
        if bad:
            raise InputValueError(f"GridResult JSON: per_view of {bad} is not [{shape[0]}, {shape[1]}, V]")
        return result


def make_pipeline(effects: Mapping[str, Any] | None = None, optics_mode: str = "fast", lens: LensSpec = None) -> Pipeline:
    """The evaluation pipeline E_s from ``effects`` (default :data:`DEFAULT_EFFECTS`) simulating ``lens``
    (:func:`~controlgs_adapter.downstream.optics.lenses.effects_for_lens`; default the shipped Cardboard lens)
    with the optics operator ``optics_mode``, in eval mode."""
    pipeline = Pipeline.from_config(effects_for_lens(DEFAULT_EFFECTS if effects is None else effects, lens))
    set_optics_mode(pipeline, optics_mode)
    return pipeline.eval()


def lens_ppd(bank: PSFBank, height: int, width: int, placement: Placement = "fit") -> float:
    """On-axis pixels per degree of an ``height x width`` image seen through the lens of ``bank``
    (:meth:`VisualAngles.axis_pixels_per_degree <controlgs_adapter.downstream.optics.visual_angles.VisualAngles.axis_pixels_per_degree>`:
    a display pixel of pitch p mm centred on the axis subtends ``2 atan(M p / 2 D)``, M the reference
    magnification, D the virtual image distance; a distortion profile's from its field angles). The shipped
    Cardboard bank at 1024 x 1024: 34.13."""
    return VisualAngles.of_bank(bank).axis_pixels_per_degree(height, width, placement)


def pipeline_lens(pipeline: Pipeline) -> tuple[PSFBank, Placement]:
    """The lens a pipeline simulates: its ``optics`` stage's PSF bank and placement, else the shipped
    Cardboard bank (:meth:`PSFBank.default`) with ``"fit"``."""
    if "optics" in pipeline:
        optics = pipeline["optics"]
        bank = getattr(optics, "bank", None)
        if isinstance(bank, PSFBank):
            return bank, "stretch" if getattr(optics, "placement", "fit") == "stretch" else "fit"
    return PSFBank.default(), "fit"


def _cvvdp_ppd(pipeline: Pipeline) -> tuple[Callable[[int, int], float] | None, dict[str, Any]]:
    """ColorVideoVDP's pixels per degree for ``pipeline``'s lens, ``(H, W) -> ppd``, and what the report says
    of it (``{"skipped": why}`` when it cannot run)."""
    bank, placement = pipeline_lens(pipeline)
    try:
        lens_ppd(bank, 2, 2, placement)
    except InputValueError as e:
        return None, {"skipped": str(e)}
    missing = cvvdp_missing()
    if missing is not None:
        return None, {"skipped": missing}
    lens = bank.meta.get("prescription", {}).get("name", "the PSF bank's lens")
    return (lambda h, w: lens_ppd(bank, h, w, placement)), {"lens": lens, "placement": placement, "display": CVVDP_DISPLAY}


def scores(eye: torch.Tensor, gt: torch.Tensor, extra: Mapping[str, Any]) -> dict[str, float]:
    """The grid's metrics of one eye image ``[3, H, W]`` (clamped to [0, 1], as a display holds it) vs
    the ground truth: PSNR, SSIM and each ``extra`` ``{name: fn(eye, gt)}``. An eye image at the display
    size (the ``oled`` stage off) is scored as the display's pixels shown as boxes at the ground truth's size."""
    if eye.shape[-2:] != gt.shape[-2:]:
        eye = oled_emission(eye, (gt.shape[-2], gt.shape[-1]))
    e, g = eye.detach().clamp(0.0, 1.0).double(), gt.double()
    out = {"psnr": float(psnr(e, g)), "ssim": float(ssim(e, g))}
    for name, fn in extra.items():
        out[name] = fn(e, g)
    return out


@torch.no_grad()
def evaluate_grid(model: Any, views: Views, adapters: Mapping[str, str | Path], *,
                  effects: Mapping[str, Any] | None = None, downsample: Sequence[float] = GRID_DOWNSAMPLE, power_saving: Sequence[float] = GRID_POWER_SAVING,
                  optics_mode: str = "fast", baselines: Sequence[str] = BASELINES,
                  extra_metrics: bool = True, ideal: bool = True, lpips: Any = None,
                  progress: bool = True, renderer: Renderer | Any = None, lens: LensSpec = None) -> GridResult:
    """Evaluate the baselines and every adapter file in ``adapters`` (``{method name: path}``,
    each saved by :meth:`ControlGS.save` for ``model``) on the test ``views`` (a
    :class:`~controlgs_adapter.training.Views` dataset: ``(camera, image [3, H, W])`` per view, any
    size; its ``background`` is the renders'). ``model`` must not be wrapped; each adapter is loaded
    onto it in turn and removed afterwards. Everything runs on the model's device. ``renderer``:
    how views are rendered (:mod:`controlgs_adapter.rendering.protocol`; default the model's own). ``lens``: the
    headset lens the pipeline simulates (:func:`make_pipeline`; default the shipped Cardboard lens).

    The renders that do not depend on the state are made once per view (``ss``) or once per d
    (``no_ss``); the pipeline runs for every (method, view, d, rho). ``result.info`` holds the
    number of views and their sizes. ``ideal``: also score the ground truth through the pipeline
    (method :data:`IDEAL`, once per view and state). ``extra_metrics``: FLIP, ColorVideoVDP when
    installed (at :func:`lens_ppd` of :func:`pipeline_lens`; ``info["cvvdp"]`` holds the ppd of each
    image size, or why it was skipped), and LPIPS with ``lpips`` (an :class:`~controlgs_adapter.perceptual.LPIPS`).
    """
    if isinstance(views, torch.Tensor) or not isinstance(views, Views) or not len(views):
        raise InputValueError("views must be a non-empty dataset of (camera, image) with a background "
                              f"(e.g. SceneData.views('test')), got {type(views).__name__}")
    unknown = [b for b in baselines if b not in BASELINES]
    if unknown:
        raise InputValueError(f"baselines must be among {BASELINES}, got {unknown}")
    clash = [a for a in adapters if a in (*BASELINES, IDEAL)]
    if clash:
        raise InputValueError(f"adapter names {clash} clash with the baselines {(*BASELINES, IDEAL)}")
    renderer = as_renderer(renderer, model)
    device = model_device(model)
    pipeline = make_pipeline(effects, optics_mode, lens).to(device)
    bg = getattr(views, "background", None)
    background = None if bg is None else bg.to(device)
    ppd, cvvdp_info = _cvvdp_ppd(pipeline) if extra_metrics else (None, {})
    extra = optional_metrics(None if lpips is None else lpips.to(device), ppd=ppd) if extra_metrics else {}
    names = list(baselines) + ([IDEAL] if ideal else []) + list(adapters)
    nd, npow, nv = len(downsample), len(power_saving), len(views)
    metric_names = ["psnr", "ssim", *extra]
    result = {m: {k: torch.zeros(nd, npow, nv, dtype=torch.float64) for k in metric_names} for m in names}
    bar = tqdm(total=nv * nd * npow * len(names), desc="evaluating grid", disable=not progress, dynamic_ncols=True)

    def score(name: str, i: int, j: int, v: int, rendered: torch.Tensor, state: RuntimeState, gt: torch.Tensor) -> None:
        eye = pipeline(rendered, state, reference=gt)
        for k, value in scores(eye, gt, extra).items():
            result[name][k][i, j, v] = value
        bar.update(1)

    def view(v: int) -> tuple[Camera, torch.Tensor]:
        cam, gt = views[v]
        return cam, gt.to(device, non_blocking=True)

    for v in range(nv):
        cam, gt = view(v)
        renders: dict[str, torch.Tensor] = {}  # baseline -> its render: "ss" once per view, "no_ss" once per d
        if "ss" in baselines:
            renders["ss"] = render_view(None, model, cam, None, background, renderer=renderer)
        for i, d in enumerate(downsample):
            if "no_ss" in baselines:
                renders["no_ss"] = render_view(None, model, cam.scaled(d), None, background, renderer=renderer)
            for j, rho in enumerate(power_saving):
                state = RuntimeState(downsample=d, power_saving=rho)
                for name in baselines:
                    score(name, i, j, v, renders[name], state, gt)
                if ideal:
                    score(IDEAL, i, j, v, gt, state, gt)
    for name, path in adapters.items():
        cgs = ControlGS.load(path, model)
        try:
            for v in range(nv):
                cam, gt = view(v)
                for i, d in enumerate(downsample):
                    for j, rho in enumerate(power_saving):
                        state = RuntimeState(downsample=d, power_saving=rho)
                        score(name, i, j, v, render_view(cgs, model, cam, state, background, renderer=renderer), state, gt)
        finally:
            cgs.unwrap()
    bar.close()
    describe = getattr(views, "describe", None)
    info = dict(describe()) if callable(describe) else {"views": nv, "sizes": sorted({f"{c.width}x{c.height}" for c, _ in
                                                                                       (views[v] for v in range(nv))})}
    info = {"test_" + k: v for k, v in info.items()}
    if extra_metrics:
        cvvdp = extra.get("cvvdp")
        info["cvvdp"] = {**cvvdp_info, "ppd": dict(cvvdp.ppd_used)} if isinstance(cvvdp, ColorVideoVDP) else cvvdp_info
    return GridResult(tuple(float(d) for d in downsample), tuple(float(p) for p in power_saving), result, optics_mode, info)


@torch.no_grad()
def side_by_side(model: Any, adapter: str | Path, camera: Camera, gt: torch.Tensor, *,
                 settings: Sequence[tuple[float, float]] = ((1.0, 0.0), (8.0, 0.8)), effects: Mapping[str, Any] | None = None,
                 background: torch.Tensor | None = None, optics_mode: str = "fast",
                 renderer: Renderer | Any = None, lens: LensSpec = None) -> dict[str, Any]:
    """Rendered and eye images of no-SS, SS-backbone and ControlGS (adapter file) for one view at
    ``settings`` ``[(d, rho)]`` (paper Fig. 1): ``{"gt", "settings", "rows": {method: [(rendered,
    eye, psnr, ssim)]}}``; ``lens`` as in :func:`make_pipeline`."""
    renderer = as_renderer(renderer, model)
    pipeline = make_pipeline(effects, optics_mode, lens).to(model_device(model))
    rows: dict[str, list[tuple[torch.Tensor, torch.Tensor, float, float]]] = {"no_ss": [], "ss": [], "controlgs": []}
    full = render_view(None, model, camera, None, background, renderer=renderer)

    def add(name: str, rendered: torch.Tensor, state: RuntimeState) -> None:
        eye = pipeline(rendered, state, reference=gt).clamp(0.0, 1.0)
        sc = scores(eye, gt, {})
        rows[name].append((rendered, eye, sc["psnr"], sc["ssim"]))

    for d, rho in settings:
        state = RuntimeState(downsample=d, power_saving=rho)
        add("no_ss", render_view(None, model, camera.scaled(d), None, background, renderer=renderer), state)
        add("ss", full, state)
    cgs = ControlGS.load(adapter, model)
    try:
        for d, rho in settings:
            state = RuntimeState(downsample=d, power_saving=rho)
            add("controlgs", render_view(cgs, model, camera, state, background, renderer=renderer), state)
    finally:
        cgs.unwrap()
    return {"gt": gt, "settings": [(float(d), float(r)) for d, r in settings], "rows": rows}


@torch.no_grad()
def condition_response(model: Any, adapter: str | Path, camera: Camera, *,
                       background: torch.Tensor | None = None,
                       renderer: Renderer | Any = None) -> dict[str, list[tuple[str, torch.Tensor]]]:
    """Raw renders before the pipeline while one condition varies and the others are off (paper
    Fig. 8): resample over d in {1, 2, 4, 8}, display over rho in {0, .2, .4, .6, .8}, lens off /
    on / ten times the difference. Only the adapter's modules appear."""
    renderer = as_renderer(renderer, model)
    cgs = ControlGS.load(adapter, model)
    strips: dict[str, list[tuple[str, torch.Tensor]]] = {}
    try:
        if "resample" in cgs.modules:
            strips["resample"] = [(f"d={d:g}", render_view(cgs, model, camera, RuntimeState(downsample=d), background,
                                                           modules=("resample",), renderer=renderer)) for d in GRID_DOWNSAMPLE]
        if "display" in cgs.modules:
            strips["display"] = [(f"ρ={r:.0%}", render_view(cgs, model, camera, RuntimeState(power_saving=r), background,
                                                            modules=("display",), renderer=renderer)) for r in GRID_POWER_SAVING]
        if "lens" in cgs.modules:
            off = render_view(None, model, camera, None, background, renderer=renderer)
            on = render_view(cgs, model, camera, RuntimeState(), background, modules=("lens",), renderer=renderer)
            strips["lens"] = [("off", off), ("on", on), ("|on - off| x 10", ((on - off).abs() * 10.0).clamp(0, 1))]
    finally:
        cgs.unwrap()
    return strips
