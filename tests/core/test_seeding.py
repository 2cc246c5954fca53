"""Tests of ``controlgs_adapter.seeding``."""

from __future__ import annotations

import torch


def test_seeded_draws_follow_the_seed_and_leave_the_callers_generator_alone():
    """Inside ``seeded(s)`` the global CPU generator draws what a fresh generator seeded with ``s`` draws;
    after it, the caller's generator goes on exactly where it was."""
    from controlgs_adapter.seeding import seeded

    torch.manual_seed(123)
    before = torch.rand(3)
    expected_next = torch.rand(5)
    torch.manual_seed(123)
    torch.rand(3)
    with seeded(7):
        inside = torch.rand(4)
    assert torch.equal(inside, torch.rand(4, generator=torch.Generator().manual_seed(7)))
    assert torch.equal(torch.rand(5), expected_next) and before.shape == (3,)
