"""``controlgs bench``: accuracy vs time on the built-in scene (printed; ``--doc`` writes ``docs/benchmarks.md``).

Three measured tables and links to the per-part benchmark docs:

1. per-iteration training time by phase (prefilter + decode, splat, stages, PSF, backward,
   optimizer) from a step composed of the same calls as :meth:`Trainer.step`, once per optics
   operator (distortion-only as in the first 90 % of training, then the full PSF);
2. each accuracy knob (PSF operator, SS factor, condition dimension N, number of modules): time
   per training iteration and test PSNR on the run-time grid after a short training;
3. render-time overhead and storage of ControlGS vs the SS-backbone (paper Tbl. 3).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import shlex
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
from .demo import first_views

DOC_OUT = Path("docs") / "benchmarks.md"
DEFAULT_ITERATIONS = 100
QUICK_ITERATIONS = 20
COND_DIMS: tuple[int, ...] = (2, 4, 8, 16)
#: module sets of the "number of modules" knob, lens first (it matters most, paper Sec. 4.3)
MODULE_SETS: tuple[tuple[str, ...], ...] = (("lens",), ("lens", "display"), ("lens", "resample", "display"))
PSF_MODES: tuple[str, ...] = ("distortion", "fast", "exact")
#: per-part benchmark docs (linked, not re-run)
PART_DOCS: tuple[tuple[str, str, str], ...] = (
    ("benchmarks-injector.md", "condition injector", "python benchmarks/bench_injector.py"),
    ("benchmarks-splatter.md", "splatter (rasterizer)", "python benchmarks/bench_splatter.py"),
    ("benchmarks-stages.md", "downstream stages", "python benchmarks/bench_stages.py"),
    ("optics_bench.md", "PSF operators, error vs time (design: optics.md)", "controlgs optics bench"),
    ("distributed.md", "data-parallel training", "python benchmarks/bench_distributed.py"),
)


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
        seed: training seed (the same for every knob).
    """

    resolution: int = 64
    iterations: int = DEFAULT_ITERATIONS
    phase_iterations: int = 40
    repeats: int = 20
    test_views: int = 4
    downsample: tuple[float, ...] = (1.0, 2.0, 4.0, 8.0)
    power_saving: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6, 0.8)
    variant: str = "ar"
    seed: int = 0

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


def phase_times(model: Any, scene: Any, modes: tuple[str, ...], steps: int, seed: int = 0) -> dict[str, dict[str, float]]:
    """Median seconds per training step by phase, for each optics operator of ``modes``.

    The step is :meth:`Trainer.step` (batch 1, one process) with clocks between its calls:
    ``decode`` = anchor prefilter + the adapter-injected decoders, ``splat`` = rasterization,
    ``stages`` = the pipeline without its optics stage, ``psf`` = the optics stage (timed by
    hooks on the real pipeline's stage), ``backward`` = loss + backward, ``optimizer`` = Adam step.
    Every sampled (view, state) is stepped once per mode in turn (the order rotates), so that the
    modes see the same inputs and the same machine load; the first sample is a warm-up.
    """
    from controlgs_adapter.rendering.splatter import rasterize
    from controlgs_adapter.losses import image_loss
    from controlgs_adapter.training import TrainConfig, Trainer

    trainer = Trainer(model, scene.views("train"), TrainConfig(iterations=steps + 1, checkpoint_every=0, seed=seed))
    pipeline, cgs = trainer.pipeline, trainer.cgs
    if "optics" not in pipeline:
        raise InputValueError(f"the training pipeline has no optics stage (stages: {pipeline.names})")
    optics = pipeline["optics"]
    psf_clock = [0.0, 0.0]  # [start, accumulated]
    hooks = [optics.register_forward_pre_hook(lambda *_: psf_clock.__setitem__(0, time.perf_counter())),
             optics.register_forward_hook(
                 lambda *_: psf_clock.__setitem__(1, psf_clock[1] + time.perf_counter() - psf_clock[0]))]
    names = ("decode", "splat", "stages", "psf", "backward", "optimizer", "total")
    rows: dict[str, dict[str, list[float]]] = {m: {k: [] for k in names} for m in modes}
    try:
        for it in range(steps + 1):
            view, state = trainer.sample()
            cam, gt = trainer.views[view]
            for mode in modes[it % len(modes):] + modes[:it % len(modes)]:  # rotated: no mode always runs first
                optics.mode = mode
                trainer.optimizer.zero_grad(set_to_none=True)
                psf_clock[1] = 0.0
                t0 = time.perf_counter()
                visible = model.visible_anchors(cam)
                with cgs.conditioned(state, cam, visible):
                    g = model.decode(cam, visible)
                    t1 = time.perf_counter()
                    image = rasterize(g.means, g.scales, g.rotations, g.opacities, g.colors, cam, scene.background).color
                t2 = time.perf_counter()
                eye = pipeline(image, state, reference=gt)
                t3 = time.perf_counter()
                image_loss(eye, gt, trainer.config.loss).backward()
                t4 = time.perf_counter()
                trainer.optimizer.step()
                t5 = time.perf_counter()
                if it == 0:  # warm-up
                    continue
                for k, v in zip(names, (t1 - t0, t2 - t1, t3 - t2 - psf_clock[1], psf_clock[1], t4 - t3, t5 - t4, t5 - t0)):
                    rows[mode][k].append(v)
    finally:
        for h in hooks:
            h.remove()
        cgs.unwrap()
    return {m: {k: statistics.median(v) for k, v in r.items()} for m, r in rows.items()}


def _knob_configs(s: BenchSettings) -> list[tuple[str, str, dict[str, Any]]]:
    """(knob, setting, TrainConfig keyword arguments); the reference is the Trainer's defaults
    (N = 8, all modules, distortion-only then 10 % fast PSF)."""
    rows: list[tuple[str, str, dict[str, Any]]] = [("reference", "N=8, 3 modules, 90% distortion + 10% fast", {})]
    for mode in PSF_MODES:
        kw = {"psf_fraction": 0.0} if mode == "distortion" else {"psf_fraction": 1.0, "psf_mode": mode}
        rows.append(("PSF operator (whole training)", mode, kw))
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
    from controlgs_adapter.training import TrainConfig, Trainer

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
    result = evaluate_grid(model, first_views(scene.data, "test", s.test_views), adapters, downsample=s.downsample, power_saving=s.power_saving, optics_mode="exact",
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


# ---------------------------------------------------------------------- report
def _ms(x: float) -> str:
    return f"{x * 1e3:.1f}"


def _size(b: float) -> str:
    return f"{b / 1e3:.1f} kB" if b < 1e6 else f"{b / 1e6:.2f} MB"


def format_report(r: BenchResult, command: str) -> str:
    """The Markdown report (tables in the order of the module docstring)."""
    i = r.info
    grid = f"d in {{{', '.join(f'{d:g}' for d in i['downsample'])}}} x rho in {{{', '.join(f'{p:g}' for p in i['power_saving'])}}}"
    lines = [
        "# Benchmarks: accuracy vs time",
        "",
        f"Generated by `{command}` on {r.info['date']}; machine: `nproc` = {i['nproc']}, torch threads = {i['threads']}, "
        f"torch {i['torch']}. Built-in scene `{i['scene']}` ({i['anchors']} anchors) at S = {i['resolution']} px.",
        "Timings are wall-clock (`time.perf_counter`) on whatever else the machine was running: on a shared 2-core "
        "machine compare rows of the same table (measured in the same run), not absolute figures across runs.",
        "",
        "## 1. Training time per iteration by phase",
        "",
        f"One training step of `Trainer.step` (batch 1) with clocks between its calls; median of {i['phase_iterations']} "
        "samples after a warm-up, each sample stepped in every optics mode in turn, in a rotating order (same inputs, "
        "same machine load), "
        "in ms; *total* is the median of the whole step. *decode*: anchor prefilter + adapter-injected decoders; *splat*: rasterization; "
        "*stages*: the downstream pipeline without its optics; *PSF*: the optics stage; *backward*: loss + backward "
        "through all of them; *optimizer*: Adam. Training runs the distortion-only optics for the first 90 % of the "
        "iterations and the full PSF (`fast` by default) for the rest.",
        "",
        "| optics | decode | splat | stages | PSF | backward | optimizer | total | total vs distortion |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    base = r.phases["distortion"]["total"]
    for mode, p in r.phases.items():
        lines.append(f"| {mode} | " + " | ".join(_ms(p[k]) for k in ("decode", "splat", "stages", "psf", "backward", "optimizer", "total"))
                     + f" | {p['total'] / base:.2f}x |")
    ref = next(k for k in r.knobs if k["knob"] == "reference")
    lines += [
        "",
        "## 2. Accuracy knobs: cost vs quality",
        "",
        f"Each row trains an adapter for {i['iterations']} iterations (seed {i['seed']}, otherwise the Trainer's defaults) "
        f"and evaluates it on {i['test_views']} test view(s) over the grid {grid} through the pipeline with the *exact* PSF. "
        "The trainings step in turn (one iteration of each setting, then the next) on their own copies of the backbone "
        "and the time per iteration is the median of a setting's steps, so that machine load hits all rows alike "
        "(for the reference this is its distortion-phase step). The *modules* rows keep every downstream stage "
        "(the adapter lacks the other conditions); PSNR / SSIM are means over views and grid "
        "(paper Tbl. 1). These are short trainings: differences of a few hundredths of a dB are within run-to-run noise.",
        "",
        "| knob | setting | ms / iteration | PSNR (dB) | Δ PSNR vs reference | SSIM |",
        "|---|---|---:|---:|---:|---:|",
    ]
    for k in r.knobs:
        lines.append(f"| {k['knob']} | {k['setting']} | {_ms(k['s_per_it'])} | {k['psnr']:.2f} | "
                     f"{k['psnr'] - ref['psnr']:+.2f} | {k['ssim']:.4f} |")
    lines += [
        "",
        f"SS factor: the backbone rendered at S/d (no SS) vs at S and area-pooled (SS-backbone, and ControlGS's "
        f"reference adapter above), at rho = 0; render time of one test frame (median of {i['repeats']} interleaved "
        "calls, no grad) and PSNR of the eye image (mean over the test views).",
        "",
        "| d | render at S/d (ms) | render at S (ms) | PSNR no-SS | PSNR SS-backbone | PSNR ControlGS |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for row in r.ss:
        lines.append(f"| {row['d']:g} | {_ms(row['render_s_no_ss'])} | {_ms(row['render_s_ss'])} | {row['psnr_no_ss']:.2f} | "
                     f"{row['psnr_ss']:.2f} | {row['psnr_controlgs']:.2f} |")
    o = r.overhead
    lines += [
        "",
        "## 3. Render overhead and storage (paper Tbl. 3)",
        "",
        f"One frame at S of a test view (median of {i['repeats']} interleaved calls, no grad): the SS-backbone bare vs wrapped by the "
        "reference adapter inside `conditioned` (state d = 2, rho = 0.4: strengths, injected decoders). Storage: the "
        "adapter file (`ControlGS.save`, float32 and float16) vs the backbone's Scaffold-GS files (`point_cloud/`). "
        f"Most adapter parameters are the per-anchor conditions ({o['params_conditions']:.0f} = anchors x modules x N), "
        "so the relative storage grows with N and the number of modules and shrinks with the backbone's per-anchor size.",
        "",
        "| | SS-backbone | ControlGS | overhead |",
        "|---|---:|---:|---:|",
        f"| render time (ms) | {_ms(o['render_s_ss'])} | {_ms(o['render_s_controlgs'])} | "
        f"{(o['render_s_controlgs'] / o['render_s_ss'] - 1) * 100:+.1f} % |",
        f"| parameters | {o['params_backbone']:.0f} | +{o['params_adapter']:.0f} | "
        f"+{o['params_adapter'] / o['params_backbone'] * 100:.1f} % |",
        f"| storage (float32) | {_size(o['bytes_backbone'])} | +{_size(o['bytes_adapter'])} | "
        f"+{o['bytes_adapter'] / o['bytes_backbone'] * 100:.1f} % |",
        f"| storage (adapter float16) | | +{_size(o['bytes_adapter_fp16'])} | "
        f"+{o['bytes_adapter_fp16'] / o['bytes_backbone'] * 100:.1f} % |",
        "",
        "## 4. Per-part benchmarks",
        "",
        "Measured by their own scripts (not re-run by `controlgs bench`):",
        "",
    ]
    lines += [f"- [{doc}]({doc}): {what} (`{cmd}`)" for doc, what, cmd in PART_DOCS]
    return "\n".join(lines) + "\n"


def write_report(text: str, path: str | Path) -> Path:
    """Write ``text`` to ``path`` atomically."""
    from controlgs_adapter.formats.safetensors import atomic_write

    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


# ---------------------------------------------------------------------- CLI
def add_parser(sub: "argparse._SubParsersAction") -> None:
    from .demo import DEFAULT_RESOLUTION

    p = sub.add_parser("bench", help="accuracy vs time on the built-in scene: phases, knobs, overhead (printed; "
                                      "--doc writes docs/benchmarks.md)")
    p.add_argument("--out", type=Path, default=None, help="Markdown report to write (default: print only)")
    p.add_argument("--doc", dest="out", action="store_const", const=DOC_OUT, help=f"write {DOC_OUT}")
    p.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION, help="native resolution S (pixels)")
    p.add_argument("--iterations", type=int, default=None,
                   help=f"training iterations per knob (default {DEFAULT_ITERATIONS}; {QUICK_ITERATIONS} with --quick)")
    p.add_argument("--test-views", type=int, default=None, help="test views of the quality evaluation (default 4; 1 with --quick)")
    p.add_argument("--quick", action="store_true", help="about 2 minutes: fewer iterations, one test view, a 2 x 2 grid")
    p.add_argument("--variant", choices=("ar", "vr"), default="ar")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", dest="progress", action="store_false")
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace) -> BenchSettings:
    """:class:`BenchSettings` of the command line (``--quick`` changes only what is not given)."""
    quick = {"iterations": QUICK_ITERATIONS, "phase_iterations": 6, "repeats": 5, "test_views": 1,
             "downsample": (1.0, 4.0), "power_saving": (0.0, 0.6)} if args.quick else {}
    if args.iterations is not None:
        quick["iterations"] = args.iterations
    if args.test_views is not None:
        quick["test_views"] = args.test_views
    return BenchSettings(resolution=args.resolution, variant=args.variant, seed=args.seed, **quick)


def run(args: argparse.Namespace) -> int:
    settings = settings_from_args(args)
    t0 = time.perf_counter()
    result = run_bench(settings, progress=args.progress)
    result.info["date"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    argv = sys.argv[1:] if sys.argv[1:2] == ["bench"] else ["bench"]
    text = format_report(result, "controlgs " + " ".join(shlex.quote(a) for a in argv))
    text += f"\nTotal time of this run: {math.ceil(time.perf_counter() - t0)} s.\n"
    print(text)
    if args.out is not None:
        print(f"wrote {write_report(text, args.out)}")
    return 0
