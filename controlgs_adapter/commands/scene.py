"""``controlgs scene``: the built-in scene (bake its backbone, write its ground-truth views)."""

from __future__ import annotations

import argparse


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("scene", help="the built-in diorama scene: bake its backbone, export its views")
    ssub = p.add_subparsers(dest="scene_command", metavar="ACTION", required=True)
    b = ssub.add_parser("build-backbone", help="train the reference model on the built-in scene and bake it "
                                               "(Scaffold-GS format) into --out (the shipped one: "
                                               "controlgs_adapter/data/builtin_scene/VARIANT of a checkout)")
    b.add_argument("--variant", choices=("ar", "vr"), default="ar", help="object-centric AR or immersive VR (default ar)")
    b.add_argument("--resolution", type=int, default=128, help="native resolution S of the training views")
    b.add_argument("--iterations", type=int, default=1500, help="training iterations of the reference model (default 1500)")
    b.add_argument("--max-anchors", type=int, default=3000, help="anchor budget of the baked model (default 3000)")
    b.add_argument("--n-offsets", type=int, default=5, help="K Gaussians per anchor")
    b.add_argument("--out", required=True, help="folder to write (never the installed package by default)")
    b.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    b.set_defaults(func=run_build)
    e = ssub.add_parser("export", help="write the ground-truth views as PNG files")
    e.add_argument("--variant", choices=("ar", "vr"), default="ar", help="object-centric AR or immersive VR (default ar)")
    e.add_argument("--resolution", type=int, default=128, help="native resolution S of the views (default 128)")
    e.add_argument("--out", required=True, help="folder to write train/NNN.png and test/NNN.png into")
    e.set_defaults(func=run_export)


def run_build(args: argparse.Namespace) -> int:
    from controlgs_adapter.checks import check_number
    from controlgs_adapter.scene import build_builtin_backbone

    from .common import check_out_path

    for option, value in (("--resolution", args.resolution), ("--iterations", args.iterations),
                          ("--max-anchors", args.max_anchors), ("--n-offsets", args.n_offsets)):
        check_number(option, value, integer=True, low=1, high=2**63 - 1)
    check_number("--seed", args.seed, integer=True, low=0, high=2**63 - 1)
    check_out_path(args.out, "--out", folder=True)  # before the training
    path = build_builtin_backbone(args.variant, resolution=args.resolution, iterations=args.iterations,
                                  max_anchors=args.max_anchors, n_offsets=args.n_offsets, out=args.out, seed=args.seed)
    print(f"backbone written to {path} (see build.json there)")
    return 0


def run_export(args: argparse.Namespace) -> int:
    import matplotlib.image

    from controlgs_adapter.checks import check_number
    from controlgs_adapter.formats.safetensors import atomic_write
    from controlgs_adapter.scene import load_builtin_scene

    from .common import check_out_path

    check_number("--resolution", args.resolution, integer=True, low=1, high=2**63 - 1)
    out = check_out_path(args.out, "--out", folder=True)
    for split in ("train", "test"):
        check_out_path(out / split, "--out", folder=True)
    scene = load_builtin_scene(args.variant, args.resolution, cache=True)
    for split, images in (("train", scene.train_images), ("test", scene.test_images)):
        for i, img in enumerate(images):
            arr = img.permute(1, 2, 0).numpy()
            atomic_write(out / split / f"{i:03d}.png", lambda tmp: matplotlib.image.imsave(tmp, arr, format="png"))
    print(f"{len(scene.train_images)} train and {len(scene.test_images)} test views written to {out}")
    return 0
