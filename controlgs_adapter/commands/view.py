"""``controlgs view``: the interactive viewer. Loads a user's model + dataset (``--model``/``--data``,
by default those ``RUN/run.json`` records) or the built-in scene, the adapters of a run folder
(``--run``; for the built-in scene without one, a quick adapter is trained first), and serves the page
on the loopback interface until interrupted."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any, Callable

from .common import (add_data_arguments, add_lens_argument, add_render_arguments, apply_run_defaults, cache_bytes,
                     check_options, check_rasterizer_name, load_lens_arg, make_renderer, parse_device, user_scene)

#: the built-in scene's default resolution in the viewer (the latency benchmark's 128 px)
VIEW_RESOLUTION = 128
#: iterations of the quick adapter trained for the built-in scene when no --run is given: fewer than
#: `controlgs train`'s (:data:`.adapters.DEMO_ITERATIONS`) and the paper's (``TrainConfig.iterations``)
#: on purpose, since it is trained while the user waits for the page; a stand-in for a run
QUICK_ITERATIONS = 150


def add_parser(sub: "argparse._SubParsersAction") -> None:
    from .adapters import DEMO_ITERATIONS

    p = sub.add_parser("view", help="interactive viewer in the browser: no-SS, SS-backbone and ControlGS at any state")
    p.add_argument("--run", default=None, help="folder written by `controlgs train` or `controlgs demo` (its adapters "
                                               "are shown; its run.json gives --model/--data)")
    p.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: a free one)")
    p.add_argument("--variant", choices=("ar", "vr"), default="ar", help="built-in scene: object-centric AR or immersive VR")
    p.add_argument("--resolution", type=int, default=None,
                   help=f"longer side in pixels (built-in scene: S x S, default {VIEW_RESOLUTION}; your data: default 256)")
    p.add_argument("--test-views", type=int, default=None, help="offer only the first N test views")
    p.add_argument("--iterations", type=int, default=QUICK_ITERATIONS,
                   help=f"built-in scene without --run: iterations of the quick adapter trained before serving (default "
                        f"{QUICK_ITERATIONS}: a stand-in for a run, kept short; `controlgs train` runs {DEMO_ITERATIONS})")
    p.add_argument("--threads", type=int, default=None,
                   help="torch intra-op threads on the CPU (default: torch's; 1 can be faster on a busy machine)")
    add_lens_argument(p, from_run=True)
    add_data_arguments(p)
    add_render_arguments(p, from_run=True)
    p.set_defaults(func=run)


def _adapters(run_dir: Path) -> dict[str, Path]:
    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.ablations import ABLATIONS

    found = {n: run_dir / f"{n}.controlgs.safetensors" for n in ("controlgs", *ABLATIONS)}
    found = {n: p for n, p in found.items() if p.is_file()}
    if "controlgs" not in found:
        raise InputValueError(f"{run_dir}: no controlgs.controlgs.safetensors (train one with `controlgs train --out {run_dir}`)")
    return found


def _quick_adapter(model: Any, views: Any, folder: Path, iterations: int, renderer: Any = None,
                   lens: Any = None) -> dict[str, Path]:
    """Train a short ControlGS adapter on the built-in scene's training views through ``lens`` (a stand-in for a run)."""
    from controlgs_adapter.training import TrainConfig, Trainer

    trainer = Trainer(model, views, TrainConfig(iterations=iterations, checkpoint_every=0), renderer=renderer, lens=lens)
    try:
        trainer.train(progress=True)
        path = trainer.cgs.save(folder / "controlgs.controlgs.safetensors")
    finally:
        trainer.cgs.unwrap()
    return {"controlgs": Path(path)}


def _exact_truth(builtin: Any) -> Callable[[Any], Any]:
    """The built-in scene's exact ground truth of any camera (ray cast, as its dataset's images)."""
    from controlgs_adapter.scene import render_planes

    background = tuple(builtin.background.tolist())
    return lambda camera: render_planes(builtin.planes, camera, background=background)[0].float()


def run(args: argparse.Namespace) -> int:
    import torch

    from controlgs_adapter.checks import check_number
    from controlgs_adapter.errors import InputValueError
    from controlgs_adapter.viewer import ViewerSession, make_server

    check_number("--port", args.port, integer=True, low=0, high=65535)
    check_options(args)
    if args.threads is not None:
        torch.set_num_threads(int(check_number("--threads", args.threads, integer=True, low=1, high=4096)))
    run_dir = None if args.run is None else Path(args.run)
    if run_dir is not None:
        if not run_dir.is_dir():
            raise InputValueError(f"--run {run_dir}: no such folder")
        apply_run_defaults(args, run_dir)
        adapters = _adapters(run_dir)
    check_rasterizer_name(args.rasterizer)  # before loading anything
    lens = load_lens_arg(args)
    with tempfile.TemporaryDirectory(prefix="controlgs-view-") as tmp:
        truth: Callable[[Any], Any] | None = None
        if user_scene(args):
            from .common import load_user_scene

            if run_dir is None:
                raise InputValueError("--model/--data need --run RUN (the folder with the trained adapters)")
            scene = load_user_scene(args)
            model, name = scene.model, f"{scene.family} {args.model}"
            renderer = make_renderer(args, model)
            views = scene.data.views("test", resolution=scene.resolution, cache_bytes=cache_bytes(args), first=args.test_views)
        else:
            from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

            from .demo import DEFAULT_RESOLUTION

            device = parse_device(args.device)
            builtin = load_builtin_scene(args.variant, args.resolution or VIEW_RESOLUTION, cache=True)
            model, name = load_builtin_backbone(args.variant).to(device), builtin.name
            renderer = make_renderer(args, model)
            views = builtin.data.views("test", first=args.test_views)
            truth = _exact_truth(builtin)
            if run_dir is None:
                check_number("--iterations", args.iterations, integer=True, low=1, high=2**63 - 1)
                print(f"no --run: training a quick ControlGS adapter ({args.iterations} iterations) on {name}; "
                      "`controlgs demo --out report` then `controlgs view --run report` shows a fully trained one")
                train = load_builtin_scene(args.variant, DEFAULT_RESOLUTION, cache=True).views("train")  # the demo's size
                adapters = _quick_adapter(model, train, Path(tmp), args.iterations, renderer, lens)
        session = ViewerSession(model, views, adapters, truth=truth, name=name, renderer=renderer, lens=lens)
        server = make_server(session, args.port)
        print(f"controlgs view: {name}, methods {', '.join(session.methods)} on {session.device}", flush=True)
        print(f"serving on {server.url} (loopback only; Ctrl-C stops)", flush=True)
        try:
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            server.server_close()
    return 0
