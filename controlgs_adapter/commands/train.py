"""``controlgs train``: train a ControlGS adapter on the built-in scene's baked backbone
(checkpoints resume exactly after an interruption; the adapter is saved as safetensors).
Under ``torchrun`` it trains data-parallel, or with ``--scenes`` one scene per process
(docs/distributed.md)."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from ..distributed import DistContext, add_distributed_arguments, init_distributed, shard_scenes
from ..lock import run_lock
from .demo import add_common, add_training, train_adapters


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("train", help="train a ControlGS adapter (frozen backbone) on the built-in scene")
    p.add_argument("--out", default="controlgs-run", help="folder for the adapter file(s) and checkpoints")
    add_common(p)
    add_training(p)
    add_distributed_arguments(p, scene_choices=("ar", "vr"))
    p.add_argument("--ablation", choices=("wo_lens", "wo_display", "wo_resample", "state_blind"), action="append",
                   default=[], help="also train this ablation (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    names = ["controlgs", *args.ablation]
    with init_distributed(args.dist_backend, timeout=args.dist_timeout, exchange=args.exchange) as dist:

        def load(variant: str):  # views and backbone on this rank's device (cuda:<LOCAL_RANK> with NCCL)
            scene = load_builtin_scene(variant, args.resolution, cache=True)
            return scene.views("train"), load_builtin_backbone(variant).to(dist.device)

        if args.scenes:  # many-scenes mode: this process's scenes, each trained alone (and locked) by it
            for variant in shard_scenes(args.scenes, dist):
                with run_lock(Path(args.out) / variant):
                    paths = train_adapters(*load(variant), Path(args.out) / variant, args, names, dist=DistContext())
                for name, path in paths.items():
                    print(f"[rank {dist.rank}] {variant} {name}: {path}")
            return 0
        with run_lock(Path(args.out)) if dist.is_main else contextlib.nullcontext():  # rank 0 holds the folder
            paths = train_adapters(*load(args.variant), Path(args.out), args, names, dist=dist)
        if dist.is_main:
            for name, path in paths.items():
                print(f"{name}: {path}")
    return 0
