"""Sweep seed 11230003 (sample of 600 at 127eaac): survivors the lead triaged."""

from __future__ import annotations

import warnings

import torch

from controlgs_adapter.scene.planes import TexturedPlane, plane_points, render_planes
from controlgs_adapter.state import Camera


def test_plane_points_and_render_warn_nothing():
    """The built-in scene's plane sampler and renderer run silently: no deprecation or user warning from
    torch (e.g. ``meshgrid`` without ``indexing=``) reaches a user's console. The grid is by hand: a 2 x 1
    plane sampled every 0.5 gives 4 x 2 points at the cell centres, row by row (down) then across (right)."""
    tex = torch.rand(3, 4, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    plane = TexturedPlane("p", torch.tensor([0.0, 0.0, 2.0]), torch.tensor([1.0, 0.0, 0.0]),
                          torch.tensor([0.0, 0.5, 0.0]), tex)
    cam = Camera(torch.eye(4, dtype=torch.float64),
                 torch.tensor([[6.0, 0.0, 3.0], [0.0, 6.0, 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64), 6, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        xyz, rgb = plane_points(plane, 0.5)
        image, coverage, _ = render_planes([plane], cam, samples=2)
    a = torch.tensor([-0.75, -0.25, 0.25, 0.75], dtype=torch.float64)
    b = torch.tensor([-0.5, 0.5], dtype=torch.float64)
    want = torch.stack([torch.stack([x, 0.5 * y, torch.tensor(2.0, dtype=torch.float64)]) for y in b for x in a])
    torch.testing.assert_close(xyz, want, rtol=0, atol=1e-15)
    assert rgb.shape == (8, 3)
    # the plane spans x in [-1, 1], y in [-0.5, 0.5] at z = 2: u = 6 x / 2 + 3 in [0, 6], v = 6 y / 2 + 2 in [0.5, 3.5]
    assert torch.equal(coverage[0, 1:3], torch.ones(2, 6, dtype=torch.float64))
    assert torch.equal(coverage[0, [0, 3]], torch.full((2, 6), 0.5, dtype=torch.float64))


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
