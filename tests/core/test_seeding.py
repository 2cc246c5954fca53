"""Seeded blocks: inside ``seeded(s)`` the global generator draws what a fresh one seeded with ``s``
draws, and the caller's generator goes on afterwards exactly where it was."""

from __future__ import annotations

import torch

from controlgs_adapter.seeding import seeded


def test_seeded_draws_follow_the_seed_and_leave_the_callers_generator_alone():
    """Inside ``seeded(s)`` the global CPU generator draws what a fresh generator seeded with ``s`` draws;
    after it, the caller's generator goes on exactly where it was."""
    torch.manual_seed(123)
    torch.rand(3)
    expected_next = torch.rand(5)
    torch.manual_seed(123)
    torch.rand(3)
    with seeded(7):
        inside = torch.rand(4)
    assert torch.equal(inside, torch.rand(4, generator=torch.Generator().manual_seed(7)))
    assert torch.equal(torch.rand(5), expected_next)
