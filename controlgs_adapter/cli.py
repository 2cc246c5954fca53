"""The ``controlgs`` command. Each sub-command lives in ``controlgs_adapter/commands/<name>.py``
with ``add_parser(subparsers)`` (which sets ``func``) and is listed in :data:`COMMANDS`."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import sys
import warnings
from typing import Any, Iterator

from ._version import __version__

COMMANDS: tuple[str, ...] = ("plugins", "optics", "scene", "backbone", "train", "eval", "demo", "bench", "view")

#: (command, action) -> (extra, import names, what for): optional dependencies checked before the work starts
REQUIRES: dict[tuple[str, str | None], tuple[str, tuple[str, ...], str]] = {
    ("demo", None): ("demo", ("skimage", "matplotlib"), "the built-in scene and the report's plots"),
    ("eval", None): ("demo", ("matplotlib",), "the report's plots"),
    ("optics", "bench"): ("demo", ("skimage", "matplotlib"), "the optics benchmark's test image and plot"),
    ("scene", "export"): ("demo", ("skimage", "matplotlib"), "exporting the built-in scene's views as PNG"),
}


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


@contextlib.contextmanager
def warnings_as_lines(command: str) -> Iterator[None]:
    """Inside the block every warning Python prints is one line ``controlgs <command>: warning:
    <message>`` on stderr (no file, line or source line: they would point into the library, not at the
    user's input), written around any progress bar. It replaces ``warnings.formatwarning`` (put back
    after), so a caller recording warnings (``warnings.catch_warnings(record=True)``) still gets them."""

    def line(message: Any, category: Any, filename: str, lineno: int, line: Any = None) -> str:
        from tqdm import tqdm

        tqdm.write(f"controlgs {command}: warning: {' '.join(str(message).split())}", file=sys.stderr)
        return ""  # written above, clear of the progress bars

    before = warnings.formatwarning
    warnings.formatwarning = line
    try:
        yield
    finally:
        warnings.formatwarning = before


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # the command line as given, for reports that name it
    if not getattr(args, "func", None):
        parser.print_help()
        return 0
    from .errors import ControlGSError
    from .extras import require

    try:
        action = next((v for k, v in vars(args).items() if k.endswith("_command") and isinstance(v, str)), None)
        with warnings_as_lines(args.command):
            need = REQUIRES.get((args.command, action))
            if need is not None:
                require(need[0], f"controlgs {args.command}" + (f" {action}" if action else "") + f" ({need[2]})", need[1])
            return int(args.func(args) or 0)
    except (ControlGSError, OSError) as e:  # bad input, unwritable or full disk: one clear line, not a traceback
        message = " ".join(str(e).split()) if isinstance(e, ControlGSError) else f"{type(e).__name__}: {e}"
        print(f"controlgs {args.command}: error: {message}", file=sys.stderr)
        return 2
    except ImportError as e:  # an optional dependency the table above does not know about
        hint = (f"needs the Python package {e.name!r}, which is not installed" if isinstance(e, ModuleNotFoundError)
                else " ".join(str(e).split()))
        print(f"controlgs {args.command}: error: {hint} (pip install 'controlgs-adapter[demo]' installs the optional ones)",
              file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
