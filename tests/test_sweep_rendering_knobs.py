"""``controlgs bench``'s knob table (issue 15 section 5): the trainers and the evaluation it runs,
recorded as the real ones run (one iteration each on the built-in scene at 16 px)."""

from __future__ import annotations

from typing import Any

import pytest

import controlgs_adapter.benchmarking.accuracy_time as at
import controlgs_adapter.evaluation as evaluation
from controlgs_adapter.benchmarking.accuracy_time import BenchSettings, _knob_configs
from controlgs_adapter.training import Trainer


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
