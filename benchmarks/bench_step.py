"""Time of one ControlGS training step by phase, and its peak memory, at real model sizes.

The scene: a synthetic reference model (:class:`NeuralGaussianModel`, K = 10 offsets, F = 32) whose
anchors lie on the surfaces of a room seen by a 16:9 camera at the origin (back wall, floor,
spheres), spacing from the surface area per anchor, offsets and decoders random (seeded), so that
about 60 % of the K Gaussians of every anchor have a positive opacity. ``--preset dense``
(``--scale 2 --opacity-gain 3``) makes the Gaussians twice as large and more opaque (about 4x the
pairs per pixel of the light scene).

The step is :meth:`Trainer.step` itself (adapter on lens, resample and display, the default
downstream pipeline, the default loss, Adam; view and state sampled as in training) on a one-view
dataset, timed by its :class:`~controlgs_adapter.benchmarking.PhaseClock` (on CUDA each lap waits for
the device): ``sample``, ``decode`` (prefilter, adapter-injected decoders, the rest of the render
call), ``splat`` (rasterizer forward), ``stages`` (pipeline without optics), ``PSF`` (the optics
stage), ``loss``, ``backward``, ``optimizer`` (Adam and the parameter check). Optics: ``exact`` is
the full PSF with the exact operator (the paper's setting), ``fast`` the full PSF with the fast
operator, ``distortion`` the distortion-only optics of the first 90 % of the default training.

One row per device x rasterizer x anchors x size x optics, each in a fresh subprocess; the
fastest of ``--reps`` steps after a warm-up. Peak memory: CPU, the highest resident memory during
the timed steps (sampled every 5 ms) minus that before the warm-up step; CUDA,
``torch.cuda.max_memory_allocated`` during the steps minus the memory allocated before them.
CUDA rows are measured where ``torch.cuda.is_available()``; elsewhere the output says so.
``--baseline FILE`` also runs the CPU cases with the ``rasterize`` of a splatter module loaded from
FILE (e.g. ``git show REV:controlgs_adapter/rendering/splatter.py > /tmp/splatter_before.py``), in
the same run.

Prints the table; ``--doc`` rewrites docs/benchmarks/training-step-cpu.md, or docs/benchmarks/training-step-gpu.md when
only CUDA rows were measured (the generated part; the page's hand-written section from
``## Reading the numbers`` on is kept), so a GPU run does not replace the CPU rows.

Usage: ``python benchmarks/bench_step.py [--anchors 10000 100000] [--sizes 256 512 1024]
[--optics exact distortion] [--device cpu cuda] [--rasterizer torch gsplat] [--preset dense]
[--threads 2] [--reps 2] [--baseline FILE] [--profile] [--doc | --out FILE]``.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import importlib.util
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import torch

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.benchmarking import ClockedRasterizer, PhaseClock, clock_stage
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.rasterizers import Rasterizer, select_rasterizer, use_rasterizer
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig, Trainer

ROOT = Path(__file__).resolve().parent.parent
DOC = ROOT / "docs" / "benchmarks" / "training-step-cpu.md"
DOC_GPU = ROOT / "docs" / "benchmarks" / "training-step-gpu.md"
READING = "## Reading the numbers"
#: column label -> lap(s) of the step's clock
PHASES: dict[str, tuple[str, ...]] = {"sample": ("sample",), "decode": ("decode", "render"), "splat": ("splat",),
                                      "stages": ("stages", "pipeline"), "PSF": ("psf",), "loss": ("loss",),
                                      "backward": ("backward",), "optimizer": ("optimizer",)}
PRESETS = {"light": (1.0, 1.0), "dense": (2.0, 3.0)}  # (scale, opacity gain)
NO_GPU = "no GPU available in this run: GPU rows not measured"
SPLATTER_PHASES = ("splatter.project", "splatter.bin", "splatter.expand_pairs", "splatter.accumulate",
                   "splatter.backward_pairs")


def camera(width: int) -> Camera:
    """16:9 pinhole camera at the origin looking down +z, horizontal FoV 64 deg."""
    height = round(width * 9 / 16)
    k = torch.tensor([[0.8 * width, 0.0, width / 2], [0.0, 0.8 * width, height / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, width, height)


def make_model(anchors: int, seed: int = 0, scale: float = 1.0, opacity_gain: float = 1.0) -> NeuralGaussianModel:
    """Reference model with ``anchors`` anchors on the room's surfaces (see the module docstring);
    ``scale`` multiplies the Gaussians' size (not their offsets), ``opacity_gain`` the pre-activation of
    the opacity MLP's tanh (higher: more opaque Gaussians, the same ones kept)."""
    g = torch.Generator().manual_seed(seed)

    def u(n: int, lo: float, hi: float) -> torch.Tensor:
        return lo + (hi - lo) * torch.rand(n, generator=g)

    centres = torch.stack([u(12, -2.5, 2.5), u(12, -1.0, 1.0), u(12, 3.0, 7.0)], 1)
    radii = u(12, 0.3, 0.9)
    areas = torch.tensor([11.2 * 4.5, 0.7 * (8.0**2 - 3.0**2), float((4 * math.pi * radii**2).sum())])
    n_wall, n_floor = (int(anchors * float(a / areas.sum())) for a in areas[:2])
    n_sph = anchors - n_wall - n_floor
    wall = torch.stack([u(n_wall, -5.6, 5.6), u(n_wall, -3.0, 1.5), torch.full((n_wall,), 8.0)], 1)
    zf = torch.sqrt(u(n_floor, 3.0**2, 8.0**2))  # uniform over the floor's area
    floor = torch.stack([u(n_floor, -0.7, 0.7) * zf, torch.full((n_floor,), 1.5), zf], 1)
    which = torch.multinomial(radii**2, n_sph, replacement=True, generator=g)
    dirs = torch.nn.functional.normalize(torch.randn(n_sph, 3, generator=g), dim=1)
    sph = centres[which] + radii[which, None] * dirs
    spacing = math.sqrt(float(areas.sum()) / anchors)  # mean distance between neighbouring anchors
    model = NeuralGaussianModel(anchors, feat_dim=32, n_offsets=10, voxel_size=spacing)
    with torch.no_grad():
        model._anchor.copy_(torch.cat([wall, floor, sph]))
        model._offset.copy_(0.6 * torch.randn(anchors, 10, 3, generator=g))
        model._anchor_feat.copy_(torch.randn(anchors, 32, generator=g))
        model._scaling.copy_(torch.tensor([math.log(spacing)] * 3 + [math.log(0.3 * scale * spacing)] * 3).expand(anchors, 6))
        for mlp in (model.mlp_opacity, model.mlp_cov, model.mlp_color):
            for layer in mlp:
                if isinstance(layer, torch.nn.Linear):
                    layer.weight.copy_(torch.randn(layer.weight.shape, generator=g) / math.sqrt(layer.in_features))
                    layer.bias.zero_()
        model.mlp_opacity[-2].bias.fill_(0.3)
        model.mlp_opacity[-2].weight.mul_(opacity_gain)
        model.mlp_opacity[-2].bias.mul_(opacity_gain)
    return model


class OneView:
    """A one-view training dataset (:class:`~controlgs_adapter.training.Views`): ``camera`` and a
    random sRGB target ``[3, H, W]`` (seeded), black background."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera
        self.image = torch.rand(3, camera.height, camera.width, generator=torch.Generator().manual_seed(1))
        self.background = torch.zeros(3)

    def __len__(self) -> int:
        return 1

    def __getitem__(self, i: int) -> tuple[Camera, torch.Tensor]:
        return self.camera, self.image


class FunctionRasterizer(Rasterizer):
    """A ``rasterize`` function with the splatter's signature as a rasterizer (the ``--baseline``
    module's, or this tree's with another ``transmittance_min``)."""

    def __init__(self, name: str, fn: Callable[..., Any]) -> None:
        self.name, self.fn = name, fn  # type: ignore[misc]

    def unavailable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        return None

    def __call__(self, means, scales, rotations, opacities, colors, camera, background=None):  # noqa: D102
        return self.fn(means, scales, rotations, opacities, colors, camera, background)


class CountingClockedRasterizer(ClockedRasterizer):
    """:class:`ClockedRasterizer` that also keeps the last render's Gaussians and visibility mask
    (read after the step: no host sync inside it)."""

    last: tuple[int, torch.Tensor] | None = None

    def __call__(self, means, scales, rotations, opacities, colors, camera, background=None):  # noqa: D102
        out = super().__call__(means, scales, rotations, opacities, colors, camera, background)
        self.last = (int(means.shape[0]), out.visible)
        return out


def load_rasterize(baseline: str) -> Callable[..., Any]:
    """``rasterize`` of the splatter module in the file ``baseline``."""
    spec = importlib.util.spec_from_file_location("controlgs_adapter.rendering._splatter_baseline", baseline)
    if spec is None or spec.loader is None:
        raise InputValueError(f"--baseline {baseline}: not a Python module file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module.rasterize


class PeakRSS:
    """Highest resident memory (bytes) of this process while the block runs, sampled every 5 ms."""

    def __enter__(self) -> "PeakRSS":
        self.peak, self._stop = rss_bytes(), threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)
        self._thread.start()
        return self

    def _poll(self) -> None:
        while not self._stop.wait(0.005):
            self.peak = max(self.peak, rss_bytes())

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, rss_bytes())


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def measure_case(device: str, rasterizer: str, anchors: int, width: int, optics: str, args: argparse.Namespace,
                 baseline: str | None) -> dict[str, Any]:
    """Run in a subprocess: seconds per phase of the fastest of ``args.reps`` steps after a warm-up,
    process CPU seconds of that step, peak MiB, Gaussians drawn."""
    dev = torch.device(device)
    scale, gain = PRESETS[args.preset] if args.preset else (args.scale, args.opacity_gain)
    if baseline:
        inner: str | Rasterizer = FunctionRasterizer("baseline", load_rasterize(baseline))
    elif args.transmittance_min is not None and rasterizer == "torch":
        inner = FunctionRasterizer(f"torch, transmittance_min {args.transmittance_min:g}",
                                   functools.partial(splatter.rasterize, transmittance_min=args.transmittance_min))
    else:
        inner = rasterizer
    model = make_model(anchors, scale=scale, opacity_gain=gain).to(dev)
    views = OneView(camera(width))
    psf = {"psf_fraction": 0.0} if optics == "distortion" else {"psf_fraction": 1.0, "psf_mode": optics}
    trainer = Trainer(model, views, TrainConfig(iterations=args.reps + 1, checkpoint_every=0, **psf))
    clock = PhaseClock(dev)
    raster = CountingClockedRasterizer(clock, inner)

    def step() -> dict[str, float]:
        cpu = time.process_time()
        with use_rasterizer(raster), clock_stage(clock, trainer.pipeline["optics"], "psf", before="stages"):
            trainer.step(clock)
        times = {label: sum(clock.laps[k] for k in laps) for label, laps in PHASES.items()}
        return {**times, "total": clock.total, "cpu": time.process_time() - cpu}

    cuda = dev.type == "cuda"
    try:
        base = torch.cuda.memory_allocated(dev) if cuda else rss_bytes()
        step()  # warm-up
        if cuda:
            torch.cuda.reset_peak_memory_stats(dev)
        with PeakRSS() as rss:
            runs = [step() for _ in range(args.reps)]
        peak = torch.cuda.max_memory_allocated(dev) if cuda else rss.peak
        assert raster.last is not None
        result: dict[str, Any] = {
            "device": device, "rasterizer": select_rasterizer(dev, torch.float32, inner).name,
            "anchors": anchors, "width": views.camera.width, "height": views.camera.height, "optics": optics,
            "s": min(runs, key=lambda r: r["total"]), "peak_mib": max(peak - base, 0) / 2**20,
            "gaussians": raster.last[0], "visible": int(raster.last[1].sum())}
        if args.profile:
            from torch.profiler import profile as torch_profile

            with torch_profile() as prof:
                step()
            events = {e.key: e for e in prof.key_averages()}
            result["splatter_ms"] = {k: events[k].cpu_time_total / 1e3 if k in events else 0.0 for k in SPLATTER_PHASES}
    finally:
        trainer.cgs.unwrap()
    return result


def case_options(args: argparse.Namespace) -> list[str]:
    """The options of this run that a case subprocess needs."""
    opts = ["--reps", str(args.reps), "--threads", str(args.threads)]
    opts += ["--preset", args.preset] if args.preset else ["--scale", str(args.scale), "--opacity-gain", str(args.opacity_gain)]
    if args.transmittance_min is not None:
        opts += ["--transmittance-min", str(args.transmittance_min)]
    return opts + (["--profile"] if args.profile else [])


def run_case(case: tuple[str, str, int, int, str], args: argparse.Namespace, baseline: str | None) -> dict[str, Any]:
    """:func:`measure_case` in a fresh process."""
    cmd = [sys.executable, __file__, "--case", *map(str, case), *case_options(args)]
    if baseline:
        cmd += ["--baseline", baseline]
    env = dict(os.environ)
    if args.omp_wait_policy != "default":
        env["OMP_WAIT_POLICY"] = args.omp_wait_policy  # read by OpenMP when the process starts
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if res.returncode:
        raise RuntimeError(f"case {case} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def plan(args: argparse.Namespace) -> tuple[list[tuple[str, str]], list[str]]:
    """(device, rasterizer) pairs to measure, and a line for each pair that cannot run here (why)."""
    pairs, notes = [], []
    for device in args.device:
        if torch.device(device).type == "cuda" and not torch.cuda.is_available():
            notes.append(NO_GPU + f" ({device}: torch.cuda.is_available() is False).")
            continue
        for name in args.rasterizer:
            try:
                pairs.append((device, select_rasterizer(device, torch.float32, name).name))
            except InputValueError as e:
                notes.append(f"not measured: {device} x {name}: {e}.")
    return pairs, notes


def header(args: argparse.Namespace) -> list[str]:
    cols = ["device", "rasterizer", "anchors", "size", "optics", "Gaussians (visible)", *PHASES, "step (s)", "it/s",
            "step CPU (s)", "peak (MiB)"]
    if args.baseline:
        cols += ["baseline step (s)", "baseline CPU (s)", "speed-up (CPU)"]
    return ["| " + " | ".join(cols) + " |", "|" + "---|" * 5 + "---:|" * (len(cols) - 5)]


def row(r: dict[str, Any], b: dict[str, Any] | None, baseline_cols: bool) -> str:
    """Table row of case ``r`` (and its baseline ``b``; empty cells when ``baseline_cols`` and none)."""
    s = r["s"]
    cells = [r["device"], r["rasterizer"], str(r["anchors"]), f"{r['width']}x{r['height']}", r["optics"],
             f"{r['gaussians']} ({r['visible']})", *(f"{s[k]:.2f}" for k in PHASES), f"**{s['total']:.2f}**",
             f"{1 / s['total']:.2f}", f"{s['cpu']:.2f}", f"{r['peak_mib']:.0f}"]
    if b is not None:
        bs = b["s"]
        cells += [f"{bs['total']:.2f}", f"{bs['cpu']:.2f}", f"{bs['total'] / s['total']:.1f}x ({bs['cpu'] / s['cpu']:.1f}x)"]
    elif baseline_cols:
        cells += ["", "", ""]
    return "| " + " | ".join(cells) + " |"


def machine_line(args: argparse.Namespace) -> str:
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "none"
    return (f"Machine: {platform.machine()}, {os.cpu_count()} logical CPUs (load average {os.getloadavg()[0]:.1f} "
            f"when started), GPU: {gpu}; torch {torch.__version__}, {args.threads} CPU thread(s), "
            f"OMP_WAIT_POLICY={args.omp_wait_policy}, float32; "
            f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC.")


def tree_line() -> str:
    """The measured code: its commit and the library files that differ from it (a row measures the
    working tree as its process found it)."""
    def git(*cmd: str) -> str:
        res = subprocess.run(["git", "-C", str(ROOT), *cmd], capture_output=True, text=True)
        return res.stdout if res.returncode == 0 else ""

    head = git("rev-parse", "--short", "HEAD").strip()
    if not head:
        return "Code: not a git checkout."
    dirty = [line[3:] for line in git("status", "--porcelain", "--", "controlgs_adapter", "backends", "downstream").splitlines()]
    return f"Code: commit {head}" + (f", with uncommitted changes in {', '.join(dirty)}." if dirty else ", no uncommitted changes.")


def write_doc(path: Path, generated: list[str]) -> None:
    """Rewrite ``path``: the generated part, then the page's hand-written reading section (kept)."""
    old = path.read_text() if path.is_file() else ""
    reading = old[old.index(READING):] if READING in old else f"{READING}\n\n(to be written)\n"
    path.write_text("\n".join(generated) + "\n\n" + reading)


def doc_page(pairs: list[tuple[str, str]]) -> Path:
    """The page ``--doc`` rewrites for the (device, rasterizer) pairs measured: the GPU page when
    all are CUDA, else the CPU page."""
    return DOC_GPU if pairs and all(torch.device(d).type == "cuda" for d, _ in pairs) else DOC


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--anchors", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024], help="image widths, the longer side (16:9)")
    ap.add_argument("--optics", nargs="+", choices=("exact", "fast", "distortion"), default=["exact", "distortion"],
                    help="optics of the step (default: exact, the paper's full PSF, and distortion, the default "
                         "training's first 90%%)")
    ap.add_argument("--device", nargs="+", default=["cpu", "cuda"], help="devices (CUDA rows where a GPU is available)")
    ap.add_argument("--rasterizer", nargs="+", default=["torch", "gsplat"],
                    help="registered rasterizers to measure on each device where they run (default: torch, gsplat)")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op CPU threads (default 2)")
    ap.add_argument("--omp-wait-policy", choices=("passive", "active", "default"), default="passive",
                    help="OMP_WAIT_POLICY of the case processes (default passive: idle OpenMP threads sleep; with "
                         "the runtime's default they spin, and on a shared machine the step then measures waiting)")
    ap.add_argument("--reps", type=int, default=2, help="timed steps per case after a warm-up (fastest reported)")
    ap.add_argument("--preset", choices=tuple(PRESETS), help="scene preset: light (--scale 1 --opacity-gain 1) or "
                                                             "dense (--scale 2 --opacity-gain 3)")
    ap.add_argument("--scale", type=float, default=1.0, help="Gaussian size factor (default 1: the light scene)")
    ap.add_argument("--opacity-gain", type=float, default=1.0, help="gain of the opacity MLP's tanh pre-activation")
    ap.add_argument("--transmittance-min", type=float,
                    help="the torch splatter's early-termination threshold (default: its default)")
    ap.add_argument("--baseline", help="splatter module file to compare the CPU torch rows against (same cases, same run)")
    ap.add_argument("--profile", action="store_true", help="also profile the splatter's phases (one more step)")
    ap.add_argument("--doc", action="store_true", help=f"rewrite {DOC.relative_to(ROOT)}, or {DOC_GPU.relative_to(ROOT)} "
                                                       "when only CUDA rows are measured")
    ap.add_argument("--out", type=Path, help="write the page to this Markdown file")
    ap.add_argument("--case", nargs=5, metavar=("DEVICE", "RASTERIZER", "ANCHORS", "WIDTH", "OPTICS"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.case:
        device, rasterizer, anchors, width, optics = args.case
        print(json.dumps(measure_case(device, rasterizer, int(anchors), int(width), optics, args, args.baseline)))
        return

    pairs, notes = plan(args)
    if args.doc:
        args.out = doc_page(pairs)
    command = "python benchmarks/bench_step.py " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    scene = f"preset {args.preset}" if args.preset else f"--scale {args.scale:g} --opacity-gain {args.opacity_gain:g}"
    title = "Training step on a GPU" if any(d != "cpu" for d, _ in pairs) else "Training step on the CPU"
    lines = [f"# {title}", "",
             f"Generated by `{command.strip()}` (`benchmarks/bench_step.py`: what is measured and how). Scene: {scene}; "
             f"fastest of {args.reps} step(s) after a warm-up, each case in a fresh process; times in seconds.", "",
             machine_line(args), tree_line(), "", *(line for n in sorted(notes, key=lambda n: not n.startswith(NO_GPU))
                                        for line in (f"**{n}**" if n.startswith(NO_GPU) else n, "")),
             *header(args)]
    print("\n".join(lines), flush=True)
    profiles = []
    for device, rasterizer in pairs:
        for anchors in args.anchors:
            for width in args.sizes:
                for optics in args.optics:
                    case = (device, rasterizer, anchors, width, optics)
                    r = run_case(case, args, None)
                    b = run_case(case, args, args.baseline) if args.baseline and device == "cpu" and rasterizer == "torch" else None
                    if args.profile:
                        profiles.append((f"{device} {rasterizer} {anchors} x {r['width']}x{r['height']} {optics}", r["splatter_ms"]))
                    lines.append(row(r, b, bool(args.baseline)))
                    print(lines[-1], flush=True)
    lines += ["", "Load average when finished: {:.1f} / {:.1f} / {:.1f} (1 / 5 / 15 min).".format(*os.getloadavg())]
    print(lines[-1], flush=True)
    if profiles:
        extra = ["", "Splatter phases, ms (torch profiler, one step):", "",
                 "| case | " + " | ".join(f"`{k}`" for k in SPLATTER_PHASES) + " |", "|---|" + "---:|" * len(SPLATTER_PHASES)]
        extra += [f"| {name} | " + " | ".join(f"{ms[k]:.0f}" for k in SPLATTER_PHASES) + " |" for name, ms in profiles]
        print("\n".join(extra), flush=True)
        lines += extra
    if args.out:
        write_doc(args.out, lines)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
