"""scripts/mutation_sweep.py's own parsing: coverage.py's numbits decoded (coverage is not a test
dependency: the encoding is written here from its documented layout), and the usage errors of --shard
and --lines."""

import argparse
import importlib.util
import sys
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

_spec = importlib.util.spec_from_file_location("mutation_sweep", Path(__file__).parents[1] / "scripts" / "mutation_sweep.py")
assert _spec is not None and _spec.loader is not None
sweep = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = sweep  # its dataclass looks the module up there
_spec.loader.exec_module(sweep)


def _encode(lines: set[int]) -> bytes:
    """coverage.py's numbits: bit ``k`` of byte ``j`` set when line ``8 j + k`` ran."""
    out = bytearray((max(lines) // 8 + 1) if lines else 0)
    for n in lines:
        out[n // 8] |= 1 << (n % 8)
    return bytes(out)


@given(st.sets(st.integers(1, 5000), max_size=300))
def test_numbits_decode(lines):
    assert sweep._numbits_to_lines(_encode(lines)) == sorted(lines)


def test_numbits_by_hand():
    assert sweep._numbits_to_lines(bytes([0b00000110, 0, 0b10000000])) == [1, 2, 23]


def test_shard_and_line_range_parse_and_refuse():
    assert sweep._shard("0/1") == (0, 1) and sweep._shard("14/15") == (14, 15)
    for bad in ("1/1", "3/2", "a/2", "2", "-1/2"):
        with pytest.raises(argparse.ArgumentTypeError, match=f"expected I/N with 0 <= I < N, got '{bad}'"):
            sweep._shard(bad)
    assert sweep._line_range("5-9") == (5, 9)
    with pytest.raises(argparse.ArgumentTypeError, match="expected A-B with A <= B, got '9-5'"):
        sweep._line_range("9-5")
