"""``controlgs plugins``: list registered backends, stages, schedules and rasterizers with their source."""

from __future__ import annotations

import argparse
import re
import sys
from typing import TYPE_CHECKING

from controlgs_adapter.errors import PluginLoadError

if TYPE_CHECKING:  # pragma: no cover
    from controlgs_adapter.downstream.stage import Stage
    from controlgs_adapter.plugins import PluginInfo


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("plugins", help="list registered backends, stages, schedules and rasterizers with their source distribution")
    p.add_argument("--strict", action="store_true", help="fail if an installed plug-in does not load")
    p.set_defaults(func=run)


def _what(info: PluginInfo, width: int = 60) -> str:
    """One line on what the item does: a backend's or stage's docstring summary, a schedule's mapping."""
    if info.kind == "schedule":
        text = repr(info.obj).split("(", 1)[-1].rstrip(")")
    else:
        cls = info.obj if isinstance(info.obj, type) else type(info.obj)
        text = " ".join((cls.__doc__ or "").strip().split("\n\n")[0].split()).replace("``", "")
        text = re.sub(r":\w+:`~?([^`]*)`", r"\1", text)  # :class:`X` -> X
        if info.kind == "stage":
            stage: type[Stage] = info.obj
            text = f"[order {stage.order:g}, {stage.domain}] {text}"
    return text if len(text) <= width else text[: width - 3].rstrip() + "..."


def run(args: argparse.Namespace) -> int:
    from controlgs_adapter import plugins

    try:
        plugins.get_plugin_manager(strict=args.strict or None)
        report = plugins.plugin_report()
    except PluginLoadError as e:
        print(f"controlgs plugins: {e}", file=sys.stderr)
        return 1
    head = ("kind", "name", "plugin", "source", "what")
    rows = [(i.kind, i.name, i.plugin, "built-in" if i.source == plugins.BUILTIN_DIST else i.source, _what(i))
            for i in report]
    widths = [max(len(str(r[c])) for r in [head, *rows]) for c in range(len(head))]

    def line(r: tuple[str, ...]) -> str:
        return "  ".join(str(v).ljust(w) for v, w in zip(r, widths)).rstrip()

    print(line(head))
    print(line(tuple("-" * w for w in widths)))
    for k, r in enumerate(rows):
        if k and r[0] != rows[k - 1][0]:
            print()
        print(line(r))
    print("\nbackends and rasterizers are tried in the order listed (plug-ins first); a plug-in item replaces a "
          "built-in of the same name")
    for msg in plugins.load_failures():
        print(f"FAILED: {msg}")
    return 0
