"""Tests of ``controlgs_adapter.benchmarking.accuracy_time``."""

from __future__ import annotations

import math
import re
import time
from typing import Any

import pytest

import controlgs_adapter.benchmarking.accuracy_time as at
import controlgs_adapter.evaluation as evaluation
from controlgs_adapter.benchmarking.accuracy_time import (
    COND_DIMS,
    MODULE_SETS,
    PSF_MODES,
    BenchSettings,
    _knob_configs,
    _median_times,
    run_bench,
)
from controlgs_adapter.benchmarking.report import PART_DOCS, format_report, write_report
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.training import TrainConfig, Trainer


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


def test_bench_is_quiet_unless_asked_for_progress(capsys):
    """``run_bench(progress=False)`` (the default, as a library call) writes nothing to stderr or stdout;
    with ``progress=True`` it names its phases on stderr, starting with the phase timings."""
    from controlgs_adapter.benchmarking.accuracy_time import BenchSettings, run_bench

    s = BenchSettings(resolution=16, iterations=1, phase_iterations=1, repeats=1, test_views=1,
                      downsample=(1.0,), power_saving=(0.0,))
    run_bench(s)
    quiet = capsys.readouterr()
    assert (quiet.out, quiet.err) == ("", "")
    run_bench(s, progress=True)
    loud = capsys.readouterr()
    assert loud.out == ""
    assert loud.err.splitlines()[0] == "training phases"


# ---------------------------------------------------------------- settings and knobs
def test_bench_settings_defaults() -> None:
    s = BenchSettings()
    assert (s.resolution, s.iterations, s.phase_iterations, s.repeats, s.test_views) == (64, 100, 40, 20, 4)
    assert s.downsample == (1.0, 2.0, 4.0, 8.0) and s.power_saving == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert s.variant == "ar" and s.seed == TrainConfig.seed
    assert (at.DEFAULT_ITERATIONS, at.QUICK_ITERATIONS) == (100, 20)
    assert at.COND_DIMS == (2, 4, 8, 16) and at.PSF_MODES == ("distortion", "fast", "exact")


@pytest.mark.parametrize("name", ["resolution", "iterations", "phase_iterations", "repeats", "test_views"])
def test_bench_settings_refuse_counts_below_one(name: str) -> None:
    BenchSettings(**{name: 1})  # the bound itself is allowed
    with pytest.raises(InputValueError, match=f"{name} must be >= 1, got 0"):
        BenchSettings(**{name: 0})


def test_bench_settings_need_the_grid_origin() -> None:
    BenchSettings(downsample=(1.0,), power_saving=(0.0,))
    with pytest.raises(InputValueError, match=r"the grid must contain d = 1 and rho = 0, got d \(2.0,\)"):
        BenchSettings(downsample=(2.0,), power_saving=(0.0, 0.4))
    with pytest.raises(InputValueError, match=r"rho \(0.4,\)"):
        BenchSettings(downsample=(1.0, 2.0), power_saving=(0.4,))


def test_knob_configs_list() -> None:
    rows = _knob_configs(BenchSettings())
    assert rows == [
        ("reference", "N=8, 3 modules, 90% distortion + 10% fast", {}),
        ("PSF operator (whole training)", "distortion", {"psf_fraction": 0.0}),
        ("PSF operator (whole training)", "fast", {"psf_fraction": 1.0, "psf_mode": "fast"}),
        ("PSF operator (whole training)", "exact", {"psf_fraction": 1.0, "psf_mode": "exact"}),
        ("condition dim N", "N=2", {"cond_dim": 2}),
        ("condition dim N", "N=4", {"cond_dim": 4}),
        ("condition dim N", "N=16", {"cond_dim": 16}),  # N = 8 is the reference
        ("modules", "lens", {"modules": ("lens",)}),
        ("modules", "lens+display", {"modules": ("lens", "display")}),  # all three modules: the reference
    ]
    # the reference row is what its label says: the Trainer's defaults
    c = TrainConfig()
    assert (c.cond_dim, c.modules, c.psf_fraction, c.psf_mode) == (8, None, 0.1, "fast")  # None: every module


# ---------------------------------------------------------------- the interleaved median timer
def test_median_times_interleaves_after_one_warm_up(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fake clock that each call advances by a scripted duration: the medians are those of the
    scripted durations without the warm-up call (which is the slowest, so it would show)."""
    now = [0.0]
    order: list[str] = []
    monkeypatch.setattr(at.time, "perf_counter", lambda: now[0])

    def fn(name: str, durations: list[float]) -> Any:
        it = iter(durations)

        def call() -> None:
            order.append(name)
            now[0] += next(it)
        return call

    # a: warm-up 100 then 1, 5, 3 -> median 3; b: warm-up 100 then 2, 2, 8 -> median 2
    got = _median_times([fn("a", [100.0, 1.0, 5.0, 3.0]), fn("b", [100.0, 2.0, 2.0, 8.0])], repeats=3)
    assert got == [3.0, 2.0]
    assert order == ["a", "b"] * 4  # interleaved: a, b, a, b, ... (repeats + 1 rounds)
    order.clear()
    assert _median_times([fn("c", [50.0, 7.0])], repeats=1) == [7.0]
    assert order == ["c", "c"]


def test_psf_keywords() -> None:
    assert at.psf_keywords("distortion") == {"psf_fraction": 0.0}
    assert at.psf_keywords("fast") == {"psf_fraction": 1.0, "psf_mode": "fast"}
    assert at.psf_keywords("exact") == {"psf_fraction": 1.0, "psf_mode": "exact"}


def test_phase_times_configs_order_and_phases_adding_up(tiny: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Trainers recorded as the real ones run: one per mode with its optics for the whole run, the
    seed given, steps + 1 iterations (a warm-up), stepping in turn in a rotating order; with one timed
    step the phases of a mode add up to its total exactly (each is the one lap, not a median of sums)."""
    from controlgs_adapter.training import Trainer

    scene, model = tiny
    made: list[Any] = []
    order: list[str] = []

    class Recorded(Trainer):
        def __init__(self, *args: Any, **kw: Any) -> None:
            super().__init__(*args, **kw)
            made.append(self)

        def step(self, *args: Any, **kw: Any) -> float:
            c = self.config
            order.append("distortion" if c.psf_fraction == 0 else c.psf_mode)
            return super().step(*args, **kw)

    monkeypatch.setattr(at, "Trainer", Recorded)
    phases = at.phase_times(model, scene, ("distortion", "exact"), steps=2, seed=3)
    assert [(t.config.iterations, t.config.checkpoint_every, t.config.seed, t.config.psf_fraction, t.config.psf_mode)
            for t in made] == [(3, 0, 3, 0.0, "fast"), (3, 0, 3, 1.0, "exact")]
    assert order == ["distortion", "exact", "exact", "distortion", "distortion", "exact"]  # rotated each iteration
    assert all(t.model is not model for t in made)  # each on its own copy
    assert all(not t.cgs._wrapped for t in made)  # unwrapped at the end
    assert list(phases) == ["distortion", "exact"]
    names = ["sample", "decode", "splat", "stages", "psf", "loss", "backward", "optimizer", "total"]
    for mode, p in phases.items():
        assert list(p) == names and all(v > 0 for v in p.values()), (mode, p)
    made.clear()
    order.clear()
    one = at.phase_times(model, scene, ("fast",), steps=1)  # the default seed: 0
    assert made[0].config.seed == 0 and order == ["fast", "fast"]
    p = one["fast"]
    assert p["total"] == pytest.approx(sum(v for k, v in p.items() if k != "total"), rel=1e-12, abs=0)


def test_knob_results_trains_each_setting_in_turn_and_evaluates_them_all(tmp_path: Any,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    from controlgs_adapter.scene import load_builtin_backbone, load_builtin_scene

    s = BenchSettings(resolution=16, iterations=2, test_views=1, downsample=(1.0, 2.0), power_saving=(0.0,), seed=5)
    scene = load_builtin_scene(s.variant, s.resolution, views=8, test_every=4, samples=1)
    assert len(scene.test_cameras) == 2  # more test views than the settings ask for
    model = load_builtin_backbone(s.variant)
    made: list[Trainer] = []
    order: list[int] = []
    calls: list[dict[str, Any]] = []

    class Recorded(Trainer):
        def __init__(self, *args: Any, **kw: Any) -> None:
            super().__init__(*args, **kw)
            made.append(self)

        def step(self, *args: Any, **kw: Any) -> float:
            order.append(made.index(self))
            return super().step(*args, **kw)

    real = evaluation.evaluate_grid

    def recorded_grid(model: Any, views: Any, adapters: Any, **kw: Any) -> Any:
        calls.append({"model": model, "views": len(views), "adapters": dict(adapters), **kw})
        return real(model, views, adapters, **kw)

    monkeypatch.setattr(at, "Trainer", Recorded)
    monkeypatch.setattr(evaluation, "evaluate_grid", recorded_grid)
    rows, result = at.knob_results(model, scene, s, tmp_path)

    configs = _knob_configs(s)
    assert len(made) == len(configs) == 9
    for t, (_, _, kw) in zip(made, configs):
        c = t.config
        assert (c.iterations, c.checkpoint_every, c.seed) == (2, 0, 5)
        assert all(getattr(c, k) == v for k, v in kw.items())
        assert t.model is not model and not t.cgs._wrapped  # its own backbone, unwrapped at the end
    assert order == list(range(9)) * 2  # iteration i of every setting, then i + 1
    (call,) = calls
    assert call["model"] is model and call["views"] == 1  # the first test_views views
    assert call["adapters"] == {f"k{i}": tmp_path / f"k{i}.controlgs.safetensors" for i in range(9)}
    assert (call["downsample"], call["power_saving"], call["optics_mode"], call["extra_metrics"]) == (
        (1.0, 2.0), (0.0,), "exact", False)
    assert [(r["knob"], r["setting"]) for r in rows] == [(k, st) for k, st, _ in configs]
    for i, r in enumerate(rows):
        assert r["psnr"] == float(result.per_view[f"k{i}"]["psnr"].mean())
        assert r["ssim"] == float(result.per_view[f"k{i}"]["ssim"].mean())
        assert r["s_per_it"] > 0
    assert len({r["psnr"] for r in rows}) > 1  # the settings train different adapters
