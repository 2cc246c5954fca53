"""``controlgs bench`` machinery at a tiny size: every table is there with finite positive times."""

import math
import re
import time

from controlgs_adapter.benchmarking.accuracy_time import COND_DIMS, MODULE_SETS, PSF_MODES, BenchSettings, run_bench
from controlgs_adapter.benchmarking.report import PART_DOCS, format_report, write_report


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


def test_bench_report_tiny(tmp_path):
    s = BenchSettings(resolution=16, iterations=2, phase_iterations=1, repeats=1, test_views=1,
                      downsample=(1.0, 2.0), power_saving=(0.0, 0.6))
    t0 = time.perf_counter()
    r = run_bench(s)
    wall = time.perf_counter() - t0
    for k in r.knobs:  # a step's median time: positive, and a small part of the whole run
        assert 0 < k["s_per_it"] < wall / s.iterations, k
    r.info["date"] = "test"
    text = format_report(r, "controlgs bench --test")
    path = write_report(text, tmp_path / "benchmarks.md")
    assert path.read_text() == text

    phases = _table_rows(text, "| optics |")
    assert [row[0] for row in phases] == list(PSF_MODES)
    for mode, p in r.phases.items():  # the PSF phase is timed by hooks on the real optics stage: > 0 in every mode
        assert all(math.isfinite(v) and v > 0 for v in p.values()), (mode, p)
        assert p["total"] >= sum(v for k, v in p.items() if k != "total") * 0.999

    knobs = _table_rows(text, "| knob |")
    settings = [row[1] for row in knobs]
    assert set(PSF_MODES) <= set(settings)
    assert {f"N={n}" for n in COND_DIMS if n != 8} <= set(settings)
    assert {"+".join(m) for m in MODULE_SETS if len(m) < 3} <= set(settings)
    for row in knobs:
        _positive(row[2])  # ms / iteration
        assert math.isfinite(float(row[3])) and math.isfinite(float(row[4]))
    ref = next(row for row in knobs if row[0] == "reference")
    assert float(ref[4]) == 0.0

    ss = _table_rows(text, "| d |")
    assert [float(row[0]) for row in ss] == [1.0, 2.0]
    for row in ss:
        _positive(row[1]), _positive(row[2]), _positive(row[3]), _positive(row[4]), _positive(row[5])

    overhead = _table_rows(text, "| | SS-backbone |")
    assert [row[0] for row in overhead][:3] == ["render time (ms)", "parameters", "storage (float32)"]
    _positive(overhead[0][1]), _positive(overhead[0][2])
    assert r.overhead["bytes_adapter_fp16"] < r.overhead["bytes_adapter"]
    # reference adapter: N = 8 per anchor for each of the three modules, plus the projections
    assert r.overhead["params_conditions"] == r.info["anchors"] * 3 * 8 < r.overhead["params_adapter"]
    for doc, _, _ in PART_DOCS:
        assert f"]({doc})" in text


def test_bench_step_prints_the_table_and_rewrites_only_the_generated_part(tmp_path):
    """``benchmarks/bench_step.py`` at a tiny size: one CPU row whose phases add up to the step, the
    no-GPU line where CUDA is missing, and ``--out`` keeps the page's hand-written reading section."""
    import subprocess
    import sys
    from pathlib import Path

    import torch

    root = Path(__file__).resolve().parent.parent
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

    root = Path(__file__).resolve().parent.parent
    spec = importlib.util.spec_from_file_location("bench_step_doc", root / "benchmarks" / "bench_step.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    assert mod.doc_page([("cuda", "torch"), ("cuda:0", "gsplat")]).name == "benchmarks-step-gpu.md"
    assert mod.doc_page([("cpu", "torch"), ("cuda", "gsplat")]).name == "benchmarks-step.md"
    assert mod.doc_page([("cpu", "torch")]).name == "benchmarks-step.md"
    assert mod.doc_page([]).name == "benchmarks-step.md"  # nothing measured (no GPU): the CPU page, with its note
