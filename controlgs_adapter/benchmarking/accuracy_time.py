"""What ``controlgs bench`` measures on the built-in scene (the report: :mod:`.report`).

1. per-iteration training time by phase: :meth:`Trainer.step` itself, timed by a
   :class:`~.clock.PhaseClock` (prefilter + decode, splat, stages, PSF, loss, backward, optimizer),
   once per optics operator (distortion-only as in the first 90 % of training, then the full PSF);
2. each accuracy knob (PSF operator, SS factor, condition dimension N, number of modules): time
   per training iteration and test PSNR on the run-time grid after a short training;
3. render-time overhead and storage of ControlGS vs the SS-backbone (paper Tbl. 3).
"""

from __future__ import annotations

import copy
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import torch
from tqdm.auto import tqdm

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.training import TrainConfig, Trainer

from .clock import ClockedRasterizer, PhaseClock, clock_stage

DEFAULT_ITERATIONS = 100
QUICK_ITERATIONS = 20
COND_DIMS: tuple[int, ...] = (2, 4, 8, 16)
#: module sets of the "number of modules" knob, lens first (it matters most, paper Sec. 4.3)
MODULE_SETS: tuple[tuple[str, ...], ...] = (("lens",), ("lens", "display"), ("lens", "resample", "display"))
PSF_MODES: tuple[str, ...] = ("distortion", "fast", "exact")



@dataclass
class BenchSettings:
    """What ``controlgs bench`` runs.

    Attributes:
        resolution: native resolution S of the built-in scene (pixels, square).
        iterations: training iterations of each knob's adapter.
        phase_iterations: timed steps per optics operator in the phase table (after one warm-up).
        repeats: timed frames per render measurement (median reported).
        test_views: test views of the quality evaluation.
        downsample, power_saving: the evaluation grid.
        variant: built-in scene variant.
        seed: training seed (the same for every knob; default :class:`TrainConfig`'s).
    """

    resolution: int = 64
    iterations: int = DEFAULT_ITERATIONS
    phase_iterations: int = 40
    repeats: int = 20
    test_views: int = 4
    downsample: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
    power_saving: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6, 0.8)
    variant: str = "ar"
    seed: int = TrainConfig.seed

    def __post_init__(self) -> None:
        for name in ("resolution", "iterations", "phase_iterations", "repeats", "test_views"):
            if int(getattr(self, name)) < 1:
                raise InputValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if 0.0 not in self.power_saving or 1.0 not in self.downsample:
            raise InputValueError(f"the grid must contain d = 1 and rho = 0, got d {self.downsample}, rho {self.power_saving}")


@dataclass
class BenchResult:
    """Every figure of the report.

    Attributes:
        phases: ``{optics mode: {phase: seconds per iteration}}`` (median over the timed steps).
        knobs: rows ``{"knob", "setting", "s_per_it", "psnr", "ssim"}``.
        ss: rows ``{"d", "render_s_no_ss", "render_s_ss", "psnr_no_ss", "psnr_ss", "psnr_controlgs"}`` (rho = 0).
        overhead: ``{"render_s_ss", "render_s_controlgs", "params_adapter", "params_conditions", "params_backbone",
            "bytes_adapter", "bytes_adapter_fp16", "bytes_backbone"}``.
        info: machine and settings.
    """

    phases: dict[str, dict[str, float]] = field(default_factory=dict)
    knobs: list[dict[str, Any]] = field(default_factory=list)
    ss: list[dict[str, float]] = field(default_factory=list)
    overhead: dict[str, float] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)


def _median_times(fns: Sequence[Any], repeats: int) -> list[float]:
    """Median wall time of each ``fn()`` over ``repeats`` calls after one warm-up call each; the
    calls are interleaved so that a change of machine load hits every ``fn`` alike."""
    times: list[list[float]] = [[] for _ in fns]
    for r in range(repeats + 1):
        for fn, ts in zip(fns, times):
            t = time.perf_counter()
            fn()
            if r:
                ts.append(time.perf_counter() - t)
    return [statistics.median(ts) for ts in times]


def psf_keywords(mode: str) -> dict[str, Any]:
    """:class:`TrainConfig` keywords that run the optics operator ``mode`` of :data:`PSF_MODES` for the
    whole training: ``distortion`` (no PSF), else that PSF mode from the first iteration."""
    return {"psf_fraction": 0.0} if mode == "distortion" else {"psf_fraction": 1.0, "psf_mode": mode}


def phase_times(model: Any, scene: Any, modes: tuple[str, ...], steps: int, seed: int = 0) -> dict[str, dict[str, float]]:
    """Median seconds per training step by phase, for each optics operator of ``modes``.

    One :class:`Trainer` per mode (on its own copy of ``model``, all with ``seed``: the same
    views and states in the same order) steps with a :class:`~.clock.PhaseClock`, split further by a
    :class:`~.clock.ClockedRasterizer` and hooks on the optics stage. Phases: ``sample`` (view and
    state), ``decode`` (prefilter, adapter-injected decoders and the rest of the render call),
    ``splat`` (rasterization), ``stages`` (the pipeline without its optics), ``psf`` (the optics
    stage), ``loss``, ``backward``, ``optimizer`` (Adam and the parameter check), ``total``. The
    trainers step in turn, in a rotating order, so that the modes see the same machine load; the
    first step of each is a warm-up.
    """
    from controlgs_adapter.rendering.rasterizers import use_rasterizer

    def config(mode: str) -> TrainConfig:
        return TrainConfig(iterations=steps + 1, checkpoint_every=0, seed=seed, **psf_keywords(mode))

    trainers = {}
    try:
        for mode in modes:
            trainers[mode] = Trainer(copy.deepcopy(model), scene.views("train"), config(mode))
            if "optics" not in trainers[mode].pipeline:
                raise InputValueError(f"the training pipeline has no optics stage (stages: {trainers[mode].pipeline.names})")
        clock = PhaseClock(trainers[modes[0]].device)
        names = ("sample", "decode", "splat", "stages", "psf", "loss", "backward", "optimizer", "total")
        rows: dict[str, dict[str, list[float]]] = {m: {k: [] for k in names} for m in modes}
        with use_rasterizer(ClockedRasterizer(clock)):
            for it in range(steps + 1):
                for mode in modes[it % len(modes):] + modes[:it % len(modes)]:  # rotated: no mode always runs first
                    trainer = trainers[mode]
                    with clock_stage(clock, trainer.pipeline["optics"], "psf", before="stages"):
                        trainer.step(clock)
                    if it == 0:  # warm-up
                        continue
                    lap = clock.laps
                    for k, v in (("sample", lap["sample"]), ("decode", lap["decode"] + lap["render"]),
                                 ("splat", lap["splat"]), ("stages", lap["stages"] + lap["pipeline"]),
                                 ("psf", lap["psf"]), ("loss", lap["loss"]), ("backward", lap["backward"]),
                                 ("optimizer", lap["optimizer"]), ("total", clock.total)):
                        rows[mode][k].append(v)
    finally:
        for trainer in trainers.values():
            trainer.cgs.unwrap()
    return {m: {k: statistics.median(v) for k, v in r.items()} for m, r in rows.items()}


def _knob_configs(s: BenchSettings) -> list[tuple[str, str, dict[str, Any]]]:
    """(knob, setting, TrainConfig keyword arguments); the reference is the Trainer's defaults
    (N = 8, all modules, distortion-only then 10 % fast PSF)."""
    rows: list[tuple[str, str, dict[str, Any]]] = [("reference", "N=8, 3 modules, 90% distortion + 10% fast", {})]
    for mode in PSF_MODES:
        rows.append(("PSF operator (whole training)", mode, psf_keywords(mode)))
    rows += [("condition dim N", f"N={n}", {"cond_dim": n}) for n in COND_DIMS if n != 8]
    rows += [("modules", "+".join(m), {"modules": m}) for m in MODULE_SETS if len(m) < 3]
    return rows


def knob_results(model: Any, scene: Any, s: BenchSettings, workdir: Path, progress: bool = False) -> tuple[list[dict[str, Any]], Any]:
    """Train one adapter per knob setting for ``s.iterations`` and evaluate all of them (and the
    two baselines) on the grid with the exact PSF. Returns the knob rows and the :class:`GridResult`.

    Each setting trains on its own copy of the backbone and the trainers step in turn (iteration
    i of every setting, then i + 1), so that a change of machine load hits all settings alike;
    the time per iteration is the median over a setting's steps."""
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.scene import load_builtin_backbone

    configs = _knob_configs(s)
    trainers = [Trainer(load_builtin_backbone(s.variant), scene.views("train"),
                        TrainConfig(iterations=s.iterations, checkpoint_every=0, seed=s.seed, **kw))
                for _, _, kw in configs]
    steps: list[list[float]] = [[] for _ in configs]
    adapters: dict[str, Path] = {}
    try:
        for _ in tqdm(range(s.iterations), desc="training knobs", disable=not progress, dynamic_ncols=True):
            for trainer, times in zip(trainers, steps):  # Trainer.train without checkpoints, each step timed
                t = time.perf_counter()
                trainer.step()
                times.append(time.perf_counter() - t)
        for i, trainer in enumerate(trainers):
            adapters[f"k{i}"] = trainer.cgs.save(workdir / f"k{i}.controlgs.safetensors")
    finally:
        for trainer in trainers:
            trainer.cgs.unwrap()
    speed = {f"k{i}": statistics.median(times) for i, times in enumerate(steps)}
    result = evaluate_grid(model, scene.data.views("test", first=s.test_views), adapters, downsample=s.downsample, power_saving=s.power_saving, optics_mode="exact",
                           extra_metrics=False, progress=progress)
    rows = [{"knob": knob, "setting": setting, "s_per_it": speed[f"k{i}"],
             "psnr": result.mean(f"k{i}", "psnr"), "ssim": result.mean(f"k{i}", "ssim")}
            for i, (knob, setting, _) in enumerate(configs)]
    return rows, result


def ss_rows(model: Any, scene: Any, result: Any, s: BenchSettings) -> list[dict[str, float]]:
    """SS factor: render time at S/d (no SS) and at S (SS) and PSNR at rho = 0 of no-SS,
    SS-backbone and the reference adapter (``k0`` of ``result``), per d of the grid."""
    from controlgs_adapter.rendering.protocol import render_view

    cam = scene.test_cameras[0]
    j = list(result.power_saving).index(0.0)
    with torch.no_grad():
        rows = []
        for i, d in enumerate(result.downsample):
            small, full = _median_times([lambda: render_view(None, model, cam.scaled(d), None, scene.background),
                                         lambda: render_view(None, model, cam, None, scene.background)], s.repeats)
            rows.append({"d": d, "render_s_no_ss": small, "render_s_ss": full,
                         "psnr_no_ss": float(result.grid("no_ss", "psnr")[i, j]), "psnr_ss": float(result.grid("ss", "psnr")[i, j]),
                         "psnr_controlgs": float(result.grid("k0", "psnr")[i, j])})
    return rows


def render_overhead(model: Any, scene: Any, adapter: Path, workdir: Path, repeats: int) -> dict[str, float]:
    """Paper Tbl. 3: one frame at S, bare (SS-backbone) vs inside ``conditioned`` (prefilter,
    strengths, injected decoders, splat), and the storage of the adapter vs the backbone."""
    from controlgs_adapter.controlgs import ControlGS
    from controlgs_adapter.scene import builtin_backbone_dir
    from controlgs_adapter.state import RuntimeState
    from controlgs_adapter.rendering.protocol import render_view

    cam = scene.test_cameras[0]
    state = RuntimeState(downsample=2.0, power_saving=0.4)
    backbone_params = sum(p.numel() for p in model.parameters())
    with torch.no_grad():
        cgs = ControlGS.load(adapter, model)
        try:
            bare, wrapped = _median_times([lambda: render_view(None, model, cam, None, scene.background),
                                           lambda: render_view(cgs, model, cam, state, scene.background)], repeats)
            params = sum(p.numel() for p in cgs.trainable_parameters())
            conditions = cgs.injector.conditions.numel()
            fp16 = cgs.save(workdir / "fp16.controlgs.safetensors", dtype=torch.float16)
        finally:
            cgs.unwrap()
    backbone_dir = builtin_backbone_dir(scene.variant) / "point_cloud"
    return {"render_s_ss": bare, "render_s_controlgs": wrapped, "params_adapter": float(params), "params_conditions": float(conditions),
            "params_backbone": float(backbone_params), "bytes_adapter": float(Path(adapter).stat().st_size),
            "bytes_adapter_fp16": float(fp16.stat().st_size),
            "bytes_backbone": float(sum(p.stat().st_size for p in backbone_dir.rglob("*") if p.is_file()))}


def run_bench(s: BenchSettings, progress: bool = False) -> BenchResult:
    """Measure everything of the report on the built-in scene at ``s``."""
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    scene = load_builtin_scene(s.variant, s.resolution, cache=True)
    model = load_builtin_backbone(s.variant)
    nproc = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()  # as `nproc`
    out = BenchResult(info={"nproc": nproc, "threads": torch.get_num_threads(), "torch": torch.__version__,
                            "scene": scene.name, "anchors": model.num_anchors, **vars(s)})
    if progress:
        print("training phases", file=sys.stderr)
    out.phases = phase_times(model, scene, PSF_MODES, s.phase_iterations, s.seed)
    with tempfile.TemporaryDirectory(prefix="controlgs-bench-") as tmp:
        work = Path(tmp)
        out.knobs, grid = knob_results(model, scene, s, work, progress)
        out.ss = ss_rows(model, scene, grid, s)
        out.overhead = render_overhead(model, scene, work / "k0.controlgs.safetensors", work, s.repeats)
    return out

