"""Cost of the condition injector: decoder time and storage, wrapped vs the bare backbone.

Model: the project's Scaffold-GS reference model (``NeuralGaussianModel``: feat_dim 32, K = 10,
decoders ``mlp_opacity``/``mlp_cov``/``mlp_color`` with ``Linear(35, 32)`` first layers), random
anchors in front of the camera, every anchor visible (rows = anchors).

Time: the three decoders on the ``[A, 35]`` decoder input, bare vs inside
``cgs.conditioned(state, camera, anchor_ids=visible_mask)`` (entering the block included: it
projects the anchors for the lens strength). Bare and wrapped runs alternate and each is the
minimum over the repeats, so drifting machine load affects both alike. Times are CPU time of the calling
thread (``time.thread_time``) with ``torch.set_num_threads(--threads)``, which keeps a loaded
shared machine from inflating them. Also measured: the full Scaffold-GS decode
(``model.decode``: gathers, concatenations, masks) and the wrapped model outside a block.

Storage: a real Scaffold-GS output directory (``save_scaffold_dir``: PLY + TorchScript decoders +
cfg_args) vs the adapter file (``cgs.save``), float32 and float16 conditions.

    python benchmarks/bench_injector.py --doc           # ~1-2 min, writes docs/benchmarks/injector.md (default: print only)
    python benchmarks/bench_injector.py --anchors 10000 --repeats 3 --no-write   # quick look
"""

from __future__ import annotations

import argparse
import copy
import platform
import tempfile
import time
from pathlib import Path

import torch

from controlgs_adapter import Camera, ControlGS, RuntimeState, __version__
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.backends.scaffold_io import save_scaffold_dir

MODULE_SETS = {1: ("lens",), 2: ("lens", "resample"), 3: ("lens", "resample", "display")}
STATE = RuntimeState(downsample=4.0, power_saving=0.4)  # every module's strength is > 0
DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "injector.md"


def make_model(num_anchors: int, seed: int = 0) -> tuple[NeuralGaussianModel, Camera, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    model = NeuralGaussianModel(num_anchors)
    with torch.no_grad():
        model._anchor.copy_(torch.rand(num_anchors, 3, generator=g) * 2 - 1)
        model._anchor_feat.copy_(torch.randn(num_anchors, 32, generator=g))
        model._offset.copy_(torch.randn(num_anchors, 10, 3, generator=g) * 0.5)
    w2c = torch.eye(4)
    w2c[2, 3] = 3.0
    cam = Camera(w2c, torch.tensor([[800.0, 0, 400], [0, 800.0, 300], [0, 0, 1]]), 800, 600)
    with torch.no_grad():
        view = model.get_anchor - cam.center
        x = torch.cat([model._anchor_feat, view / view.norm(dim=1, keepdim=True)], dim=1)  # [A, 35]
    return model, cam, x


def paired_times(bare, wrapped, repeats: int) -> tuple[float, float, float]:
    """(bare ms, wrapped ms, wrapped / bare): minimum over ``repeats`` alternating runs of each
    (interference from other jobs only ever adds time, so the minimum is the cleanest estimate)."""
    bare(), wrapped()  # warm-up
    tb, tw = [], []
    for _ in range(repeats):
        for f, acc in ((bare, tb), (wrapped, tw)):
            t0 = time.thread_time()
            f()
            acc.append(time.thread_time() - t0)
    return min(tb) * 1e3, min(tw) * 1e3, min(tw) / min(tb)


def decoders(model: NeuralGaussianModel, x: torch.Tensor) -> None:
    model.mlp_opacity(x), model.mlp_cov(x), model.mlp_color(x)


@torch.no_grad()
def time_rows(anchors: list[int], cond_dims: list[int], module_counts: list[int], repeats: int) -> list[dict]:
    rows = []
    for a in anchors:
        model, cam, x = make_model(a)
        visible = torch.ones(a, dtype=torch.bool)
        for n in cond_dims:
            for mc in module_counts:
                cgs = ControlGS.wrap(model, modules=MODULE_SETS[mc], cond_dim=n)
                torch.nn.init.normal_(cgs.injector.conditions, std=0.1)

                def wrapped() -> None:
                    with cgs.conditioned(STATE, camera=cam, anchor_ids=visible):
                        decoders(model, x)

                bare_ms, wrapped_ms, ratio = paired_times(lambda: decoders(model, x), wrapped, repeats)
                rows.append(dict(anchors=a, N=n, modules=mc, bare=bare_ms, wrapped=wrapped_ms, ratio=ratio))
                print(f"  A={a:>6} N={n:>2} modules={mc}: bare {bare_ms:7.2f} ms  wrapped {wrapped_ms:7.2f} ms  "
                      f"x{ratio:.3f}", flush=True)
                cgs.unwrap()
    return rows


@torch.no_grad()
def time_full_decode(anchors: list[int], repeats: int) -> list[dict]:
    """Scaffold-GS's whole decode inside a block vs outside it, and the wrapped decoders outside a
    block vs hook-free copies (N = 8, three modules)."""
    rows = []
    for a in anchors:
        model, cam, x = make_model(a)
        visible = torch.ones(a, dtype=torch.bool)
        copies = copy.deepcopy((model.mlp_opacity, model.mlp_cov, model.mlp_color))  # before any hook exists
        cgs = ControlGS.wrap(model, cond_dim=8)
        torch.nn.init.normal_(cgs.injector.conditions, std=0.1)
        idle_ratio = paired_times(lambda: [d(x) for d in copies], lambda: decoders(model, x), repeats)[2]

        def wrapped_decode() -> None:
            with cgs.conditioned(STATE, camera=cam, anchor_ids=visible):
                model.decode(cam, visible)

        b, w, r = paired_times(lambda: model.decode(cam, visible), wrapped_decode, repeats)
        cgs.unwrap()
        rows.append(dict(anchors=a, bare=b, wrapped=w, ratio=r, idle_ratio=idle_ratio))
        print(f"  A={a:>6} full decode: bare {b:7.2f} ms  wrapped {w:7.2f} ms  x{r:.3f}; idle hooks x{idle_ratio:.3f}",
              flush=True)
    return rows


@torch.no_grad()
def storage_rows(anchors: list[int], cond_dims: list[int]) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for a in anchors:
            model, _, _ = make_model(a)
            folder = save_scaffold_dir(model, Path(tmp) / f"scene{a}", iteration=1)
            bare = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
            bare += (Path(tmp) / f"scene{a}" / "cfg_args").stat().st_size
            for n in cond_dims:
                cgs = ControlGS.wrap(model, cond_dim=n)
                f32 = cgs.save(Path(tmp) / "a32.safetensors").stat().st_size
                f16 = cgs.save(Path(tmp) / "a16.safetensors", dtype=torch.float16).stat().st_size
                cgs.unwrap()
                rows.append(dict(anchors=a, N=n, bare=bare, f32=f32, f16=f16))
    return rows


@torch.no_grad()
def fp16_effect(num_anchors: int = 20000) -> dict:
    """Max/mean abs change of the decoder outputs when conditions are stored in float16, for
    conditions of typical trained size (std 0.1)."""
    model, cam, x = make_model(num_anchors)
    cgs = ControlGS.wrap(model)
    torch.nn.init.normal_(cgs.injector.conditions, std=0.1)
    with cgs.conditioned(STATE, camera=cam):
        ref = [model.mlp_opacity(x), model.mlp_cov(x), model.mlp_color(x)]
    with tempfile.TemporaryDirectory() as tmp:
        path = cgs.save(Path(tmp) / "a.safetensors", dtype=torch.float16)
        cgs.unwrap()
        cgs = ControlGS.load(path, model)
    with cgs.conditioned(STATE, camera=cam):
        got = [model.mlp_opacity(x), model.mlp_cov(x), model.mlp_color(x)]
    cgs.unwrap()
    diffs = torch.cat([(a - b).abs().flatten() for a, b in zip(ref, got)])
    return dict(max=float(diffs.max()), mean=float(diffs.mean()))


def render_markdown(args, timing, full, storage, fp16) -> str:
    load = " ".join(f"{v:.1f}" for v in __import__("os").getloadavg())
    lines = [
        "# Injector benchmark (`benchmarks/bench_injector.py`)",
        "",
        f"controlgs-adapter {__version__}, torch {torch.__version__}, {platform.processor() or platform.machine()}, "
        f"{args.threads} thread(s); load average at the end of the run: {load}.",
        "Numbers are CPU time of the calling thread on a shared machine (other jobs were running); "
        "each figure is the minimum over alternating bare/wrapped runs in the same process. Re-run on your machine: "
        "`python benchmarks/bench_injector.py`.",
        "",
        "Model: Scaffold-GS reference model, feat_dim 32, K = 10; all anchors visible. *Wrapped* = entering "
        "`cgs.conditioned(state, camera, anchor_ids=mask)` (per-anchor lens strength from projecting the anchors) "
        "+ the three decoders with the injection. Modules: 1 = lens, 2 = lens + resample, "
        "3 = lens + resample + display (all strengths > 0).",
        "",
        "## Decoder forward time (three decoders)",
        "",
        "| anchors | N | modules | bare (ms) | wrapped (ms) | added time |",
        "| ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [f"| {r['anchors']:,} | {r['N']} | {r['modules']} | {r['bare']:.2f} | {r['wrapped']:.2f} | "
              f"{(r['ratio'] - 1) * 100:+.1f}% |" for r in timing]
    if full:
        lines += [
            "",
            "## Whole Scaffold-GS decode (`model.decode`: gathers, concatenation, decoders, masks), N = 8, 3 modules",
            "",
            "Bare = the wrapped model's decode outside a block (its hooks idle: see the last column).",
            "",
            "| anchors | bare (ms) | wrapped (ms) | added time | wrapped decoders outside a block vs hook-free copies |",
            "| ---: | ---: | ---: | ---: | ---: |",
        ]
        lines += [f"| {r['anchors']:,} | {r['bare']:.2f} | {r['wrapped']:.2f} | {(r['ratio'] - 1) * 100:+.1f}% | "
                  f"{(r['idle_ratio'] - 1) * 100:+.1f}% |" for r in full]
    lines += [
        "",
        "## Storage (3 modules)",
        "",
        "Bare = a Scaffold-GS output directory (`point_cloud.ply`, three TorchScript decoders, `cfg_args`); "
        "adapter = the `.safetensors` file written by `cgs.save` (conditions `[A, 3, N]` + projections + header).",
        "",
        "| anchors | N | bare (MB) | adapter fp32 (MB) | added fp32 | adapter fp16 (MB) | added fp16 |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [f"| {r['anchors']:,} | {r['N']} | {r['bare'] / 1e6:.2f} | {r['f32'] / 1e6:.2f} | "
              f"{r['f32'] / r['bare'] * 100:+.1f}% | {r['f16'] / 1e6:.2f} | {r['f16'] / r['bare'] * 100:+.1f}% |"
              for r in storage]
    lines += [
        "",
        "## Reading the numbers",
        "",
        "- The injection is one gather of `[R, M, N]` conditions, one `[R, M*N] x [M*N, D1]` matmul per distinct "
        "FC1 width (shared by the three decoders) and an in-place add per decoder; the lens strength needs one "
        "affine projection of the visible anchors per block. With N = 8 and three modules that matmul is "
        "768 multiply-adds per row against the backbone's 6,880 (three FC1s of 35 x 32, FC2s of 32 x 110), "
        "so on a compute-bound single CPU thread the decoders alone cannot get below about +11%; the rest is "
        "memory traffic (adds, gathers) and a fixed per-block cost of a few tenths of a millisecond (Python "
        "and small tensor ops) that dominates at 10k anchors.",
        "- Relative to the whole Scaffold-GS decode (gathers, concatenations, masks: what a frame pays) the cost "
        "is much smaller, and rasterisation (not included) dwarfs both; the paper reports about 20% lower FPS "
        "end to end on a GPU.",
        "- Outside a `conditioned` block the hooks return at once: the wrapped decoders run at the bare speed "
        "(within noise) and their outputs are bit-identical (tested).",
        "- Modules that are off, or whose strength is zero for every row (e.g. d = 1 for resample, rho = 0 for "
        "display), are not computed at all; at the neutral state the block costs only the strength evaluation.",
        "- Storage: fp32 conditions add 3 x N x 4 bytes per anchor (30% at N = 8, the paper's figure); fp16 halves "
        "that (15% at N = 8, 7.6% at N = 4) against Scaffold-GS's 79 float32 PLY fields per anchor.",
    ]
    if fp16:
        lines += [
            "",
            f"Effect of fp16 storage on the decoder outputs (20,000 anchors, N = 8, 3 modules, conditions with "
            f"std 0.1): max abs change {fp16['max']:.2e}, mean {fp16['mean']:.2e}.",
        ]
    return "\n".join(lines) + "\n"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--anchors", type=int, nargs="+", default=[10_000, 30_000, 100_000])
    p.add_argument("--cond-dims", type=int, nargs="+", default=[4, 8, 16])
    p.add_argument("--modules", type=int, nargs="+", default=[1, 2, 3], choices=[1, 2, 3])
    p.add_argument("--repeats", type=int, default=15, help="bare/wrapped pairs per configuration")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--out", type=Path, default=None, help="write the report to this file (default: print only)")
    p.add_argument("--doc", dest="out", action="store_const", const=DOC, help="write docs/benchmarks/injector.md")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    print("decoder time:")
    timing = time_rows(args.anchors, args.cond_dims, args.modules, args.repeats)
    print("full decode:")
    full = time_full_decode(args.anchors, args.repeats)
    print("storage:")
    storage = storage_rows(args.anchors, args.cond_dims)
    fp16 = fp16_effect()
    text = render_markdown(args, timing, full, storage, fp16)
    print(text)
    if args.out is not None:
        args.out.write_text(text)
        print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
