"""Speed and memory of the CPU splatter (``controlgs_adapter.rendering.splatter.rasterize``).

Measures, on a synthetic scene whose Gaussians fill the view (projected standard deviations
log-normal around ``sqrt(50k / N)`` px at 256^2, opacities U(0.05, 0.95), random rotations):

1. forward and forward+backward time and peak memory for N in {1k, 10k, 50k} at 128^2, 256^2, 512^2
   (each case in a fresh subprocess; peak = max RSS during the render minus RSS before it);
2. the brute-force reference (``rasterize_reference``) on a small case, as the speed-up baseline;
3. the cost of supersampling as in the paper's Tbl. S2: render at S then area-pool to S/d versus
   render directly at S/d (``camera.scaled(d)``), d in {2, 4, 8};
4. where the time goes (top operators of one 50k @ 256^2 forward+backward, torch profiler);
5. the training scene of ``bench_step.py``'s dense preset (100k anchors, ~640k visible Gaussians) at
   288x512 and 576x1024: forward and backward CPU time of the splatter alone, and of the splatter in
   the file ``--baseline`` (e.g. ``git show REV:controlgs_adapter/rendering/splatter.py > /tmp/splatter_before.py``)
   in the same run, each case in a fresh process.

Usage: ``python benchmarks/bench_splatter.py [--quick] [--threads 2] [--baseline FILE] [--dense-only]
[--doc | --out FILE]`` (prints; ``--doc`` writes docs/benchmarks/splatter.md).
"""

from __future__ import annotations

import argparse
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

from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.state import Camera

ROOT = Path(__file__).resolve().parent.parent


def make_scene(n: int, size: int, seed: int = 0):
    """``n`` Gaussians in the view frustum of a ``size`` x ``size`` camera (f = size px, 53 deg FoV).
    The world-space scene does not depend on ``size``."""
    g = torch.Generator().manual_seed(seed)
    z = 2.0 + 4.0 * torch.rand(n, generator=g)
    xy = (torch.rand(n, 2, generator=g) * 2 - 1) * 0.5 * z[:, None]
    means = torch.cat([xy, z[:, None]], -1)
    sigma_px_at_256 = torch.exp(0.4 * torch.randn(n, 3, generator=g)) * math.sqrt(50_000 / n)
    scales = sigma_px_at_256 * z[:, None] / 256.0
    rotations = torch.randn(n, 4, generator=g)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [means, scales, rotations, opacities, colors], camera(size)


def camera(size: int) -> Camera:
    k = torch.tensor([[float(size), 0.0, size / 2], [0.0, float(size), size / 2], [0.0, 0.0, 1.0]])
    return Camera(torch.eye(4), k, size, size)


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _time_both(fn, reps: int) -> tuple[float, float]:
    """(fastest wall-clock, fastest process CPU) seconds of ``reps`` runs after a warm-up."""
    fn()
    wall, cpu = [], []
    for _ in range(reps):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return min(wall), min(cpu)


def measure_case(n: int, size: int, reps: int) -> dict:
    """Run in a subprocess: times (s) and peak memory (MiB) of forward and forward+backward."""
    params, cam = make_scene(n, size)
    leaves = [p.clone().requires_grad_() for p in params]

    def forward():
        with torch.no_grad():
            return rasterize(*params, cam)

    def forward_backward():
        out = rasterize(*leaves, cam)
        (out.color.sum() + out.depth.sum()).backward()
        return out

    base = _rss_bytes()
    t_fwd, cpu_fwd = _time_both(forward, reps)
    peak_fwd = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base
    t_fb, cpu_fb = _time_both(forward_backward, reps)
    peak_fb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base
    out = forward()
    return {
        "n": n, "size": size, "fwd_s": t_fwd, "fwd_bwd_s": t_fb, "fwd_cpu_s": cpu_fwd, "fwd_bwd_cpu_s": cpu_fb,
        "peak_fwd_mib": max(peak_fwd, 0) / 2**20, "peak_fwd_bwd_mib": max(peak_fb, 0) / 2**20,
        "visible": int(out.visible.sum()), "mean_alpha": float(out.alpha.mean()),
    }


def run_case_subprocess(n: int, size: int, reps: int, threads: int) -> dict:
    cmd = [sys.executable, __file__, "--case", str(n), str(size), "--reps", str(reps), "--threads", str(threads)]
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def measure_reference(n: int, size: int) -> list[tuple[float, float]]:
    """(wall, CPU) forward+backward seconds of the tiled splatter and of the brute-force reference."""
    from controlgs_adapter.rendering.splatter_reference import rasterize_reference

    params, cam = make_scene(n, size)
    times = []
    for fn in (rasterize, rasterize_reference):
        leaves = [p.clone().requires_grad_() for p in params]

        def step():
            out = fn(*leaves, cam)
            (out.color.sum() + out.depth.sum()).backward()

        times.append(_time_both(step, 1))
    return times


def measure_supersampling(n: int, size: int, reps: int) -> list[dict]:
    """Render at S and area-pool to S/d vs render directly at S/d (forward, and forward+backward)."""
    from controlgs_adapter.downstream.resample import area_resample

    params, cam = make_scene(n, size)
    rows = []
    for d in (2, 4, 8):
        small = cam.scaled(d)

        def ss(grad: bool):
            leaves = [p.clone().requires_grad_(grad) for p in params]
            img = area_resample(rasterize(*leaves, cam).color, d)
            if grad:
                img.sum().backward()

        def direct(grad: bool):
            leaves = [p.clone().requires_grad_(grad) for p in params]
            img = rasterize(*leaves, small).color
            if grad:
                img.sum().backward()

        row = {"d": d, "size": size, "small": small.width}
        for grad in (False, True):
            key = "fwd_bwd" if grad else "fwd"
            row[f"ss_{key}_s"] = _time_both(lambda: ss(grad), reps)
            row[f"direct_{key}_s"] = _time_both(lambda: direct(grad), reps)
        rows.append(row)
    return rows


DENSE_WIDTHS = (512, 1024)


def measure_dense(width: int, reps: int, baseline: str | None) -> dict:
    """Run in a subprocess: fastest forward and backward CPU seconds of the splatter (this tree's, or the
    one in the file ``baseline``) on ``bench_step.py``'s dense scene at ``width`` px (16:9)."""
    from bench_step import PRESETS, camera as step_camera, load_rasterize, make_model

    fn = load_rasterize(baseline) if baseline else rasterize
    scale, gain = PRESETS["dense"]
    model, cam = make_model(100_000, scale=scale, opacity_gain=gain), step_camera(width)
    with torch.no_grad():
        g = model.decode(cam, model.visible_anchors(cam))
    params = [g.means, g.scales, g.rotations, g.opacities, g.colors]
    weights = torch.rand(3, cam.height, cam.width, generator=torch.Generator().manual_seed(1))
    times = []
    for _ in range(reps + 1):  # the first is a warm-up
        leaves = [p.clone().requires_grad_() for p in params]
        c0 = time.process_time()
        out = fn(*leaves, cam, torch.zeros(3))
        c1 = time.process_time()
        (out.color * weights).sum().backward()
        times.append((c1 - c0, time.process_time() - c1))
    return {"width": cam.width, "height": cam.height, "gaussians": len(params[0]), "visible": int(out.visible.sum()),
            "fwd_cpu_s": min(t[0] for t in times[1:]), "bwd_cpu_s": min(t[1] for t in times[1:])}


def run_dense_subprocess(width: int, reps: int, threads: int, baseline: str | None) -> dict:
    cmd = [sys.executable, __file__, "--dense-case", str(width), "--reps", str(reps), "--threads", str(threads)]
    res = subprocess.run(cmd + (["--baseline", baseline] if baseline else []), capture_output=True, text=True, check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def dense_section(reps: int, threads: int, baseline: str | None) -> list[str]:
    """The dense training scene's table (markdown lines)."""
    lines = [
        "## Dense training scene (`bench_step.py --preset dense`, 100k anchors)",
        "",
        f"The Gaussians one training step renders (decoded once, no grad through the decoder), `rasterize` "
        f"with early termination at its default, then `backward` of a weighted colour sum; process CPU seconds "
        f"(all threads), fastest of {reps} after a warm-up, each case in a fresh process"
        + (f"; baseline: the splatter in `{baseline}`, same run." if baseline else "."),
        "",
        "| size | Gaussians (visible) | splatter | fwd CPU (s) | bwd CPU (s) | fwd+bwd CPU (s) | speed-up (fwd+bwd) |",
        "|---:|---:|---|---:|---:|---:|---:|",
    ]
    for width in DENSE_WIDTHS:
        r = run_dense_subprocess(width, reps, threads, None)
        b = run_dense_subprocess(width, reps, threads, baseline) if baseline else None
        for name, x in (("this tree", r), ("baseline", b)):
            if x is None:
                continue
            total = x["fwd_cpu_s"] + x["bwd_cpu_s"]
            speed = f"{(b['fwd_cpu_s'] + b['bwd_cpu_s']) / total:.1f}x" if b and x is r else ""
            lines.append(f"| {x['height']}x{x['width']} | {x['gaussians']} ({x['visible']}) | {name} | "
                         f"{x['fwd_cpu_s']:.2f} | {x['bwd_cpu_s']:.2f} | {total:.2f} | {speed} |")
            print(lines[-1], flush=True)
    return lines


PHASES = ("splatter.project", "splatter.bin", "splatter.expand_pairs", "splatter.accumulate",
          "splatter.backward_pairs")


def profile_phases(n: int, size: int) -> tuple[list[tuple[str, float]], float]:
    """CPU ms of each ``splatter.*`` phase (profiler labels) in one forward+backward, and the total."""
    from torch.profiler import profile

    params, cam = make_scene(n, size)
    leaves = [p.clone().requires_grad_() for p in params]
    out = rasterize(*leaves, cam)  # warm-up
    out.color.sum().backward()
    with profile() as prof:
        out = rasterize(*leaves, cam)
        (out.color.sum() + out.depth.sum()).backward()
    events = {e.key: e for e in prof.key_averages()}
    total = sum(e.self_cpu_time_total for e in events.values()) / 1e3
    return [(k, events[k].cpu_time_total / 1e3 if k in events else 0.0) for k in PHASES], total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small run: 1k/10k at 128^2/256^2, one repetition")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads (default 2)")
    ap.add_argument("--reps", type=int, default=3, help="timed repetitions per case (the fastest is reported)")
    ap.add_argument("--out", type=Path, default=None, help="write the report to this file (default: print only)")
    ap.add_argument("--doc", dest="out", action="store_const", const=ROOT / "docs" / "benchmarks" / "splatter.md",
                    help="write docs/benchmarks/splatter.md")
    ap.add_argument("--baseline", help="splatter module file for the dense scene's baseline rows (same run)")
    ap.add_argument("--dense-only", action="store_true", help="only the dense training scene's table")
    ap.add_argument("--case", nargs=2, type=int, metavar=("N", "SIZE"), help=argparse.SUPPRESS)
    ap.add_argument("--dense-case", type=int, metavar="WIDTH", help=argparse.SUPPRESS)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.case:
        print(json.dumps(measure_case(args.case[0], args.case[1], args.reps)))
        return
    if args.dense_case:
        print(json.dumps(measure_dense(args.dense_case, args.reps, args.baseline)))
        return
    if args.dense_only:
        print("\n".join(dense_section(args.reps, args.threads, args.baseline)))
        return

    counts = (1_000, 10_000) if args.quick else (1_000, 10_000, 50_000)
    sizes = (128, 256) if args.quick else (128, 256, 512)
    reps = 1 if args.quick else args.reps
    lines = [
        "# CPU splatter benchmark",
        "",
        f"`python benchmarks/bench_splatter.py{' --quick' if args.quick else ''} --threads {args.threads}"
        f"{' --baseline ' + args.baseline if args.baseline else ''} --doc` on "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} logical CPUs, torch {torch.__version__}, "
        f"{args.threads} thread(s), float32, fastest of {reps} run(s) after a warm-up; load average "
        f"{os.getloadavg()[0]:.1f} when started. On a machine shared with other jobs the wall-clock "
        "figures are upper bounds; the process CPU time (all threads) is less sensitive to that load.",
        "",
        "Scene: N Gaussians filling the view, projected sigma log-normal around sqrt(50k/N) px at 256^2 "
        "(same world-space scene at every resolution), opacities U(0.05, 0.95). Peak memory: max RSS during "
        "the render minus RSS before it (fresh process per case).",
        "",
        "## Forward and forward+backward",
        "",
        "| N | size | visible | mean alpha | fwd wall (ms) | fwd+bwd wall (ms) | fwd CPU (ms) | fwd+bwd CPU (ms) "
        "| bwd / fwd (CPU) | peak fwd (MiB) | peak fwd+bwd (MiB) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for n in counts:
        for size in sizes:
            r = run_case_subprocess(n, size, reps, args.threads)
            bwd = r["fwd_bwd_cpu_s"] - r["fwd_cpu_s"]
            line = (
                f"| {n} | {size}^2 | {r['visible']} | {r['mean_alpha']:.2f} | {1e3 * r['fwd_s']:.0f} | "
                f"{1e3 * r['fwd_bwd_s']:.0f} | {1e3 * r['fwd_cpu_s']:.0f} | {1e3 * r['fwd_bwd_cpu_s']:.0f} | "
                f"{bwd / r['fwd_cpu_s']:.2f} | {r['peak_fwd_mib']:.0f} | {r['peak_fwd_bwd_mib']:.0f} |"
            )
            print(line, flush=True)
            lines.append(line)

    ref_n, ref_size = (100, 32) if args.quick else (300, 48)
    (w_fast, c_fast), (w_ref, c_ref) = measure_reference(ref_n, ref_size)
    lines += [
        "",
        "## Against the brute-force reference",
        "",
        f"{ref_n} Gaussians at {ref_size}^2, forward+backward, wall (CPU): tiled {1e3 * w_fast:.0f} "
        f"({1e3 * c_fast:.0f}) ms, brute-force float64 reference {1e3 * w_ref:.0f} ({1e3 * c_ref:.0f}) ms, "
        f"{c_ref / c_fast:.0f}x the CPU time.",
    ]
    print(lines[-1], flush=True)

    ss_n, ss_size = (10_000, 256) if args.quick else (50_000, 512)
    lines += [
        "",
        f"## Supersampling cost (paper Tbl. S2): {ss_n} Gaussians, S = {ss_size}^2",
        "",
        "SS: render at S, area-pool to S/d (`downstream.resample.area_resample`); direct: render at "
        "`camera.scaled(d)`. Ratio of CPU times; > 1: supersampling is slower.",
        "",
        "| d | S/d | SS fwd, ms wall (CPU) | direct fwd | ratio (CPU) | SS fwd+bwd | direct fwd+bwd | ratio (CPU) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def cell(t: tuple[float, float]) -> str:
        return f"{1e3 * t[0]:.0f} ({1e3 * t[1]:.0f})"

    ss_rows = measure_supersampling(ss_n, ss_size, reps)
    for r in ss_rows:
        line = (
            f"| {r['d']} | {r['small']}^2 | {cell(r['ss_fwd_s'])} | {cell(r['direct_fwd_s'])} | "
            f"{r['ss_fwd_s'][1] / r['direct_fwd_s'][1]:.2f} | {cell(r['ss_fwd_bwd_s'])} | "
            f"{cell(r['direct_fwd_bwd_s'])} | {r['ss_fwd_bwd_s'][1] / r['direct_fwd_bwd_s'][1]:.2f} |"
        )
        print(line, flush=True)
        lines.append(line)

    prof_n = 10_000 if args.quick else 50_000
    phases, total = profile_phases(prof_n, 256)
    lines += [
        "",
        f"## Where the time goes ({prof_n} Gaussians, 256^2, forward+backward, torch profiler)",
        "",
        "| phase | ms | share |",
        "|---|---:|---:|",
    ]
    for key, ms in phases:
        lines.append(f"| `{key}` | {ms:.0f} | {100 * ms / total:.0f} % |")
    rest = total - sum(ms for _, ms in phases)
    lines.append(f"| rest (projection autograd, background blend, Python) | {rest:.0f} | {100 * rest / total:.0f} % |")
    print("\n".join(lines[-9:]))
    lines += [""] + dense_section(reps, args.threads, args.baseline)
    ss_ratios = ", ".join(f"{r['ss_fwd_s'][1] / r['direct_fwd_s'][1]:.1f}x" for r in ss_rows)
    lines += [
        "",
        "## Reading the numbers",
        "",
        "- Work grows with the number of (pixel, Gaussian) pairs inside the footprints, not with N alone: "
        "the scene keeps the coverage similar for every N, so the rows differ mostly by resolution.",
        f"- Supersampling (render at S, pool) costs {ss_ratios} the CPU time of direct rendering at S/d "
        f"for d = {', '.join(str(r['d']) for r in ss_rows)} (forward). On the CPU "
        "the work follows the pair count, which shrinks with the image; on a GPU small images leave the device "
        "idle, which is why the paper's Tbl. S2 finds supersampling about as fast or faster there.",
        "- With more torch threads than free cores (a shared machine), every parallel operator waits "
        "for a busy core: use `--threads 1` there (and `torch.set_num_threads(1)` when training).",
        "- Peak memory is bounded by the candidate pairs of one pass (`_PAIR_BUDGET`, 2^21, ~45 bytes of temporaries "
        "each, counted, not measured) and by the pairs kept for the backward pass (`_CACHE_BYTES`, 512 MiB at 15 bytes "
        "per drawn pair; beyond it backward recomputes).",
    ]
    text = "\n".join(lines) + "\n"
    if args.out is None:
        print(text)
        return
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
