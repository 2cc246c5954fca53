"""Time each downstream stage and the whole pipeline (no PSF), forward and forward+backward.

    python benchmarks/bench_stages.py [--sizes 256 512 1024] [--device cpu|cuda] [--out docs/benchmarks-stages.md]

Images are ``[1, 3, S, S]`` float32. Each row reports the best time over repeats and its ratio
to an elementwise copy of the same image (``x * 1``), measured in the same run: a memory-bound
unit that makes numbers from different machines comparable. The table is printed and written to
``--out`` (markdown).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path
from typing import Callable

import torch

from controlgs_adapter.downstream.color import linear_to_srgb, srgb_to_linear
from controlgs_adapter.downstream.display import display_mapping
from controlgs_adapter.downstream.lens import CARDBOARD_RADIAL, RadialMap, lens_prewarp
from controlgs_adapter.downstream.oled import box_emission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.state import RuntimeState


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time(fn: Callable[[], object], device: torch.device, budget_s: float, max_reps: int) -> float:
    """Best (minimum) seconds of ``fn`` over the repeats after two warm-up calls: on a shared
    machine the load only adds time, so the minimum is the stablest estimate of the cost."""
    for _ in range(2):
        fn()
    _sync(device)
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < max_reps and (len(times) < 3 or time.perf_counter() - start < budget_s):
        t0 = time.perf_counter()
        fn()
        _sync(device)
        times.append(time.perf_counter() - t0)
    return min(times)


def _cases(size: int, device: torch.device) -> dict[str, Callable[[torch.Tensor], torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 3, size, size, generator=g).to(device)
    gt_lin = srgb_to_linear(gt)
    grid, _ = RadialMap(CARDBOARD_RADIAL).to(device)((size, size), torch.float32, device)
    low = (round(size / 2.5),) * 2
    pipeline = Pipeline.from_config({"lens": True, "resample": True, "display": True}).to(device)
    state = RuntimeState(2.5, 0.4)
    return {
        "copy (x * 1, unit)": lambda x: x * 1.0,
        "sRGB decode": srgb_to_linear,
        "sRGB encode": linear_to_srgb,
        "lens pre-warp (radial, 3 ch)": lambda x: lens_prewarp(x, grid),
        "resample d=2 (avg-pool path)": lambda x: area_resample(x, 2.0),
        "resample d=2.5 (area taps)": lambda x: area_resample(x, 2.5),
        "display rho=0.4 (at S/2.5)": lambda x: display_mapping(x[..., : low[0], : low[1]], 0.4, gt_lin),
        "OLED S/2.5 -> S": lambda x: box_emission(x[..., : low[0], : low[1]], (size, size)),
        "pipeline d=2.5 rho=0.4 (no PSF)": lambda x: pipeline(x, state, reference=gt),
    }


def run(sizes: list[int], device: torch.device, budget_s: float, max_reps: int) -> list[dict]:
    rows = []
    for size in sizes:
        x = torch.rand(1, 3, size, size, device=device)
        xg = x.clone().requires_grad_(True)
        unit_f = unit_b = None
        for name, fn in _cases(size, device).items():
            fwd = _time(lambda: fn(x), device, budget_s, max_reps)

            def fwd_bwd() -> None:
                xg.grad = None
                fn(xg).sum().backward()

            both = _time(fwd_bwd, device, budget_s, max_reps)
            if unit_f is None:
                unit_f, unit_b = fwd, both
            rows.append({"size": size, "stage": name, "fwd_ms": fwd * 1e3, "fwd_bwd_ms": both * 1e3,
                         "fwd_x": fwd / unit_f, "fwd_bwd_x": both / unit_b})
            print(f"{size:5d}  {name:34s} fwd {fwd * 1e3:9.3f} ms ({fwd / unit_f:6.1f}x)   "
                  f"fwd+bwd {both * 1e3:9.3f} ms ({both / unit_b:6.1f}x)", flush=True)
    return rows


def to_markdown(rows: list[dict], device: torch.device) -> str:
    if device.type == "cuda":
        where = torch.cuda.get_device_name(device)
    else:
        where = f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, {os.cpu_count()} cores)"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    lines = [
        "# Downstream stage benchmark",
        "",
        f"`python benchmarks/bench_stages.py` on {where}, torch {torch.__version__}, float32, image `[1, 3, S, S]`;"
        f" load average at the end {load:.1f}.",
        "Best-of-repeats times; `x` = ratio to an elementwise copy of the same image in the same run (memory-bound unit)."
        " On a shared machine absolute times vary with the load; compare ratios within one run.",
        "Display and OLED rows run at the display size of d = 2.5. The pipeline is lens + resample + display +"
        " OLED with the sRGB decode/encode (the optics/PSF stage is not included).",
        "",
        "| S | stage | fwd ms | fwd x | fwd+bwd ms | fwd+bwd x |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(f"| {r['size']} | {r['stage']} | {r['fwd_ms']:.3f} | {r['fwd_x']:.1f} | {r['fwd_bwd_ms']:.3f} | {r['fwd_bwd_x']:.1f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--budget", type=float, default=1.0, help="seconds of repeats per measurement")
    ap.add_argument("--max-reps", type=int, default=50)
    ap.add_argument("--threads", type=int, default=0, help="CPU intra-op threads (0: torch's default)")
    ap.add_argument("--out", type=Path, default=Path("docs/benchmarks-stages.md"))
    args = ap.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    table = to_markdown(run(args.sizes, device, args.budget, args.max_reps), device)
    print(table)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table)


if __name__ == "__main__":
    main()
