"""Profile one CUDA training step of ``bench_step.py``'s scene: kernel launches, host syncs and copies
per phase, the ops that synchronise (``torch.cuda.set_sync_debug_mode``), and torch.profiler's top ops.
The source of the launch and sync counts in docs/benchmarks/training-step-gpu.md.

Usage: ``python benchmarks/profile_step.py --rasterizer torch --anchors 100000 --width 1024 --optics exact
--out profile.txt`` (needs a CUDA device).
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
import warnings
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile, record_function

import bench_step
from controlgs_adapter.benchmarking import ClockedRasterizer, PhaseClock, clock_stage
from controlgs_adapter.benchmarking.accuracy_time import psf_keywords
from controlgs_adapter.rendering.rasterizers import use_rasterizer
from controlgs_adapter.training import TrainConfig, Trainer

LAUNCH = {"cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx"}
SYNC = {"cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize"}


class MarkClock(PhaseClock):
    """A phase clock that never synchronises: each lap is a zero-length profiler range."""

    def __init__(self) -> None:
        super().__init__(None)

    def start(self) -> None:
        super().start()
        with record_function("LAP:start"):
            pass

    def lap(self, name: str) -> None:
        super().lap(name)
        with record_function("LAP:" + name):
            pass


def _kind(name: str) -> str | None:
    if name in LAUNCH:
        return "launch"
    if name in SYNC:
        return "sync"
    if name.startswith("cudaMemcpy"):
        return "memcpy"
    return "item" if name in ("aten::item", "aten::_local_scalar_dense") else None


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--rasterizer", default="torch", help="registered rasterizer (torch, gsplat)")
    ap.add_argument("--anchors", type=int, default=100_000)
    ap.add_argument("--width", type=int, default=1024, help="image width, the longer side (16:9)")
    ap.add_argument("--optics", default="exact", choices=("exact", "fast", "distortion"))
    ap.add_argument("--out", type=Path, required=True, help="text file for the report")
    args = ap.parse_args()
    if not torch.cuda.is_available():
        sys.exit("profile_step.py: no GPU available in this run (it profiles a CUDA step)")
    model = bench_step.make_model(args.anchors).to("cuda")
    trainer = Trainer(model, bench_step.OneView(bench_step.camera(args.width)),
                      TrainConfig(iterations=20, checkpoint_every=0, **psf_keywords(args.optics)))
    clock = MarkClock()
    raster = ClockedRasterizer(clock, args.rasterizer)

    def step() -> None:
        with use_rasterizer(raster), clock_stage(clock, trainer.pipeline["optics"], "psf", before="stages"):
            trainer.step(clock)

    for _ in range(3):  # warm-up
        step()
    walls = []
    for _ in range(3):
        torch.cuda.synchronize()
        t = time.perf_counter()
        step()
        torch.cuda.synchronize()
        walls.append(time.perf_counter() - t)
    lines = [f"# {args.rasterizer}, {args.anchors} anchors, {args.width} px, {args.optics}: step {min(walls):.4f} s "
             f"(fastest of {[round(w, 4) for w in walls]}, no phase syncs)"]
    sites: collections.Counter[tuple[str, str]] = collections.Counter()
    torch.cuda.set_sync_debug_mode("warn")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        step()
    torch.cuda.set_sync_debug_mode(0)
    for w in caught:
        sites[(str(w.message).split("\n")[0][:60], f"{Path(w.filename).name}:{w.lineno}")] += 1
    lines.append(f"\n## synchronizing ops in one step: {sum(sites.values())}")
    lines += [f"{n:6d}  {where:40s} {msg}" for (msg, where), n in sites.most_common(40)]
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        step()
        torch.cuda.synchronize()
    events = list(prof.events())
    marks = sorted((e.time_range.start, e.name[4:]) for e in events if e.name.startswith("LAP:"))
    per: dict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    gpu_us = 0.0
    for e in events:
        if e.device_type == torch.autograd.DeviceType.CUDA:
            gpu_us += e.time_range.end - e.time_range.start
        elif (kind := _kind(e.name)) is not None:
            phase = next((name for start, name in marks if e.time_range.start < start), "after")
            per[phase][kind] += 1
    lines.append(f"\n## per phase ({(marks[-1][0] - marks[0][0]) / 1e3:.1f} ms from first to last lap under the "
                 f"profiler, GPU kernel time {gpu_us / 1e3:.1f} ms)")
    lines.append("phase        ms   launch  sync  memcpy  item")
    for (prev, _), (start, name) in zip(marks, marks[1:]):
        c = per[name]
        lines.append(f"{name:10s} {(start - prev) / 1e3:7.1f} {c['launch']:7d} {c['sync']:5d} {c['memcpy']:7d} {c['item']:5d}")
    lines.append("\n## top by self CPU time\n" + prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30))
    lines.append("\n## top by CUDA time\n" + prof.key_averages().table(sort_by="cuda_time_total", row_limit=25))
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines[:60]))
    trainer.cgs.unwrap()


if __name__ == "__main__":
    main()
