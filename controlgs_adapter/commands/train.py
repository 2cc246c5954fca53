"""``controlgs train``: train a ControlGS adapter on the built-in scene's baked backbone
(checkpoints resume exactly after an interruption; the adapter is saved as safetensors)."""

from __future__ import annotations

import argparse
from pathlib import Path

from .demo import add_common, add_training, train_adapters


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("train", help="train a ControlGS adapter (frozen backbone) on the built-in scene")
    p.add_argument("--out", default="controlgs-run", help="folder for the adapter file(s) and checkpoints")
    add_common(p)
    add_training(p)
    p.add_argument("--ablation", choices=("wo_lens", "wo_display", "wo_resample", "state_blind"), action="append",
                   default=[], help="also train this ablation (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    scene = load_builtin_scene(args.variant, args.resolution, cache=True)
    model = load_builtin_backbone(args.variant)
    paths = train_adapters(scene, model, Path(args.out), args, ["controlgs", *args.ablation])
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0
