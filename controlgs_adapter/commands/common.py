"""What ``controlgs train`` and ``controlgs eval`` share for a user's own scene: the options naming a
trained model folder and its dataset, loading both, the up-front scene check and ``RUN/run.json``
(what a run was trained on, so that ``eval`` needs only ``--run``)."""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import InputValueError

#: default working resolution of a user's dataset (longer side in pixels; never upscaled)
DEFAULT_DATA_RESOLUTION = 256
#: default budget of the decoded-image cache (MiB)
DEFAULT_CACHE_MIB = 1024
RUN_FILE = "run.json"
#: run.json keys that ``eval`` takes as defaults for its options
_RUN_DEFAULTS = ("model", "data", "family", "model_iteration", "format", "images", "holdout", "white_background",
                 "resolution", "allow_unquantized", "effects")


def add_data_arguments(p: argparse.ArgumentParser) -> None:
    """Options naming a user's model folder and dataset (``--model``/``--data`` and how to read them)."""
    from ..backends.model_dir import FAMILIES
    from ..datasets.detect import FORMATS

    g = p.add_argument_group("your own scene (without --model/--data: the built-in scene, --variant)")
    g.add_argument("--model", help="trained output folder of Scaffold-GS, Octree-GS, HAC++/HAC, ContextGS or CompGS "
                                   "(family detected from its files)")
    g.add_argument("--data", help="its dataset: COLMAP (sparse/0 + images/), Blender (transforms_{train,test}.json) or "
                                  "instant-ngp (transforms.json); format detected")
    g.add_argument("--family", choices=tuple(FAMILIES), default=None, help="the model folder's family (default: detected)")
    g.add_argument("--model-iteration", type=int, default=None, help="point_cloud/iteration_<N> to load (default: the last)")
    g.add_argument("--allow-unquantized", action="store_true", default=None,
                   help="HAC++/HAC/ContextGS raw checkpoints, CompGS: use the stored unquantised values (docs/backends.md)")
    g.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected)")
    g.add_argument("--images", default=None, help="COLMAP image folder, e.g. images_4 (default: images/ or the "
                                                 "downscaled folder that fits --resolution)")
    g.add_argument("--holdout", type=int, default=None, help="every N-th view is a test view (COLMAP, instant-ngp; default 8)")
    g.add_argument("--white-background", action="store_true", default=None,
                   help="composite RGBA images over white (the model was trained with --white_background)")
    g.add_argument("--cache-mib", type=int, default=DEFAULT_CACHE_MIB,
                   help="memory budget of the decoded-image cache (MiB; images are read lazily, never all at once)")
    g.add_argument("--device", default="cpu", help="torch device of the model and the whole pipeline (cpu, cuda, cuda:1)")


def user_scene(args: argparse.Namespace) -> bool:
    """True when the command runs on a user's model + dataset (``--model``/``--data``), False for the
    built-in scene; half of the pair is an error."""
    if (args.model is None) != (args.data is None):
        raise InputValueError("give both --model MODEL_DIR and --data DATA_DIR (or neither, for the built-in scene)")
    return args.model is not None


def apply_run_defaults(args: argparse.Namespace, run_dir: Path) -> dict[str, Any] | None:
    """Fill the options left unset from ``run_dir/run.json`` (written by ``controlgs train``); returns it."""
    path = run_dir / RUN_FILE
    if not path.is_file():
        return None
    try:
        run = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputValueError(f"{path}: not a controlgs run file ({e})") from None
    for key in _RUN_DEFAULTS:
        if getattr(args, key, None) is None and run.get(key) is not None:
            setattr(args, key, run[key])
    return run


@dataclass
class UserScene:
    """A user's model and dataset, loaded. ``model`` on ``device``; ``resolution`` = longer side (pixels)."""

    model: Any
    family: str
    data: Any
    resolution: int
    device: Any

    def record(self, args: argparse.Namespace, **extra: Any) -> dict[str, Any]:
        """JSON-able description of the run (``run.json``; the report's info)."""
        return {"model": str(Path(args.model).resolve()), "data": str(Path(args.data).resolve()), "family": self.family,
                "model_iteration": args.model_iteration, "allow_unquantized": bool(args.allow_unquantized),
                "format": self.data.format, "images": args.images, "holdout": args.holdout,
                "white_background": bool(args.white_background), "resolution": self.resolution, **extra}


def parse_device(name: str) -> Any:
    """``--device`` as a ``torch.device``, refused (one line) when unknown or when CUDA is missing."""
    import torch

    try:
        device = torch.device(name)
    except RuntimeError as e:
        raise InputValueError(f"--device {name!r}: {e}") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise InputValueError(f"--device {name}: CUDA is not available on this machine")
    return device


def load_user_scene(args: argparse.Namespace) -> UserScene:
    """Load ``--model`` (family detected unless ``--family``) onto ``--device`` and read ``--data``."""

    from ..backends.model_dir import detect_family, load_model_dir
    from ..datasets.detect import load_dataset

    device = parse_device(args.device)
    if args.resolution is None:
        args.resolution = DEFAULT_DATA_RESOLUTION
    if args.holdout is None:
        args.holdout = 8
    family = args.family or detect_family(args.model, iteration=args.model_iteration)
    model = load_model_dir(args.model, family=family, iteration=args.model_iteration,
                           allow_unquantized=bool(args.allow_unquantized)).to(device)
    data = load_dataset(args.data, format=args.format, images=args.images, resolution=args.resolution,
                        holdout=args.holdout, white_background=bool(args.white_background))
    return UserScene(model, family, data, int(args.resolution), device)


def anchor_positions(model: Any) -> Any:
    """``[A, 3]`` anchor positions of ``model`` as the backend that recognises it reads them (CPU)."""
    from .. import plugins

    for info in plugins.backends().values():
        if info.obj.matches(model):
            return info.obj.anchor_positions(model).detach().float().cpu()
    return None


def check_line(report: dict[str, Any]) -> str:
    """One line summing up :func:`~controlgs_adapter.datasets.check_scene`'s report."""
    splits = ", ".join(f"{n} {s}" for s, n in report["splits"].items())
    line = f"scene check: {report['format'] or 'dataset'} {report['source']}: {splits} views, image sizes match their cameras"
    seen = report["in_front"]
    if seen:
        ok = len(seen) - len(report["blind"])
        line += (f"; the model's {report['points']} anchors are in view of {ok}/{len(seen)} cameras "
                 f"(median {sorted(seen.values())[len(seen) // 2]:.0%} inside the image)")
    return line


def cache_bytes(args: argparse.Namespace) -> int:
    """``--cache-mib`` in bytes (checked: an int >= 0)."""
    mib = getattr(args, "cache_mib", DEFAULT_CACHE_MIB)
    if not isinstance(mib, int) or mib < 0:
        raise InputValueError(f"--cache-mib must be an int >= 0 (MiB), got {mib!r}")
    return mib << 20
