"""Seeded initialisation that leaves every caller's random generator as it was."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def seeded(seed: int, device: torch.device | str = "cpu") -> Iterator[None]:
    """Run the block with the generators that draw on ``device`` seeded with ``seed``: the CPU's, plus
    that CUDA device's when ``device`` is one. Those generators are restored on exit and no other one
    is touched (``torch.manual_seed`` would also reseed, and not restore, every CUDA generator)."""
    dev = torch.device(device)
    cuda = dev.type == "cuda"
    index = (dev.index if dev.index is not None else torch.cuda.current_device()) if cuda else None
    with torch.random.fork_rng(devices=[] if index is None else [index]):
        torch.random.default_generator.manual_seed(int(seed))
        if index is not None:
            with torch.cuda.device(index):
                torch.cuda.manual_seed(int(seed))
        yield
