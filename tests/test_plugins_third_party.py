"""A third-party plug-in end to end (register, listed by ``controlgs plugins``, used) and
entry-point loading from (fake) installed distributions."""

from __future__ import annotations

import importlib.metadata
import importlib.util
from pathlib import Path

import pytest
import torch

import controlgs_adapter
from controlgs_adapter import ControlGS, RuntimeState, cli, plugins
from controlgs_adapter.errors import PluginLoadError

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "third_party_plugin.py"


@pytest.fixture()
def fresh_plugins(monkeypatch):
    monkeypatch.delenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    monkeypatch.delenv("CONTROLGS_STRICT_PLUGINS", raising=False)
    plugins.reset_plugin_manager()
    yield
    plugins.reset_plugin_manager()


@pytest.fixture()
def example():
    spec = importlib.util.spec_from_file_location("third_party_plugin_example", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_example_plugin_registers_lists_and_works(fresh_plugins, example, capsys):
    plugins.register_plugin(example, name="tiny_ng_example")
    assert cli.main(["plugins"]) == 0
    listing = capsys.readouterr().out
    rows = [line.split()[:4] for line in listing.splitlines()]
    assert ["backend", "tiny_ng", "tiny_ng_example", "runtime"] in rows
    assert ["stage", "vignette", "tiny_ng_example", "runtime"] in rows
    assert rows.index(["backend", "tiny_ng", "tiny_ng_example", "runtime"]) < rows.index(
        ["backend", "scaffold_gs", "controlgs_adapter.backends.builtin", "built-in"])  # plug-ins are tried first
    assert "Darkens the image towards the corners" in listing  # the stage's own description

    # the custom backend wraps its family (first match: plug-ins come before the built-ins)
    model = example.TinyNeuralGaussians(num_anchors=20)
    x = model.features
    with torch.no_grad():
        bare = model.head(x)
    cgs = ControlGS.wrap(model, modules=("resample",))
    assert cgs.backend.name == "tiny_ng" and [t.fc1 for t in cgs.targets] == ["head.0"]
    with torch.no_grad():
        cgs.injector.condition("resample").normal_()
        with cgs.conditioned(RuntimeState(downsample=8.0)):
            conditioned = model.head(x)
    assert not torch.equal(conditioned, bare)
    cgs.unwrap()

    # the custom stage runs in the pipeline, inserted by its order
    from controlgs_adapter.downstream.pipeline import Pipeline

    stage_cls = plugins.stages()["vignette"].obj
    assert stage_cls is example.VignetteStage
    pipeline = Pipeline.from_config({"lens": True, "vignette": {"strength": 0.5}, "resample": True, "oled": False})
    assert pipeline.names.index("vignette") == pipeline.names.index("lens") + 1
    image = torch.full((3, 8, 8), 0.5)
    direct = example.VignetteStage(0.5)(image, RuntimeState(), None)
    assert float(direct[0, 0, 0]) < float(direct[0, 4, 4]) <= 0.5
    eye = Pipeline.from_config({"vignette": {"strength": 0.5}, "oled": False})(image, RuntimeState())
    assert float(eye[0, 0, 0]) < float(eye[0, 4, 4])


class _FakeEntryPoint:
    def __init__(self, name, target, group=plugins.ENTRY_POINT_GROUP):
        self.name, self.group, self._target = name, group, target

    def load(self):
        if isinstance(self._target, BaseException):
            raise self._target
        return self._target


class _FakeDistribution:
    def __init__(self, name, version, entry_points):
        self.metadata = {"name": name}
        self.version = version
        self.entry_points = entry_points


class _GoodPlugin:
    @controlgs_adapter.hookimpl
    def controlgs_register_stages(self):
        from controlgs_adapter.downstream.stage import Stage

        class Sharpen(Stage):
            name = "sharpen_test"

            def forward(self, image, state, ctx):
                return image

        return [Sharpen]


def _fake_distributions(monkeypatch, *dists):
    real = importlib.metadata.distributions
    monkeypatch.setattr(importlib.metadata, "distributions", lambda: [*real(), *dists])


def test_entry_point_plugins_load_with_their_distribution(fresh_plugins, monkeypatch):
    _fake_distributions(monkeypatch, _FakeDistribution("acme-xr", "1.2.3", [
        _FakeEntryPoint("acme", _GoodPlugin()),
        _FakeEntryPoint("unrelated", ImportError("never loaded"), group="other_group"),
    ]))
    info = plugins.stages()["sharpen_test"]
    assert (info.plugin, info.source) == ("acme", "acme-xr 1.2.3")
    assert plugins.load_failures() == []


def test_a_broken_plugin_is_reported_and_skipped_or_fatal_in_strict_mode(fresh_plugins, monkeypatch, capsys):
    _fake_distributions(monkeypatch, _FakeDistribution("broken-xr", "0.1", [
        _FakeEntryPoint("broken", ModuleNotFoundError("No module named 'cupy'")),
    ]), _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", _GoodPlugin())]))
    with pytest.warns(RuntimeWarning, match="'broken' from broken-xr 0.1 failed to load"):
        plugins.get_plugin_manager()
    assert "sharpen_test" in plugins.stages() and "scaffold_gs" in plugins.backends()  # the host still works
    assert cli.main(["plugins"]) == 0
    assert "FAILED: plug-in 'broken' from broken-xr 0.1 failed to load: ModuleNotFoundError" in capsys.readouterr().out

    plugins.reset_plugin_manager()
    with pytest.raises(PluginLoadError, match="'broken' from broken-xr 0.1.*cupy"):
        plugins.get_plugin_manager(strict=True)
    plugins.reset_plugin_manager()
    monkeypatch.setenv("CONTROLGS_STRICT_PLUGINS", "1")
    capsys.readouterr()
    assert cli.main(["plugins"]) == 1
    assert "'broken' from broken-xr 0.1 failed to load" in capsys.readouterr().err


def _stage_named(stage_name: str) -> type:
    from controlgs_adapter.downstream.stage import Stage

    return type(f"Stage_{stage_name}", (Stage,), {"name": stage_name, "forward": lambda self, image, state, ctx: image})


class _StagePlugin:
    def __init__(self, stage_name: str) -> None:
        self.stage = _stage_named(stage_name)

    @controlgs_adapter.hookimpl
    def controlgs_register_stages(self):
        return [self.stage]


def test_a_name_registered_twice(fresh_plugins, monkeypatch, tmp_path):
    lens = _StagePlugin("lens")  # a third-party stage named as a built-in one replaces it, with a warning
    plugins.register_plugin(lens, name="my_lens")
    with pytest.warns(UserWarning, match="stage 'lens' from my_lens \\(runtime\\) replaces the built-in"):
        assert plugins.stages()["lens"].obj is lens.stage
    plugins.register_plugin(_StagePlugin("lens"), name="other_lens")  # two third-party ones: refused, both named
    with pytest.raises(PluginLoadError, match="stage 'lens' is registered twice: by other_lens \\(runtime\\) and "
                                              "my_lens \\(runtime\\)"):
        plugins.stages()
    plugins.reset_plugin_manager()  # two built-in modules with one name: refused too
    (tmp_path / "dup_builtin_stage.py").write_text(
        "from controlgs_adapter.hookspecs import hookimpl\n"
        "from controlgs_adapter.downstream.lens import LensPrewarp\n\n"
        "@hookimpl(trylast=True)\ndef controlgs_register_stages():\n    return [LensPrewarp]\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(plugins, "BUILTIN_PLUGINS", (*plugins.BUILTIN_PLUGINS, "dup_builtin_stage"))
    with pytest.raises(PluginLoadError, match="stage 'lens' is registered twice: by .*built-in"):
        plugins.stages()


@pytest.mark.parametrize("value, strict", [("0", False), ("", False), ("1", True), ("yes", True)])
def test_strict_plugins_environment_variable(fresh_plugins, monkeypatch, value, strict):
    _fake_distributions(monkeypatch, _FakeDistribution("broken-xr", "0.1", [
        _FakeEntryPoint("broken", ModuleNotFoundError("No module named 'cupy'"))]))
    monkeypatch.setenv("CONTROLGS_STRICT_PLUGINS", value)
    if strict:
        with pytest.raises(PluginLoadError, match="'broken' from broken-xr 0.1"):
            plugins.get_plugin_manager()
    else:
        with pytest.warns(RuntimeWarning, match="'broken' from broken-xr 0.1 failed to load"):
            plugins.get_plugin_manager()


def test_register_blocked_unregister_and_report(fresh_plugins):
    pm = plugins.get_plugin_manager()
    pm.set_blocked("blocked_one")
    with pytest.raises(PluginLoadError, match="plug-in 'blocked_one' is blocked"):
        plugins.register_plugin(_StagePlugin("never"), name="blocked_one")
    plugins.register_plugin(_StagePlugin("extra_stage"), name="mine")
    info = plugins.stages()["extra_stage"]
    assert (info.kind, info.plugin, info.source) == ("stage", "mine", "runtime")
    report = plugins.plugin_report()
    assert [i for i in report if i.name == "extra_stage"] == [info]
    assert {i.kind for i in report} == {"backend", "stage", "schedule", "rasterizer"}
    plugins.unregister_plugin("mine")
    assert "extra_stage" not in plugins.stages() and pm.get_plugin("mine") is None
