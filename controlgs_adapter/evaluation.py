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

The foveation axis (:class:`FoveationAxis`; only when the effects include ``foveation``): the grid itself runs
without a gaze (the stage is then the identity); then at each gaze of ``gazes`` (default
:data:`FOVEATION_GAZES`) and each (d, rho) of a subset of the grid (:data:`FOVEATION_SETTINGS`, three settings
instead of twenty to keep the CPU cost at 3 x 3 evaluations per method and view) the SS-backbone, the ideal render
and the adapters (the ablations other than ``wo_foveation`` left out) go through the pipeline with the gaze in the
state, scored on the whole image and per eccentricity band (:data:`BANDS`, visual degrees through the lens from
the gaze): PSNR from the band's MSE, SSIM as the SSIM map averaged over the windows centred in the band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
from tqdm.auto import tqdm

from .controlgs import ControlGS
from .ablations import ABLATIONS
from .downstream.foveation import Foveation
from .downstream.oled import oled_emission
from .downstream.optics.bank import PSFBank
from .downstream.optics.lenses import LensSpec, effects_for_lens
from .downstream.optics.stage import set_optics_mode
from .downstream.optics.visual_angles import VisualAngles, eccentricity
from .downstream.pipeline import Pipeline
from .downstream.placement import Placement
from .errors import InputValueError
from .metrics import CVVDP_DISPLAY, ColorVideoVDP, cvvdp_missing, optional_metrics, psnr, ssim, ssim_map
from .state import Camera, RuntimeState
from controlgs_adapter.rendering.protocol import Renderer, as_renderer, model_device, render_view
from .training import DEFAULT_EFFECTS, Views

__all__ = ["GRID_DOWNSAMPLE", "GRID_POWER_SAVING", "BASELINES", "IDEAL", "GridResult", "evaluate_grid", "make_pipeline",
           "side_by_side", "condition_response", "scores", "lens_ppd", "pipeline_lens", "BANDS", "FOVEATION_GAZES",
           "FOVEATION_SETTINGS", "FoveationAxis", "band_masks", "band_scores"]

GRID_DOWNSAMPLE: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
GRID_POWER_SAVING: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6, 0.8)
#: the two backbone baselines, always evaluated
BASELINES: tuple[str, ...] = ("no_ss", "ss")
#: the ideal-render bound's method name: the ground truth through the pipeline
IDEAL = "ideal"
#: eccentricity bands ``(name, low, high)`` in visual degrees from the gaze, ``low <= e < high``: the foveal
#: plateau and its margin (< 5), the parafovea (5-15), the periphery (>= 15) (Guenter et al. 2012; Spjut et al. 2019)
BANDS: tuple[tuple[str, float, float], ...] = (("foveal", 0.0, 5.0), ("parafoveal", 5.0, 15.0),
                                               ("periphery", 15.0, math.inf))
#: the foveation axis's gazes ``(azimuth, elevation)`` in degrees: the lens axis, 10 deg along +x, and about
#: 19.4 deg off axis along the +x +y diagonal (the shipped Cardboard lens's field ends at 15 deg along +x)
FOVEATION_GAZES: tuple[tuple[float, float], ...] = ((0.0, 0.0), (10.0, 0.0), (14.0, 14.0))
#: the (d, rho) settings evaluated at each gaze: the grid's two corners and a middle setting
FOVEATION_SETTINGS: tuple[tuple[float, float], ...] = ((1.0, 0.0), (2.0, 0.4), (8.0, 0.8))


def _nan_json(values: Any) -> Any:
    """Nested lists of floats with NaN (a band without pixels) as None, for JSON."""
    if isinstance(values, list):
        return [_nan_json(v) for v in values]
    return None if isinstance(values, float) and math.isnan(values) else values


@dataclass(eq=False)
class FoveationAxis:
    """Scores at each gaze (the grid's foveation axis).

    Attributes:
        gazes: ``(azimuth, elevation)`` degrees from the lens axis.
        settings: the ``(d, rho)`` evaluated at each gaze.
        model: the foveation stage's model (``omega0``, ``slope``, ``max_scale``).
        bands: :data:`BANDS` used.
        per_view: ``{method: {metric: Tensor[G, S, V]}}`` (float64), metrics ``psnr``, ``ssim`` and
            ``<metric>_<band>`` per band; NaN where a band holds no pixel of the view.
    """

    gazes: tuple[tuple[float, float], ...]
    settings: tuple[tuple[float, float], ...]
    model: dict[str, float | None]
    bands: tuple[tuple[str, float, float], ...] = BANDS
    per_view: dict[str, dict[str, torch.Tensor]] = field(default_factory=dict)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FoveationAxis):
            return NotImplemented
        return (self.gazes == other.gazes and self.settings == other.settings and self.model == other.model
                and self.bands == other.bands
                and {m: list(v) for m, v in self.per_view.items()} == {m: list(v) for m, v in other.per_view.items()}
                and all(torch.equal(v.nan_to_num(-1.0), other.per_view[m][k].nan_to_num(-1.0))
                        and torch.equal(v.isnan(), other.per_view[m][k].isnan())
                        for m, mv in self.per_view.items() for k, v in mv.items()))

    def mean(self, method: str, metric: str, gaze: int) -> float | None:
        """Mean over the settings and views of gaze index ``gaze``, the views without the band left out;
        None when no view has it."""
        v = self.per_view[method][metric][gaze]
        v = v[~v.isnan()]
        return float(v.mean()) if v.numel() else None

    def to_json(self) -> dict[str, Any]:
        """Every number, NaN as null."""
        return {"gazes": [list(g) for g in self.gazes], "settings": [list(s) for s in self.settings],
                "model": dict(self.model), "bands": [[n, lo, None if math.isinf(hi) else hi] for n, lo, hi in self.bands],
                "methods": {m: {k: {"mean": [self.mean(m, k, g) for g in range(len(self.gazes))],
                                    "per_view": _nan_json(v.tolist())} for k, v in mv.items()}
                            for m, mv in self.per_view.items()}}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "FoveationAxis":
        """Inverse of :meth:`to_json` (InputValueError naming what is wrong)."""
        try:
            per_view = {m: {k: torch.tensor(_nan_back(v["per_view"]), dtype=torch.float64) for k, v in mv.items()}
                        for m, mv in data["methods"].items()}
            axis = cls(tuple((float(a), float(e)) for a, e in data["gazes"]),
                       tuple((float(d), float(r)) for d, r in data["settings"]), dict(data["model"]),
                       tuple((str(n), float(lo), math.inf if hi is None else float(hi)) for n, lo, hi in data["bands"]),
                       per_view)
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise InputValueError(f"not a FoveationAxis JSON ({type(e).__name__}: {e})") from None
        _check_per_view("FoveationAxis", per_view, (len(axis.gazes), len(axis.settings)))
        return axis


def _nan_back(values: Any) -> Any:
    """Inverse of :func:`_nan_json`."""
    if isinstance(values, list):
        return [_nan_back(v) for v in values]
    return math.nan if values is None else values


@dataclass(eq=False)
class GridResult:
    """Metrics of every method on the grid.

    Attributes:
        downsample, power_saving: the grid axes.
        per_view: ``{method: {metric: Tensor[D, P, V]}}`` (float64).
        optics_mode: the optics operator used.
        info: JSON-able facts about the run (test views, their sizes, ...), kept in ``results.json``.
        foveation: the foveation axis (:class:`FoveationAxis`), None without the foveation effect.
    """

    downsample: tuple[float, ...]
    power_saving: tuple[float, ...]
    per_view: dict[str, dict[str, torch.Tensor]] = field(default_factory=dict)
    optics_mode: str = "fast"
    info: dict[str, Any] = field(default_factory=dict)
    foveation: FoveationAxis | None = None

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GridResult):
            return NotImplemented
        return (self.downsample == other.downsample and self.power_saving == other.power_saving
                and self.foveation == other.foveation
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
        """Every number: per-view values, grid means and overall means (and ``foveation``, the axis's)."""
        return {
            **({"foveation": self.foveation.to_json()} if self.foveation is not None else {}),
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
            fov = data.get("foveation")
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise InputValueError(f"not a GridResult JSON ({type(e).__name__}: {e})") from None
        _check_per_view("GridResult", per_view, (len(result.downsample), len(result.power_saving)))
        if fov is not None:
            result.foveation = FoveationAxis.from_json(fov)
        return result


def make_pipeline(effects: Mapping[str, Any] | None = None, optics_mode: str = "fast", lens: LensSpec = None) -> Pipeline:
    """The evaluation pipeline E_s from ``effects`` (default :data:`DEFAULT_EFFECTS`) simulating ``lens``
    (:func:`~controlgs_adapter.downstream.optics.lenses.effects_for_lens`; default the shipped Cardboard lens)
    with the optics operator ``optics_mode``, in eval mode."""
    pipeline = Pipeline.from_config(effects_for_lens(DEFAULT_EFFECTS if effects is None else effects, lens))
    set_optics_mode(pipeline, optics_mode)
    return pipeline.eval()


def _check_per_view(kind: str, per_view: Mapping[str, Mapping[str, torch.Tensor]], shape: tuple[int, int]) -> None:
    """InputValueError naming every ``method.metric`` of a ``kind`` JSON whose values are not ``[*shape, V]``."""
    bad = [f"{m}.{k}" for m, mv in per_view.items() for k, v in mv.items() if v.dim() != 3 or tuple(v.shape[:2]) != shape]
    if bad:
        raise InputValueError(f"{kind} JSON: per_view of {bad} is not [{shape[0]}, {shape[1]}, V]")


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
    e, g = _compared(eye, gt)
    out = {"psnr": float(psnr(e, g)), "ssim": float(ssim(e, g))}
    for name, fn in extra.items():
        out[name] = fn(e, g)
    return out


def _compared(eye: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The eye image at the ground truth's size, clamped to [0, 1], and the ground truth, both float64."""
    if eye.shape[-2:] != gt.shape[-2:]:
        eye = oled_emission(eye, (gt.shape[-2], gt.shape[-1]))
    return eye.detach().clamp(0.0, 1.0).double(), gt.double()


def band_masks(angles: VisualAngles, height: int, width: int, gaze: Sequence[float], *,
               bands: Sequence[tuple[str, float, float]] = BANDS, placement: Placement = "fit") -> torch.Tensor:
    """``[B, H, W]`` bool: the pixels of an ``H x W`` image (placed on the display) whose direction through the
    lens (``angles``) lies ``low <= e < high`` degrees from ``gaze`` ``(azimuth, elevation)``, per band."""
    ecc = eccentricity(angles.pixel_directions(height, width, placement), gaze)
    return torch.stack([(ecc >= lo) & (ecc < hi) for _, lo, hi in bands])


def band_scores(eye: torch.Tensor, gt: torch.Tensor, masks: torch.Tensor,
                names: Sequence[str] | None = None) -> dict[str, float]:
    """``psnr_<band>`` and ``ssim_<band>`` of an eye image ``[3, H, W]`` vs the ground truth (as :func:`scores`)
    over each band's pixels ``masks`` ``[B, H, W]`` (``names``: the bands', default :data:`BANDS`'): PSNR from the band's MSE over its pixels and channels, SSIM
    the mean of the SSIM map over the windows centred in the band. NaN for a band without a pixel (or a window)."""
    e, g = _compared(eye, gt)
    sq = (e - g).square().mean(dim=0)
    smap = ssim_map(e, g).mean(dim=0)
    r = (sq.shape[-2] - smap.shape[-2]) // 2
    out = {}
    for name, mask in zip([b[0] for b in BANDS] if names is None else names, masks, strict=True):
        inner = mask[r:mask.shape[0] - r, r:mask.shape[1] - r]
        out[f"psnr_{name}"] = float(-10.0 * torch.log10(sq[mask].mean())) if mask.any() else math.nan
        out[f"ssim_{name}"] = float(smap[inner].mean()) if inner.any() else math.nan
    return out


@torch.no_grad()
def evaluate_grid(model: Any, views: Views, adapters: Mapping[str, str | Path], *,
                  effects: Mapping[str, Any] | None = None, downsample: Sequence[float] = GRID_DOWNSAMPLE, power_saving: Sequence[float] = GRID_POWER_SAVING,
                  optics_mode: str = "fast", baselines: Sequence[str] = BASELINES,
                  extra_metrics: bool = True, ideal: bool = True, lpips: Any = None,
                  progress: bool = True, renderer: Renderer | Any = None, lens: LensSpec = None,
                  gazes: Sequence[Sequence[float]] | None = None,
                  foveation_settings: Sequence[Sequence[float]] = FOVEATION_SETTINGS) -> GridResult:
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
    With a foveation stage in ``effects`` the result has the foveation axis (module docstring): ``gazes``
    ``[(azimuth, elevation)]`` degrees (default :data:`FOVEATION_GAZES`; each must lie in the lens's field) at the
    ``foveation_settings`` ``[(d, rho)]``; the bands are measured through the pipeline's lens at the ground truth's size.
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
    fov_stage = pipeline["foveation"] if "foveation" in pipeline else None
    fov = _foveation_axis(fov_stage, gazes, foveation_settings) if isinstance(fov_stage, Foveation) else None
    ppd, cvvdp_info = _cvvdp_ppd(pipeline) if extra_metrics else (None, {})
    extra = optional_metrics(None if lpips is None else lpips.to(device), ppd=ppd) if extra_metrics else {}
    names = list(baselines) + ([IDEAL] if ideal else []) + list(adapters)
    nd, npow, nv = len(downsample), len(power_saving), len(views)
    metric_names = ["psnr", "ssim", *extra]
    result = {m: {k: torch.zeros(nd, npow, nv, dtype=torch.float64) for k in metric_names} for m in names}
    fov_names = [n for n in names if n != "no_ss" and (n not in ABLATIONS or n == "wo_foveation")] if fov else []
    if fov is not None:
        fov_metrics = ["psnr", "ssim", *(f"{k}_{b[0]}" for b in fov.bands for k in ("psnr", "ssim"))]
        fov.per_view = {m: {k: torch.zeros(len(fov.gazes), len(fov.settings), nv, dtype=torch.float64)
                            for k in fov_metrics} for m in fov_names}
    nfov = 0 if fov is None else len(fov.gazes) * len(fov.settings)
    bar = tqdm(total=nv * (nd * npow * len(names) + nfov * len(fov_names)), desc="evaluating grid",
               disable=not progress, dynamic_ncols=True)
    masks: dict[tuple[int, int, int], torch.Tensor] = {}

    def fov_states() -> list[tuple[int, int, RuntimeState]]:
        assert fov is not None
        return [(g, k, RuntimeState(downsample=d, power_saving=rho, gaze=gaze)) for g, gaze in enumerate(fov.gazes)
                for k, (d, rho) in enumerate(fov.settings)]

    def score_fov(name: str, g: int, k: int, v: int, rendered: torch.Tensor, state: RuntimeState, gt: torch.Tensor) -> None:
        assert fov is not None and isinstance(fov_stage, Foveation) and state.gaze is not None
        key = (g, gt.shape[-2], gt.shape[-1])
        if key not in masks:
            masks[key] = band_masks(fov_stage.angles, gt.shape[-2], gt.shape[-1], state.gaze, bands=fov.bands,
                                    placement=fov_stage.placement).to(device)
        eye = pipeline(rendered, state, reference=gt)
        values = {**scores(eye, gt, {}), **band_scores(eye, gt, masks[key], [b[0] for b in fov.bands])}
        for metric, value in values.items():
            fov.per_view[name][metric][g, k, v] = value
        bar.update(1)

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
        for g, k, state in fov_states() if fov is not None else []:
            if "ss" in fov_names:
                score_fov("ss", g, k, v, renders["ss"], state, gt)
            if IDEAL in fov_names:
                score_fov(IDEAL, g, k, v, gt, state, gt)
    for name, path in adapters.items():
        cgs = ControlGS.load(path, model)
        try:
            for v in range(nv):
                cam, gt = view(v)
                for i, d in enumerate(downsample):
                    for j, rho in enumerate(power_saving):
                        state = RuntimeState(downsample=d, power_saving=rho)
                        score(name, i, j, v, render_view(cgs, model, cam, state, background, renderer=renderer), state, gt)
                for g, k, state in fov_states() if name in fov_names else []:
                    score_fov(name, g, k, v, render_view(cgs, model, cam, state, background, renderer=renderer), state, gt)
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
    return GridResult(tuple(float(d) for d in downsample), tuple(float(p) for p in power_saving), result, optics_mode,
                      info, fov)


def _foveation_axis(stage: Foveation, gazes: Sequence[Sequence[float]] | None,
                    settings: Sequence[Sequence[float]]) -> FoveationAxis | None:
    """The empty axis of ``stage`` (None when its preset is off), the gazes and settings checked."""
    if stage.model is None:
        return None
    chosen = FOVEATION_GAZES if gazes is None else gazes
    pairs = []
    for what, values in (("gazes", chosen), ("foveation_settings", settings)):
        try:
            pair = tuple((float(a), float(b)) for a, b in values)
        except (TypeError, ValueError):
            raise InputValueError(f"{what} must be a non-empty list of number pairs, got {values!r}") from None
        if not pair or not all(math.isfinite(x) for p in pair for x in p):
            raise InputValueError(f"{what} must be a non-empty list of finite number pairs, got {values!r}")
        pairs.append(pair)
    for gaze in pairs[0]:
        stage.angles.check_gaze(gaze)
    for d, rho in pairs[1]:
        RuntimeState(downsample=d, power_saving=rho)
    m = stage.model
    return FoveationAxis(pairs[0], pairs[1], {"omega0": m.omega0, "slope": m.slope, "max_scale": m.max_scale})


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
