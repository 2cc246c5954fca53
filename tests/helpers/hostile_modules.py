"""TorchScript modules that do harm when ``torch.jit.load`` or their forward runs (they write a file of the
test's choosing), for the tests that check such archives are refused and never run."""

from __future__ import annotations

import torch
from torch import nn


class Writer(nn.Module):
    """``forward`` overwrites ``target`` (``torch.from_file(path, True, n)``) and returns a Linear's output."""

    def __init__(self, target: str) -> None:
        super().__init__()
        self.lin = nn.Linear(4, 4)
        self.target = target

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        t = torch.from_file(self.target, True, 8, dtype=torch.uint8)
        t.fill_(65)
        return self.lin(x) + t[:1].float() * 0


class SetState(nn.Module):
    """A scripted ``__setstate__`` (run by ``torch.jit.load`` itself) that writes ``target``."""

    def __init__(self, target: str) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(4, 4))
        self.target = target

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x @ self.weight

    @torch.jit.export
    def __getstate__(self) -> tuple[str, torch.Tensor, bool]:
        return (self.target, self.weight, self.training)

    @torch.jit.export
    def __setstate__(self, state: tuple[str, torch.Tensor, bool]) -> None:
        self.target = state[0]
        t = torch.from_file(self.target, True, 8, dtype=torch.uint8)
        self.weight = state[1] + t[:1].float().fill_(0)
        self.training = state[2]


class Loop(nn.Module):
    """A forward that never returns."""

    def __init__(self) -> None:
        super().__init__()
        self.lin = nn.Linear(4, 4)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        while True:
            x = x + 1
        return self.lin(x)
