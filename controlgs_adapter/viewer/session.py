"""What the viewer renders for one state: every method's rendered frame and eye image, the ground
truth, difference images, metrics and the adapters' condition strengths.

:class:`ViewerSession` owns the model, the test views and the adapters (each loaded once onto its
own shallow copy of the model, sharing the backbone's tensors, so no adapter is loaded per request).
Renders that do not depend on the state are cached: the ground truth and the SS-backbone per camera,
the backbone without supersampling per display size. The pipeline runs once per method (with
``record``), and the metrics are :func:`~controlgs_adapter.evaluation.evaluate_grid`'s own.
"""

from __future__ import annotations

import base64
import copy
import io
import math
import time
from collections import OrderedDict
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Hashable, Mapping

import torch
import torch.nn.functional as F

from controlgs_adapter.rendering.protocol import Renderer, model_device, render_view, renderer_for

from ..checks import brief, check_number
from ..controlgs import ControlGS
from ..downstream.oled import oled_emission
from ..downstream.optics.bank import PSFBank
from ..downstream.optics.lenses import LensSpec, load_lens
from ..downstream.optics.stage import MODES, set_optics_mode
from ..downstream.optics.visual_angles import VisualAngles
from ..downstream.placement import to_display
from ..errors import InputValueError
from ..downstream.foveation import Foveation
from ..evaluation import BANDS, BASELINES, band_masks, band_scores, make_pipeline, scores
from ..metrics import optional_metrics
from ..report import METHOD_LABELS
from ..state import Camera, RuntimeState
from ..training import DEFAULT_EFFECTS, view_cameras

if TYPE_CHECKING:  # pragma: no cover
    from ..downstream.pipeline import Pipeline

__all__ = ["STAGES", "OPTICS_MODES", "ViewState", "parse_state", "ViewerSession", "Superseded", "orbit_camera",
           "scene_centre", "encode_png"]

#: downstream stages the page can switch on and off: the default effects' (pipeline order)
STAGES: tuple[str, ...] = (*DEFAULT_EFFECTS, "foveation")
#: the optics stage's modes
OPTICS_MODES: tuple[str, ...] = MODES
#: the sliders' ranges (the paper's training ranges)
DOWNSAMPLE_RANGE = (1.0, 8.0)
POWER_SAVING_RANGE = (0.0, 0.8)
AZIMUTH_RANGE = (-180.0, 180.0)
ELEVATION_RANGE = (-80.0, 80.0)
#: difference images show |eye - ground truth| times this
DIFF_GAIN = 2.0
_FIELDS = ("view", "azimuth", "elevation", "downsample", "power_saving", "optics", "stages", "gaze")


class Superseded(Exception):
    """A newer request arrived; this one's work was dropped."""


@dataclass(frozen=True)
class ViewState:
    """Everything a page request asks for (see :func:`parse_state`)."""

    view: int = 0
    azimuth: float = 0.0
    elevation: float = 0.0
    downsample: float = 2.0
    power_saving: float = 0.4
    optics: str = "fast"
    stages: tuple[str, ...] = STAGES
    gaze: tuple[float, float] | None = None

    @property
    def runtime(self) -> RuntimeState:
        """The run-time state without the gaze: a clicked image position becomes a direction in degrees
        through the session's lens (:meth:`ViewerSession.runtime`)."""
        return RuntimeState(downsample=self.downsample, power_saving=self.power_saving)

    @property
    def effects(self) -> dict[str, bool]:
        """The pipeline's effects: every stage named, off ones False (``oled`` is on unless named off)."""
        return {name: name in self.stages for name in STAGES}

    @property
    def orbit(self) -> bool:
        """True when the camera is rotated away from the dataset view."""
        return self.azimuth != 0.0 or self.elevation != 0.0

    def to_json(self) -> dict[str, Any]:
        out = asdict(self)
        out["stages"], out["gaze"] = list(self.stages), None if self.gaze is None else list(self.gaze)
        return out


def parse_state(data: Any, views: int) -> ViewState:
    """A :class:`ViewState` from a request's JSON object; fields left out take the defaults.

    Raises:
        InputValueError: naming the field, its allowed values and what was given.
    """
    if not isinstance(data, Mapping):
        raise InputValueError(f"the state must be a JSON object with fields {', '.join(_FIELDS)}, got {type(data).__name__}")
    unknown = sorted(str(k) for k in data if k not in _FIELDS)
    if unknown:
        raise InputValueError(f"unknown state field(s) {brief(unknown)}; fields: {', '.join(_FIELDS)}")
    d = ViewState()
    view = check_number("view", data.get("view", d.view), integer=True, low=0, high=views - 1)
    values = {k: check_number(k, data.get(k, getattr(d, k)), low=lo, high=hi)
              for k, (lo, hi) in (("azimuth", AZIMUTH_RANGE), ("elevation", ELEVATION_RANGE),
                                  ("downsample", DOWNSAMPLE_RANGE), ("power_saving", POWER_SAVING_RANGE))}
    optics = data.get("optics", d.optics)
    if not isinstance(optics, str) or optics not in OPTICS_MODES:
        raise InputValueError(f"optics must be one of {', '.join(OPTICS_MODES)}, got {brief(optics)}")
    stages = data.get("stages", list(d.stages))
    if not isinstance(stages, list) or not all(isinstance(s, str) for s in stages):
        raise InputValueError(f"stages must be a list of stage names among {', '.join(STAGES)}, got {brief(stages)}")
    bad = [s for s in stages if s not in STAGES]
    if bad:
        raise InputValueError(f"stages: unknown {brief(bad)}; stages are {', '.join(STAGES)}")
    gaze = data.get("gaze")
    if gaze is not None:
        if not isinstance(gaze, list) or len(gaze) != 2:
            raise InputValueError(f"gaze must be null or [x, y] in [-1, 1] (the clicked image position, normalised), "
                                  f"got {brief(gaze)}")
        gaze = (check_number("gaze x", gaze[0], low=-1, high=1), check_number("gaze y", gaze[1], low=-1, high=1))
    return ViewState(int(view), values["azimuth"], values["elevation"], values["downsample"], values["power_saving"],
                     optics, tuple(s for s in STAGES if s in stages), gaze)


def _rotation(axis: torch.Tensor, degrees: float) -> torch.Tensor:
    """Rodrigues: ``[3, 3]`` rotation by ``degrees`` about the unit ``axis`` (right-handed)."""
    k = axis / axis.norm()
    kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])  # dtype follows the 0-d entries of k
    t = math.radians(degrees)
    return torch.eye(3, dtype=k.dtype) + math.sin(t) * kx + (1.0 - math.cos(t)) * (kx @ kx)


def orbit_camera(camera: Camera, centre: torch.Tensor, azimuth: float, elevation: float) -> Camera:
    """``camera`` moved on a sphere about ``centre``: ``azimuth`` degrees about its own up axis (positive:
    to the right of the scene), then ``elevation`` degrees about its right axis (positive: up); its
    orientation turns with it, so a camera looking at the centre keeps looking at it."""
    w2c = camera.world_to_camera.detach().double().cpu()
    r, c = w2c[:3, :3], camera.center.detach().double().cpu()
    right, up = r[0], -r[1]  # OpenCV: x right, y down
    q = _rotation(up, azimuth) @ _rotation(right, -elevation)
    o = centre.detach().double().cpu()
    new_c, new_r = o + q @ (c - o), r @ q.T
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3], out[:3, 3] = new_r, -(new_r @ new_c)
    return Camera(out.to(camera.world_to_camera.dtype), camera.intrinsics, camera.width, camera.height,
                  dict(camera.extra))


def scene_centre(cameras: list[Camera], points: torch.Tensor | None) -> torch.Tensor:
    """The point nearest to every camera's optical axis (least squares) when the axes converge in front
    of the cameras, else the median of ``points`` (the anchors), else the origin. ``[3]`` float64."""
    if len(cameras) >= 2:
        a, b = torch.zeros(3, 3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
        for cam in cameras:
            d = cam.world_to_camera.detach().double().cpu()[2, :3]
            p = torch.eye(3, dtype=torch.float64) - torch.outer(d, d)
            a, b = a + p, b + p @ cam.center.detach().double().cpu()
        if float(torch.linalg.cond(a)) < 1e4:
            x = torch.linalg.solve(a, b)
            if all(float(cam.to_camera(x[None].to(cam.world_to_camera)).detach()[0, 2]) > 0 for cam in cameras):
                return x
    if points is not None and len(points):
        return points.detach().double().cpu().median(dim=0).values
    return torch.zeros(3, dtype=torch.float64)


def encode_png(image: torch.Tensor, level: int = 1) -> str:
    """``[3 or 4, H, W]`` in [0, 1] -> base64 PNG (Pillow, low compression: fast)."""
    from PIL import Image

    arr = (image.detach().clamp(0.0, 1.0) * 255.0 + 0.5).to(torch.uint8).permute(1, 2, 0).cpu().numpy()
    buf = io.BytesIO()
    Image.fromarray(arr, "RGBA" if arr.shape[2] == 4 else "RGB").save(buf, "PNG", compress_level=level)
    return base64.b64encode(buf.getvalue()).decode("ascii")


#: heat colour map (black -> purple -> orange -> yellow), strength 0..1
_HEAT = torch.tensor([[0.0, 0.0, 0.2], [0.45, 0.05, 0.55], [0.9, 0.35, 0.1], [1.0, 0.95, 0.3]])


def heat_overlay(positions: torch.Tensor, strength: torch.Tensor, camera: Camera) -> torch.Tensor:
    """RGBA ``[4, H, W]``: per-anchor ``strength`` (``[R]``) splatted at the anchors' pixels
    (``positions`` ``[R, 3]`` world), smoothed, as a heat map; transparent where no anchor lands."""
    h, w = camera.height, camera.width
    uv, z = camera.project(positions.float())
    x, y = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    ok = (z > 0) & (x >= 0) & (x < w) & (y >= 0) & (y < h) & torch.isfinite(strength)
    idx = (y * w + x)[ok].cpu()
    num = torch.zeros(h * w).index_add_(0, idx, strength[ok].float().cpu()).view(1, 1, h, w)
    cnt = torch.zeros(h * w).index_add_(0, idx, torch.ones(idx.numel())).view(1, 1, h, w)
    k = 2 * max(1, round(max(h, w) / 48)) + 1
    num, cnt = (F.avg_pool2d(t, k, 1, k // 2, count_include_pad=False) for t in (num, cnt))
    lam = (num / cnt.clamp_min(1e-12)).clamp(0.0, 1.0)[0, 0]
    t = lam * (len(_HEAT) - 1)
    i0 = t.floor().long().clamp(max=len(_HEAT) - 2)
    rgb = torch.lerp(_HEAT[i0], _HEAT[i0 + 1], (t - i0).unsqueeze(-1)).permute(2, 0, 1)
    alpha = (cnt[0] * k * k * 4.0).clamp(0.0, 1.0) * 0.55
    return torch.cat([rgb, alpha])


def _shared_copy(model: Any) -> Any:
    """A copy of ``model``'s module tree that shares every parameter, buffer and tensor attribute
    (no tensor memory is duplicated): an adapter wraps the copy without touching ``model``."""
    memo: dict[int, Any] = {}
    modules = model.modules() if isinstance(model, torch.nn.Module) else [model]
    for m in modules:
        for v in vars(m).values():
            if isinstance(v, torch.Tensor):
                memo[id(v)] = v
        if isinstance(m, torch.nn.Module):
            for t in (*m.parameters(recurse=False), *m.buffers(recurse=False)):
                memo[id(t)] = t
    return copy.deepcopy(model, memo)


class _Cache(OrderedDict):
    """A small least-recently-used dict."""

    def __init__(self, size: int) -> None:
        super().__init__()
        self.size = size

    def get_or(self, key: Hashable, make: Callable[[], Any]) -> Any:
        if key in self:
            self.move_to_end(key)
            return self[key]
        value = self[key] = make()
        while len(self) > self.size:
            self.popitem(last=False)
        return value


class ViewerSession:
    """The renders behind the viewer page.

    Args:
        model: the backbone (not wrapped), on the device everything runs on.
        views: the test views (a :class:`~controlgs_adapter.training.Views` dataset with ``background``).
        adapters: ``{method name: adapter file}`` (``controlgs`` and any ablations of a run).
        truth: ground truth of any camera (the built-in scene renders it exactly), used for orbit
            views; None: orbit views have no ground truth (the SS-backbone stands in as the display's
            power reference and no metrics are shown).
        renderer: how the model renders (default :func:`~controlgs_adapter.rendering.protocol.renderer_for`).
        name: the scene's name, shown on the page.
        lens: the headset lens the pipeline simulates (:func:`~controlgs_adapter.evaluation.make_pipeline`;
            default the shipped Cardboard lens).
    """

    def __init__(self, model: Any, views: Any, adapters: Mapping[str, str | Path], *,
                 truth: Callable[[Camera], torch.Tensor] | None = None, renderer: Renderer | None = None,
                 name: str = "", lens: LensSpec = None) -> None:
        clash = [a for a in adapters if a in BASELINES]
        if clash:
            raise InputValueError(f"adapter names {clash} clash with the baselines {BASELINES}")
        if not len(views):
            raise InputValueError("the viewer needs at least one view")
        self.model, self.views, self.truth, self.name = model, views, truth, name
        self.lens = None if lens is None else load_lens(lens)
        self.device = model_device(model)
        self.renderer = renderer or renderer_for(model)
        bg = getattr(views, "background", None)
        self.background = None if bg is None else bg.to(self.device)
        self.adapter_files = {m: Path(p) for m, p in adapters.items()}
        self.adapters: dict[str, tuple[Any, ControlGS]] = {}
        for method, path in adapters.items():
            copy_ = _shared_copy(model)
            self.adapters[method] = (copy_, ControlGS.load(path, copy_))
        self.methods = [*BASELINES, *self.adapters]
        self.cameras = view_cameras(views)
        points = None
        if self.adapters:
            cgs = next(iter(self.adapters.values()))[1]
            points = cgs.backend.anchor_positions(cgs.model)
        self.centre = scene_centre(self.cameras, points)
        self.extra_metrics = optional_metrics()
        self._pipelines: dict[tuple[str, ...], Pipeline] = {}
        self._frames = _Cache(16)    # (camera key) -> (camera, gt or None, ss render, png of both)
        self._small = _Cache(32)     # (camera key, w, h) -> no-SS render
        self._last: tuple[int, dict[str, torch.Tensor], torch.Tensor | None] | None = None

    def info(self) -> dict[str, Any]:
        """What the page needs to build its controls."""
        return {"name": self.name, "views": [f"test view {i} ({c.width}x{c.height})" for i, c in enumerate(self.cameras)],
                "methods": [{"name": m, "label": METHOD_LABELS.get(m, m)} for m in self.methods],
                "stages": list(STAGES), "optics_modes": list(OPTICS_MODES), "defaults": ViewState().to_json(),
                "ranges": {"downsample": DOWNSAMPLE_RANGE, "power_saving": POWER_SAVING_RANGE,
                           "azimuth": AZIMUTH_RANGE, "elevation": ELEVATION_RANGE},
                "orbit_truth": self.truth is not None, "extra_metrics": list(self.extra_metrics),
                "diff_gain": DIFF_GAIN, "device": str(self.device),
                "bands": [[n, lo, None if math.isinf(hi) else hi] for n, lo, hi in BANDS]}

    def _pipeline(self, state: ViewState) -> Pipeline:
        if state.stages not in self._pipelines:
            self._pipelines[state.stages] = make_pipeline(state.effects, "fast", self.lens).to(self.device)
        pipeline = self._pipelines[state.stages]
        set_optics_mode(pipeline, state.optics)
        return pipeline

    def _frame(self, state: ViewState) -> tuple[Camera, torch.Tensor | None, torch.Tensor, dict[str, str]]:
        def make() -> tuple[Camera, torch.Tensor | None, torch.Tensor, dict[str, str]]:
            cam, gt = self.views[state.view]
            if state.orbit:
                cam = orbit_camera(cam, self.centre, state.azimuth, state.elevation)
                gt = None if self.truth is None else self.truth(cam)
            gt = None if gt is None else gt.to(self.device)
            full = render_view(None, self.model, cam, None, self.background, renderer=self.renderer)
            pngs = {"ss": encode_png(full), **({"gt": encode_png(gt)} if gt is not None else {})}
            return cam, gt, full, pngs

        return self._frames.get_or((state.view, state.azimuth, state.elevation), make)

    def runtime(self, state: ViewState, camera: Camera) -> RuntimeState:
        """``state``'s run-time state, its gaze (a position on ``camera``'s image, image-normalised) turned
        into the direction in degrees it is seen in through the session's lens (the image placed "fit")."""
        rs = state.runtime
        if state.gaze is None:
            return rs
        angles = VisualAngles.of_bank(PSFBank.default() if self.lens is None else self.lens.bank)
        xy = torch.tensor(state.gaze, dtype=torch.float64).clamp(-0.999, 0.999)  # inside the display's outline
        gaze = angles.directions(to_display(xy, camera.height, camera.width))
        return replace(rs, gaze=(float(gaze[0]), float(gaze[1])))

    def render(self, state: ViewState, check: Callable[[], None] = lambda: None, tag: int = 0) -> dict[str, Any]:
        """Every method at ``state``: base64 PNGs (``rendered``, ``eye``, ``diff``, lens ``overlay``),
        PSNR / SSIM against the ground truth (as :func:`evaluate_grid` computes them; with a gaze and the
        foveation stage also per eccentricity band, ``bands``: :func:`~controlgs_adapter.evaluation.band_scores`) and the
        condition strengths. ``check`` is called between methods and raises :class:`Superseded` to
        drop the work when a newer request arrived; ``tag`` names this render for :meth:`extra`."""
        t0 = time.perf_counter()
        with torch.no_grad():
            cam, gt, full, pngs = self._frame(state)
            check()
            pipeline, rs = self._pipeline(state), self.runtime(state, cam)
            reference = full if gt is None else gt
            out: dict[str, Any] = {"state": state.to_json(), "size": [cam.width, cam.height], "has_truth": gt is not None,
                                   "gt": pngs.get("gt"), "methods": []}
            eyes: dict[str, torch.Tensor] = {}
            fov = pipeline["foveation"] if "foveation" in pipeline else None
            masks = (band_masks(fov.angles, gt.shape[-2], gt.shape[-1], rs.gaze, placement=fov.placement).to(gt.device)
                     if isinstance(fov, Foveation) and fov.model is not None and rs.gaze is not None and gt is not None
                     else None)
            for method in self.methods:
                strengths: dict[str, Any] = {}
                overlay = None
                if method == "ss":
                    rendered, png = full, pngs["ss"]
                elif method == "no_ss":
                    small = cam.scaled(state.downsample)
                    rendered = self._small.get_or((state.view, state.azimuth, state.elevation, small.width, small.height),
                                                  lambda: render_view(None, self.model, small, None, self.background,
                                                                      renderer=self.renderer))
                    png = encode_png(rendered)
                else:
                    copy_, cgs = self.adapters[method]
                    rendered = render_view(cgs, copy_, cam, rs, self.background, renderer=self.renderer)
                    png = encode_png(rendered)
                    strengths, overlay = self._strengths(cgs, copy_, cam, rs)
                eye, record = pipeline.run_recorded(rendered, rs, reference=reference)
                if eye.shape[-2:] != reference.shape[-2:]:  # oled off: the display's pixels as boxes at S
                    eye = oled_emission(eye, (reference.shape[-2], reference.shape[-1]))
                eye = eye.clamp(0.0, 1.0)
                eyes[method] = eye
                entry = {"name": method, "label": METHOD_LABELS.get(method, method), "rendered": png, "eye": encode_png(eye),
                         "rendered_size": [rendered.shape[-1], rendered.shape[-2]], "strengths": strengths,
                         "overlay": overlay, "stages_run": record["stages_run"], "metrics": None, "diff": None,
                         "bands": None}
                if gt is not None:
                    entry["metrics"] = {k: v if math.isfinite(v) else None for k, v in scores(eye, gt, {}).items()}
                    entry["diff"] = encode_png(((eye - gt).abs() * DIFF_GAIN).clamp(0.0, 1.0))
                if masks is not None and gt is not None:
                    entry["bands"] = {k: v if math.isfinite(v) else None for k, v in band_scores(eye, gt, masks).items()}
                out["methods"].append(entry)
                check()
        self._last = (tag, eyes, gt)
        out["server_ms"] = round(1000.0 * (time.perf_counter() - t0), 1)
        return out

    def _strengths(self, cgs: ControlGS, model: Any, cam: Camera, rs: RuntimeState) -> tuple[dict[str, Any], str | None]:
        """The adapter's strengths at ``rs``: global ones as numbers, per-anchor ones as mean / min / max
        over the visible anchors, and the lens (else foveation) strength as a heat overlay (base64 PNG).
        A lens conditioned in its (x, y) frame shows the larger of ``|lambda_x|``, ``|lambda_y|``."""
        visible = self.renderer.visible(model, cam)
        ids = cgs.anchor_ids(visible)
        lam = {m: v.abs().amax(-1) if v.dim() == 2 else v for m, v in cgs.strengths(rs, cam, ids).items()}
        out: dict[str, Any] = {}
        overlay = None
        one: dict[str, torch.Tensor] | None = None  # strengths of anchor 0: the global values when none is visible
        for m, v in lam.items():
            if cgs.schedules[m].per_anchor and not cgs.state_blind:
                out[m] = {"mean": float(v.mean()) if v.numel() else 0.0, "min": float(v.min()) if v.numel() else 0.0,
                          "max": float(v.max()) if v.numel() else 0.0}
            else:
                if not v.numel():
                    one = one or cgs.strengths(rs, cam, torch.zeros(1, dtype=torch.long, device=ids.device))
                    v = one[m]
                out[m] = float(v[0])
        shown = next((m for m in ("lens", "foveation") if m in lam), None)
        if shown is not None:
            positions = cgs.backend.anchor_positions(cgs.model).detach()
            overlay = encode_png(heat_overlay(positions.index_select(0, ids.to(positions.device)), lam[shown], cam))
        return out, overlay

    def extra(self, tag: int, check: Callable[[], None] = lambda: None) -> dict[str, dict[str, float | None]]:
        """The slower metrics (FLIP, ...) of the eye images of render ``tag``, per method (empty without
        ground truth; None for a non-finite value); ``check`` between methods as in :meth:`render`.

        Raises:
            Superseded: ``tag`` is not the last completed render."""
        if self._last is None or self._last[0] != tag:
            raise Superseded(f"render {tag} is not the last one")
        _, eyes, gt = self._last
        if gt is None or not self.extra_metrics:
            return {}
        out = {}
        for method, eye in eyes.items():
            values = {k: fn(eye.double(), gt.double()) for k, fn in self.extra_metrics.items()}
            out[method] = {k: v if math.isfinite(v) else None for k, v in values.items()}
            check()
        return out
