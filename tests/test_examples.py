"""The README's quick start runs as written (examples/quickstart.py): finite losses through the
whole XR pipeline, and the saved adapter reloads onto the unwrapped backbone."""

import runpy
from pathlib import Path

import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_quickstart_runs_and_round_trips(capsys):
    runpy.run_path(str(EXAMPLES / "quickstart.py"), run_name="__main__")
    out = capsys.readouterr().out
    losses = [float(line.split()[-1]) for line in out.splitlines() if line.startswith("step ")]
    assert len(losses) == 5 and all(torch.isfinite(torch.tensor(losses)))
    assert "saved and reloaded" in out and "anchors=2148" in out
