"""``controlgs bench`` checks ``--out`` and its numbers before measuring anything."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cli_runs import error_line

import controlgs_adapter.commands.bench as bench_command
from controlgs_adapter.cli import main


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the measurements started")

    monkeypatch.setattr(bench_command, "run_bench", refuse)


def test_out_that_cannot_be_written_is_refused_first(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     no_work: None) -> None:
    assert main(["bench", "--out", str(tmp_path)]) == 2
    assert error_line(capsys, "bench") == f"--out {tmp_path}: is a folder; expected the path of a file to write"
    blocker = tmp_path / "blocker"
    blocker.write_text("mine")
    assert main(["bench", "--out", str(blocker / "bench.md")]) == 2
    assert error_line(capsys, "bench") == f"--out {blocker / 'bench.md'}: {blocker} is a file, not a folder"
    assert blocker.read_text() == "mine"


@pytest.mark.parametrize("option, value", [("--test-views", "0"), ("--resolution", "0"), ("--iterations", "-1"),
                                           ("--seed", "-2")])
def test_numbers_are_checked_first(capsys: pytest.CaptureFixture[str], no_work: None, option: str, value: str) -> None:
    assert main(["bench", option, value]) == 2
    line = error_line(capsys, "bench")
    assert line.startswith(f"{option} must be an integer") and line.endswith(f"got {value}")


import argparse
import math
import re
import shlex
import subprocess
import sys

import torch

from controlgs_adapter import cli
from controlgs_adapter.benchmarking.accuracy_time import BenchSettings
from controlgs_adapter.cli import build_parser


def _table_rows(text: str, header_start: str) -> list[list[str]]:
    """Cells of the Markdown table whose header line starts with ``header_start``."""
    lines = text.splitlines()
    i = next(k for k, line in enumerate(lines) if line.startswith(header_start))
    rows = []
    for line in lines[i + 2:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows


def _positive(cell: str) -> float:
    value = float(re.sub(r"[^0-9.eE+-]", "", cell))
    assert math.isfinite(value) and value > 0, cell
    return value


def test_bench_step_prints_the_table_and_rewrites_only_the_generated_part(tmp_path):
    """``benchmarks/bench_step.py`` at a tiny size: one CPU row whose phases add up to the step, the
    no-GPU line where CUDA is missing, and ``--out`` keeps the page's hand-written reading section."""
    import subprocess
    import sys
    from pathlib import Path


    root = Path(__file__).resolve().parents[2]
    page = tmp_path / "step.md"
    page.write_text("# old page\n\nstale table\n\n## Reading the numbers\n\nhand-written text\n")
    cmd = [sys.executable, str(root / "benchmarks" / "bench_step.py"), "--anchors", "300", "--sizes", "64", "--reps", "1",
           "--optics", "distortion", "--threads", "1", "--out", str(page)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=root, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    text = page.read_text()
    assert text.startswith("# Training-step benchmark") and "stale table" not in text
    assert text.endswith("## Reading the numbers\n\nhand-written text\n")
    rows = _table_rows(text, "| device |")
    header = next(line for line in text.splitlines() if line.startswith("| device |"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    cpu = [dict(zip(cols, r)) for r in rows if r[0] == "cpu"]
    assert [(r["rasterizer"], r["anchors"], r["size"], r["optics"]) for r in cpu] == [("torch", "300", "64x36", "distortion")]
    r = cpu[0]
    phases = sum(float(r[k]) for k in ("sample", "decode", "splat", "stages", "PSF", "loss", "backward", "optimizer"))
    step = _positive(r["step (s)"])
    assert abs(phases - step) <= 0.005 * 9 + 1e-9  # eight phase cells and the step cell, each rounded to 0.01 s
    # both cells rounded to 0.01: some true step time t with |t - step| <= 0.005 has 1/t within 0.005 of it/s
    its = float(r["it/s"])
    assert 1 / (its + 0.005) <= step + 0.005 + 1e-9 and 1 / (its - 0.005) >= step - 0.005 - 1e-9, (its, step)
    for phase in ("splat", "backward"):  # measured; under 5 ms (an idle machine, this tiny scene) it reads 0.00
        assert re.fullmatch(r"\d+\.\d\d", r[phase]), r[phase]
    gaussians, visible = re.match(r"(\d+) \((\d+)\)", r["Gaussians (visible)"]).groups()
    assert 0 < int(visible) <= int(gaussians) <= 300 * 10
    if not torch.cuda.is_available():
        assert "no GPU available in this run: GPU rows not measured" in res.stdout
        assert "no GPU available in this run: GPU rows not measured" in text
        assert not [row for row in rows if row[0].startswith("cuda")]


def test_bench_step_doc_page_keeps_cpu_and_gpu_rows_apart():
    """``--doc`` writes the GPU page only when every measured pair is on CUDA (a GPU run does not
    replace the CPU rows), else the CPU page."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    spec = importlib.util.spec_from_file_location("bench_step_doc", root / "benchmarks" / "bench_step.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.doc_page([("cuda", "torch"), ("cuda:0", "gsplat")]).name == "benchmarks-step-gpu.md"
    assert mod.doc_page([("cpu", "torch"), ("cuda", "gsplat")]).name == "benchmarks-step.md"
    assert mod.doc_page([("cpu", "torch")]).name == "benchmarks-step.md"
    assert mod.doc_page([]).name == "benchmarks-step.md"  # nothing measured (no GPU): the CPU page, with its note


def test_bench_writes_docs_only_with_doc() -> None:
    parser = build_parser()
    assert parser.parse_args(["bench"]).out is None
    assert parser.parse_args(["bench", "--doc"]).out == Path("docs") / "benchmarks.md"
    assert parser.parse_args(["optics", "bench"]).out is None
    assert parser.parse_args(["optics", "bench", "--doc"]).out == Path("docs")


# ------------------------------------------------------------------------------ controlgs bench
@pytest.mark.slow
def test_bench_report_names_the_command_line_it_was_run_with(tmp_path):
    """``docs/benchmarks.md`` starts with how it was generated: the report names ``controlgs bench`` with the
    options given, quoted so that a shell runs the same command again."""
    out = tmp_path / "my report.md"
    args = ["bench", "--quick", "--resolution", "16", "--iterations", "2", "--test-views", "1", "--no-progress",
            "--out", str(out)]
    p = subprocess.run([sys.executable, "-c", "import sys; from controlgs_adapter.cli import main; sys.exit(main())",
                        *args], capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    text = out.read_text()
    assert text in p.stdout  # printed too
    m = re.search(r"Generated by `([^`]*)`", text)
    assert m is not None, text[:500]
    assert shlex.split(m.group(1)) == ["controlgs", *args], m.group(1)


def _parse(*argv: str) -> argparse.Namespace:
    return cli.build_parser().parse_args(list(argv))


def test_bench_settings_from_the_command_line():
    from controlgs_adapter.commands.bench import settings_from_args

    s = settings_from_args(_parse("bench"))
    assert s == BenchSettings(resolution=96, variant="ar", seed=0)
    assert (s.iterations, s.test_views, s.repeats) == (100, 4, 20)
    q = settings_from_args(_parse("bench", "--quick", "--variant", "vr", "--seed", "3", "--resolution", "32"))
    assert (q.iterations, q.phase_iterations, q.repeats, q.test_views, q.downsample, q.power_saving) == \
        (20, 6, 5, 1, (1.0, 4.0), (0.0, 0.6))
    assert (q.resolution, q.variant, q.seed) == (32, "vr", 3)
    o = settings_from_args(_parse("bench", "--quick", "--iterations", "7", "--test-views", "3"))
    assert (o.iterations, o.test_views, o.repeats) == (7, 3, 5)  # given options win over --quick's
    assert settings_from_args(_parse("bench", "--iterations", "9")).iterations == 9
