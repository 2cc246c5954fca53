"""The ``controlgs`` command. Each sub-command lives in ``controlgs_adapter/commands/<name>.py``
with ``add_parser(subparsers)`` (which sets ``func``) and is listed in :data:`COMMANDS`."""

from __future__ import annotations

import argparse
import importlib
import sys

from ._version import __version__

COMMANDS: tuple[str, ...] = ("plugins", "optics", "scene", "train", "eval", "demo", "bench")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="controlgs",
        description="ControlGS adapters for neural-Gaussian renderers in XR: train, evaluate, benchmark, inspect.",
    )
    parser.add_argument("--version", action="version", version=f"controlgs-adapter {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"controlgs_adapter.commands.{name}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from .errors import ControlGSError

    try:
        return int(args.func(args) or 0)
    except ControlGSError as e:  # bad input: a clear message, not a traceback
        print(f"controlgs {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
