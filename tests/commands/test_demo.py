"""Tests of ``controlgs_adapter.commands.demo``: its defaults, a tiny demo's report and seeds, and what it refuses in
one line before taking the report folder's lock (a refused demo creates no folder)."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest
import torch
from helpers.cli_runs import error_line, needs_backbone, timings_within
from safetensors.torch import load_file

from controlgs_adapter import cli
from controlgs_adapter.cli import main
from controlgs_adapter.commands.demo import seed_runs
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import GridResult

GRID = ((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8))


# ----------------------------------------------------------------------------- options

def test_demo_defaults() -> None:
    d = cli.build_parser().parse_args(["demo"])
    assert (d.out, d.ablations, d.iterations, d.resolution, d.variant) == ("report", True, 1000, None, "ar")


@pytest.mark.parametrize("option, value", [("--iterations", "-1"), ("--seed", "-1"), ("--lr", "nan"),
                                           ("--test-views", "0"), ("--seeds", "0"), ("--effects", "blur"),
                                           ("--resolution", "0"), ("--gazes", "0;0")])
def test_a_refused_demo_creates_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
                                        value: str) -> None:
    out = tmp_path / "report"
    assert main(["demo", "--out", str(out), "--no-progress", option, value]) == 2
    line = error_line(capsys, "demo")
    assert line.startswith(f"{option} ") and value in line, line
    assert not out.exists()


def test_an_out_that_is_a_file_or_cannot_be_written_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["demo", "--out", str(taken), "--no-progress"]) == 2
    assert error_line(capsys, "demo") == f"--out {taken}: is a file; expected a folder to write into"
    assert taken.read_text() == "mine"
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        assert main(["demo", "--out", str(ro / "report")]) == 2
        assert str(ro) in error_line(capsys, "demo")


def test_seed_runs(tmp_path: Path) -> None:
    """One seed: the report folder itself; several: ``seed-<s>/`` from ``--seed``; ``--seeds`` must be >= 1."""
    assert seed_runs(tmp_path, 3, None) == [(3, tmp_path)]
    assert seed_runs(tmp_path, 3, 2) == [(3, tmp_path / "seed-3"), (4, tmp_path / "seed-4")]
    with pytest.raises(InputValueError, match="--seeds.*got 0"):
        seed_runs(tmp_path, 0, 0)


# ----------------------------------------------------------------------------- a tiny demo

@needs_backbone
def test_tiny_demo_writes_the_report(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "report"
    rc = main(["demo", "--out", str(out), "--resolution", "16", "--iterations", "2", "--psf-fraction", "0.5",
               "--test-views", "1", "--checkpoint-every", "1", "--no-progress", "--no-ablations"])
    assert rc == 0
    for name in ("results.json", "report.md", "heatmap.png", "comparison.png", "condition_response.png",
                 "controlgs.controlgs.safetensors"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    data = json.loads((out / "results.json").read_text())
    assert set(data["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    for m in data["methods"].values():
        grid = torch.tensor(m["psnr"]["grid"], dtype=torch.float64)
        assert grid.shape == (4, 5) and bool(torch.isfinite(grid).all())
        assert m["psnr"]["mean"] == pytest.approx(float(grid.mean()), rel=1e-9)
    assert data["info"]["iterations"] == 2
    back = GridResult.from_json(data)
    assert back.mean("controlgs", "psnr") == data["methods"]["controlgs"]["psnr"]["mean"]


@needs_backbone
def test_demo_with_two_seeds(tmp_path, monkeypatch, capsys):
    """``controlgs demo --seeds 2 --seed 5``: one adapter per seed in ``seed-5/`` and ``seed-6/``, each trained
    with its own seed (they differ); the options reach the evaluation (``--resolution``, ``--test-views``)
    and info records them; the reported phase times are parts of the command's wall time."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "report"
    t0 = time.perf_counter()
    assert main(["demo", "--out", str(out), "--resolution", "16", "--iterations", "1", "--test-views", "1",
                     "--effects", "display", "--checkpoint-every", "0", "--no-ablations", "--no-progress",
                     "--seeds", "2", "--seed", "5"]) == 0
    wall = time.perf_counter() - t0
    a, b = (load_file(out / f"seed-{s}" / "controlgs.controlgs.safetensors") for s in (5, 6))
    assert a.keys() == b.keys() and any(not torch.equal(a[k], b[k]) for k in a)
    data = json.loads((out / "results.json").read_text())
    info = data["info"]
    assert (info["resolution"], info["test_views"], info["seeds"], info["seed"], info["iterations"]) == (16, 1, 2, 5, 1)
    assert info["test_sizes"] == ["16x16"]
    timings_within(info, ("load_s", "train_s", "eval_s", "figures_s"), wall)
    assert info["train_s"] > 0 and info["eval_s"] > 0


# ----------------------------------------------------------------------------- pooling seeds, the run-folder lock and optional packages


