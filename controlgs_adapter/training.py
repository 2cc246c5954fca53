"""Training a ControlGS adapter on a frozen backbone (paper Sec. 3.4, Supp. A).

Per iteration: one training view and one run-time state sampled as the paper does (downsample d
log-uniform in [1, d_max], power saving rho uniform in [0, rho_max], the lens condition from each
anchor's projection under the sampled camera), a render at the native resolution S through the
wrapped backbone (supersampling), the downstream pipeline E_s, and the image loss against the
ground truth; only the adapter's parameters are optimised (Adam). Optics run distortion-only for
the first ``1 - psf_fraction`` of the iterations and with the full PSF after.

The training views are a dataset (:class:`Views`: a :class:`~controlgs_adapter.datasets.PosedImages`
or any sequence of ``(camera, image)`` with a ``background``); each step reads its view's image
from it (lazily loaded and cached there) and moves it to the device of the render.

Checkpoints (adapter, optimizer, RNG state, iteration; the file format in
:mod:`controlgs_adapter.formats.checkpoint`) are safetensors files written atomically; resuming
from one continues bit-for-bit as if never interrupted (same thread count). A checkpoint records
the fingerprint of its training views and is refused for other data.
"""

from __future__ import annotations

import hashlib
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Protocol, runtime_checkable

import torch
from tqdm.auto import tqdm

from .clock import PhaseClock
from .checks import check_number, value_checks
from .controlgs import ControlGS
from .distributed import DistContext
from .downstream.foveation import Foveation
from .downstream.oled import oled_emission
from .downstream.optics.lenses import LensSpec, effects_for_lens
from .downstream.bank_maps import bank_fingerprint
from .downstream.optics.bank import PSFBank
from .downstream.optics.stage import set_optics_mode
from .downstream.optics.visual_angles import VisualAngles
from .downstream.pipeline import Pipeline
from .errors import FileFormatError, InputValueError, NonFiniteError
from controlgs_adapter.formats.checkpoint import Checkpoint, read_checkpoint, write_checkpoint
from .losses import LossWeights, image_loss
from .seeding import seeded
from controlgs_adapter.rendering.protocol import Renderer, as_renderer, model_device, render_view
from .state import Camera, RuntimeState

__all__ = ["TrainConfig", "Trainer", "TrainingJob", "Views", "DEFAULT_EFFECTS", "modules_for", "views_fingerprint"]

#: the downstream path of the paper's evaluation: lens pre-warp, area resampling, uniform
#: dimming, OLED box pixels and the Cardboard PSF optics
DEFAULT_EFFECTS: dict[str, Any] = {"lens": True, "resample": True, "display": True, "oled": True, "optics": True}

# condition module -> downstream stages that make it useful
_MODULE_STAGES = {"lens": ("lens", "optics"), "resample": ("resample",), "display": ("display",),
                  "foveation": ("foveation",)}


def _pipeline_lens(pipeline: Pipeline) -> PSFBank | None:
    """The lens the lens condition is trained for: the optics stage's PSF bank, else the lens stage's
    (its pre-warp map's) bank, else None (a centred radius frame)."""
    optics = getattr(pipeline["optics"], "bank", None) if "optics" in pipeline else None
    if isinstance(optics, PSFBank):
        return optics
    prewarp = getattr(getattr(pipeline["lens"], "map", None), "bank", None) if "lens" in pipeline else None
    return prewarp if isinstance(prewarp, PSFBank) else None


def _no_lap(name: str) -> None:
    """The lap of a step without a clock."""


def modules_for(effects: Mapping[str, Any]) -> tuple[str, ...]:
    """The condition modules a scene's downstream ``effects`` call for (only those whose stage is on)."""
    on = {k for k, v in effects.items() if v is not None and v is not False}
    return tuple(m for m, stages in _MODULE_STAGES.items() if on.intersection(stages))


@runtime_checkable
class Views(Protocol):
    """The dataset protocol of :class:`Trainer` and :func:`~controlgs_adapter.evaluation.evaluate_grid`.

    ``views[i]`` is ``(camera, image)``: a :class:`Camera` and its sRGB ground truth ``[3, H, W]``
    float in [0, 1] at the camera's size (sizes may differ between views; any aspect ratio);
    ``len(views)`` views; ``background`` is the ``[3]`` render background (or None: the model's
    default). Optional: ``fingerprint() -> str`` identifying the data (else derived from the
    cameras) and ``cameras`` (the list of cameras, read without loading images).
    :class:`~controlgs_adapter.datasets.PosedImages` implements all of it with lazy, cached images.
    """

    background: torch.Tensor | None

    def __len__(self) -> int: ...

    def __getitem__(self, i: int) -> tuple[Camera, torch.Tensor]: ...


def view_cameras(views: Views) -> list[Camera]:
    """The cameras of ``views`` (``views.cameras`` when present, else read view by view)."""
    cams = getattr(views, "cameras", None)
    return list(cams) if cams is not None else [views[i][0] for i in range(len(views))]


def _view_label(views: Views, i: int) -> str:
    """``"view 3"``, with the frame's name where the dataset has one (``"view 3 ('train/0003.png')"``)."""
    frames = getattr(views, "frames", None)
    try:
        name = getattr(frames[i], "name", None) if frames is not None else None
    except (IndexError, KeyError, TypeError):
        name = None
    return f"view {i}" if name is None else f"view {i} ({name!r})"


def views_fingerprint(views: Views) -> str:
    """``views.fingerprint()`` when it has one, else a hash of the cameras' sizes and matrices."""
    fp = getattr(views, "fingerprint", None)
    if callable(fp):
        return str(fp())
    h = hashlib.sha256()
    for c in view_cameras(views):
        h.update(f"{c.width}x{c.height}".encode())
        h.update(c.world_to_camera.double().cpu().numpy().round(6).tobytes())
        h.update(c.intrinsics.double().cpu().numpy().round(4).tobytes())
    return h.hexdigest()[:16]


@dataclass(frozen=True)
class TrainConfig:
    """Training hyper-parameters (defaults: the paper's, Supp. A).

    Attributes:
        iterations: optimisation steps.
        lr: Adam learning rate of conditions and projections.
        modules: condition modules; None = those the downstream effects call for (:func:`modules_for`).
        cond_dim: N per module.
        state_blind: the ablation with strength 1 everywhere.
        max_downsample: d is sampled log-uniformly in [1, max_downsample].
        max_power_saving: rho is sampled uniformly in [0, max_power_saving].
        psf_fraction: final fraction of the iterations run with the full PSF (``psf_mode``); the
            rest use distortion-only optics.
        psf_mode: optics operator of that final phase (``"fast"`` or ``"exact"``).
        loss: weights of Eq. 14.
        checkpoint_every: write a checkpoint every this many iterations (0 = only at the end).
        seed: seeds view and state sampling.
        batch_size: (view, state) samples per step, the global batch (split over the processes
            of a distributed run, :mod:`controlgs_adapter.distributed`); the loss is their mean.
        lens_conditioning: the lens condition's frame (``ControlGS.wrap``): ``"radius"`` about the
            lens axis, ``"xy"`` the signed position in the lens's own coordinates (``cond_dim`` even),
            None: from the lens (radius for a centred, rotationally symmetric one, else xy).
        gaze_jitter_deg: with a foveation stage, the adapter is conditioned on the sampled gaze offset by
            up to this many degrees (uniform in a disc) from the gaze the stage uses: robustness to
            eye-tracker lag; 0: the same gaze.
    """

    iterations: int = 10_000
    lr: float = 3e-3
    modules: tuple[str, ...] | None = None
    cond_dim: int = 8
    state_blind: bool = False
    max_downsample: float = 8.0
    max_power_saving: float = 0.8
    psf_fraction: float = 0.1
    psf_mode: str = "fast"
    loss: LossWeights = field(default_factory=LossWeights)
    checkpoint_every: int = 500
    seed: int = 0
    batch_size: int = 1
    lens_conditioning: str | None = None
    gaze_jitter_deg: float = 0.0

    def __post_init__(self) -> None:
        numbers: dict[str, dict[str, Any]] = {
                   "iterations": dict(integer=True, low=0), "lr": dict(low=0.0, low_open=True, high=1e3),
                   "cond_dim": dict(integer=True, low=1), "max_downsample": dict(low=1.0, high=1e4),
                   "max_power_saving": dict(low=0.0, high=1.0, high_open=True), "psf_fraction": dict(low=0.0, high=1.0),
                   "checkpoint_every": dict(integer=True, low=0), "seed": dict(integer=True, low=0, high=2**63 - 1),
                   "batch_size": dict(integer=True, low=1), "gaze_jitter_deg": dict(low=0.0, high=30.0)}
        for name, limits in numbers.items():
            if limits.get("integer"):  # counts and sizes fit an int64 (a float product of them stays finite)
                limits = {"high": 2**63 - 1, **limits}
            object.__setattr__(self, name, check_number(f"TrainConfig.{name}", getattr(self, name), **limits))
        if not isinstance(self.state_blind, bool):
            raise InputValueError(f"TrainConfig.state_blind must be a bool, got {self.state_blind!r}")
        if self.psf_mode not in ("fast", "exact"):
            raise InputValueError(f"TrainConfig.psf_mode must be 'fast' or 'exact', got {self.psf_mode!r}")
        if self.lens_conditioning not in (None, "radius", "xy"):
            raise InputValueError(f"TrainConfig.lens_conditioning must be 'radius', 'xy' or None, got {self.lens_conditioning!r}")
        if not isinstance(self.loss, LossWeights):
            raise InputValueError(f"TrainConfig.loss must be a LossWeights, got {type(self.loss).__name__}")
        modules = self.modules
        if isinstance(modules, str):  # one module name, not its letters
            modules = (modules,)
        if modules is not None:
            if not isinstance(modules, (list, tuple)) or not all(isinstance(m, str) for m in modules):
                raise InputValueError(f"TrainConfig.modules must be None or a sequence of module names, got {self.modules!r}")
            object.__setattr__(self, "modules", tuple(modules))

    def as_header(self) -> dict[str, Any]:
        """JSON-able form (for checkpoints and reports)."""
        d = asdict(self)
        d["modules"] = None if self.modules is None else list(self.modules)
        return d


class Trainer:
    """Train a ControlGS adapter on a frozen backbone.

    Args:
        model: the backbone (any model ``ControlGS.wrap`` takes; the user's object, wrapped in
            place); frozen.
        views: the training views (:class:`Views`, e.g. ``SceneData.views("train", resolution=...)``);
            its ``background`` is the renders' background.
        config: :class:`TrainConfig`.
        effects: the downstream pipeline's stages (:meth:`Pipeline.from_config`); default
            :data:`DEFAULT_EFFECTS`.
        checkpoint: path of the checkpoint file to write (and to resume from, see :meth:`resume`).
        dist: this process's place in a data-parallel run (:func:`~controlgs_adapter.distributed.init_distributed`);
            default a single process.
        renderer: how a view is rendered (:mod:`controlgs_adapter.rendering.protocol`: a ``Renderer`` or a
            render function); default the model's own (:func:`~controlgs_adapter.rendering.protocol.renderer_for`).
        lens: the headset lens the effects simulate (:func:`~controlgs_adapter.downstream.optics.lenses.effects_for_lens`:
            a shipped name, a bank / prescription / profile path, a ``Lens`` or a ``PSFBank``); default the
            shipped Cardboard lens.

    Everything runs on the model's device; inside a step the per-tensor value checks (NaN/Inf,
    ranges: host syncs) are off, and the loss and the updated parameters are checked once instead;
    each view's image is checked for NaN/Inf the first time it is read (:meth:`load_view`).

    Attributes: ``cgs`` (the :class:`ControlGS`), ``views``, ``renderer``, ``device`` (the model's), ``pipeline``,
    ``optimizer``, ``generator`` (CPU: view and state sampling stays on the host),
    ``iteration``, ``history`` (loss of every iteration, kept across resumes), ``seconds`` (wall time of the
    last :meth:`train` call; 0.0 before the first).
    """

    def __init__(self, model: Any, views: Views, config: TrainConfig = TrainConfig(),
                 *, effects: Mapping[str, Any] | None = None,
                 checkpoint: str | Path | None = None, dist: DistContext | None = None,
                 renderer: Renderer | Any = None, lens: LensSpec = None) -> None:
        if isinstance(views, torch.Tensor) or not isinstance(views, Views) or not len(views):
            raise InputValueError("views must be a non-empty dataset of (camera, image) with a background "
                                  f"(e.g. SceneData.views('train')), got {type(views).__name__}")
        if not isinstance(config, TrainConfig):
            raise InputValueError(f"config must be a TrainConfig, got {type(config).__name__}")
        self.config = config
        self.effects = effects_for_lens(DEFAULT_EFFECTS if effects is None else effects, lens)
        modules = modules_for(self.effects) if config.modules is None else tuple(config.modules)
        if not modules:
            raise InputValueError(f"no condition module to train: the effects {sorted(self.effects)} call for none")
        self.model, self.views = model, views
        self.renderer = as_renderer(renderer, model)
        self.device = model_device(model)
        bg = getattr(views, "background", None)
        self.background = None if bg is None else bg.to(self.device)
        self.data_fingerprint = views_fingerprint(views)
        self.pipeline = Pipeline.from_config(self.effects).to(self.device)
        with seeded(int(config.seed), self.device):  # the projections' initialisation follows the seed, not the global RNG
            lens = _pipeline_lens(self.pipeline)
            self._lens_fingerprint = None if lens is None else bank_fingerprint(lens)
            self.cgs = ControlGS.wrap(model, modules=modules, cond_dim=config.cond_dim, state_blind=config.state_blind,
                                      lens=lens,
                                      lens_conditioning=config.lens_conditioning if "lens" in modules else None)
        try:  # a failure below leaves the user's model as it was
            set_optics_mode(self.pipeline, self.optics_mode(0))  # refuses an optics stage without modes before any step
            self.optimizer = torch.optim.Adam(list(self.cgs.trainable_parameters()), lr=config.lr)
            self.dist = DistContext() if dist is None else dist
            self.dist.check_batch(config.batch_size)
            self.dist.broadcast_parameters(self.cgs.trainable_parameters())  # every replica starts as rank 0
        except BaseException:
            self.cgs.unwrap()
            raise
        self.generator = torch.Generator().manual_seed(int(config.seed))
        self._checked_views: set[int] = set()  # views whose image passed load_view's check
        self.iteration = 0
        self.history: list[float] = []
        self.seconds = 0.0  # wall time of the last train() call
        self.checkpoint_path = None if checkpoint is None else Path(checkpoint)

    # ------------------------------------------------------------------ one step
    def sample(self) -> tuple[int, RuntimeState]:
        """Draw a training view index and a run-time state (from :attr:`generator`); with a foveation
        stage, the gaze is the direction of a display position drawn uniformly (inside the lens's field)."""
        g, c = self.generator, self.config
        view = int(torch.randint(len(self.views), (1,), generator=g))
        u = torch.rand(2, generator=g, dtype=torch.float64)
        d = math.exp(float(u[0]) * math.log(c.max_downsample)) if "resample" in self.pipeline else 1.0
        rho = float(u[1]) * c.max_power_saving if "display" in self.pipeline else 0.0
        gaze = None
        angles = self._gaze_angles()
        if angles is not None:
            a, e = angles.directions(torch.rand(2, generator=g, dtype=torch.float64) * 2 - 1).tolist()
            gaze = (a, e)
        return view, RuntimeState(downsample=min(d, c.max_downsample), power_saving=rho, gaze=gaze)

    def _gaze_angles(self) -> VisualAngles | None:
        """The visual angles of the pipeline's foveation stage (where gazes are drawn), or None."""
        stage = self.pipeline["foveation"] if "foveation" in self.pipeline else None
        return stage.angles if isinstance(stage, Foveation) else None

    def conditioning_state(self, state: RuntimeState) -> RuntimeState:
        """The state the adapter is conditioned on: ``state`` with its gaze offset by up to
        ``gaze_jitter_deg`` (uniform in a disc, from :attr:`generator`; kept where it would leave the field)."""
        jitter = self.config.gaze_jitter_deg
        if state.gaze is None or jitter == 0.0:
            return state
        u = torch.rand(2, generator=self.generator, dtype=torch.float64)
        r, t = jitter * math.sqrt(float(u[0])), 2 * math.pi * float(u[1])
        gaze = (state.gaze[0] + r * math.cos(t), state.gaze[1] + r * math.sin(t))
        angles = self._gaze_angles()
        return replace(state, gaze=gaze) if angles is None or angles.in_field(gaze) else state

    def load_view(self, i: int) -> tuple[Camera, torch.Tensor]:
        """``views[i]``; the first time a view is read (a lazily loaded image: when it is first
        loaded) its image is checked to be a finite tensor (one host sync per view).

        Raises:
            InputValueError: the image holds NaN or Inf (the message names the view).
        """
        cam, gt = self.views[i]
        if i not in self._checked_views:
            if not isinstance(gt, torch.Tensor):
                raise InputValueError(f"{_view_label(self.views, i)}: image must be a torch.Tensor, got {type(gt).__name__}")
            bad = int((~torch.isfinite(gt)).sum()) if gt.is_floating_point() or gt.is_complex() else 0
            if bad:
                raise InputValueError(f"{_view_label(self.views, i)}: image holds {bad} NaN/Inf value(s) of {gt.numel()}; "
                                      "fix or drop the view before training")
            self._checked_views.add(i)
        return cam, gt

    def optics_mode(self, iteration: int) -> str:
        """``"distortion"`` for the first ``1 - psf_fraction`` of the iterations, then ``psf_mode``."""
        switch = round(self.config.iterations * (1.0 - self.config.psf_fraction))
        return "distortion" if iteration < switch else self.config.psf_mode

    def step(self, clock: PhaseClock | None = None) -> float:
        """One optimisation step; returns the loss.

        ``clock``: a :class:`~controlgs_adapter.clock.PhaseClock` to time the step's phases
        (:data:`~controlgs_adapter.clock.STEP_PHASES`); None (default): not timed, no syncs added.
        """
        lap = _no_lap if clock is None else clock.lap
        if clock is not None:
            clock.start()
        set_optics_mode(self.pipeline, self.optics_mode(self.iteration))
        batch = [self.sample() for _ in range(self.config.batch_size)]  # the global batch, the same on every rank
        conditioned = [self.conditioning_state(state) for _, state in batch]  # drawn on every rank alike
        self.optimizer.zero_grad()  # set_to_none=True: the default since torch 2.0
        value = 0.0
        for view, state, cond_state in self.dist.shard([(v, s, c) for (v, s), c in zip(batch, conditioned)]):
            cam, gt = self.load_view(view)
            lap("sample")
            with value_checks(False):  # no host syncs in the forward; the loss is checked below
                image = render_view(self.cgs, self.model, cam, cond_state, self.background,
                                    renderer=self.renderer)
                if tuple(gt.shape) != tuple(image.shape):
                    raise InputValueError(f"view {view}: image is {list(gt.shape)}, its camera renders {list(image.shape)}")
                gt = gt.to(image.device, non_blocking=True)
                lap("render")
                eye = self.pipeline(image, state, reference=gt)
                if eye.shape[-2:] != gt.shape[-2:]:  # oled off: the display's pixels as boxes at S (as the viewer scores them)
                    eye = oled_emission(eye, (gt.shape[-2], gt.shape[-1]))
                lap("pipeline")
                loss = image_loss(eye, gt, self.config.loss) / len(batch)
                lap("loss")
            if loss.requires_grad:  # else no module was active for this sample (all strengths 0): no gradient
                loss.backward()
            lap("backward")
            value += float(loss.detach())  # the loss log: the step's one device sync besides the check below
        value = self.dist.sync_gradients(self.cgs.trainable_parameters(), row_sparse=(self.cgs.injector.conditions,),
                                         loss=value, step=self.iteration)
        if not math.isfinite(value):
            raise NonFiniteError(f"training diverged at iteration {self.iteration}: the loss is {value}; the adapter "
                                 "was not updated and no checkpoint of this state was written")
        self.optimizer.step()
        params = dict(self.cgs.injector.named_parameters())
        finite = torch.stack([torch.isfinite(p).all() for p in params.values()])
        if not bool(finite.all()):  # one sync for all parameters
            bad = [name for name, ok in zip(params, finite.tolist()) if not ok]
            bad_grads = [name for name, p in params.items() if p.grad is not None and not bool(torch.isfinite(p.grad).all())]
            cause = (f"(lr {self.config.lr:g})" if not bad_grads else
                     f"from NaN/Inf gradients of {bad_grads} with a finite loss: not the learning rate, a degenerate "
                     "input of the render or the pipeline (a NaN/Inf or overflowing value in the model or the views)")
            raise NonFiniteError(f"training diverged at iteration {self.iteration}: parameter(s) {bad} became NaN/Inf "
                                 f"{cause}; the last good checkpoint was kept, this state not written")
        lap("optimizer")
        self.iteration += 1
        self.history.append(value)
        return value

    def train(self, *, until: int | None = None, progress: bool = True, desc: str | None = None,
              job: "TrainingJob | None" = None) -> ControlGS:
        """Run steps up to iteration ``until`` (default ``config.iterations``), writing checkpoints
        every ``config.checkpoint_every`` iterations and at the end when a path was given.

        ``desc``: the progress bar's title (default ``"training ControlGS"``). ``job``: the
        :class:`TrainingJob` this training is one of; the bar is then titled ``[k/N] <desc>`` and
        shows the estimated time left for the whole job."""
        end = self.config.iterations if until is None else min(int(until), self.config.iterations)
        title = "training ControlGS" if desc is None else desc
        if job is not None:
            title = job.start(title, self.iteration)
        bar = tqdm(total=self.config.iterations, initial=self.iteration, desc=title,
                   disable=not progress or not self.dist.is_main,
                   dynamic_ncols=True)
        every = self.config.checkpoint_every
        t0 = time.perf_counter()
        try:
            while self.iteration < end:
                t_step = time.perf_counter()
                loss = self.step()
                if job is not None:
                    job.step(time.perf_counter() - t_step)
                bar.update(1)
                postfix = {"loss": f"{loss:.4f}", "optics": self.optics_mode(self.iteration - 1)}
                if job is not None:
                    postfix["total left"] = job.remaining_text()
                bar.set_postfix(postfix, refresh=False)
                if self.checkpoint_path is not None and every and self.iteration % every == 0:
                    self.save_checkpoint(self.checkpoint_path)
        finally:
            bar.close()
        self.seconds = time.perf_counter() - t0
        if self.checkpoint_path is not None:
            self.save_checkpoint(self.checkpoint_path)
        return self.cgs

    # ------------------------------------------------------------------ checkpoints
    def checkpoint_state(self) -> Checkpoint:
        """The run's current state as a :class:`~controlgs_adapter.formats.checkpoint.Checkpoint` (tensors not copied)."""
        opt = self.optimizer.state_dict()
        return Checkpoint(adapter=self.cgs.injector.state_dict(), optimizer_state=opt["state"],
                          param_groups=opt["param_groups"], rng=self.generator.get_state(), iteration=self.iteration,
                          history=self.history, config=self.config.as_header(), modules=list(self.cgs.modules),
                          effects=sorted(k for k, v in self.effects.items() if v is not None and v is not False),
                          fingerprint=self.cgs.fingerprint, data=self.data_fingerprint, lens=self._lens_fingerprint)

    def save_checkpoint(self, path: str | Path) -> Path:
        """Write adapter, optimizer state, RNG state and iteration to ``path`` (atomically,
        :mod:`controlgs_adapter.formats.checkpoint`; in a distributed run only rank 0 writes, the
        replicas being identical)."""
        self.dist.last_checkpoint = (str(path), self.iteration)
        if not self.dist.is_main:
            return Path(path)
        return write_checkpoint(path, self.checkpoint_state())

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore the state written by :meth:`save_checkpoint`; the trainer must have been built
        with the same backbone, views, config and effects (checked, naming what differs; nothing
        changes when the file is refused)."""
        shapes = [p.shape for g in self.optimizer.param_groups for p in g["params"]]
        saved = read_checkpoint(path, self.checkpoint_state(), shapes)
        try:
            self.optimizer.load_state_dict({"state": saved.optimizer_state, "param_groups": saved.param_groups})
        except (ValueError, KeyError, TypeError, IndexError, RuntimeError) as e:
            raise FileFormatError(f"{path}: checkpoint optimizer state does not fit this optimizer: {e}") from None
        self.cgs.injector.load_state_dict(saved.adapter)
        self.generator.set_state(saved.rng)
        self.iteration = saved.iteration
        self.history = list(saved.history)

    def resume(self) -> bool:
        """Load :attr:`checkpoint_path` if it exists; True if it did."""
        if self.checkpoint_path is not None and self.checkpoint_path.is_file():
            self.load_checkpoint(self.checkpoint_path)
            return True
        return False


def _duration(seconds: float) -> str:
    """``"45s"``, ``"4m10s"``, ``"2h05m"``."""
    s = int(round(seconds))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


class TrainingJob:
    """Progress of a job of several trainings (``controlgs train`` / ``demo``: ControlGS and the
    ablations, times ``--seeds``): each :meth:`Trainer.train` given the job titles its bar
    ``[k/N] <what>`` (``[3/10] training w/o Lens, seed 1``) and shows an estimate of the time the whole job has left, the
    iterations left in it times the mean time of the iterations run so far (a resumed checkpoint's
    iterations count as done and are not timed).

    Args:
        trainings: N, the number of trainings in the job.
        iterations: iterations of each training.
    """

    def __init__(self, trainings: int, iterations: int) -> None:
        self.trainings = int(check_number("trainings", trainings, integer=True, low=1))
        self.iterations = int(check_number("iterations", iterations, integer=True, low=0))
        self.index = 0  # trainings started
        self.done = 0  # iterations of the job done (run or resumed)
        self.ran = 0  # iterations run by this process
        self.seconds = 0.0  # their wall time

    def start(self, what: str, already: int = 0) -> str:
        """Begin the next training (``already``: iterations a checkpoint brought); returns its bar title."""
        self.index = min(self.index + 1, self.trainings)
        self.done = (self.index - 1) * self.iterations + min(int(already), self.iterations)
        return f"[{self.index}/{self.trainings}] {what}"

    def step(self, seconds: float) -> None:
        """One iteration ran, in ``seconds``."""
        self.done += 1
        self.ran += 1
        self.seconds += float(seconds)

    def remaining(self) -> float | None:
        """Estimated seconds left for the whole job (None before an iteration ran)."""
        if not self.ran:
            return None
        return max(0, self.trainings * self.iterations - self.done) * self.seconds / self.ran

    def remaining_text(self) -> str:
        """:meth:`remaining` for a progress bar: ``"~4m10s"`` (``"?"`` before an iteration ran)."""
        left = self.remaining()
        return "?" if left is None else "~" + _duration(left)
