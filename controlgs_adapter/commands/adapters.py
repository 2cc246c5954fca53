"""Training adapters from the command line, shared by ``controlgs demo`` and ``controlgs train``: the
training options (defaults: the :class:`~controlgs_adapter.training.TrainConfig` fields, but for
``--iterations``), the data-parallel options, the config built from them and :func:`train_adapters`."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

from ..errors import InputValueError

if TYPE_CHECKING:
    from ..training import TrainConfig

#: ``--iterations`` of demo / train: a CPU-sized run on purpose, 10x fewer than the paper's 10,000
#: (``TrainConfig.iterations``); every other training option defaults to its :class:`TrainConfig` field
DEMO_ITERATIONS = 1000


def effects_from(names: str | list[str] | None) -> dict[str, Any]:
    """Downstream effects from a comma-separated list of stages (None: :data:`DEFAULT_EFFECTS`; ``foveation``
    is on only where named)."""
    from ..training import DEFAULT_EFFECTS

    if names is None:
        return dict(DEFAULT_EFFECTS)
    known = ("foveation", *DEFAULT_EFFECTS)
    chosen = [n.strip() for n in names.split(",") if n.strip()] if isinstance(names, str) else list(names)
    bad = [n for n in chosen if n not in known]
    if bad or not chosen:
        raise InputValueError(f"--effects must be a comma-separated list of {', '.join(known)}, got {names!r}")
    return {n: True for n in known if n in chosen}


def add_training(p: argparse.ArgumentParser) -> None:
    """The adapter-training options of demo and train (``--optics`` and ``--seed`` are in ``add_common``)."""
    from ..training import DEFAULT_EFFECTS, TrainConfig

    base = TrainConfig()
    p.add_argument("--effects", default=None, help=f"downstream stages the adapter is trained and evaluated through, "
                                                   f"comma-separated (default: all of {','.join(DEFAULT_EFFECTS)})")
    p.add_argument("--iterations", type=int, default=DEMO_ITERATIONS,
                   help=f"adapter training iterations (default {DEMO_ITERATIONS}, a CPU-sized demo; the paper and "
                        f"TrainConfig use {base.iterations})")
    p.add_argument("--psf-fraction", type=float, default=base.psf_fraction,
                   help=f"final fraction of iterations with the full PSF (default {base.psf_fraction:g})")
    p.add_argument("--lr", type=float, default=base.lr, help=f"Adam learning rate (default {base.lr:g})")
    p.add_argument("--cond-dim", type=int, default=base.cond_dim, help=f"N per module (default {base.cond_dim})")
    p.add_argument("--lens-conditioning", choices=("radius", "xy"), default=None,
                   help="the lens condition's frame: radius about the lens axis or the signed (x, y) position in the "
                        "lens's own coordinates (default: radius for a centred, rotationally symmetric lens, else xy)")
    p.add_argument("--gaze-jitter-deg", type=float, default=base.gaze_jitter_deg,
                   help="with the foveation effect: condition the adapter on the gaze offset by up to this many "
                        "degrees from the one the stage uses (eye-tracker lag; default 0)")
    p.add_argument("--checkpoint-every", type=int, default=base.checkpoint_every,
                   help=f"checkpoint every this many iterations (default {base.checkpoint_every}; 0: only at the end)")


def add_distributed_arguments(p: argparse.ArgumentParser, scene_choices: Sequence[str] | None = None) -> None:
    """The ``controlgs train`` options of data-parallel and many-scenes training (torchrun;
    :mod:`controlgs_adapter.distributed`)."""
    from ..distributed import DEFAULT_TIMEOUT_S, EXCHANGES
    from ..training import TrainConfig

    batch = TrainConfig().batch_size
    g = p.add_argument_group("distributed training (launch with torchrun; see docs/how-to/distributed.md)")
    g.add_argument("--batch-size", type=int, default=batch,
                   help=f"views per step, the global batch split over the processes (the same batch size gives the "
                        f"same result on any number of processes; default {batch})")
    g.add_argument("--scenes", nargs="+", choices=scene_choices, metavar="SCENE",
                   help="many-scenes mode: train every SCENE's adapter(s) into OUT/<SCENE>/, the scenes split over "
                        "the processes (each process trains its scenes alone)"
                        + (f"; one of {', '.join(scene_choices)}" if scene_choices else ""))
    g.add_argument("--dist-backend", choices=("gloo", "nccl"), default=None,
                   help="process-group backend (default: nccl with --device cuda, one GPU per process, else gloo)")
    g.add_argument("--dist-timeout", type=float, default=DEFAULT_TIMEOUT_S,
                   help=f"seconds a collective waits for the other processes before the run fails (default {DEFAULT_TIMEOUT_S:g})")
    g.add_argument("--exchange", choices=EXCHANGES, default=EXCHANGES[0],
                   help="how per-anchor condition gradients travel: touched rows only, a dense all-reduce, or the "
                        f"cheaper of the two per step (default {EXCHANGES[0]})")


def train_config(args: argparse.Namespace, name: str, seed: int | None = None) -> TrainConfig:
    """The :class:`~controlgs_adapter.training.TrainConfig` of adapter ``name`` ("controlgs" or an
    ablation of :data:`~controlgs_adapter.ablations.ABLATIONS`) from the parsed options; ``seed``
    overrides ``--seed``. An option a command does not have (``--batch-size`` in demo) keeps the
    TrainConfig default."""
    from ..ablations import ABLATIONS
    from ..training import TrainConfig

    base = TrainConfig()
    modules, blind = ABLATIONS.get(name, (base.modules, base.state_blind))
    return TrainConfig(iterations=args.iterations, lr=args.lr, modules=modules, cond_dim=args.cond_dim,
                       state_blind=blind, psf_fraction=args.psf_fraction, psf_mode=args.optics,
                       checkpoint_every=args.checkpoint_every, seed=args.seed if seed is None else seed,
                       batch_size=getattr(args, "batch_size", base.batch_size),
                       lens_conditioning=getattr(args, "lens_conditioning", None),
                       gaze_jitter_deg=getattr(args, "gaze_jitter_deg", base.gaze_jitter_deg))


def training_job(args: argparse.Namespace, names: Sequence[str], seeds: int = 1) -> Any:
    """The :class:`~controlgs_adapter.training.TrainingJob` of training ``names`` for ``seeds`` seeds:
    its bars say which training of how many runs and the time the whole job has left (seeds x
    adapters trainings of ``--iterations`` each)."""
    from ..training import TrainingJob

    return TrainingJob(max(1, len(names) * seeds), args.iterations)


def train_adapters(views: Any, model: Any, out: Path, args: argparse.Namespace, names: list[str],
                   dist: Any = None, trained: dict[str, int] | None = None, seed: int | None = None,
                   renderer: Any = None, job: Any = None, lens: Any = None) -> dict[str, Path]:
    """Train (or resume from a checkpoint; a finished one is just saved again) the adapters ``names`` ("controlgs" and ablation
    names) on the training ``views`` (a :class:`~controlgs_adapter.training.Views` dataset); returns ``{name: adapter
    file}``. Checkpoints go to ``out/checkpoints``. ``dist``: this process's
    :class:`~controlgs_adapter.distributed.DistContext` in a data-parallel run (rank 0 writes the files). ``trained``, if
    given, receives the iterations each adapter was actually trained for (a resumed run may hold more than asked).
    ``seed``: the training seed (default ``args.seed``). ``renderer``: the :class:`Trainer`'s (None: the model's own).
    ``job``: the :func:`training_job` these trainings belong to (None: one of ``names``); each bar reads
    ``[k/N] training <method>, seed <s>`` with the job's estimated time left. ``lens``: the :class:`Trainer`'s (None:
    the shipped Cardboard lens)."""
    from ..report import METHOD_LABELS
    from ..training import Trainer

    job = training_job(args, names) if job is None else job
    paths = {}
    for name in names:
        config = train_config(args, name, seed)
        target = out / f"{name}.controlgs.safetensors"
        ckpt = out / "checkpoints" / f"{name}.ckpt.safetensors"
        trainer = Trainer(model, views, config, effects=effects_from(getattr(args, "effects", None)), checkpoint=ckpt,
                          dist=dist, renderer=renderer, lens=lens)
        main = trainer.dist.is_main
        if trainer.resume() and main:
            print(f"{name}: resuming at iteration {trainer.iteration}")
        if trainer.iteration > config.iterations and main:
            print(f"{name}: the checkpoint is already at iteration {trainer.iteration} > --iterations "
                  f"{config.iterations}; keeping what was trained")
        try:
            trainer.train(progress=args.progress, desc=f"training {METHOD_LABELS.get(name, name)}, seed {config.seed}",
                          job=job)
            if main:
                trainer.cgs.save(target)
        finally:
            trainer.cgs.unwrap()
        paths[name] = target
        if trained is not None:
            trained[name] = trainer.iteration
    return paths
