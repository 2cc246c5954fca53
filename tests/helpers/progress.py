"""Progress bars recorded instead of drawn: what a library module asks of ``tqdm`` (title, total, updates,
postfix), for tests of the progress reported without depending on how tqdm renders it."""

from __future__ import annotations

from types import ModuleType
from typing import Any

import pytest


class RecordedBar:
    """Stands in for a ``tqdm`` bar: keeps its title (``desc``), ``total``, count ``n``, ``disable`` and
    every postfix set."""

    def __init__(self, iterable: Any = None, *, desc: str | None = None, total: int | None = None, initial: int = 0,
                 disable: bool = False, **_: Any) -> None:
        self.desc, self.total, self.n, self.disable = desc, total, initial, disable
        self.postfixes: list[dict[str, Any]] = []
        self.closed = False

    def update(self, n: int = 1) -> None:
        self.n += n

    def set_postfix(self, ordered_dict: dict[str, Any] | None = None, refresh: bool = True, **kwargs: Any) -> None:
        self.postfixes.append({**(ordered_dict or {}), **kwargs})

    def close(self) -> None:
        self.closed = True


def record_bars(monkeypatch: pytest.MonkeyPatch, module: ModuleType) -> list[RecordedBar]:
    """Replace ``module.tqdm`` by :class:`RecordedBar`; returns the list every bar made is appended to."""
    bars: list[RecordedBar] = []

    def make(*args: Any, **kwargs: Any) -> RecordedBar:
        bars.append(RecordedBar(*args, **kwargs))
        return bars[-1]

    monkeypatch.setattr(module, "tqdm", make)
    return bars
