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


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_lenses_page_reports_the_gains_per_lens_from_the_summaries():
    """The per-lens gains are differences of the seed means in the runs' summaries (ControlGS - SS-backbone,
    ControlGS - w/o Lens), one column per lens, and the step table's ratio is against Cardboard's."""
    lenses = _script("bench_lenses")

    def summary(cgs: float, ss: float, wo: float) -> dict:
        one = lambda v: {"psnr": [v, 0.01], "ssim": [0.5, 0.0], "flip": [0.3, 0.0]}  # noqa: E731
        return {"controlgs": one(cgs), "ss": one(ss), "wo_lens": one(wo), "ideal": one(20.0)}

    res = {"builtin": {"cardboard": {"summary": summary(21.0, 20.5, 20.9), "wall_s": 60.0},
                       "compact": {"summary": summary(21.5, 20.75, 21.25), "wall_s": 120.0}},
           "steps": {"cardboard": {"distortion": 50.0, "exact": 80.0}, "compact": {"distortion": 40.0, "exact": 60.0}}}
    args = type("A", (), {"seeds": 2, "iterations": 5, "step_resolution": 96, "step_reps": 3})()
    text = "\n".join(lenses.page(args, res))
    assert "| ControlGS − SS-backbone, PSNR dB | +0.50 | +0.75 |" in text
    assert "| ControlGS − w/o Lens, PSNR dB | +0.10 | +0.25 |" in text
    assert "| compact | 40 | 60 | 0.75x |" in text and "| cardboard | 50 | 80 | 1.00x |" in text
    assert "under the compact lens and +0.50 dB under Cardboard" in text


def test_bench_foveation_quality_page_averages_seeds_per_gaze_and_band():
    fq = _script("bench_foveation_quality")
    methods = {m: {"psnr": [[v, v + 0.2]], "psnr_foveal": [[None, None]], "psnr_parafoveal": [[v, v]],
                   "psnr_periphery": [[1.0, 3.0]]} for m, v in (("ss", 20.0), ("controlgs", 21.0), ("wo_foveation", 20.5))}
    res = {"builtin": {"gazes": [[10.0, 0.0]], "bands": ["foveal", "parafoveal", "periphery"], "methods": methods}}
    args = type("A", (), {"seeds": 2, "iterations": 5})()
    text = "\n".join(fq.page(args, res))
    assert "| (10, 0) | ControlGS | 21.10 ± 0.14 | – | 21.00 ± 0.00 | 2.00 ± 1.41 |" in text
    assert "ControlGS − w/o Foveation, whole image: (10, 0): +0.500 dB." in text
