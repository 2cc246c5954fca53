"""Tests of ``controlgs_adapter.benchmarks.scripts``."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "benchmarks").glob("*.py")))
def test_benchmark_scripts_default_to_printing(script: str) -> None:
    text = (ROOT / "benchmarks" / script).read_text()
    defaults = re.findall(r"add_argument\([^)]*default=([^,)]*)", text)
    assert not [d for d in defaults if "docs" in d], f"{script}: a default path into docs/"
