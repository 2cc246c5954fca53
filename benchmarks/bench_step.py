"""Time of one ControlGS training step by phase, and its peak memory, at real model sizes.

The scene: a synthetic reference model (:class:`NeuralGaussianModel`, K = 10 offsets, F = 32) whose
anchors lie on the surfaces of a room seen by a 16:9 camera at the origin (back wall, floor,
spheres), spacing from the surface area per anchor, offsets and decoders random (seeded), so that
about 60 % of the K Gaussians of every anchor have a positive opacity. One step is what
``Trainer.step`` does (adapter on all three condition modules, the default downstream pipeline with
distortion-only optics as in the first 90 % of training, the default loss, Adam), split into:

* ``decode``: prefilter (``visible_anchors``) and decoding inside ``cgs.conditioned``;
* ``splat``: ``rasterize`` forward;
* ``pipeline``: downstream pipeline and loss, forward;
* ``backward``: ``loss.backward()`` (pipeline, splatter and decoder backward);
* ``optimizer``: ``Adam.step``.

Each case runs in a fresh subprocess; peak memory is the max RSS during the timed steps minus the
RSS before them. ``--baseline FILE`` runs the same cases with a splatter module loaded from FILE
(e.g. ``git show REV:backends/splatter.py > /tmp/splatter_before.py``) as the reference for the
speed-up column, measured in the same run.

Usage: ``python benchmarks/bench_step.py [--anchors 10000 100000] [--sizes 256 512 1024]
[--threads 2] [--reps 2] [--baseline FILE] [--profile] [--out docs/benchmarks-step.md]``.
"""

from __future__ import annotations

import argparse
import functools
import importlib.util
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

from controlgs_adapter import ControlGS
from controlgs_adapter.rendering import splatter
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.losses import LossWeights, image_loss
from controlgs_adapter.state import Camera, RuntimeState
from controlgs_adapter.training import DEFAULT_EFFECTS, modules_for

ROOT = Path(__file__).resolve().parent.parent
PHASES = ("decode", "splat", "pipeline", "backward", "optimizer")
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


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def load_rasterize(baseline: str | None):
    """``rasterize`` of this tree, or of the splatter module in the file ``baseline``."""
    if not baseline:
        return splatter.rasterize
    spec = importlib.util.spec_from_file_location("controlgs_adapter.backends._splatter_baseline", baseline)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module.rasterize


def measure_case(anchors: int, width: int, args: argparse.Namespace, baseline: str | None) -> dict:
    """Run in a subprocess: seconds per phase (fastest of ``args.reps`` steps after a warm-up), peak MiB."""
    reps, profile = args.reps, args.profile
    rasterize = load_rasterize(baseline)
    if not baseline and args.transmittance_min is not None:
        rasterize = functools.partial(rasterize, transmittance_min=args.transmittance_min)
    model = make_model(anchors, scale=args.scale, opacity_gain=args.opacity_gain)
    cam = camera(width)
    cgs = ControlGS.wrap(model, modules=modules_for(DEFAULT_EFFECTS))
    pipeline = Pipeline.from_config(DEFAULT_EFFECTS)
    pipeline["optics"].mode = "distortion"
    opt = torch.optim.Adam(list(cgs.trainable_parameters()), lr=3e-3)
    gt = torch.rand(3, cam.height, cam.width, generator=torch.Generator().manual_seed(1))
    bg = torch.zeros(3)
    state = RuntimeState(downsample=2.0, power_saving=0.4)
    info: dict = {}

    def step() -> dict[str, float]:
        times, t, cpu = {}, time.perf_counter(), time.process_time()

        def lap(name: str) -> None:
            nonlocal t
            now = time.perf_counter()
            times[name], t = now - t, now

        opt.zero_grad(set_to_none=True)
        visible = model.visible_anchors(cam)
        with cgs.conditioned(state, cam, visible):
            g = model.decode(cam, visible)
        lap("decode")
        out = rasterize(g.means, g.scales, g.rotations, g.opacities, g.colors, cam, bg)
        lap("splat")
        loss = image_loss(pipeline(out.color, state, reference=gt), gt, LossWeights())
        lap("pipeline")
        loss.backward()
        lap("backward")
        opt.step()
        lap("optimizer")
        times["cpu"] = time.process_time() - cpu
        info.update(gaussians=int(g.means.shape[0]), visible=int(out.visible.sum()), anchors_visible=int(visible.sum()))
        return times

    step()  # warm-up
    base = _rss_bytes()
    runs = [step() for _ in range(reps)]
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base
    best = {k: min(r[k] for r in runs) for k in PHASES}
    best["total"] = min(sum(r[k] for k in PHASES) for r in runs)
    best["cpu"] = min(r["cpu"] for r in runs)
    result = {"anchors": anchors, "width": cam.width, "height": cam.height, "s": best,
              "peak_mib": max(peak, 0) / 2**20, **info}
    if profile:
        from torch.profiler import profile as torch_profile

        with torch_profile() as prof:
            step()
        events = {e.key: e for e in prof.key_averages()}
        result["splatter_ms"] = {k: events[k].cpu_time_total / 1e3 if k in events else 0.0 for k in SPLATTER_PHASES}
    return result


def run_case_subprocess(anchors: int, width: int, args: argparse.Namespace, baseline: str | None) -> dict:
    cmd = [sys.executable, __file__, "--case", str(anchors), str(width), "--reps", str(args.reps),
           "--threads", str(args.threads), "--scale", str(args.scale), "--opacity-gain", str(args.opacity_gain)]
    if args.transmittance_min is not None:
        cmd += ["--transmittance-min", str(args.transmittance_min)]
    if baseline:
        cmd += ["--baseline", baseline]
    if args.profile:
        cmd.append("--profile")
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode:
        raise RuntimeError(f"case {anchors} x {width} failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--anchors", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024], help="image widths (16:9)")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    ap.add_argument("--reps", type=int, default=2, help="timed steps per case after a warm-up (fastest reported)")
    ap.add_argument("--baseline", help="splatter module file to compare against (same cases, same run)")
    ap.add_argument("--profile", action="store_true", help="also profile the splatter's phases (one more step)")
    ap.add_argument("--scale", type=float, default=1.0,
                    help="Gaussian size factor (1: light scene, ~37 pairs/px; 3: dense scene, see docs/benchmarks-step.md)")
    ap.add_argument("--opacity-gain", type=float, default=1.0, help="gain of the opacity MLP's tanh pre-activation")
    ap.add_argument("--transmittance-min", type=float,
                    help="rasterize's early-termination threshold for this tree's splatter (default: its default)")
    ap.add_argument("--out", type=Path, help="write the tables to this markdown file")
    ap.add_argument("--case", nargs=2, type=int, metavar=("ANCHORS", "WIDTH"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.case:
        print(json.dumps(measure_case(args.case[0], args.case[1], args, args.baseline)))
        return

    header = ("| anchors | size | Gaussians (visible) | " + " | ".join(PHASES) + " | step (s) | step CPU (s) | peak (MiB) |"
              + (" baseline step (s) | baseline CPU (s) | speed-up (CPU) |" if args.baseline else ""))
    lines = [
        f"`python benchmarks/bench_step.py {' '.join(sys.argv[1:])}` on {platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} logical CPUs, torch {torch.__version__}, {args.threads} thread(s), float32; fastest of "
        f"{args.reps} step(s) after a warm-up; load average {os.getloadavg()[0]:.1f} when started.",
        "",
        header,
        "|" + "---:|" * (header.count("|") - 1),
    ]
    print("\n".join(lines), flush=True)
    profiles = []
    for anchors in args.anchors:
        for width in args.sizes:
            r = run_case_subprocess(anchors, width, args, None)
            s = r["s"]
            line = (f"| {anchors} | {r['width']}x{r['height']} | {r['gaussians']} ({r['visible']}) | "
                    + " | ".join(f"{s[k]:.2f}" for k in PHASES) + f" | **{s['total']:.2f}** | {s['cpu']:.2f} | {r['peak_mib']:.0f} |")
            if args.baseline:
                b = run_case_subprocess(anchors, width, args, args.baseline)
                line += (f" {b['s']['total']:.2f} | {b['s']['cpu']:.2f} | {b['s']['total'] / s['total']:.1f}x "
                         f"({b['s']['cpu'] / s['cpu']:.1f}x) |")
                if args.profile:
                    profiles.append((f"{anchors} x {r['width']}x{r['height']} (baseline)", b["splatter_ms"]))
            if args.profile:
                profiles.append((f"{anchors} x {r['width']}x{r['height']}", r["splatter_ms"]))
            print(line, flush=True)
            lines.append(line)
    if profiles:
        lines += ["", "Splatter phases, ms (torch profiler, one step):", "",
                  "| case | " + " | ".join(f"`{k}`" for k in SPLATTER_PHASES) + " |",
                  "|---|" + "---:|" * len(SPLATTER_PHASES)]
        lines += [f"| {name} | " + " | ".join(f"{ms[k]:.0f}" for k in SPLATTER_PHASES) + " |" for name, ms in profiles]
        print("\n".join(lines[-len(profiles) - 4:]), flush=True)
    if args.out:
        args.out.write_text("\n".join(lines) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
