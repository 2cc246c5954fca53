"""Distributed training on this machine: 1 vs 2 processes (torchrun, gloo over loopback).

Part 1 (training): the ControlGS trainer on the built-in scene (same global batch on 1 and 2
processes), condition gradients exchanged as touched rows (``sparse``) or by a dense all-reduce;
seconds per iteration, bytes one rank sends per step (ring model, counted by
``DistContext.stats``), bytes that crossed the loopback interface (``/proc/net/dev``, every
rank, TCP overhead included) and the fraction of condition rows a rank touched.

Part 2 (exchange only): one gradient exchange of a condition table of A anchors x 3 modules x 8
with a given fraction of rows touched per rank (random rows, no rendering), sparse vs dense:
bytes sent per rank and milliseconds. This is the regime of scenes with millions of anchors.

    python benchmarks/bench_distributed.py [--resolution 48] [--iterations 6] [--doc | --out FILE]

Prints the tables; ``--doc`` rewrites them between the markers in ``docs/benchmarks/distributed.md`` (``--out FILE``: another file). Each configuration runs in a
fresh torchrun (OMP_NUM_THREADS=1 per process, so 1 vs 2 processes compares 1 vs 2 cores).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
BEGIN, END = "<!-- bench_distributed:begin -->", "<!-- bench_distributed:end -->"
VIEWS_KIND = "controlgs_bench_views"


def _loopback_bytes() -> int:
    """Bytes transmitted on the loopback interface so far (Linux), or -1."""
    try:
        for line in Path("/proc/net/dev").read_text().splitlines():
            name, _, rest = line.partition(":")
            if name.strip() == "lo":
                return int(rest.split()[8])
    except OSError:
        pass
    return -1


# ------------------------------------------------------------------------------------ workers
def _worker_train(a: argparse.Namespace) -> None:
    from controlgs_adapter.backends.scaffold_io import load_scaffold_dir
    from controlgs_adapter.datasets.memory import posed_images
    from controlgs_adapter.distributed import init_distributed
    from controlgs_adapter.formats.safetensors import load_tensors
    from controlgs_adapter.state import Camera
    from controlgs_adapter.training import TrainConfig, Trainer

    t, h = load_tensors(Path(a.data) / "views.safetensors", kind=VIEWS_KIND, max_version=1)
    cams = [Camera(m, k, h["size"], h["size"]) for m, k in zip(t["w2c"], t["K"])]
    model = load_scaffold_dir(Path(a.data) / "backbone").eval()
    with init_distributed(exchange=a.exchange, timeout=600) as ctx:
        config = TrainConfig(iterations=a.iterations, batch_size=a.batch, checkpoint_every=0, seed=0)
        trainer = Trainer(model, posed_images(t["images"], cams, background=t["background"]), config,
                          effects=json.loads(a.effects), dist=ctx)
        trainer.step()  # warm-up
        ctx.barrier()
        sent0, dense0, steps0 = ctx.stats.bytes_sent, ctx.stats.dense_bytes, ctx.stats.steps
        rows0 = ctx.stats.rows_touched
        lo0, t0 = _loopback_bytes(), time.perf_counter()
        while trainer.iteration < a.iterations:
            trainer.step()
        ctx.barrier()
        seconds, lo1 = time.perf_counter() - t0, _loopback_bytes()
        n = max(ctx.stats.steps - steps0, 1)
        mine = {"rows": (ctx.stats.rows_touched - rows0) / n, "sent": (ctx.stats.bytes_sent - sent0) / n}
        everyone = ctx.all_gather_json(mine)
        if ctx.is_main:
            steps = a.iterations - 1
            out = {"s_per_it": seconds / steps, "bytes": max(e["sent"] for e in everyone),
                   "dense_bytes": (ctx.stats.dense_bytes - dense0) / n,
                   "rows": sum(e["rows"] for e in everyone) / len(everyone), "anchors": trainer.cgs.num_anchors,
                   "loopback": (lo1 - lo0) / steps if lo0 >= 0 else None, "exchange": ctx.stats.last.get("exchange"),
                   "loss": trainer.history[-1]}
            Path(a.result).write_text(json.dumps(out))


def _worker_exchange(a: argparse.Namespace) -> None:
    from controlgs_adapter.distributed import init_distributed

    with init_distributed(exchange=a.exchange, timeout=600) as ctx:
        g = torch.Generator().manual_seed(ctx.rank)
        cond = torch.nn.Parameter(torch.zeros(a.anchors, 3, 8))
        proj = torch.nn.Parameter(torch.zeros(3 * 32, 8))
        k = max(1, int(a.touched * a.anchors))
        times = []
        for rep in range(a.reps + 1):
            cond.grad = torch.zeros_like(cond)
            rows = torch.randperm(a.anchors, generator=g)[:k]
            cond.grad[rows] = torch.randn(k, 3, 8, generator=g)
            proj.grad = torch.randn(proj.shape, generator=g)
            ctx.barrier()
            t0 = time.perf_counter()
            ctx.sync_gradients([cond, proj], row_sparse=[cond], step=rep)
            if rep:  # the first is warm-up
                times.append(time.perf_counter() - t0)
        if ctx.is_main:
            times.sort()
            Path(a.result).write_text(json.dumps({"ms": 1e3 * times[len(times) // 2], "bytes": ctx.stats.last["bytes_sent"],
                                                  "dense_bytes": ctx.stats.last["dense_bytes"],
                                                  "exchange": ctx.stats.last["exchange"]}))


# ------------------------------------------------------------------------------------ launcher
def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _launch(nproc: int, argv: list[str]) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "result.json"
        env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": "lo", "PYTHONWARNINGS": "ignore"}
        cmd = [sys.executable, "-m", "torch.distributed.run", "--nnodes=1", f"--nproc_per_node={nproc}",
               "--master_addr=127.0.0.1", f"--master_port={_free_port()}", "--max_restarts=0", __file__, "--worker",
               *argv, "--result", str(result)]
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        if proc.returncode:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stdout}\n{proc.stderr}")
        return json.loads(result.read_text())


def _prepare(data: Path, variant: str, resolution: int, spacing: float) -> str:
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.backends.scaffold_io import save_scaffold_dir
    from controlgs_adapter.formats.safetensors import save_tensors
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene(variant, resolution)
    try:
        from controlgs_adapter.scene import load_builtin_backbone

        model = load_builtin_backbone(variant)
        source = f"the baked built-in {variant} backbone"
    except Exception:  # not baked in this checkout: anchors from the scene's points, colour-fitted
        xyz, rgb = scene.points(spacing)
        model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=32, n_offsets=5, color_fit_steps=100)
        source = f"an untrained reference model on the {variant} scene's points (spacing {spacing})"
    save_scaffold_dir(model, data / "backbone", iteration=0)
    cams = scene.train_cameras
    save_tensors(data / "views.safetensors", {"images": scene.train_images, "background": scene.background,
                                              "w2c": torch.stack([c.world_to_camera for c in cams]),
                                              "K": torch.stack([c.intrinsics for c in cams])},
                 {"size": resolution, "source": source}, kind=VIEWS_KIND, format_version=1)
    return source


def _table(headers: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def _kb(x: float | None) -> str:
    return "n/a" if x is None else f"{x / 1024:,.1f}"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--task", default="train", help=argparse.SUPPRESS)
    p.add_argument("--data", help=argparse.SUPPRESS)
    p.add_argument("--result", help=argparse.SUPPRESS)
    p.add_argument("--anchors", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--touched", type=float, default=0.1, help=argparse.SUPPRESS)
    p.add_argument("--reps", type=int, default=5, help=argparse.SUPPRESS)
    p.add_argument("--exchange", default="sparse", help=argparse.SUPPRESS)
    p.add_argument("--effects", default='{"lens": true, "resample": true, "display": true, "oled": true}',
                   help="downstream effects (JSON) of the training part")
    p.add_argument("--variant", default="vr", choices=("ar", "vr"))
    p.add_argument("--resolution", type=int, default=48)
    p.add_argument("--spacing", type=float, default=0.08, help="point spacing of the stand-in backbone")
    p.add_argument("--iterations", type=int, default=6, help="timed iterations + 1 warm-up")
    p.add_argument("--batch", type=int, default=2, help="global batch (views per step)")
    p.add_argument("--sizes", default="100000,1000000", help="anchor counts of the exchange-only part")
    p.add_argument("--fractions", default="0.01,0.1,0.5", help="fractions of rows touched per rank (exchange-only)")
    p.add_argument("--out", type=Path, default=None, help="file whose marked block to rewrite (default: print only)")
    p.add_argument("--doc", dest="out", action="store_const", const=ROOT / "docs" / "benchmarks" / "distributed.md",
                   help="rewrite the block in docs/benchmarks/distributed.md")
    a = p.parse_args()
    if a.worker:
        (_worker_train if a.task == "train" else _worker_exchange)(a)
        return

    with tempfile.TemporaryDirectory() as data:
        source = _prepare(Path(data), a.variant, a.resolution, a.spacing)
        rows = []
        base = None
        for nproc, exchange in ((1, "sparse"), (2, "sparse"), (2, "dense")):
            r = _launch(nproc, ["--task=train", f"--data={data}", f"--exchange={exchange}", f"--iterations={a.iterations}",
                                f"--batch={a.batch}", f"--effects={a.effects}"])
            base = base or r["s_per_it"]
            print(nproc, exchange, r, flush=True)
            two = nproc > 1
            rows.append([str(nproc), exchange if two else "-", f"{r['s_per_it']:.3f}", f"{base / r['s_per_it']:.2f}x",
                         _kb(r["bytes"]) if two else "0", _kb(r["dense_bytes"]) if two else "0",
                         _kb(r["loopback"]) if two else "-",
                         f"{r['rows']:.0f} / {r['anchors']} ({100 * r['rows'] / r['anchors']:.0f}%)" if two else "-"])
        train_table = _table(["processes", "condition exchange", "s / iteration", "speed-up", "KiB sent / rank / step",
                              "KiB dense all-reduce would send", "KiB on loopback / step (all ranks)",
                              "condition rows touched / rank (of anchors)"], rows)

        rows = []
        for anchors in (int(s) for s in a.sizes.split(",")):
            for frac in (float(f) for f in a.fractions.split(",")):
                res = {ex: _launch(2, ["--task=exchange", f"--anchors={anchors}", f"--touched={frac}",
                                       f"--exchange={ex}"]) for ex in ("sparse", "dense", "auto")}
                print(anchors, frac, res, flush=True)
                rows.append([f"{anchors:,}", f"{100 * frac:g}%", _kb(res["sparse"]["bytes"]), _kb(res["dense"]["bytes"]),
                             f"{res['dense']['bytes'] / res['sparse']['bytes']:.1f}x",
                             f"{res['sparse']['ms']:.1f}", f"{res['dense']['ms']:.1f}", res["auto"]["exchange"]])
        exchange_table = _table(["anchors", "rows touched / rank", "sparse KiB / rank", "dense KiB / rank",
                                 "bytes saved", "sparse ms", "dense ms", "auto picks"], rows)

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    text = (f"{BEGIN}\n_Measured by `python benchmarks/bench_distributed.py --doc` on {platform.machine()}, "
            f"{os.cpu_count()} cores, torch {torch.__version__}, gloo over loopback, 1 thread per process; "
            f"load average {load:.1f} during the run. Training part: built-in `{a.variant}` scene at "
            f"{a.resolution} px, {source}, global batch {a.batch}, mean of {a.iterations - 1} iterations after one "
            f"warm-up, effects {a.effects}._\n\n**Training, 1 vs 2 processes**\n\n{train_table}\n\n"
            f"**Gradient exchange alone, 2 processes** (conditions A x 3 x 8 float32 + projections; median of "
            f"5)\n\n{exchange_table}\n{END}")
    print(text)
    if a.out is None:
        return
    doc = a.out.read_text() if a.out.exists() else ""
    if BEGIN in doc and END in doc:
        doc = doc[:doc.index(BEGIN)] + text + doc[doc.index(END) + len(END):]
        a.out.write_text(doc)
        print(f"updated {a.out}")


if __name__ == "__main__":
    main()
