"""Tests of ``controlgs_adapter.downstream.optics.bench``: the PSF-operator benchmark's sizes, defaults,
rows (each operator's error against exact, recomputed here), timer, report tables and figure."""

from __future__ import annotations

import inspect
import itertools
import math
import os

import pytest
import torch

from controlgs_adapter.downstream.optics import bench
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.operators import psf_distortion, psf_exact, psf_fast
from controlgs_adapter.errors import InputValueError


def test_parse_size():
    assert bench.parse_size("24") == (24, 24) and bench.parse_size("18x32") == (18, 32) and bench.parse_size(20) == (20, 20)
    assert bench.parse_size("576X1024") == (576, 1024) and bench.parse_size("2") == (2, 2)
    for bad in ("0", "1", "2x1", "", "-4", "12x", "x12", "1x2x3", "a"):
        with pytest.raises(ValueError, match="size must be N or HxW"):
            bench.parse_size(bad)


def test_bench_run_defaults_are_the_documented_command_defaults():
    """docs/reference/cli.md, ``controlgs optics bench``: ``--sizes 256 512 1024 576x1024``, ``--radiometry
    radiance energy``, ``--tols 0.02``, ``--zone 5``, ``--threads 2``, ``--repeat 3``, ``--exact-max 1024``,
    scaling on unless ``--no-scaling``: ``bench.run`` has the same defaults."""
    p = {k: v.default for k, v in inspect.signature(bench.run).parameters.items()}
    assert tuple(p["sizes"]) == bench.SIZES == ("256", "512", "1024", "576x1024") and tuple(p["tols"]) == bench.TOLS == (0.02,)
    assert tuple(p["radiometries"]) == ("radiance", "energy")
    assert (p["zone"], p["threads"], p["repeat"], p["exact_max"], p["scaling"]) == (5, 2, 3, 1024, True)
    assert p["out"] is None and p["command"] == "controlgs optics bench --doc"


def test_a_small_bench_run(tmp_path, monkeypatch, capsys):
    """Two sizes, both radiometries, tol 0.3, exact timed up to 20 px: a table-build row per (size,
    radiometry) in that order; every operator's ``rel_l2`` = ||y - exact|| / ||exact|| and ``max_rel`` =
    max|y - exact| / max|exact|, recomputed here in float64 from the public operators on the bench's own
    image (exact against itself: 0); the printed header gives the threads and the machine's 1-minute load
    average; the report names the command and holds the radiance / energy ratios."""
    pytest.importorskip("skimage")
    monkeypatch.setattr(os, "getloadavg", lambda: (1.3, 5.5, 15.75))
    n = torch.get_num_threads()
    try:
        rows = bench.run(sizes=["12", "12x20"], exact_max=20, threads=1, tols=(0.3,), repeat=1, scaling=False,
                         out=tmp_path, command="test")
    finally:
        torch.set_num_threads(n)                                     # the bench sets the process's threads
    header = capsys.readouterr().out.splitlines()[0]
    assert "load average 1.3," in header and "1 threads" in header
    tables = [r for r in rows if r["op"] == "tables"]
    assert [(r["size"], r["radiometry"]) for r in tables] == [("12x12", "radiance"), ("12x12", "energy"),
                                                              ("12x20", "radiance"), ("12x20", "energy")]
    assert all(list(r["fast_s"]) == [0.3] for r in tables)
    exact = [r for r in rows if r["op"] == "exact"]
    assert len(exact) == 4 and all(r["rel_l2"] == 0 and r["max_rel"] == 0 for r in exact)
    for radiometry in ("radiance", "energy"):
        by = {r["op"]: r for r in rows if (r["size"], r["radiometry"]) == ("12x12", radiometry)}
        assert sorted(by) == ["distortion", "exact", "fast", "tables"] and by["fast"]["knob"] == "tol=0.3, zone=5"
        rb = PSFBank.default().resample_to(12, 12, radiometry=radiometry)
        x = bench._image(12)
        with torch.no_grad():
            ref = psf_exact(x, rb).double()
            outs = {"distortion": psf_distortion(x, rb), "fast": psf_fast(x, rb, 0.3, 5)}
        for op, y in outs.items():
            d = y.double() - ref
            assert by[op]["rel_l2"] == pytest.approx((d.norm() / ref.norm()).item(), rel=1e-4, abs=1e-9), op
            assert by[op]["max_rel"] == pytest.approx((d.abs().max() / ref.abs().max()).item(), rel=1e-4, abs=1e-9), op
        if radiometry == "energy":                                   # the energy form's PSFs reach past a pixel here
            assert by["distortion"]["rel_l2"] > 1e-4 and by["fast"]["rel_l2"] > 1e-6
        assert math.isfinite(by["fast"]["fwd_bwd_s"]) and by["fast"]["fwd_bwd_s"] > 0
    text = (tmp_path / "optics_bench.md").read_text()
    assert "| 12x20 | exact fwd+bwd |" in text and "Command: `test`" in text


def test_bench_timer_keeps_the_best_of_its_repeats(monkeypatch):
    """``_time`` runs the call ``repeat`` times and keeps the smallest wall-clock and the smallest CPU time
    (clocks replaced by scripted readings: start and end of each run)."""
    calls = []
    wall = itertools.chain([0.0, 5.0, 10.0, 12.0, 20.0, 24.0], itertools.count(100.0))   # runs of 5, 2, 4 s
    cpu = itertools.chain([0.0, 1.0, 2.0, 5.0, 6.0, 6.5], itertools.count(100.0))        # runs of 1, 3, 0.5 s
    monkeypatch.setattr(bench.time, "perf_counter", lambda: next(wall))
    monkeypatch.setattr(bench.time, "process_time", lambda: next(cpu))
    assert bench._time(lambda: calls.append(1), repeat=3) == (2.0, 0.5)
    assert len(calls) == 3
    assert bench._clock(lambda: math.sqrt(16.0))[0] == 4.0


def test_bench_ratio_tables():
    rows = [dict(size="8x8", radiometry="radiance", op="tables", knob="-", resample_s=1.0, resample_cpu=2.0,
                 exact_s=3.0, exact_cpu=4.0),
            dict(size="8x8", radiometry="energy", op="tables", knob="-", resample_s=0.5, resample_cpu=1.0,
                 exact_s=1.5, exact_cpu=2.0),
            dict(size="8x8", radiometry="radiance", op="fast", knob="tol=0.02, zone=5", fwd_bwd_s=6.0, fwd_bwd_cpu=9.0),
            dict(size="8x8", radiometry="energy", op="fast", knob="tol=0.02, zone=5", fwd_bwd_s=2.0, fwd_bwd_cpu=3.0),
            dict(size="8x8", radiometry="radiance", op="exact", knob="-", fwd_bwd_s=1.0, fwd_bwd_cpu=1.0)]
    ratios = bench._ratios(rows)                     # the radiance exact row has no energy partner: no ratio
    assert ratios == [dict(size="8x8", op="tables (resample_to + exact)", wall=2.0, cpu=2.0, rad_s=4.0, en_s=2.0),
                      dict(size="8x8", op="fast fwd+bwd (tol=0.02, zone=5)", wall=3.0, cpu=3.0, rad_s=6.0, en_s=2.0)]
    lines = bench._ratio_lines(ratios)
    assert lines[2] == "| 8x8 | tables (resample_to + exact) | 4.000 | 2.000 | 2.00 | 2.00 |"
    assert lines[3] == "| 8x8 | fast fwd+bwd (tol=0.02, zone=5) | 6.000 | 2.000 | 3.00 | 3.00 |" and len(lines) == 4
    assert bench._ratio_lines([]) == []


def test_bench_report_tables(tmp_path):
    rows = [dict(size="8x8", radiometry="radiance", op="tables", knob="-", resample_s=1.0, resample_cpu=2.0,
                 exact_s=3.0, exact_cpu=4.0, fast_s={0.02: 0.5}, fast_cpu={0.02: 0.25}),
            dict(size="8x8", radiometry="radiance", op="fast", knob="tol=0.02, zone=5", fwd_s=0.125, fwd_cpu=0.25,
                 fwd_bwd_s=0.5, fwd_bwd_cpu=1.0, rel_l2=0.0123, max_rel=0.0456),
            dict(size="8x8", radiometry="radiance", op="exact", knob="-", fwd_s=0.1, fwd_cpu=0.2,
                 fwd_bwd_s=0.3, fwd_bwd_cpu=0.4, rel_l2=0.0, max_rel=0.0)]
    bench._write(rows, [], [(33, 0.5), (129, 1.5)], threads=2, repeat=3, out=tmp_path / "o", command="cmd")
    lines = (tmp_path / "o" / "optics_bench.md").read_text().splitlines()
    assert lines[0] == "# PSF operators: speed and error"
    assert "2 CPU threads, best of 3" in lines[2] and "Command: `cmd; " in lines[2]
    assert "| 8x8 | radiance | 1.00 (2.00) | 3.00 (4.00) | tol 0.02: 0.50 (0.25) |" in lines
    assert "| 8x8 | radiance | fast | tol=0.02, zone=5 | 0.125 | 0.250 | 0.500 | 1.000 | 1.23e-02 | 4.56e-02 |" in lines
    assert "| 8x8 | radiance | exact | - | 0.100 | 0.200 | 0.300 | 0.400 | 0.00e+00 | 0.00e+00 |" in lines
    assert ("Kernel-size scaling of the fast mode (Gaussian PSF banks, fwd+bwd CPU time): k = 33: 0.500 s, "
            "k = 129: 1.500 s (ratio 3.00)") in lines
    assert lines[-1] == "![error vs fwd+bwd time of the PSF operators](optics_bench.png)"
    assert not any("Radiance (default) vs energy" in ln for ln in lines)
    if (tmp_path / "o" / "optics_bench.png").exists():
        assert (tmp_path / "o" / "optics_bench.png").stat().st_size > 1000


def test_bench_kernel_scaling_banks_span_33_and_129_px():
    """Gaussian banks whose stored window spans k = 33 and 129 output px (24 / size mm per px, K = 33
    cells): the resampled kernels are 33 and 129 (+2: the float32 pitch rounds the margin up) px wide."""
    pytest.importorskip("skimage")
    out = bench._kernel_scaling(16, zone=6)
    assert [k for k, _ in out][0] == 33 and [k for k, _ in out][1] in (129, 131)
    assert all(t > 0 for _, t in out)


def test_bench_figure_lines_labels_and_exact_marker():
    plt = pytest.importorskip("matplotlib.pyplot")

    def row(rad, op, knob, cpu, rel):
        return dict(size="8x8", radiometry=rad, op=op, knob=knob, fwd_bwd_cpu=cpu, rel_l2=rel)

    ops = [row("radiance", "distortion", "-", 0.5, 0.2), row("radiance", "fast", "tol=0.02, zone=5", 2.0, 0.0),
           row("radiance", "exact", "-", 4.0, 0.0), row("energy", "distortion", "-", 0.25, 0.3),
           row("energy", "fast", "tol=0.05, zone=5", 1.0, 0.01)]
    fig = bench._figure(plt, ops)
    try:
        ax = fig.axes[0]
        rad, exact, en = ax.lines                                                   # the energy key has no exact row
        assert list(rad.get_xdata()) == [0.5, 2.0] and list(rad.get_ydata()) == [0.2, 1e-7]   # 0 floored at 1e-7
        assert (rad.get_marker(), rad.get_linestyle()) == ("o", "-") and rad.get_label() == "8x8 radiance"
        assert list(en.get_xdata()) == [0.25, 1.0] and list(en.get_ydata()) == [0.3, 0.01]
        assert (en.get_marker(), en.get_linestyle()) == ("s", "--") and en.get_label() == "8x8 energy"
        assert list(exact.get_xdata()) == [4.0, 4.0] and exact.get_linestyle() == ":"
        assert exact.get_color() == rad.get_color()
        notes = [(t.get_text(), tuple(t.xy)) for t in ax.texts]
        assert notes == [("distortion", (0.5, 0.2)), ("tol=0.02", (2.0, 1e-7)), ("distortion", (0.25, 0.3)),
                         ("tol=0.05", (1.0, 0.01))]
        assert {t.get_fontsize() for t in ax.texts} == {6}
        assert (ax.get_xscale(), ax.get_yscale()) == ("log", "log")
    finally:
        plt.close(fig)


@pytest.mark.parametrize("kw, name", [(dict(repeat=0), "repeat"), (dict(repeat=-1), "repeat"), (dict(zone=0), "zone"),
                                      (dict(threads=0), "threads"), (dict(threads=10**40), "threads")])
def test_run_refuses_bad_counts_before_timing(kw, name, capsys):
    """Counts below 1 (and threads beyond the limit) are refused naming the option, before anything is printed."""
    with pytest.raises(InputValueError, match=f"^{name} must be an integer in "):
        bench.run(sizes=[8], **kw)
    assert capsys.readouterr().out == ""


def test_the_exact_operator_is_timed_only_when_the_longer_side_is_within_exact_max(tmp_path):
    """``exact_max`` bounds the longer side: a 12 x 20 image is timed with the exact operator at
    ``exact_max = 20`` and not at 16 (its shorter side, 12, would pass)."""
    pytest.importorskip("skimage")
    n = torch.get_num_threads()
    try:
        ops = {m: {r["op"] for r in bench.run(sizes=["12x20"], exact_max=m, threads=1, tols=(0.3,), repeat=1,
                                               scaling=False, out=None, command="test")}
               for m in (16, 20)}
    finally:
        torch.set_num_threads(n)
    assert "exact" not in ops[16] and "exact" in ops[20]
