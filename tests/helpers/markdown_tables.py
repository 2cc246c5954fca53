"""Reading the Markdown tables of the benchmark pages."""

from __future__ import annotations

import math
import re


def table_rows(text: str, header_start: str) -> list[list[str]]:
    """Cells of the Markdown table whose header line starts with ``header_start``."""
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def positive(cell: str) -> float:
    """The number in ``cell`` (units stripped), asserted finite and > 0."""
    value = float(re.sub(r"[^0-9.eE+-]", "", cell))
    assert math.isfinite(value) and value > 0, cell
    return value
