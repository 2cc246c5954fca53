"""The scripts in ``examples/`` run end to end: the quick start, and training with one's own renderer."""

from __future__ import annotations

import runpy
from pathlib import Path

import torch

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_quickstart_runs_and_round_trips(capsys):
    runpy.run_path(str(EXAMPLES / "quickstart.py"), run_name="__main__")
    out = capsys.readouterr().out
    losses = [float(line.split()[-1]) for line in out.splitlines() if line.startswith("step ")]
    assert len(losses) == 5 and all(torch.isfinite(torch.tensor(losses)))
    assert "saved and reloaded" in out and "anchors=2148" in out


def test_own_renderer_trains_resumes_and_catches_a_missed_injection(capsys):
    """examples/own_renderer.py: a plain-Python model with TorchScript decoders and its own render
    function trains through the render protocol (checkpoint + resume), renders exactly as the
    library's reference model, and rendering another object than the wrapped one is an error."""
    runpy.run_path(str(EXAMPLES / "own_renderer.py"), run_name="__main__")
    out = capsys.readouterr().out
    lines = {line.split(":")[0]: line for line in out.splitlines()}
    assert float(lines["own render vs the library's reference model"].split()[-1]) <= 1e-6
    assert "Sequential decoders on the user's object" in out  # the TorchScript ones were rebuilt ON it
    losses = [float(line.split()[-1]) for line in out.splitlines() if line.startswith("step ")]
    assert len(losses) == 4 and all(torch.isfinite(torch.tensor(losses)))
    assert float(lines["adapter changes the own render"].split()[-1]) > 0
    assert "injection missed: caught" in out
