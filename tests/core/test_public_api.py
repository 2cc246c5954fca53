"""Tests of ``controlgs_adapter.public_api``."""

from __future__ import annotations

import subprocess
import sys


def test_training_loads_on_first_use() -> None:
    code = ("import sys, controlgs_adapter as c; assert 'controlgs_adapter.training' not in sys.modules; "
            "c.TrainConfig; assert 'controlgs_adapter.training' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
