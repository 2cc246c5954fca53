"""Time each downstream stage and the whole pipeline (no PSF), forward and forward+backward.

    python benchmarks/bench_stages.py [--sizes 256 512 1024] [--device cpu|cuda] [--reps 10] [--threads N]
                                      [--doc | --out FILE]

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
from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.downstream.resample import area_resample
from controlgs_adapter.state import RuntimeState


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _time_interleaved(fns: dict[str, Callable[[], object]], device: torch.device, reps: int) -> dict[str, float]:
    """Best (minimum) seconds of each function over ``reps`` round-robin repeats, after two warm-up
    calls. Interleaving spreads a shared machine's load over all cases alike, and the load only
    adds time, so the minimum is the stablest estimate of the cost."""
    for fn in fns.values():
        for _ in range(2):
            fn()
    _sync(device)
    best = {name: float("inf") for name in fns}
    for _ in range(reps):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            _sync(device)
            best[name] = min(best[name], time.perf_counter() - t0)
    return best


def _cases(size: int, device: torch.device) -> dict[str, Callable[[torch.Tensor], torch.Tensor]]:
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(1, 3, size, size, generator=g).to(device)
    gt_lin = srgb_to_linear(gt)
    grid, _ = RadialMap(CARDBOARD_RADIAL).to(device)((size, size), torch.float32, device)
    low = (round(size / 2.5),) * 2
    pipeline = Pipeline.from_config({"lens": True, "resample": True, "display": True}).to(device)
    state = RuntimeState(2.5, 0.4)
    power_ref = pipeline["display"].reference_power(gt, torch.float32)

    def by_hand(x: torch.Tensor) -> torch.Tensor:  # the same E_s from the functionals: pipeline overhead
        y = area_resample(lens_prewarp(srgb_to_linear(x), grid), 2.5)
        return linear_to_srgb(oled_emission(display_mapping(y, 0.4, reference_power=power_ref), (size, size)))

    return {
        "copy (x * 1, unit)": lambda x: x * 1.0,
        "sRGB decode": srgb_to_linear,
        "sRGB encode": linear_to_srgb,
        "lens pre-warp (radial, 3 ch)": lambda x: lens_prewarp(x, grid),
        "lens pre-warp, 2 x 2 samples per pixel": lambda x: lens_prewarp(x, grid, supersample=2),
        "resample d=2 (avg-pool path)": lambda x: area_resample(x, 2.0),
        "resample d=2.5 (area taps)": lambda x: area_resample(x, 2.5),
        "display rho=0.4 (at S/2.5)": lambda x: display_mapping(x[..., : low[0], : low[1]], 0.4, gt_lin),
        "OLED S/2.5 -> S": lambda x: oled_emission(x[..., : low[0], : low[1]], (size, size)),
        "functionals composed by hand": by_hand,
        "pipeline d=2.5 rho=0.4 (no PSF)": lambda x: pipeline(x, state, reference=gt),
    }


def run(sizes: list[int], device: torch.device, reps: int) -> list[dict]:
    rows = []
    for size in sizes:
        x = torch.rand(1, 3, size, size, device=device)
        xg = x.clone().requires_grad_(True)
        cases = _cases(size, device)

        def backward_of(fn: Callable[[torch.Tensor], torch.Tensor]) -> Callable[[], None]:
            def run_once() -> None:
                xg.grad = None
                fn(xg).sum().backward()
            return run_once

        fwd = _time_interleaved({name: (lambda fn=fn: fn(x)) for name, fn in cases.items()}, device, reps)
        both = _time_interleaved({name: backward_of(fn) for name, fn in cases.items()}, device, reps)
        unit = next(iter(cases))
        for name in cases:
            f, b = fwd[name], both[name]
            rows.append({"size": size, "stage": name, "fwd_ms": f * 1e3, "fwd_bwd_ms": b * 1e3,
                         "fwd_x": f / fwd[unit], "fwd_bwd_x": b / both[unit]})
            print(f"{size:5d}  {name:34s} fwd {f * 1e3:9.3f} ms ({f / fwd[unit]:6.1f}x)   "
                  f"fwd+bwd {b * 1e3:9.3f} ms ({b / both[unit]:6.1f}x)", flush=True)
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
        f"`python benchmarks/bench_stages.py --doc` on {where}, torch {torch.__version__}, float32, image `[1, 3, S, S]`;"
        f" load average at the end {load:.1f}.",
        "Best of round-robin repeats; `x` = ratio to an elementwise copy of the same image in the same run (memory-bound unit)."
        " On a shared machine absolute times vary with the load; compare ratios within one run.",
        "Display and OLED rows run at the display size of d = 2.5. The pipeline is lens + resample + display +"
        " OLED with the sRGB decode/encode (the optics/PSF stage is not included); the row above it runs the same"
        " functionals composed by hand, so their ratio is the pipeline's own overhead.",
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
    ap.add_argument("--reps", type=int, default=10, help="round-robin repeats (the best of them is reported)")
    ap.add_argument("--threads", type=int, default=0, help="CPU intra-op threads (0: torch's default)")
    ap.add_argument("--out", type=Path, default=None, help="write the table to this file (default: print only)")
    ap.add_argument("--doc", dest="out", action="store_const", const=Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "stages.md",
                    help="write docs/benchmarks/stages.md")
    args = ap.parse_args()
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    table = to_markdown(run(args.sizes, device, args.reps), device)
    print(table)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(table)


if __name__ == "__main__":
    main()
