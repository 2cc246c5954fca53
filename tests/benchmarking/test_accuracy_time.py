"""Tests of ``controlgs_adapter.benchmarking.accuracy_time``: the benchmark's settings, the knobs it trains, the
phase timings, the interleaved median timer, the SS rows and the render overhead, and a tiny run end to end."""

from __future__ import annotations

import math
import os
import time
from typing import Any

import pytest
import torch
from helpers.markdown_tables import positive, table_rows

import controlgs_adapter.benchmarking.accuracy_time as at
import controlgs_adapter.evaluation as evaluation
import controlgs_adapter.rendering.protocol as protocol
from controlgs_adapter import ControlGS
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
from controlgs_adapter.evaluation import GridResult
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_backbone, load_builtin_scene
from controlgs_adapter.training import TrainConfig, Trainer


# ----------------------------------------------------------------------------- settings and knobs

def test_bench_settings_defaults() -> None:
    s = BenchSettings()
    assert (s.resolution, s.iterations, s.phase_iterations, s.repeats, s.test_views) == (64, 100, 40, 20, 4)
    assert s.downsample == (1.0, 2.0, 4.0, 8.0) and s.power_saving == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert s.variant == "ar" and s.seed == TrainConfig.seed
    assert (at.DEFAULT_ITERATIONS, at.QUICK_ITERATIONS) == (100, 20)
    assert at.COND_DIMS == (2, 4, 8, 16) and at.PSF_MODES == ("distortion", "fast", "exact")
    assert at.psf_keywords("distortion") == {"psf_fraction": 0.0}
    assert at.psf_keywords("fast") == {"psf_fraction": 1.0, "psf_mode": "fast"}
    assert at.psf_keywords("exact") == {"psf_fraction": 1.0, "psf_mode": "exact"}


@pytest.mark.parametrize("name", ["resolution", "iterations", "phase_iterations", "repeats", "test_views"])
def test_bench_settings_refuse_counts_below_one(name: str) -> None:
    BenchSettings(**{name: 1})  # the bound itself is allowed
    with pytest.raises(InputValueError, match=f"{name}.*got 0$"):
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


# ----------------------------------------------------------------------------- timings

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


def test_phase_times_configs_order_and_phases_adding_up(tiny: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Trainers recorded as the real ones run: one per mode with its optics for the whole run, the
    seed given, steps + 1 iterations (a warm-up), stepping in turn in a rotating order; with one timed
    step the phases of a mode add up to its total exactly (each is the one lap, not a median of sums)."""
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


def test_ss_rows_read_the_rho_0_column_of_each_method(tiny: Any) -> None:
    """A hand-made grid (rho = 0 second, so its index matters): per-view PSNR base + 10 i + p + v / 2, whose
    view mean at (i, p) is base + 10 i + p + 0.25; the rows take p = 1 (rho = 0)."""
    scene, model = tiny

    def psnr(base: float) -> dict[str, torch.Tensor]:
        i, p, v = torch.meshgrid(torch.arange(2.0), torch.arange(2.0), torch.arange(2.0), indexing="ij")
        return {"psnr": (base + 10 * i + p + 0.5 * v).double()}

    grid = GridResult(downsample=(1.0, 2.5), power_saving=(0.4, 0.0),
                      per_view={"no_ss": psnr(100.0), "ss": psnr(200.0), "k0": psnr(300.0)})
    sizes: list[tuple[int, Any, Any]] = []
    real = protocol.render_view

    def recorded(cgs: Any, m: Any, cam: Any, state: Any, *args: Any, **kw: Any) -> Any:
        sizes.append((cam.width, cgs, state))
        return real(cgs, m, cam, state, *args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(protocol, "render_view", recorded)
        rows = at.ss_rows(model, scene, grid, BenchSettings(repeats=1))
    # per d: the bare backbone at S / d and at S (16 px), interleaved, a warm-up and one timed call each
    assert sizes == [(16, None, None)] * 4 + [(round(16 / 2.5), None, None), (16, None, None)] * 2
    assert [r["d"] for r in rows] == [1.0, 2.5]
    assert [(r["psnr_no_ss"], r["psnr_ss"], r["psnr_controlgs"]) for r in rows] == [
        (101.25, 201.25, 301.25), (111.25, 211.25, 311.25)]
    assert all(r["render_s_no_ss"] > 0 and r["render_s_ss"] > 0 for r in rows)


def test_render_overhead_counts_and_sizes(tiny: Any, tmp_path: Any) -> None:
    scene, model = tiny
    cgs = ControlGS.wrap(model)  # lens, resample, display with N = 8
    adapter = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    seen: list[tuple[Any, ...]] = []
    real = protocol.render_view

    def recorded(cgs: Any, m: Any, cam: Any, state: Any, *args: Any, **kw: Any) -> Any:
        seen.append((cgs is None, cam is scene.test_cameras[0], None if state is None else
                     (state.downsample, state.power_saving)))
        return real(cgs, m, cam, state, *args, **kw)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(protocol, "render_view", recorded)
        o = at.render_overhead(model, scene, adapter, tmp_path, repeats=2)
    # bare, then through the adapter at d = 2, rho = 0.4, on the first test camera: a warm-up and two timed calls
    assert seen == [(True, True, None), (False, True, (2.0, 0.4))] * 3
    assert o["render_s_ss"] > 0 and o["render_s_controlgs"] > 0
    assert o["params_conditions"] == model.num_anchors * 3 * 8
    assert o["params_backbone"] == float(sum(t.numel() for t in model.state_dict().values() if t.is_floating_point()))
    assert o["params_conditions"] < o["params_adapter"] < o["params_conditions"] * 2
    assert o["bytes_adapter"] == os.path.getsize(adapter)
    fp16 = tmp_path / "fp16.controlgs.safetensors"
    assert o["bytes_adapter_fp16"] == os.path.getsize(fp16)
    # float16: the conditions take half the bytes (the header is the same order of size)
    assert o["bytes_adapter"] - o["bytes_adapter_fp16"] >= 0.9 * 2 * o["params_conditions"]
    folder = builtin_backbone_dir(scene.variant) / "point_cloud"
    want = sum(os.path.getsize(os.path.join(d, f)) for d, _, files in os.walk(folder) for f in files)
    assert o["bytes_backbone"] == want > 0
    assert not any(p.name.startswith("k0") for p in tmp_path.iterdir())  # writes only its fp16 copy


# ----------------------------------------------------------------------------- run_bench

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

    phases = table_rows(text, "| optics |")
    assert [row[0] for row in phases] == list(PSF_MODES)
    for mode, p in r.phases.items():  # the PSF phase is timed by hooks on the real optics stage: > 0 in every mode
        assert all(math.isfinite(v) and v > 0 for v in p.values()), (mode, p)
        assert p["total"] >= sum(v for k, v in p.items() if k != "total") * 0.999

    knobs = table_rows(text, "| knob |")
    settings = [row[1] for row in knobs]
    assert set(PSF_MODES) <= set(settings)
    assert {f"N={n}" for n in COND_DIMS if n != 8} <= set(settings)
    assert {"+".join(m) for m in MODULE_SETS if len(m) < 3} <= set(settings)
    for row in knobs:
        positive(row[2])  # ms / iteration
        assert math.isfinite(float(row[3])) and math.isfinite(float(row[4]))
    ref = next(row for row in knobs if row[0] == "reference")
    assert float(ref[4]) == 0.0

    ss = table_rows(text, "| d |")
    assert [float(row[0]) for row in ss] == [1.0, 2.0]
    for row in ss:
        positive(row[1]), positive(row[2]), positive(row[3]), positive(row[4]), positive(row[5])

    overhead = table_rows(text, "| | SS-backbone |")
    assert [row[0] for row in overhead][:3] == ["render time (ms)", "parameters", "storage (float32)"]
    positive(overhead[0][1]), positive(overhead[0][2])
    assert r.overhead["bytes_adapter_fp16"] < r.overhead["bytes_adapter"]
    # reference adapter: N = 8 per anchor for each of the three modules, plus the projections
    assert r.overhead["params_conditions"] == r.info["anchors"] * 3 * 8 < r.overhead["params_adapter"]
    for doc, _, _ in PART_DOCS:
        assert f"]({doc})" in text


def test_bench_is_quiet_unless_asked_for_progress(capsys):
    """``run_bench(progress=False)`` (the default, as a library call) writes nothing to stderr or stdout;
    with ``progress=True`` it names its phases on stderr, starting with the phase timings."""
    s = BenchSettings(resolution=16, iterations=1, phase_iterations=1, repeats=1, test_views=1,
                      downsample=(1.0,), power_saving=(0.0,))
    run_bench(s)
    quiet = capsys.readouterr()
    assert (quiet.out, quiet.err) == ("", "")
    run_bench(s, progress=True)
    loud = capsys.readouterr()
    assert loud.out == ""
    assert loud.err.splitlines()[0] == "training phases"
