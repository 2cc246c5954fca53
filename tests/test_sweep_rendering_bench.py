"""``controlgs bench``'s pure parts pinned by number (issue 15 section 5): the Markdown report of a
hand-made result (every cell computed by hand in the comments), the settings' defaults and
refusals, the knob list, the interleaved median timer, and the phase clock's laps and hooks."""

from __future__ import annotations

import math
import os
from typing import Any

import pytest
import torch
from torch import nn

import controlgs_adapter.benchmarking.accuracy_time as at
from controlgs_adapter.benchmarking import STEP_PHASES, ClockedRasterizer, PhaseClock, clock_stage
from controlgs_adapter.benchmarking.accuracy_time import BenchResult, BenchSettings, _knob_configs, _median_times
from controlgs_adapter.benchmarking.report import PART_DOCS, format_report, write_report
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV
from controlgs_adapter.rendering.splatter import RasterOutput
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig


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


# ---------------------------------------------------------------- the report
def _result() -> BenchResult:
    phases = {
        "distortion": {"sample": 0.001, "decode": 0.002, "splat": 0.003, "stages": 0.004, "psf": 0.0005,
                       "loss": 0.0006, "backward": 0.007, "optimizer": 0.0008, "total": 0.020},
        "fast": {"sample": 0.001, "decode": 0.002, "splat": 0.003, "stages": 0.004, "psf": 0.0105,
                 "loss": 0.0006, "backward": 0.009, "optimizer": 0.0008, "total": 0.031},
    }
    knobs = [{"knob": "PSF operator (whole training)", "setting": "exact", "s_per_it": 0.0456, "psnr": 30.125, "ssim": 0.91234},
             {"knob": "reference", "setting": "ref", "s_per_it": 0.0123, "psnr": 31.0, "ssim": 0.95}]
    ss = [{"d": 1.0, "render_s_no_ss": 0.004, "render_s_ss": 0.004, "psnr_no_ss": 25.0, "psnr_ss": 25.0, "psnr_controlgs": 26.5},
          {"d": 2.5, "render_s_no_ss": 0.0012, "render_s_ss": 0.0041, "psnr_no_ss": 20.0, "psnr_ss": 24.25, "psnr_controlgs": 27.0}]
    overhead = {"render_s_ss": 0.010, "render_s_controlgs": 0.0125, "params_adapter": 2500.0, "params_conditions": 2400.0,
                "params_backbone": 100000.0, "bytes_adapter": 12000.0, "bytes_adapter_fp16": 6000.0,
                "bytes_backbone": 2_500_000.0}
    info = {"date": "2026-01-02", "nproc": 2, "threads": 1, "torch": "9.9", "scene": "ar", "anchors": 100,
            "resolution": 64, "phase_iterations": 40, "iterations": 100, "seed": 7, "test_views": 4, "repeats": 20,
            "downsample": (1.0, 2.5), "power_saving": (0.0, 0.4)}
    return BenchResult(phases=phases, knobs=knobs, ss=ss, overhead=overhead, info=info)


def test_format_report_cells_by_hand() -> None:
    text = format_report(_result(), "controlgs bench --x")
    lines = text.splitlines()
    assert lines[0] == "# Benchmarks: accuracy vs time"
    assert ("Generated by `controlgs bench --x` on 2026-01-02; machine: `nproc` = 2, torch threads = 1, torch 9.9. "
            "Built-in scene `ar` (100 anchors) at S = 64 px.") in lines
    # phases in ms with one decimal (0.0005 s = 0.5 ms); total vs distortion 0.031 / 0.020 = 1.55x
    assert "| optics | sample | decode | splat | stages | PSF | loss | backward | optimizer | total | total vs distortion |" in lines
    assert "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|" in lines
    assert "| distortion | 1.0 | 2.0 | 3.0 | 4.0 | 0.5 | 0.6 | 7.0 | 0.8 | 20.0 | 1.00x |" in lines
    assert "| fast | 1.0 | 2.0 | 3.0 | 4.0 | 10.5 | 0.6 | 9.0 | 0.8 | 31.0 | 1.55x |" in lines
    assert "median of 40 steps after a warm-up" in text
    # knobs: delta vs the reference row (whichever position it has): 30.125 - 31 = -0.875 -> -0.88 (.2f)
    assert "| PSF operator (whole training) | exact | 45.6 | 30.12 | -0.88 | 0.9123 |" in lines
    assert "| reference | ref | 12.3 | 31.00 | +0.00 | 0.9500 |" in lines
    assert "Each row trains an adapter for 100 iterations (seed 7, otherwise the Trainer's defaults) and evaluates it " \
           "on 4 test view(s) over the grid d in {1, 2.5} x rho in {0, 0.4}" in text
    # SS rows: d with :g, times in ms, PSNRs .2f
    assert "| 1 | 4.0 | 4.0 | 25.00 | 25.00 | 26.50 |" in lines
    assert "| 2.5 | 1.2 | 4.1 | 20.00 | 24.25 | 27.00 |" in lines
    assert "(median of 20 interleaved calls, no grad)" in text
    # overhead: 12.5 / 10 - 1 = +25.0 %; 2500 / 100000 = +2.5 %; 12000 B = 12.0 kB (< 1e6), 2.5e6 B = 2.50 MB;
    # 12000 / 2.5e6 = +0.5 %; 6000 B = 6.0 kB, 6000 / 2.5e6 = +0.2 % (0.24 rounded)
    assert "| render time (ms) | 10.0 | 12.5 | +25.0 % |" in lines
    assert "| parameters | 100000 | +2500 | +2.5 % |" in lines
    assert "| storage (float32) | 2.50 MB | +12.0 kB | +0.5 % |" in lines
    assert "| storage (adapter float16) | | +6.0 kB | +0.2 % |" in lines
    assert "(2400 = anchors x modules x N)" in text
    for doc, what, cmd in PART_DOCS:
        assert f"- [{doc}]({doc}): {what} (`{cmd}`)" in lines
    assert text.endswith(f"(`{PART_DOCS[-1][2]}`)\n")
    # section order: the module docstring's
    heads = [ln for ln in lines if ln.startswith("## ")]
    assert heads == ["## 1. Training time per iteration by phase", "## 2. Accuracy knobs: cost vs quality",
                     "## 3. Render overhead and storage (paper Tbl. 3)", "## 4. Per-part benchmarks"]


def test_format_report_size_unit_boundary() -> None:
    r = _result()
    # 999_999 B is still kB (999999 / 1e3 = 1000.0 kB), 1e6 B is MB (1.00 MB)
    r.overhead.update(bytes_backbone=1_000_000.0, bytes_adapter=999_999.0, bytes_adapter_fp16=500.0)
    lines = format_report(r, "c").splitlines()
    assert "| storage (float32) | 1.00 MB | +1000.0 kB | +100.0 % |" in lines
    assert "| storage (adapter float16) | | +0.5 kB | +0.1 % |" in lines  # 500 / 1e6 = 0.05 %: the float 0.05000000000000000277 rounds up to 0.1


def test_write_report_replaces_the_file(tmp_path: Any) -> None:
    path = tmp_path / "sub" / "bench.md"
    assert write_report("one\n", path) == path and path.read_text() == "one\n"
    write_report("two\n", str(path))
    assert path.read_text() == "two\n" and sorted(p.name for p in path.parent.iterdir()) == ["bench.md"]


# ---------------------------------------------------------------- the phase clock
def test_phase_clock_laps_use_the_time_between_calls(monkeypatch: pytest.MonkeyPatch) -> None:
    import controlgs_adapter.clock as clock_mod

    now = [10.0]
    monkeypatch.setattr(clock_mod.time, "perf_counter", lambda: now[0])
    clock = PhaseClock()
    assert clock.device is None and clock.laps == {}
    now[0] = 11.0
    clock.start()  # the time before start() does not count
    now[0] = 11.5
    clock.lap("a")
    now[0] = 13.5
    clock.lap("b")
    now[0] = 13.75
    clock.lap("a")
    assert clock.laps == {"a": 0.75, "b": 2.0} and list(clock.laps) == ["a", "b"] and clock.total == 2.75
    assert PhaseClock("cpu").device == torch.device("cpu")
    assert STEP_PHASES == ("sample", "render", "pipeline", "loss", "backward", "optimizer")


def test_clock_stage_laps_around_the_stage_and_removes_its_hooks() -> None:
    clock = PhaseClock()
    stage = nn.Identity()
    clock.start()
    with clock_stage(clock, stage, "psf", before="stages"):
        stage(torch.zeros(1))
    assert list(clock.laps) == ["stages", "psf"]
    assert not stage._forward_hooks and not stage._forward_pre_hooks
    clock.start()
    stage(torch.zeros(1))
    assert clock.laps == {}
    with pytest.raises(ZeroDivisionError), clock_stage(clock, stage, "x", before="y"):
        1 / 0  # noqa: B018 - an error inside the block still removes the hooks
    assert not stage._forward_hooks and not stage._forward_pre_hooks


def _gaussian_scene() -> tuple[tuple[torch.Tensor, ...], Camera]:
    k = torch.tensor([[8.0, 0.0, 4.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), k, 8, 8)
    g = (torch.tensor([[0.0, 0.0, 2.0]]), torch.full((1, 3), 0.2), torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
         torch.tensor([0.8]), torch.tensor([[1.0, 0.5, 0.25]]))
    return g, cam


def test_clocked_rasterizer_laps_and_renders_like_its_inner(monkeypatch: pytest.MonkeyPatch) -> None:
    from controlgs_adapter.rendering.splatter import rasterize

    g, cam = _gaussian_scene()
    clock = PhaseClock()
    clock.start()
    r = ClockedRasterizer(clock, "torch")
    assert r.name == "clocked" and r.inner == "torch"
    out = r(*g, cam, torch.tensor([0.0, 0.0, 1.0]))
    assert isinstance(out, RasterOutput) and list(clock.laps) == ["decode", "splat"]
    want = rasterize(*g, cam, torch.tensor([0.0, 0.0, 1.0]))
    assert torch.equal(out.color, want.color)  # the background is passed on
    # unavailable is the inner one's; None inner: $CONTROLGS_RASTERIZER, else auto
    assert r.unavailable(torch.device("cpu"), torch.float32) is None
    assert r.unavailable(torch.device("cpu"), torch.float16) == (
        "rasterizer 'torch' cannot render torch.float16 on cpu: needs float32 or float64, got torch.float16")
    monkeypatch.setenv(RASTERIZER_ENV, "nope")
    assert "rasterizer 'nope' is not registered" in str(ClockedRasterizer(clock).unavailable(torch.device("cpu"),
                                                                                            torch.float32))
    with pytest.raises(InputValueError, match="rasterizer 'nope' is not registered"):
        ClockedRasterizer(clock)(*g, cam)
    assert ClockedRasterizer(clock, "torch").unavailable(torch.device("cpu"), torch.float32) is None  # given: env ignored
    monkeypatch.setenv(RASTERIZER_ENV, "")
    assert ClockedRasterizer(clock).unavailable(torch.device("cpu"), torch.float32) is None  # empty: auto
    monkeypatch.delenv(RASTERIZER_ENV)
    assert ClockedRasterizer(clock).unavailable(torch.device("cpu"), torch.float32) is None
    assert math.isfinite(clock.total) and os.environ.get(RASTERIZER_ENV) is None


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


def test_ss_rows_read_the_rho_0_column_of_each_method(tiny: Any) -> None:
    """A hand-made grid (rho = 0 second, so its index matters): per-view PSNR base + 10 i + p + v / 2, whose
    view mean at (i, p) is base + 10 i + p + 0.25; the rows take p = 1 (rho = 0)."""
    from controlgs_adapter.evaluation import GridResult

    scene, model = tiny

    def psnr(base: float) -> dict[str, torch.Tensor]:
        i, p, v = torch.meshgrid(torch.arange(2.0), torch.arange(2.0), torch.arange(2.0), indexing="ij")
        return {"psnr": (base + 10 * i + p + 0.5 * v).double()}

    grid = GridResult(downsample=(1.0, 2.5), power_saving=(0.4, 0.0),
                      per_view={"no_ss": psnr(100.0), "ss": psnr(200.0), "k0": psnr(300.0)})
    import controlgs_adapter.rendering.protocol as protocol

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
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import builtin_backbone_dir

    scene, model = tiny
    cgs = ControlGS.wrap(model)  # lens, resample, display with N = 8
    adapter = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    import controlgs_adapter.rendering.protocol as protocol

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
