"""Foveation: the pixels each preset needs and the stage's cost per frame.

Pixel savings: the fraction of the display's pixels a foveated frame needs, ``mean((rate / ppd)^2)`` over the
pixels of a 1024 x 1024 image on the shipped Cardboard lens (``ppd`` through the lens, ``rate`` from the
preset's minimum-angle-of-resolution model), with the gaze on the lens axis (also the fixed mode) and 8 deg
right, 4 deg down.

Cost: the stage on a ``[3, S, S]`` float32 image at S = 256, 512, 1024 (the gaze 8 deg right, 4 deg down;
its maps are cached after the first frame), against the identity (the same stage with no gaze: it returns
its input) measured in the same run; median of ``--repeats`` frames. CPU times are the calling thread's CPU
time with one torch thread; on CUDA, wall time after a synchronize.

    python benchmarks/bench_foveation.py                 # prints
    python benchmarks/bench_foveation.py --doc           # also writes docs/benchmarks/foveation.md
    python benchmarks/bench_foveation.py --device cuda   # the stage's cost on a GPU
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Callable

import torch

from controlgs_adapter import __version__
from controlgs_adapter.downstream.foveation import PRESETS, Foveation, pixel_savings
from controlgs_adapter.downstream.optics.visual_angles import angle_to
from controlgs_adapter.state import RuntimeState

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "foveation.md"
GAZE = (8.0, 4.0)
SIZES = (256, 512, 1024)


def savings() -> list[tuple[str, float, float]]:
    """(preset, fraction with the gaze on the axis, fraction at GAZE) at 1024 x 1024."""
    stage = Foveation()
    unit, ppd, _ = stage.maps(1024, 1024)
    out = []
    for name, model in PRESETS.items():
        if model is not None:
            out.append((name, pixel_savings(angle_to(unit, (0.0, 0.0)), ppd, model),
                        pixel_savings(angle_to(unit, GAZE), ppd, model)))
    return out


def per_frame(fn: Callable[[], torch.Tensor], device: torch.device, repeats: int) -> float:
    """Median milliseconds of ``fn``."""
    times = []
    for _ in range(repeats + 1):
        if device.type == "cuda":
            torch.cuda.synchronize()
            t0 = time.perf_counter()
            fn()
            torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        else:
            t0 = time.thread_time()
            fn()
            times.append(time.thread_time() - t0)
    return 1000.0 * statistics.median(times[1:])  # the first frame builds the maps


def costs(device: torch.device, repeats: int) -> list[tuple[int, str, float, float, int]]:
    """(S, preset, foveation ms, identity ms, mip levels)."""
    rows = []
    for s in SIZES:
        image = torch.rand(3, s, s, device=device)
        for name in ("guenter-0.022", "level-16x"):
            stage = Foveation(name)
            on, off = RuntimeState(gaze=GAZE), RuntimeState()
            with torch.no_grad():
                t_on = per_frame(lambda: stage(image, on), device, repeats)
                t_off = per_frame(lambda: stage(image, off), device, repeats)
            rows.append((s, name, t_on, t_off, stage.maps(s, s, device, image.dtype)[2]))
    return rows


def render_markdown(device: torch.device, fractions: list[tuple[str, float, float]],
                    rows: list[tuple[int, str, float, float, int]]) -> str:
    load = " ".join(f"{v:.1f}" for v in os.getloadavg())
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else (
        f"{platform.processor() or platform.machine()}, 1 torch thread, CPU time of the calling thread")
    lines = [
        "# Foveation (`benchmarks/bench_foveation.py`)",
        "",
        f"controlgs-adapter {__version__}, torch {torch.__version__}, {where}; load average at the end: {load}.",
        "Re-run: `python benchmarks/bench_foveation.py` (prints; `--doc` rewrites this page). The model is in "
        "[the foveation page](../explanation/foveation.md).",
        "",
        "## Pixels a foveated frame needs",
        "",
        "Fraction of the display's pixels, `mean((rate / ppd)^2)` over a 1024 x 1024 image on the shipped "
        "Cardboard lens (the display's own density through the lens, about 34 pixels per degree at the centre, "
        "and the rate the preset's acuity model asks for). The Cardboard field is only about +-15 deg, so the "
        "periphery is near the fovea and the savings are smaller than on a wide-field headset.",
        "",
        "| preset | gaze on the axis (also fixed mode) | gaze (8, 4) deg |",
        "|---|---|---|",
    ]
    lines += [f"| `{n}` | {a:.3f} ({1 / a:.1f}x fewer) | {b:.3f} ({1 / b:.1f}x fewer) |" for n, a, b in fractions]
    lines += [
        "",
        "## Cost per frame",
        "",
        f"`[3, S, S]` float32, gaze (8, 4) deg, median of the frames after the first (which builds the maps); "
        f"the identity is the same stage with no gaze, measured in the same run, on {device.type}.",
        "",
        "| S | preset | mip levels | foveation ms | identity ms | ratio |",
        "|---|---|---|---|---|---|",
    ]
    lines += [f"| {s} | `{n}` | {k} | {a:.2f} | {b:.4f} | {a / max(b, 1e-6):.0f}x |" for s, n, a, b, k in rows]
    lines += [
        "",
        "The identity costs only the call (no work, no copy: the input object comes back), so the ratio is the "
        "stage's full cost over a call's overhead; the stage's time grows with the pixels and the mip levels "
        "(each level is reconstructed at full size, one blend per level).",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--doc", action="store_true", help=f"write {DOC}")
    args = ap.parse_args()
    torch.set_num_threads(1)
    device = torch.device(args.device)
    fractions = savings()
    rows = costs(device, args.repeats)
    text = render_markdown(device, fractions, rows)
    print(text)
    if args.doc:
        DOC.write_text(text)


if __name__ == "__main__":
    main()
