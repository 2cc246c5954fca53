"""``controlgs demo``: the main job. Loads the built-in scene and its baked backbone, trains the
ControlGS adapter (and with ``--ablations`` the ablations) for one or ``--seeds K`` seeds,
evaluates the 4 x 5 run-time grid and writes the report (tables, heatmaps, images) to a folder."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from .adapters import add_training, effects_from, train_adapters, training_job

DEFAULT_RESOLUTION = 96


def add_common(p: argparse.ArgumentParser, from_run: bool = False) -> None:
    """Options shared by demo, train and eval (``--optics`` and ``--seed`` default to the
    :class:`~controlgs_adapter.training.TrainConfig` fields they set; ``from_run``: ``--lens`` defaults to
    the run's)."""
    from controlgs_adapter.training import TrainConfig

    from .common import add_lens_argument

    base = TrainConfig()
    p.add_argument("--variant", choices=("ar", "vr"), default="ar", help="built-in scene: object-centric AR or immersive VR")
    p.add_argument("--resolution", type=int, default=None,
                   help=f"working resolution, longer side in pixels: the built-in scene's S x S (default {DEFAULT_RESOLUTION}); "
                        "your data's images are downscaled to it, never upscaled (default 256)")
    p.add_argument("--test-views", type=int, default=None, help="evaluate only the first N test views")
    p.add_argument("--optics", choices=("fast", "exact"), default=base.psf_mode,
                   help=f"PSF operator of the last training phase and of the evaluation (default {base.psf_mode})")
    p.add_argument("--seed", type=int, default=base.seed, help=f"training seed (default {base.seed})")
    p.add_argument("--seeds", type=int, default=None,
                   help="train / evaluate K seeds: --seed, --seed + 1, ... (adapters in seed-<s>/ when K > 1; "
                        "the report shows mean ± std over seeds; default 1, eval: the seed-<s>/ folders found)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")
    add_lens_argument(p, from_run=from_run)


def add_gazes(p: argparse.ArgumentParser) -> None:
    """``--gazes``: the foveation axis's gazes (with the foveation effect)."""
    p.add_argument("--gazes", nargs="+", default=None, metavar="AZ,EL",
                   help="with the foveation effect: the gazes of the evaluation's foveation axis, (azimuth, elevation) "
                        "in degrees from the lens axis, each inside the lens's field (default 0,0 10,0 14,14)")


def gazes_arg(args: argparse.Namespace, lens: Any) -> list[tuple[float, float]] | None:
    """``--gazes`` as ``[(azimuth, elevation)]`` degrees (None: the default), each checked to lie in ``lens``'s
    field; InputValueError naming --gazes."""
    import math

    from controlgs_adapter.downstream.optics.visual_angles import VisualAngles
    from controlgs_adapter.errors import InputValueError

    if args.gazes is None:
        return None
    gazes = []
    for item in args.gazes:
        parts = item.split(",")
        try:
            az, el = (float(v) for v in parts)
        except ValueError:
            raise InputValueError(f"--gazes takes AZ,EL pairs of degrees (e.g. 0,0 10,0), got {item!r}") from None
        if not (math.isfinite(az) and math.isfinite(el)):
            raise InputValueError(f"--gazes takes finite degrees, got {item!r}")
        gazes.append((az, el))
    angles = VisualAngles.of_bank(lens.bank)
    for g in gazes:
        try:
            angles.check_gaze(g)
        except InputValueError as e:
            raise InputValueError(f"--gazes: {e}") from None
    return gazes


def add_lpips(p: argparse.ArgumentParser) -> None:
    """``--lpips-weights``: local LPIPS weight files (never downloaded)."""
    p.add_argument("--lpips-weights", nargs="+", default=None, metavar="PATH",
                   help="compute LPIPS (AlexNet) from local files: torchvision's alexnet-owt-7be5be79.pth and the lpips "
                        "package's weights/v0.1/alex.pth head (found by itself when lpips is installed), or one "
                        "file with both; torch weights_only or safetensors. Nothing is downloaded")


def load_lpips_arg(args: argparse.Namespace) -> Any:
    """The LPIPS network of ``--lpips-weights`` (None without it)."""
    from controlgs_adapter.perceptual import load_lpips

    return load_lpips(args.lpips_weights) if getattr(args, "lpips_weights", None) else None


def seed_runs(out: Path, seed: int, seeds: int | None) -> list[tuple[int, Path]]:
    """``(seed, folder)`` of each of ``seeds`` seeds from ``seed`` (None: 1): ``out`` itself for one
    seed, ``out/seed-<s>`` for several."""
    from controlgs_adapter.errors import InputValueError

    k = 1 if seeds is None else seeds
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise InputValueError(f"--seeds must be an int >= 1, got {seeds!r}")
    return [(seed, out)] if k == 1 else [(seed + i, out / f"seed-{seed + i}") for i in range(k)]


def evaluate_seeds(model: Any, views: Any, adapters: dict[int, dict[str, Path]], **kwargs: Any) -> list[Any]:
    """:func:`~controlgs_adapter.evaluation.evaluate_grid` of each seed's adapters ``{seed: {name:
    file}}``; the baselines and the ideal render do not depend on the seed and are evaluated once
    (copied into every seed's result). Each result's ``info["seed"]`` is its seed."""
    from controlgs_adapter.evaluation import evaluate_grid

    results: list[Any] = []
    for seed, paths in adapters.items():
        first = results[0] if results else None
        r = evaluate_grid(model, views, paths, **kwargs) if first is None else \
            evaluate_grid(model, views, paths, baselines=(), ideal=False, **kwargs)
        if first is not None:
            shared = [m for m in first.methods if m not in paths]
            r.per_view = {**{m: first.per_view[m] for m in shared}, **r.per_view}
            if first.foveation is not None and r.foveation is not None:
                fixed = {m: v for m, v in first.foveation.per_view.items() if m not in paths}
                r.foveation.per_view = {**fixed, **r.foveation.per_view}
        r.info["seed"] = seed
        results.append(r)
    return results


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("demo", help="train ControlGS on the built-in scene, evaluate the run-time grid, write a report")
    p.add_argument("--out", default="report", help="report folder")
    add_common(p)
    add_training(p)
    add_lpips(p)
    add_gazes(p)
    p.add_argument("--ablations", action=argparse.BooleanOptionalAction, default=True,
                   help="also train and evaluate w/o lens, display, resample, state-blind, and w/o foveation when "
                        "--effects has foveation (default: on)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """The demo, holding the lock of the report folder (a second run into it is refused)."""
    from controlgs_adapter.lock import run_lock

    from .adapters import train_config
    from .common import check_options, check_out_path, load_lens_arg

    check_options(args)  # before the lock: a refused demo creates nothing
    out = check_out_path(args.out, "--out", folder=True)
    for seed, _ in seed_runs(out, args.seed, args.seeds):
        train_config(args, "controlgs", seed)
    lens = load_lens_arg(args)
    gazes_arg(args, lens)
    with run_lock(out):
        return _run(args, lens)


def _run(args: argparse.Namespace, lens: Any) -> int:
    import torch

    from controlgs_adapter.ablations import ablations_for
    from controlgs_adapter.report import seed_summary, write_report
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.resolution is None:
        args.resolution = DEFAULT_RESOLUTION
    lpips = load_lpips_arg(args)
    runs = seed_runs(out, args.seed, args.seeds)
    timings: dict[str, float] = {}
    t = time.perf_counter()
    scene = load_builtin_scene(args.variant, args.resolution, cache=True)
    model = load_builtin_backbone(args.variant)
    timings["load_s"] = time.perf_counter() - t

    t = time.perf_counter()
    names = ["controlgs", *(ablations_for(effects_from(args.effects)) if args.ablations else [])]
    trained: dict[str, int] = {}
    job = training_job(args, names, len(runs))  # seeds x adapters trainings, one bar each
    adapters = {s: train_adapters(scene.views("train"), model, folder, args, names, trained=trained, seed=s, job=job,
                                  lens=lens) for s, folder in runs}
    timings["train_s"] = time.perf_counter() - t

    t = time.perf_counter()
    views = scene.data.views("test", first=args.test_views)
    effects = effects_from(args.effects)
    results = evaluate_seeds(model, views, adapters, effects=effects, optics_mode=args.optics, lpips=lpips,
                             progress=args.progress, lens=lens, gazes=gazes_arg(args, lens))
    timings["eval_s"] = time.perf_counter() - t
    t = time.perf_counter()
    comparison, response = report_figures(model, adapters[runs[0][0]]["controlgs"], views, effects=effects,
                                          optics_mode=args.optics, lens=lens)
    timings["figures_s"] = time.perf_counter() - t
    info = {"scene": scene.name, "resolution": args.resolution, "iterations": trained["controlgs"], "test_views": len(views),
            "optics": args.optics, "lens": lens.spec, "seed": args.seed, "seeds": len(runs), "threads": torch.get_num_threads(),
            **({"lpips_weights": lpips.source} if lpips is not None else {}),
            **{k: round(v, 1) for k, v in timings.items()}}
    paths = write_report(out, results, info=info, comparison=comparison, response=response)
    summary = seed_summary(results)
    print(json.dumps({m: {k: round(v["mean"], 4) for k, v in metrics.items()} for m, metrics in summary.items()}, indent=1))
    print("report: " + ", ".join(str(p) for p in paths))
    return 0


def report_figures(model: Any, adapter: Path, views: Any, *, effects: dict[str, Any] | None = None,
                   optics_mode: str, renderer: Any = None, lens: Any = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The report's comparison (:func:`side_by_side`, through ``lens``) and condition strip
    (:func:`condition_response`) on the first of ``views``, on the model's device, rendered by ``renderer``
    (None: the model's own)."""
    from controlgs_adapter.evaluation import condition_response, side_by_side
    from controlgs_adapter.rendering.protocol import model_device

    device = model_device(model)
    cam, gt = views[0]
    bg = views.background.to(device)
    comparison = side_by_side(model, adapter, cam, gt.to(device), effects=effects, background=bg, optics_mode=optics_mode,
                              renderer=renderer, lens=lens)
    response = condition_response(model, adapter, cam, background=bg, renderer=renderer)
    return comparison, response
