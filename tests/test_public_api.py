"""The public names at the top level (lazily loaded ones included)."""

from __future__ import annotations

import subprocess
import sys

import controlgs_adapter


def test_every_public_name_resolves() -> None:
    for name in controlgs_adapter.__all__:
        assert getattr(controlgs_adapter, name) is not None, name
    from controlgs_adapter.evaluation import GridResult
    from controlgs_adapter.training import Trainer

    assert controlgs_adapter.Trainer is Trainer and controlgs_adapter.GridResult is GridResult
    assert issubclass(controlgs_adapter.StateRangeError, controlgs_adapter.StateError)


def test_training_loads_on_first_use() -> None:
    code = ("import sys, controlgs_adapter as c; assert 'controlgs_adapter.training' not in sys.modules; "
            "c.TrainConfig; assert 'controlgs_adapter.training' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
