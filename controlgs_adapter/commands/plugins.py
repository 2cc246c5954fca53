"""``controlgs plugins``: list registered backends, stages and schedules with their source."""

from __future__ import annotations

import argparse


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("plugins", help="list registered backends, stages and schedules with their source distribution")
    p.add_argument("--strict", action="store_true", help="fail if an installed plug-in does not load")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from controlgs_adapter import plugins

    plugins.get_plugin_manager(strict=args.strict or None)
    rows = [(i.kind, i.name, i.plugin, i.source) for i in plugins.plugin_report()]
    head = ("kind", "name", "plugin", "source")
    widths = [max(len(str(r[c])) for r in [head, *rows]) for c in range(4)]
    for r in [head, tuple("-" * w for w in widths), *rows]:
        print("  ".join(str(v).ljust(w) for v, w in zip(r, widths)).rstrip())
    for msg in plugins.load_failures():
        print(f"FAILED: {msg}")
    return 0
