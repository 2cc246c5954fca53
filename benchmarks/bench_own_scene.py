"""Your own scene, measured: the whole ``controlgs train`` + ``controlgs eval`` on a phone-like capture
(portrait JPEGs at full size + an instant-ngp ``transforms.json``) at 1/8 scale, and peak memory as the
number of views grows.

    python benchmarks/bench_own_scene.py                     # 50 views, 1080x1920, 1000 iterations
    python benchmarks/bench_own_scene.py --iterations 100 --views 10 50 --no-doc   # quick look

The capture is made here from the built-in VR diorama (ray cast at half size, bilinearly upsampled to
the full size, JPEG quality 95) under cameras on an arc, so that the built-in VR backbone is a model
of it; every command runs in its own process (``python -m controlgs_adapter.cli``) and its wall time
and peak resident memory (``wait4`` rusage) are recorded. Prints the report; ``--doc`` writes ``docs/benchmarks/own-scene.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from controlgs_adapter.scene import builtin_backbone_dir, diorama_planes, look_at, render_planes
from controlgs_adapter.state import Camera

ROOT = Path(__file__).resolve().parents[1]


def capture_cameras(count: int, width: int, height: int, vfov_deg: float = 55.0) -> list[Camera]:
    """``count`` portrait cameras on an arc in front of the diorama (as the built-in scene's)."""
    f = 0.5 * height / math.tan(math.radians(vfov_deg) / 2)
    k = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    cams = []
    for i in range(count):
        s = i / max(count - 1, 1)
        az = math.radians(-30.0 + 60.0 * s)
        el = math.radians(10.0 + 12.0 * (0.5 - 0.5 * math.cos(2 * math.pi * 2.5 * s)))
        r = 4.6 + 0.5 * math.cos(2 * math.pi * 1.5 * s)
        eye = (r * math.cos(el) * math.sin(az), 0.35 + r * math.sin(el), r * math.cos(el) * math.cos(az))
        w2c = look_at(eye, (0.0, 0.35, 0.0), size=16, fov_deg=50.0).world_to_camera
        cams.append(Camera(w2c, k, width, height))
    return cams


def write_capture(folder: Path, count: int, width: int, height: int) -> Path:
    """Render and write the capture (skipped when ``folder`` already holds this one)."""
    from PIL import Image

    meta = folder / "transforms.json"
    key = {"views": count, "w": width, "h": height, "version": 1}
    if meta.is_file() and json.loads(meta.read_text()).get("bench_key") == key:
        return folder
    (folder / "images").mkdir(parents=True, exist_ok=True)
    planes = diorama_planes("vr")
    cams = capture_cameras(count, width, height)
    frames = []
    t = time.perf_counter()
    for i, cam in enumerate(cams):
        half = Camera(cam.world_to_camera, cam.intrinsics * torch.tensor([[0.5], [0.5], [1.0]]), width // 2, height // 2)
        img = render_planes(planes, half, samples=1)[0].float()
        img = F.interpolate(img[None], size=(height, width), mode="bilinear", align_corners=False)[0].clamp(0, 1)
        name = f"images/frame_{i:04d}.jpg"
        Image.fromarray((img.permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)).save(folder / name, quality=95)
        c2w = torch.linalg.inv(cam.world_to_camera.double())
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL axes
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
        print(f"\rcapture: {i + 1}/{count} views ({time.perf_counter() - t:.0f} s)", end="", file=sys.stderr)
    print(file=sys.stderr)
    k = cams[0].intrinsics
    meta.write_text(json.dumps({"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]),
                                "cy": float(k[1, 2]), "w": width, "h": height, "frames": frames, "bench_key": key}))
    return folder


def timed(cmd: list[str]) -> tuple[float, float]:
    """Run ``cmd``; ``(wall seconds, peak RSS MiB)``; raises with its stderr if it fails."""
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    err = proc.stderr.read() if proc.stderr else ""
    if os.waitstatus_to_exitcode(status) != 0:
        raise SystemExit(f"failed: {' '.join(cmd)}\n{err[-2000:]}")
    return wall, usage.ru_maxrss / 1024.0  # Linux: KiB


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, nargs="+", default=[10, 50, 200], help="capture sizes for the memory table")
    ap.add_argument("--main-views", type=int, default=50, help="the capture trained and evaluated in full")
    ap.add_argument("--size", default="1080x1920", help="capture size WxH")
    ap.add_argument("--scale", type=int, default=8, help="working scale: longer side / this")
    ap.add_argument("--iterations", type=int, default=1000)
    ap.add_argument("--memory-iterations", type=int, default=100, help="iterations of each memory-table run")
    ap.add_argument("--cache-mib", type=int, default=64, help="image cache budget of the memory-table runs")
    ap.add_argument("--work", default=str(Path(os.environ.get("TMPDIR", "/tmp")) / "controlgs-bench-own-scene"))
    ap.add_argument("--doc", action="store_true", help="write docs/benchmarks/own-scene.md (default: print only)")
    a = ap.parse_args()
    width, height = (int(v) for v in a.size.lower().split("x"))
    resolution = max(width, height) // a.scale
    work = Path(a.work)
    model = str(builtin_backbone_dir("vr"))
    cli = [sys.executable, "-m", "controlgs_adapter.cli"]
    common = ["--model", model, "--resolution", str(resolution), "--no-progress"]

    main_cap = write_capture(work / f"capture-{a.main_views}", a.main_views, width, height)
    run, report = work / "run-main", work / "report-main"
    for p in (run, report):
        subprocess.run(["rm", "-rf", str(p)], check=True)
    train_s, train_mib = timed(cli + ["train", *common, "--data", str(main_cap), "--out", str(run),
                                      "--iterations", str(a.iterations), "--no-ablations"])
    eval_s, eval_mib = timed(cli + ["eval", *common, "--data", str(main_cap), "--run", str(run), "--out", str(report)])
    results = json.loads((report / "results.json").read_text())
    means = {m: v["psnr"]["mean"] for m, v in results["methods"].items()}

    rows = []
    for n in a.views:
        cap = write_capture(work / f"capture-{n}", n, width, height)
        out = work / f"run-mem-{n}"
        subprocess.run(["rm", "-rf", str(out)], check=True)
        s, mib = timed(cli + ["train", *common, "--data", str(cap), "--out", str(out), "--no-ablations",
                              "--iterations", str(a.memory_iterations), "--cache-mib", str(a.cache_mib)])
        disk = sum(p.stat().st_size for p in (cap / "images").iterdir()) / 2**20
        rows.append((n, disk, s, mib))

    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# Benchmark: your own scene (train + eval through the CLI)", "",
        f"Generated by `python benchmarks/bench_own_scene.py --doc` on {stamp}; machine: `nproc` = {os.cpu_count()}, "
        f"torch {torch.__version__}, {platform.processor() or platform.machine()}. Capture: {a.main_views} portrait views "
        f"{width}x{height} (JPEG, instant-ngp `transforms.json`) of the built-in VR diorama; model: the built-in VR "
        f"backbone (Scaffold-GS folder, 2369 anchors); working resolution {resolution} px on the longer side (1/{a.scale}).",
        "", "## Whole run", "",
        "| command | wall time | peak memory |", "|---|---:|---:|",
        f"| `controlgs train` ({a.iterations} iterations, no ablations) | {train_s / 60:.1f} min | {train_mib:.0f} MiB |",
        f"| `controlgs eval` (4 x 5 grid, all test views) | {eval_s / 60:.1f} min | {eval_mib:.0f} MiB |",
        "", "Mean PSNR over the grid (dB): " + ", ".join(f"{m} {v:.2f}" for m, v in means.items()) + ".",
        "", "## Memory as the number of views grows", "",
        f"`controlgs train` for {a.memory_iterations} iterations with `--cache-mib {a.cache_mib}`: images are decoded "
        "on demand, downscaled and kept in a bounded cache, so memory stays flat while the capture on disk grows.", "",
        "| views | capture on disk | wall time | peak memory |", "|---:|---:|---:|---:|",
        *[f"| {n} | {disk:.0f} MiB | {s:.0f} s | {mib:.0f} MiB |" for n, disk, s, mib in rows],
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.doc:
        (ROOT / "docs" / "benchmarks" / "own-scene.md").write_text(text)


if __name__ == "__main__":
    main()
