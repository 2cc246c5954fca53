"""``controlgs train``: train a ControlGS adapter (and by default the ablations) on a frozen
backbone: a user's trained model folder and its dataset (``--model`` / ``--data``), or the built-in
scene's baked backbone (``--variant``). Checkpoints resume exactly after an interruption; adapters
are saved as safetensors (with ``--seeds K``, one folder ``RUN/seed-<s>`` per seed); ``RUN/run.json``
records what the run was trained on (written once its adapters are saved; a folder trained on another
scene is refused). Under ``torchrun``
it trains data-parallel, or with ``--scenes`` one built-in scene per process (docs/how-to/distributed.md)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..ablations import ABLATIONS, ablations_for
from ..distributed import DistContext, init_distributed, shard_scenes
from .adapters import add_distributed_arguments, add_training, effects_from, train_adapters, train_config, training_job
from .common import (RUN_FILE, add_data_arguments, add_render_arguments, anchor_positions, cache_bytes, check_line,
                     check_options, check_out_path, check_rasterizer_name, lens_record, load_lens_arg, load_user_scene,
                     make_renderer, parse_device, read_run, render_record, user_scene)
from .demo import add_common, seed_runs

if TYPE_CHECKING:
    from ..downstream.optics.lenses import Lens

ABLATION_NAMES = tuple(ABLATIONS)


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("train", help="train a ControlGS adapter (frozen backbone) on your model + dataset or the built-in scene")
    p.add_argument("--out", default="controlgs-run", help="run folder: adapter file(s), checkpoints, run.json")
    add_common(p)
    add_training(p)
    add_data_arguments(p)
    add_render_arguments(p)
    add_distributed_arguments(p, scene_choices=("ar", "vr"))
    p.add_argument("--ablations", action=argparse.BooleanOptionalAction, default=True,
                   help="also train w/o lens, display, resample and state-blind, and w/o foveation when --effects has "
                        "foveation (default: on; --ablation picks some)")
    p.add_argument("--ablation", choices=ABLATION_NAMES, action="append", default=[],
                   help="train only these ablations besides ControlGS (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Train, holding the run folder's lock so that a second run into it is refused (under torchrun
    rank 0 holds it for the job; with ``--scenes`` each process locks its scenes' folders)."""
    from controlgs_adapter.lock import run_lock

    _check(args)  # every option and --out before the lock (a refused run creates nothing)
    lens = load_lens_arg(args)
    if args.scenes or os.environ.get("RANK", "0") != "0":
        return _run(args, lens)
    with run_lock(Path(args.out)):
        return _run(args, lens)


def _check(args: argparse.Namespace) -> None:
    """Refuse a run whose options cannot train (one line naming the option) before anything is written."""
    from controlgs_adapter.errors import InputValueError

    if args.scenes and user_scene(args):
        raise InputValueError("--scenes trains built-in scenes; it does not combine with --model/--data")
    check_options(args)
    writes = args.scenes or os.environ.get("RANK", "0") == "0"  # another rank of a data-parallel run writes nothing
    out = check_out_path(args.out, "--out", folder=True) if writes else Path(args.out)
    if writes and not args.scenes:  # the scene's paths now; how it is read once it is loaded
        scene = ({"model": str(Path(args.model).resolve()), "data": str(Path(args.data).resolve())} if user_scene(args)
                 else {"variant": args.variant, "model": None})
        check_same_scene(out, scene, keys=tuple(scene))
    for seed, _ in seed_runs(out, args.seed, args.seeds):
        for name in ["controlgs", *(args.ablation or (ablations_for(effects_from(args.effects)) if args.ablations else ()))]:
            train_config(args, name, seed)


#: run.json fields naming what a run folder's adapters were trained on: a later train into the folder must agree
SCENE_FIELDS = ("variant", "model", "data", "family", "model_iteration", "allow_unquantized", "format", "images",
                "holdout", "white_background", "resolution", "effects", "lens")


def check_same_scene(out: Path, record: dict[str, Any], keys: tuple[str, ...] = SCENE_FIELDS) -> None:
    """Refuse training into ``out`` when its ``run.json`` records another scene (model, data, how it is
    read, effects: the fields ``keys``) than ``record``: its adapters and record would no longer agree."""
    from controlgs_adapter.errors import InputValueError

    old = read_run(out)
    if old is None:
        return
    for key in keys:
        if key in old and old[key] != record.get(key):
            raise InputValueError(f"--out {out}: the run there was trained with {key} {old[key]!r}, this command gives "
                                  f"--{key.replace('_', '-')} {record.get(key)!r}; a run folder holds the adapters of one "
                                  "scene: choose another --out")


def _run(args: argparse.Namespace, lens: Lens) -> int:
    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.lock import run_lock
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    from .demo import DEFAULT_RESOLUTION

    names = ["controlgs", *(args.ablation or (ablations_for(effects_from(args.effects)) if args.ablations else ()))]
    out = Path(args.out)
    check_rasterizer_name(args.rasterizer)  # before loading anything
    if user_scene(args):
        if args.scenes:
            raise InputValueError("--scenes trains built-in scenes; it does not combine with --model/--data")
        return _run_user(args, names, out, lens)
    if args.resolution is None:
        args.resolution = DEFAULT_RESOLUTION
    device = parse_device(args.device)
    with init_distributed(args.dist_backend, device=device, timeout=args.dist_timeout, exchange=args.exchange) as dist:

        def load(variant: str):  # views and backbone on this rank's device (--device; cuda:<LOCAL_RANK> with NCCL)
            scene = load_builtin_scene(variant, args.resolution, cache=True)
            return scene.views("train"), load_builtin_backbone(variant).to(dist.device)

        if args.scenes:  # many-scenes mode: this process's scenes, each trained alone
            for variant in shard_scenes(args.scenes, dist):
                with run_lock(out / variant):
                    views, model = load(variant)
                    renderer = make_renderer(args, model)
                    scene_runs = seed_runs(out / variant, args.seed, args.seeds)
                    job = training_job(args, names, len(scene_runs))
                    for seed, folder in scene_runs:
                        paths = train_adapters(views, model, folder, args, names, dist=DistContext(), seed=seed,
                                               renderer=renderer, job=job, lens=lens)
                        for name, path in paths.items():
                            print(f"[rank {dist.rank}] {variant} {name}: {path}")
            return 0
        views, model = load(args.variant)
        renderer = make_renderer(args, model)
        runs = seed_runs(out, args.seed, args.seeds)
        record = {"variant": args.variant, "effects": sorted(effects_from(args.effects)), "lens": lens_record(lens),
                  "iterations": args.iterations, "seed": args.seed, "seeds": len(runs), "adapters": names,
                  **render_record(args), "distributed": _dist_record(dist)}
        check_same_scene(out, record)
        job = training_job(args, names, len(runs))  # seeds x adapters trainings, one bar each
        for seed, folder in runs:
            paths = train_adapters(views, model, folder, args, names, dist=dist, seed=seed, renderer=renderer, job=job,
                                   lens=lens)
            if dist.is_main:
                for name, path in paths.items():
                    print(f"{name}: {path}")
        if dist.is_main:  # once the adapters it describes are saved
            _write_run(out, record)
    return 0


def _run_user(args: argparse.Namespace, names: list[str], out: Path, lens: Lens) -> int:
    """Train on ``--model`` / ``--data``: load, check the scene, train, then record ``run.json``."""
    from controlgs_adapter.datasets.sanity import check_scene

    runs = seed_runs(out, args.seed, args.seeds)
    scene = load_user_scene(args)
    report = check_scene(scene.data, points=anchor_positions(scene.model))
    with init_distributed(args.dist_backend, device=scene.device, timeout=args.dist_timeout,
                          exchange=args.exchange) as dist:
        scene.model.to(dist.device)  # loaded on --device; under NCCL this rank's own GPU, cuda:<LOCAL_RANK>
        views = scene.data.views("train", resolution=scene.resolution, cache_bytes=cache_bytes(args))
        renderer = make_renderer(args, scene.model)
        record = scene.record(args, effects=sorted(effects_from(args.effects)), lens=lens_record(lens),
                              iterations=args.iterations, seed=args.seed, seeds=len(runs), adapters=names,
                              **render_record(args), distributed=_dist_record(dist))
        check_same_scene(out, record)
        if dist.is_main:
            print(check_line(report))
            print(f"model: {scene.family} {args.model}; training views: {views.describe()}")
        job = training_job(args, names, len(runs))  # seeds x adapters trainings, one bar each
        for seed, folder in runs:
            paths = train_adapters(views, scene.model, folder, args, names, dist=dist, seed=seed, renderer=renderer,
                                   job=job, lens=lens)
            if dist.is_main:
                for name, path in paths.items():
                    print(f"{name}: {path}")
        if dist.is_main:  # once the adapters it describes are saved
            _write_run(out, record)
    return 0


def _dist_record(dist: DistContext) -> dict[str, Any]:
    """How the run was spread for ``run.json``: processes, process-group backend (None: one process),
    gradient exchange (``--exchange``; it only changes what travels between processes)."""
    return {"processes": dist.world_size, "backend": dist.backend, "exchange": dist.exchange}


def _write_run(out: Path, record: dict[str, Any]) -> None:
    """Write ``out/run.json`` (atomically): what the run was trained on and with."""
    from controlgs_adapter.formats.safetensors import atomic_write

    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / RUN_FILE, lambda tmp: Path(tmp).write_text(json.dumps(record, indent=1)))
