"""``controlgs backbone train``: a backbone from your own capture. Trains the library's reference model
(Scaffold-GS's structure, :mod:`controlgs_adapter.backends.models.train_backbone`) on a dataset's
training views and writes it as a Scaffold-GS output folder, the ``--model`` that ``controlgs train``,
``eval`` and ``view`` take. Anchors come from the dataset's sparse points where it has them (COLMAP
``points3D``), else from a grid around the point the cameras look at (instant-ngp, Blender), which
models no background (docs/how-to/photos-to-report.md)."""

from __future__ import annotations

import argparse
import shlex
from pathlib import Path
from typing import Any

#: reference-model training iterations (as ``controlgs scene build-backbone``)
DEFAULT_ITERATIONS = 1500
#: anchor budget of the reference model (as ``controlgs scene build-backbone``)
DEFAULT_MAX_ANCHORS = 3000
DEFAULT_HOLDOUT = 8


def add_parser(sub: "argparse._SubParsersAction") -> None:
    from ..datasets.detect import FORMATS
    from .common import DEFAULT_DATA_RESOLUTION

    p = sub.add_parser("backbone", help="make a backbone (a Scaffold-GS model folder) from your own dataset")
    bsub = p.add_subparsers(dest="backbone_command", metavar="ACTION", required=True)
    t = bsub.add_parser("train", help="train the reference backbone on a dataset (COLMAP, Blender, instant-ngp) and "
                                      "write it as a Scaffold-GS folder for `controlgs train --model`")
    t.add_argument("--data", required=True, help="the dataset: COLMAP (sparse/0 + images/), Blender "
                                                 "(transforms_{train,test}.json) or instant-ngp (transforms.json); "
                                                 "format detected")
    t.add_argument("--out", required=True, help="model folder to write (new or empty; refused when it holds files)")
    t.add_argument("--resolution", type=int, default=DEFAULT_DATA_RESOLUTION,
                   help=f"working resolution, longer side in pixels; images are downscaled to it, never upscaled "
                        f"(default {DEFAULT_DATA_RESOLUTION}, as `controlgs train`)")
    t.add_argument("--iterations", type=int, default=DEFAULT_ITERATIONS,
                   help=f"training iterations of the backbone, one view each (default {DEFAULT_ITERATIONS})")
    t.add_argument("--max-anchors", type=int, default=DEFAULT_MAX_ANCHORS,
                   help=f"anchor budget: the voxel grows until at most this many anchors remain (default {DEFAULT_MAX_ANCHORS})")
    t.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    t.add_argument("--device", default="cpu", help="torch device the backbone trains on (cpu, cuda, cuda:1)")
    t.add_argument("--format", choices=FORMATS, default=None, help="dataset format (default: detected)")
    t.add_argument("--images", default=None, help="COLMAP image folder, e.g. images_4 (default: images/ or the "
                                                 "downscaled folder that fits --resolution)")
    t.add_argument("--holdout", type=int, default=DEFAULT_HOLDOUT,
                   help=f"every N-th view is a test view, scored at the end (COLMAP, instant-ngp; default {DEFAULT_HOLDOUT}, "
                        "as `controlgs train`; 0: none)")
    t.add_argument("--white-background", action="store_true",
                   help="composite RGBA images over white and train the backbone on a white background")
    t.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    t.set_defaults(func=run_train)


def _check(args: argparse.Namespace) -> Path:
    """Every option and ``--out`` (new or empty) checked before anything is read or written."""
    from ..checks import check_number
    from ..errors import InputValueError
    from .common import check_out_path, parse_device

    check_number("--resolution", args.resolution, integer=True, low=2, high=2**63 - 1)
    check_number("--iterations", args.iterations, integer=True, low=1, high=2**63 - 1)
    check_number("--max-anchors", args.max_anchors, integer=True, low=1, high=2**63 - 1)
    check_number("--seed", args.seed, integer=True, low=0, high=2**63 - 1)
    check_number("--holdout", args.holdout, integer=True, low=0, high=2**63 - 1)
    parse_device(args.device)
    out = check_out_path(args.out, "--out", folder=True)
    if out.is_dir():
        held = sorted(p.name for p in out.iterdir())
        if held:
            raise InputValueError(f"--out {out}: the folder is not empty (it holds {', '.join(held[:3])}"
                                  f"{', ...' if len(held) > 3 else ''}); a backbone is written into a new or empty folder: "
                                  "choose another --out")
    data = Path(args.data)
    if out.resolve() == data.resolve() or data.resolve() in out.resolve().parents:
        raise InputValueError(f"--out {out}: inside the dataset --data {data}; write the backbone elsewhere")
    return out


def _next_command(args: argparse.Namespace, out: Path) -> str:
    """The ``controlgs train`` command that trains the adapter on this backbone and dataset (read the same way)."""
    from .common import DEFAULT_DATA_RESOLUTION

    words = ["controlgs", "train", "--model", str(out), "--data", str(args.data)]
    for option, value, default in (("--format", args.format, None), ("--images", args.images, None),
                                   ("--holdout", args.holdout, DEFAULT_HOLDOUT),
                                   ("--resolution", args.resolution, DEFAULT_DATA_RESOLUTION)):
        if value != default:
            words += [option, str(value)]
    if args.white_background:
        words.append("--white-background")
    return " ".join(shlex.quote(w) for w in words + ["--out", "RUN"])


def run_train(args: argparse.Namespace) -> int:
    from ..backends.models.train_backbone import build_backbone
    from ..datasets.detect import load_dataset
    from .common import parse_device

    out = _check(args)
    device = parse_device(args.device)
    data = load_dataset(args.data, format=args.format, images=args.images, resolution=args.resolution,
                        holdout=args.holdout, white_background=bool(args.white_background))
    views = data.views("train", resolution=args.resolution)
    test = data.views("test", resolution=args.resolution) if data.splits.get("test") else None
    points = data.points if data.points is not None and data.points.shape[0] > 0 else None
    print(f"data: {data.format} {args.data}: {views.describe()['views']} training views at "
          f"{', '.join(views.describe()['sizes'])}, {len(test) if test is not None else 0} test views")
    if points is not None:
        print(f"anchors: from the {points.shape[0]} sparse points of the dataset (at most {args.max_anchors})")
    else:
        print(f"anchors: the {data.format} dataset has no sparse points; {args.max_anchors} on a grid around the point "
              "the cameras look at (what lies outside that box, the background, is not modelled)")
    record: dict[str, Any] = {"data": str(Path(args.data).resolve()), "format": data.format, "images": args.images,
                              "holdout": args.holdout, "white_background": bool(args.white_background),
                              "resolution": args.resolution, "device": str(device)}
    built = build_backbone(views, out, test_views=test, points=points, iterations=args.iterations,
                           max_anchors=args.max_anchors, seed=args.seed, device=device, progress=args.progress,
                           record=record)
    info = built.info
    print(f"backbone: {info['anchors']} anchors ({info['anchors_from']}), {info['iterations']} iterations in "
          f"{info['train_seconds']:.0f} s")
    if "test_psnr_mean" in info:
        print(f"backbone test views: PSNR {info['test_psnr_mean']:.2f} dB, SSIM {info['test_ssim_mean']:.4f} "
              f"(mean over {info['test_views']} test views, before any XR processing)")
    else:
        print("backbone test views: none (--holdout 0 or no test split): not scored")
    print(f"written to {built.path} (Scaffold-GS format; build.json records the settings and scores)")
    print(f"next: {_next_command(args, out)}")
    return 0
