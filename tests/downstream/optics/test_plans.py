"""Tests of ``controlgs_adapter.downstream.optics.plans``: fast FFT sizes and their coarse ladder, and the
eigen-PSF rank chosen per field group (smallest within the tolerance, capped by ``max_rank``)."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.banks import random_bank

from controlgs_adapter.downstream.optics.operators import psf_exact, psf_fast
from controlgs_adapter.downstream.optics.plans import fast_len, ladder_len

D64 = torch.float64


def _is_7_smooth(m: int) -> bool:
    for p in (2, 3, 5, 7):
        while m % p == 0:
            m //= p
    return m == 1


def test_fast_fft_lengths():
    # 11 -> 12 = 2^2 3; 13 -> 14 = 2 7; 97 (prime) -> 98 = 2 7^2; 121 = 11^2 -> 125 = 5^3 (122 = 2 61,
    # 123 = 3 41, 124 = 4 31); smooth numbers stay
    assert [fast_len(n) for n in (1, 8, 11, 13, 97, 121, 210)] == [1, 8, 12, 14, 98, 125, 210]


def test_ladder_len_rounds_up_to_a_coarse_ladder_of_fast_fft_sizes():
    """``ladder_len`` docstring: ``n`` rounded up to a coarse ladder of fast FFT sizes (factors 2, 3, 5, 7),
    in steps of ~12 %, so nearby lengths share one size; the ladder starts at 8 (every n <= 8 gives 8) and
    pads at most 20 % above it (10 -> 12). From 8 by steps of 1.12: 8, 8.96 -> 9, 10.04 -> 11 -> 12,
    11.24 -> 12 (kept once), 12.59 -> 13 -> 14, 14.10 -> 15, 15.79 -> 16, 17.68 -> 18, 19.81 -> 20. Up to 16384
    a ladder growing by 1.12 per step from 1 has at most log(16384) / log(1.12) + 1 ~ 86.6 rungs, far fewer than
    the 400 fast sizes (brute force); beyond the ladder (2^16) it is the next fast size."""
    assert [ladder_len(n) for n in range(1, 21)] == [8] * 8 + [9, 12, 12, 12, 14, 14, 15, 16, 18, 18, 20, 20]
    assert ladder_len(10) == 12                                                # the 20 % case
    n_max = 16384
    sizes = {}
    for n in range(1, n_max + 1):
        m = ladder_len(n)
        assert m >= n and _is_7_smooth(m) and fast_len(m) == m, (n, m)
        if n >= 8:
            assert m <= 1.2 * n, (n, m)
        sizes.setdefault(m, n)
    assert len(sizes) <= math.log(n_max) / math.log(1.12) + 1
    assert sum(_is_7_smooth(m) for m in range(1, n_max + 1)) == 400
    ladder = sorted(sizes)
    for lo, hi in zip(ladder, ladder[1:]):  # monotone: every n between two rungs takes the upper one
        assert ladder_len(lo + 1) == hi and ladder_len(hi) == hi
    assert ladder_len(200_001) == fast_len(200_001) > 200_001


@pytest.mark.parametrize("radiometry", ["radiance", "energy"])
def test_fast_mode_rank_is_the_smallest_within_the_relative_residual(radiometry):
    """Per field group, the number of eigen-PSFs is the smallest R whose truncated SVD leaves a
    relative Frobenius residual sqrt(sum_{i > R} s_i^2 / sum s_i^2) <= tol (reference: torch's SVD
    of the group's 4 kernels, float64)."""
    rb = random_bank(G=2, K=5, seed=3).resample_to(10, 10, dtype=D64, radiometry=radiometry)
    K, _ = rb.field_kernels(1, torch.arange(4))
    s = torch.linalg.svdvals(K.reshape(4, -1))
    rel = [(s[r:] ** 2).sum().sqrt().item() / (s ** 2).sum().sqrt().item() for r in range(5)]   # residual of rank r
    seen = set()
    for tol in (0.9, 0.5, 0.3, 0.1, 0.03, 0.01, 0.0):
        want = min(r for r in range(1, 5) if rel[r] <= tol or r == 4)
        (bk,) = rb.zones(2, tol)[1]
        assert bk.kernel_fft.shape[0] == want, (tol, rel)
        seen.add(want)
    assert len(seen) >= 3                                                       # the tolerances reach several ranks


def test_max_rank_caps_the_eigen_psfs_per_field_group():
    """``max_rank`` caps the eigen-PSFs per field group; without it, tol 0 keeps the full rank (exact)."""
    rb = random_bank(G=4).resample_to(12, 12, dtype=D64)
    assert {b.kernel_fft.shape[0] for bk in rb.zones(2, 0.0, 1) for b in bk} == {1}
    assert max(b.kernel_fft.shape[0] for bk in rb.zones(2, 0.0) for b in bk) == 4    # 2 x 2 random fields
    x = torch.rand(3, 12, 12, dtype=D64, generator=torch.Generator().manual_seed(7))
    assert (psf_fast(x, rb, 0.0, 2, max_rank=1) - psf_exact(x, rb)).abs().max() > 1e-4
    assert torch.allclose(psf_fast(x, rb, 0.0, 2, max_rank=4), psf_exact(x, rb), atol=1e-12)
