"""Tests of the scripts in ``benchmarks/``: they print unless asked to write a page, and ``bench_step.py`` measures
a training step whose phases add up, keeping its page's hand-written part."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers.markdown_tables import positive, table_rows

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("script", sorted(p.name for p in (ROOT / "benchmarks").glob("*.py")))
def test_benchmark_scripts_default_to_printing(script: str) -> None:
    text = (ROOT / "benchmarks" / script).read_text()
    defaults = re.findall(r"add_argument\([^)]*default=([^,)]*)", text)
    assert not [d for d in defaults if "docs" in d], f"{script}: a default path into docs/"


def test_bench_step_prints_the_table_and_rewrites_only_the_generated_part(tmp_path):
    """``benchmarks/bench_step.py`` at a tiny size: one CPU row whose phases add up to the step, the
    no-GPU line where CUDA is missing, and ``--out`` keeps the page's hand-written reading section."""
    page = tmp_path / "step.md"
    page.write_text("# old page\n\nstale table\n\n## Reading the numbers\n\nhand-written text\n")
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_step.py"), "--anchors", "300", "--sizes", "64", "--reps", "1",
           "--optics", "distortion", "--threads", "1", "--out", str(page)]
    res = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    text = page.read_text()
    assert text.startswith("# Training step on the CPU\n") and "stale table" not in text
    assert text.endswith("## Reading the numbers\n\nhand-written text\n")
    rows = table_rows(text, "| device |")
    header = next(line for line in text.splitlines() if line.startswith("| device |"))
    cols = [c.strip() for c in header.strip("|").split("|")]
    cpu = [dict(zip(cols, r)) for r in rows if r[0] == "cpu"]
    assert [(r["rasterizer"], r["anchors"], r["size"], r["optics"]) for r in cpu] == [("torch", "300", "64x36", "distortion")]
    r = cpu[0]
    phases = sum(float(r[k]) for k in ("sample", "decode", "splat", "stages", "PSF", "loss", "backward", "optimizer"))
    step = positive(r["step (s)"])
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
    spec = importlib.util.spec_from_file_location("bench_step_doc", ROOT / "benchmarks" / "bench_step.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    gpu, cpu = ROOT / "docs" / "benchmarks" / "training-step-gpu.md", ROOT / "docs" / "benchmarks" / "training-step-cpu.md"
    assert mod.doc_page([("cuda", "torch"), ("cuda:0", "gsplat")]) == gpu
    assert mod.doc_page([("cpu", "torch"), ("cuda", "gsplat")]) == cpu
    assert mod.doc_page([("cpu", "torch")]) == cpu
    assert mod.doc_page([]) == cpu  # nothing measured (no GPU): the CPU page, with its note
    assert gpu.is_file() and cpu.is_file()
