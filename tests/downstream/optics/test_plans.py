"""Tests of ``controlgs_adapter.downstream.optics.plans``."""

from __future__ import annotations

import math

from controlgs_adapter.downstream.optics import resampled as R
from controlgs_adapter.downstream.optics.resampled import fast_len, ladder_len


# ------------------------------------------------------------------ ladder_len
def _is_7_smooth(m: int) -> bool:
    for p in (2, 3, 5, 7):
        while m % p == 0:
            m //= p
    return m == 1


def test_ladder_len_rounds_up_to_a_coarse_ladder_of_fast_fft_sizes():
    """``ladder_len`` docstring: ``n`` rounded up to a coarse ladder of fast FFT sizes (factors 2, 3, 5, 7),
    in steps of ~12 %, so nearby lengths share one size. Up to 16384 a ladder growing by 1.12 per step from
    1 has at most log(16384) / log(1.12) + 1 ~ 86.6 rungs; every fast size (there are 400 up to 16384 by
    brute force) would be far more."""
    n_max = 16384
    sizes = {}
    for n in range(1, n_max + 1):
        m = ladder_len(n)
        assert m >= n and _is_7_smooth(m), (n, m)
        sizes.setdefault(m, n)
    assert len(sizes) <= math.log(n_max) / math.log(1.12) + 1
    assert sum(_is_7_smooth(m) for m in range(1, n_max + 1)) == 400  # the brute-force count quoted above
    ladder = sorted(sizes)
    for lo, hi in zip(ladder, ladder[1:]):  # monotone: every n between two rungs takes the upper one
        assert ladder_len(lo + 1) == hi and ladder_len(hi) == hi


# ----------------------------------------------------------------------------- ladder_len: where the ladder starts
def test_ladder_starts_at_8_and_pads_at_most_20_percent_above_it():
    """``ladder_len`` docstring: the ladder starts at 8 (every n <= 8 gives 8); above that n is padded by at
    most 20 % (10 -> 12). By hand: the ladder from 8 by steps of 1.12 is 8, 8.96 -> 9, 10.04 -> 11 -> 12
    (the next 7-smooth size), 11.24 -> 12, 12.59 -> 13 -> 14, 14.10 -> 15, 15.79 -> 16, 17.68 -> 18, ..."""
    assert [ladder_len(n) for n in range(1, 19)] == [8] * 8 + [9, 12, 12, 12, 14, 14, 15, 16, 18, 18]
    for n in range(8, 16385):
        m = ladder_len(n)
        assert n <= m <= 1.2 * n and fast_len(m) == m, (n, m)
    assert ladder_len(10) == 12  # the 20 % case


# ----------------------------------------------------------------------------- resampling helpers
def test_fast_fft_lengths_by_hand():
    # 11 -> 12 = 2^2 3; 13 -> 14 = 2 7; 97 (prime) -> 98 = 2 7^2; 121 = 11^2 -> 125 = 5^3 (122 = 2 61,
    # 123 = 3 41, 124 = 4 31); smooth numbers stay
    assert [R.fast_len(n) for n in (1, 8, 11, 13, 97, 121, 210)] == [1, 8, 12, 14, 98, 125, 210]
    # ladder: 8 * 1.12^i rounded up to 7-smooth sizes: 8, 8.96 -> 9, 10.04 -> 11 -> 12, 11.24 -> 12 (kept once),
    # 12.59 -> 13 -> 14, 14.10 -> 15, 15.79 -> 16, 17.69 -> 18, 19.81 -> 20
    assert [R.ladder_len(n) for n in (1, 8, 9, 10, 12, 13, 15, 16, 17, 19)] == [8, 8, 9, 12, 12, 14, 15, 16, 18, 20]
    assert R.ladder_len(200_001) == R.fast_len(200_001) > 200_001              # beyond the ladder (2^16)
