"""Latency of ``controlgs view``: time from a request with a new state to the updated images.

On the built-in scene at 128 and 256 px, for the three methods (backbone without SS, SS-backbone,
ControlGS): an HTTP client posts a sequence of states as a slider drag would (every request a new d,
so a new display size, and a new rho) to the viewer's server and waits for the JSON holding every
image (base64 PNGs) and PSNR / SSIM. The adapter has random conditions: the latency does not depend
on what it learned. With ``--screenshot-of URL``: a screenshot of a running viewer through headless
Chromium instead (``docs/viewer.png`` is ``controlgs view``'s built-in scene with its quick adapter).

    .venv/bin/python benchmarks/bench_viewer.py --doc                 # writes docs/benchmarks/viewer-latency.md (default: print)
    .venv/bin/python benchmarks/bench_viewer.py --screenshot-of http://127.0.0.1:PORT/ --screenshot docs/viewer.png
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import platform
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def make_session(size: int, adapter_dir: Path, device: str) -> Any:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene, render_planes
    from controlgs_adapter.viewer import ViewerSession
    from test_viewer import random_adapter

    scene = load_builtin_scene("ar", size, cache=True)
    model = load_builtin_backbone("ar").to(device)
    adapter = adapter_dir / "controlgs.controlgs.safetensors"
    if not adapter.is_file():
        random_adapter(load_builtin_backbone("ar"), adapter)
    return ViewerSession(model, scene.views("test"), {"controlgs": adapter}, name=f"builtin-ar at {size} px",
                         truth=lambda cam: render_planes(scene.planes, cam)[0].float())


def post(conn: http.client.HTTPConnection, state: dict[str, Any]) -> tuple[float, dict[str, Any]]:
    t = time.perf_counter()
    conn.request("POST", "/api/render", body=json.dumps(state), headers={"Content-Type": "application/json"})
    data = json.loads(conn.getresponse().read())
    return 1000.0 * (time.perf_counter() - t), data


def drag(n: int, optics: str) -> list[dict[str, Any]]:
    """``n`` states of a slider drag: d from 1.1 to 7.9 (a new display size each time), rho along."""
    return [{"downsample": 1.1 + 6.8 * i / max(n - 1, 1), "power_saving": 0.8 * i / max(n - 1, 1), "optics": optics}
            for i in range(n)]


def measure(server: Any, n: int, optics: str) -> dict[str, float]:
    conn = http.client.HTTPConnection(*server.server_address[:2], timeout=600)
    for state in drag(3, optics):  # warm-up: pipeline construction, first calls
        post(conn, {**state, "downsample": state["downsample"] + 0.013})
    client, srv = [], []
    for state in drag(n, optics):
        ms, data = post(conn, state)
        assert len(data["methods"]) == 3, data
        client.append(ms)
        srv.append(data["server_ms"])
    conn.close()
    return {"median": statistics.median(client), "p90": sorted(client)[int(0.9 * (len(client) - 1))],
            "min": min(client), "server_median": statistics.median(srv)}


def screenshot(url: str, path: Path) -> str:
    """The page at ``url`` through headless Chromium at d = 3 (the other controls at their defaults)."""
    import shutil

    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
        from selenium.webdriver.support.ui import WebDriverWait
    except ImportError:
        raise SystemExit("selenium is not installed")
    chromium, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if not chromium or not driver_path:
        raise SystemExit("chromium / chromedriver are not installed")
    options = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu", "--window-size=1280,980",
                "--hide-scrollbars"):
        options.add_argument(arg)
    options.binary_location = chromium
    driver = webdriver.Chrome(service=Service(driver_path), options=options)
    try:
        driver.get(url)
        ready = "return window.viewer.generation >= {} && document.getElementById('status').className === ''"
        WebDriverWait(driver, 300).until(lambda d: d.execute_script(ready.format(1)))
        driver.execute_script("const s = document.getElementById('downsample'); s.value = '3';"
                              "s.dispatchEvent(new Event('input'));")
        WebDriverWait(driver, 300).until(lambda d: d.execute_script(
            "return window.viewer.last && window.viewer.last.downsample === 3 && window.viewer.extra === window.viewer.generation"))
        driver.save_screenshot(str(path))
    finally:
        driver.quit()
    return str(path)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    p.add_argument("--requests", type=int, default=20, help="timed requests per size and optics mode")
    p.add_argument("--threads", type=int, nargs="+", default=[2, 1], help="torch intra-op threads (the target: 2 CPU cores)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default=None, help="write the report to this file (default: print only)")
    p.add_argument("--doc", dest="out", action="store_const", const=str(ROOT / "docs" / "benchmarks" / "viewer-latency.md"),
                   help="write docs/benchmarks/viewer-latency.md")
    p.add_argument("--screenshot-of", default=None, metavar="URL", help="only take a screenshot of the viewer at URL")
    p.add_argument("--screenshot", default="viewer.png", help="where --screenshot-of writes (docs/viewer.png: the README's)")
    args = p.parse_args()
    if args.screenshot_of:
        print(screenshot(args.screenshot_of, Path(args.screenshot)))
        return 0
    from controlgs_adapter.viewer import make_server

    rows, load_before = [], os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            session = make_session(size, Path(tmp), args.device)
            server = make_server(session)
            threading.Thread(target=server.serve_forever, daemon=True).start()
            try:
                for threads in args.threads:
                    torch.set_num_threads(threads)
                    for optics in ("fast", "distortion", "exact"):
                        r = measure(server, args.requests, optics)
                        rows.append((size, threads, optics, r))
                        print(f"{size} px, {threads} threads, {optics}: median {r['median']:.0f} ms (p90 {r['p90']:.0f}, "
                              f"min {r['min']:.0f}; server {r['server_median']:.0f})", flush=True)
            finally:
                server.shutdown()
                server.server_close()
    load_after = os.getloadavg()
    lines = [
        "# Viewer latency (`controlgs view`)", "",
        "`benchmarks/bench_viewer.py --doc`: time from an HTTP request with a new state to the JSON answer holding every",
        "updated image (rendered frame, eye image, difference, lens overlay; base64 PNG) and PSNR / SSIM, for the",
        "three methods (backbone without SS, SS-backbone, ControlGS) on the built-in scene, measured by a client",
        f"on the same machine over {args.requests} requests of a slider drag (every request a new d, so a new display",
        "size: the no-SS render is never cached; rho changes too). FLIP follows in a second request and is not",
        "included (about 0.5 s per image at 128 px on CPU).", "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}, "
        f"device {args.device}; load average {load_before[0]:.1f} before, {load_after[0]:.1f} after (above 2 on this "
        "2-core machine other jobs were running: the numbers are then upper bounds).", "",
        "| size | threads | optics | median ms | p90 ms | min ms | server median ms |", "|---:|---:|---|---:|---:|---:|---:|",
    ]
    lines += [f"| {s} | {t} | {o} | {r['median']:.0f} | {r['p90']:.0f} | {r['min']:.0f} | {r['server_median']:.0f} |"
              for s, t, o, r in rows]
    lines += ["", "Target: under 300 ms at 128 px with the fast optics. On a busy machine one intra-op thread can beat",
              "two (OpenMP threads wait for a core the other jobs hold): `controlgs view --threads 1`.", ""]
    if args.out is None:
        print("\n".join(lines))
        return 0
    Path(args.out).write_text("\n".join(lines))
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
