"""``controlgs eval``: the 4 x 5 run-time grid for the backbone without and with supersampling and
for every adapter a run folder holds, on the test views of a user's dataset (``--model`` /
``--data``, by default those ``RUN/run.json`` records) or of the built-in scene (``--variant``);
writes the report (results.json, report.md, heatmap, comparison, condition strip). A run trained
with ``--seeds K`` holds one folder ``seed-<s>`` per seed; each is evaluated and the report shows
mean ± std over them."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from .common import (add_data_arguments, add_render_arguments, apply_run_defaults, cache_bytes, check_options,
                     check_out_path, check_rasterizer_name, lens_record, load_lens_arg, make_renderer, render_record,
                     user_scene)
from .adapters import effects_from
from .demo import add_common, add_gazes, add_lpips, evaluate_seeds, gazes_arg, load_lpips_arg, report_figures, seed_runs


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("eval", help="evaluate the run-time grid (no-SS, SS-backbone, adapters) and write a report")
    p.add_argument("--run", default="controlgs-run",
                   help="folder written by `controlgs train` (every <name>.controlgs.safetensors in it is evaluated)")
    p.add_argument("--out", default=None, help="report folder (default: the run folder)")
    add_common(p, from_run=True)
    add_data_arguments(p)
    add_render_arguments(p, from_run=True)
    p.add_argument("--effects", default=None, help="downstream stages, comma-separated (default: the run's, else all)")
    add_lpips(p)
    add_gazes(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import torch

    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.ablations import ABLATIONS
    from controlgs_adapter.report import write_report

    check_options(args)  # every option, the report folder and the run file before any work
    run_dir = Path(args.run)
    out = check_out_path(args.out, "--out", folder=True) if args.out else check_out_path(run_dir, "--run", folder=True)
    recorded = apply_run_defaults(args, run_dir)
    adapters = {seed: {n: folder / f"{n}.controlgs.safetensors" for n in ("controlgs", *ABLATIONS)
                       if (folder / f"{n}.controlgs.safetensors").is_file()}
                for seed, folder in seed_folders(run_dir, args.seed, args.seeds)}
    for seed, found in adapters.items():
        if "controlgs" not in found:
            where = run_dir if len(adapters) == 1 else run_dir / f"seed-{seed}"
            raise InputValueError(f"{where}: no controlgs.controlgs.safetensors (train one with `controlgs train --out {run_dir}`)")
    if len({tuple(found) for found in adapters.values()}) > 1:
        raise InputValueError(f"{run_dir}: the seed folders hold different adapters ("
                              + "; ".join(f"seed-{s}: {', '.join(found)}" for s, found in adapters.items())
                              + "); train every seed with the same ablations")
    lpips = load_lpips_arg(args)
    check_rasterizer_name(args.rasterizer)  # before loading anything
    lens = load_lens_arg(args)
    gazes = gazes_arg(args, lens)
    t = time.perf_counter()
    if user_scene(args):
        from .common import load_user_scene

        scene = load_user_scene(args)
        model, data, name = scene.model, scene.data, f"{scene.family} {args.model} + {scene.data.format} {args.data}"
        resolution = scene.resolution
    else:
        from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

        from .demo import DEFAULT_RESOLUTION

        resolution = DEFAULT_RESOLUTION if args.resolution is None else args.resolution
        builtin = load_builtin_scene(args.variant, resolution, cache=True)
        model, data, name = load_builtin_backbone(args.variant).to(args.device), builtin.data, builtin.name
        resolution = None  # the built-in views are rendered at S
    views = data.views("test", resolution=resolution, cache_bytes=cache_bytes(args), first=args.test_views)
    renderer = make_renderer(args, model)
    load_s = time.perf_counter() - t
    t = time.perf_counter()
    effects = effects_from(args.effects)
    results = evaluate_seeds(model, views, adapters, effects=effects, optics_mode=args.optics, lpips=lpips,
                             progress=args.progress, renderer=renderer, lens=lens, gazes=gazes)
    eval_s = time.perf_counter() - t
    first = next(iter(adapters.values()))
    comparison, response = report_figures(model, first["controlgs"], views, effects=effects, optics_mode=args.optics,
                                          renderer=renderer, lens=lens)
    info = {"scene": name, "resolution": args.resolution, "test_views": len(views), "optics": args.optics,
            "adapters": list(first), "seeds": len(results), "effects": sorted(effects), "lens": lens_record(lens),
            "device": str(args.device),
            **render_record(args),
            "threads": torch.get_num_threads(),
            "load_s": round(load_s, 1), "eval_s": round(eval_s, 1),
            **({"lpips_weights": lpips.source} if lpips is not None else {}),
            **({"iterations": recorded.get("iterations"), "seed": recorded.get("seed")} if recorded else {})}
    for p in write_report(out, results, info=info, comparison=comparison,
                          response=response):
        print(p)
    return 0


def seed_folders(run_dir: Path, seed: int, seeds: int | None) -> list[tuple[int, Path]]:
    """``(seed, folder)`` to evaluate: ``--seeds K`` picks ``seed-<s>`` for s = seed .. seed + K - 1
    (``run_dir`` itself for K = 1); without it every ``seed-<s>`` folder of ``run_dir``, else ``run_dir``."""
    if seeds is not None:
        return seed_runs(run_dir, seed, seeds)
    found = sorted((int(f.name[5:]), f) for f in run_dir.glob("seed-*") if f.is_dir() and f.name[5:].lstrip("-").isdigit())
    return found or [(seed, run_dir)]
