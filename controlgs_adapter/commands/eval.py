"""``controlgs eval``: the 4 x 5 run-time grid for the backbone without and with supersampling
and for trained adapters, on the built-in scene's test views; writes results.json and report.md."""

from __future__ import annotations

import argparse
from pathlib import Path

from .demo import add_common, first_views


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("eval", help="evaluate the run-time grid (no-SS, SS-backbone, adapters) and write a report")
    p.add_argument("--run", default="controlgs-run",
                   help="folder written by `controlgs train` (its <name>.controlgs.safetensors files are evaluated)")
    p.add_argument("--out", default=None, help="report folder (default: the run folder)")
    add_common(p)
    p.add_argument("--ablations", action="store_true", help="also evaluate the ablation adapters found in the run folder")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.report import ABLATIONS, write_report
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    run_dir = Path(args.run)
    names = ["controlgs", *(ABLATIONS if args.ablations else [])]
    adapters = {n: run_dir / f"{n}.controlgs.safetensors" for n in names if (run_dir / f"{n}.controlgs.safetensors").is_file()}
    if "controlgs" not in adapters:
        raise InputValueError(f"{run_dir}: no controlgs.controlgs.safetensors (train one with `controlgs train --out {run_dir}`)")
    scene = load_builtin_scene(args.variant, args.resolution, cache=True)
    model = load_builtin_backbone(args.variant)
    views = first_views(scene.data, "test", args.test_views)
    result = evaluate_grid(model, views, adapters, optics_mode=args.optics, progress=args.progress)
    info = {"scene": scene.name, "resolution": args.resolution, "test_views": len(views), "optics": args.optics}
    for p in write_report(Path(args.out) if args.out else run_dir, result, info=info):
        print(p)
    return 0
