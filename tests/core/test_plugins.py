"""The plug-in manager: built-ins register through the same hooks as plug-ins, installed plug-ins load
from their entry points (switched off, blocked, broken or strict), runtime registration, the caches
of what is registered, the choice of a backend for a model and of a rasterizer."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from helpers.splat_scenes import gaussian_cloud
import torch
from helpers.fake_plugins import _fake_distributions, _FakeDistribution, _FakeEntryPoint, _GoodPlugin
from helpers.scaffold_standin import ScaffoldStandIn
from torch import nn

import controlgs_adapter
from controlgs_adapter import plugins
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend
from controlgs_adapter.downstream.stage import Stage
from controlgs_adapter.errors import NoMatchingBackendError, PluginLoadError
from controlgs_adapter.hookspecs import hookimpl
from controlgs_adapter.plugins import _describe
from controlgs_adapter.rendering.rasterizers import Rasterizer, TorchSplatter, rasterize_gaussians


def test_stages_are_plain_modules_with_functional_twins():
    """Every built-in stage runs as ``stage(image)`` (default state, the image's size as native
    size) and has a functional twin named after it in snake case (kornia's scheme)."""
    import re

    import controlgs_adapter.downstream as ds
    import controlgs_adapter.downstream.optics as dso

    image = torch.rand(1, 3, 12, 12, dtype=torch.float64)
    for name, info in plugins.stages().items():
        if info.source != plugins.BUILTIN_DIST:
            continue
        cls = info.obj
        twin = re.sub(r"(?<=[a-z])(?=[A-Z])|(?<=[A-Z])(?=[A-Z][a-z])", "_", cls.__name__).lower()
        assert callable(getattr(ds, twin, None) or getattr(dso, twin, None)), (cls.__name__, twin)
        if name in ("optics", "display") or cls is ds.LensPrewarp:
            continue  # need a bank / run at the default state below
        out = cls()(image)
        assert out.shape == image.shape
    assert torch.equal(ds.DisplayMapping()(image), ds.display_mapping(image, 0.0))


@pytest.fixture()
def pm(fresh_plugins, monkeypatch):
    """A fresh plug-in manager holding the built-ins only."""
    monkeypatch.setenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", "1")
    return plugins.get_plugin_manager()


class _Extra(ScaffoldGSBackend):
    name = "extra_family"


class _Plugin:
    @hookimpl
    def controlgs_register_backends(self):
        return [_Extra()]


def test_plain_pm_register_after_a_lookup_is_visible(pm):
    assert "extra_family" not in plugins.backends()  # a first lookup fills the cache
    plugin = _Plugin()
    pm.register(plugin, name="extra")  # pluggy's own call, not register_plugin
    assert "extra_family" in plugins.backends()
    assert list(plugins.backends())[0] == "extra_family"  # plug-ins are tried before the built-ins
    pm.unregister(plugin)
    assert "extra_family" not in plugins.backends()


def test_hookwrapper_and_tracing_see_the_calls(pm):
    seen: list[str] = []

    class Wrapper:
        @hookimpl(wrapper=True)
        def controlgs_register_backends(self):
            result = yield
            seen.append(f"wrapped {len(result)}")
            return result

    plugins.backends()
    pm.register(Wrapper(), name="wrapper")
    traced: list[str] = []
    undo = pm.add_hookcall_monitoring(lambda name, impls, kwargs: traced.append(name), lambda *a: None)
    backends = plugins.backends()
    assert seen == ["wrapped 1"] and traced == ["controlgs_register_backends"]
    assert backends["scaffold_gs"].plugin == "controlgs_adapter.backends.builtin"
    plugins.backends()  # cached: no second call
    assert seen == ["wrapped 1"]
    undo()


def test_implementation_returning_none_is_attributed(pm):
    class Nothing:
        @hookimpl
        def controlgs_register_backends(self):
            return None

    pm.register(Nothing(), name="nothing")
    pm.register(_Plugin(), name="extra")
    found = plugins.backends()
    assert found["extra_family"].plugin == "extra" and found["scaffold_gs"].source == plugins.BUILTIN_DIST


def test_blocking_drops_the_cache(pm):
    pm.register(SimpleNamespace(controlgs_register_backends=hookimpl(lambda: [_Extra()])), name="ns")
    assert "extra_family" in plugins.backends()
    pm.unregister(name="ns")
    pm.set_blocked("ns")
    assert "extra_family" not in plugins.backends()


def _stage_named(stage_name: str) -> type:
    return type(f"Stage_{stage_name}", (Stage,), {"name": stage_name, "forward": lambda self, image, state, ctx: image})


class _StagePlugin:
    def __init__(self, stage_name: str) -> None:
        self.stage = _stage_named(stage_name)

    @controlgs_adapter.hookimpl
    def controlgs_register_stages(self):
        return [self.stage]


def test_a_stage_name_registered_twice_replaces_a_builtin_or_is_refused(fresh_plugins, monkeypatch, tmp_path):
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
def test_strict_plugins_variable_makes_a_broken_plugin_fatal(fresh_plugins, monkeypatch, value, strict):
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
    name = plugins.register_plugin(_GoodPlugin())  # without a name: one is made up and returned
    assert plugins.stages()["sharpen_test"].plugin == name and pm.get_plugin(name) is not None
    plugins.unregister_plugin(name)
    assert "sharpen_test" not in plugins.stages()


def test_builtin_rasterizers_are_registered_through_the_hook_and_listed():
    names = list(plugins.rasterizers())
    assert names == ["gsplat", "torch"]  # the automatic choice tries gsplat first, torch always works
    assert {(i.kind, i.name) for i in plugins.plugin_report() if i.kind == "rasterizer"} == {
        ("rasterizer", "gsplat"), ("rasterizer", "torch")}
    assert all(i.source == plugins.BUILTIN_DIST for i in plugins.rasterizers().values())


def test_a_plugin_rasterizer_goes_first(fresh_plugins):
    class Counting(Rasterizer):
        """Counts renders, then splats with the torch splatter."""

        name = "counting"
        calls = 0

        def unavailable(self, device, dtype):
            return None

        def __call__(self, *args):
            Counting.calls += 1
            return TorchSplatter()(*args)

    class Plugin:
        @hookimpl
        def controlgs_register_rasterizers(self):
            return [Counting()]

    name = plugins.register_plugin(Plugin(), name="counting-rasterizer")
    try:
        assert list(plugins.rasterizers())[0] == "counting"
        scene, cam = gaussian_cloud()
        rasterize_gaussians(*scene, cam)
        assert Counting.calls == 1
    finally:
        plugins.unregister_plugin(name)
    assert "counting" not in plugins.rasterizers()


class _BadHook:
    """Registers, then fails pluggy's check: a hook implementation no specification knows."""

    @controlgs_adapter.hookimpl
    def controlgs_register_nothing(self):
        return []


@pytest.mark.parametrize("value, loaded", [("", True), ("0", True), ("1", False), ("yes", False)])
def test_entry_points_load_with_their_distribution_unless_autoload_is_off(fresh_plugins, monkeypatch, value, loaded):
    """CONTROLGS_DISABLE_PLUGIN_AUTOLOAD: an installed plug-in's entry point (of this group only) is
    registered under its name, attributed to its distribution; the built-ins are always there."""
    _fake_distributions(monkeypatch, _FakeDistribution("acme-xr", "1.2.3", [
        _FakeEntryPoint("acme", _GoodPlugin()),
        _FakeEntryPoint("unrelated", ImportError("never loaded"), group="other_group"),
    ]))
    monkeypatch.setenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", value)
    assert ("sharpen_test" in plugins.stages()) is loaded
    assert (plugins.get_plugin_manager().get_plugin("acme") is not None) is loaded
    if loaded:
        info = plugins.stages()["sharpen_test"]
        assert (info.plugin, info.source) == ("acme", "acme-xr 1.2.3")
    assert plugins.load_failures() == []
    assert "scaffold_gs" in plugins.backends()  # built-ins always


def test_entry_points_already_registered_blocked_or_failing_late(fresh_plugins, monkeypatch):
    first, second = _GoodPlugin(), _GoodPlugin()
    _fake_distributions(monkeypatch,
                        _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", first)]),
                        _FakeDistribution("acme-fork", "9.9", [_FakeEntryPoint("acme", second)]),  # same name: skipped
                        _FakeDistribution("late-xr", "0.2", [_FakeEntryPoint("late", _BadHook())]))
    with pytest.warns(RuntimeWarning, match="plug-in 'late' from late-xr 0.2 failed to load") as rec:
        pm = plugins.get_plugin_manager()
    assert len(rec) == 1 and "CONTROLGS_STRICT_PLUGINS=1" in str(rec[0].message)
    assert pm.get_plugin("acme") is first and plugins.stages()["sharpen_test"].source == "acme-xr 1.2.3"
    assert pm.get_plugin("late") is None  # registered, failed the check, unregistered again
    failures = plugins.load_failures()
    assert len(failures) == 1 and failures[0].startswith("plug-in 'late' from late-xr 0.2 failed to load: ")
    plugins.reset_plugin_manager()
    assert plugins._pm is None and plugins._sources == {} and plugins._failures == []


def test_blocked_entry_point_is_not_loaded(fresh_plugins, monkeypatch):
    _fake_distributions(monkeypatch, _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", _GoodPlugin())]))
    pm = plugins.PluginManager(controlgs_adapter.hookspecs.PROJECT)
    pm.add_hookspecs(controlgs_adapter.hookspecs)
    pm.set_blocked("acme")
    plugins._load_entry_points(pm, strict=True)
    assert pm.get_plugin("acme") is None and pm.is_blocked("acme")
    with pytest.raises(PluginLoadError, match="plug-in 'late' from late-xr 0.2 failed to load"):
        _fake_distributions(monkeypatch, _FakeDistribution("late-xr", "0.2", [_FakeEntryPoint("late", _BadHook())]))
        plugins._load_entry_points(pm, strict=True)


def test_builtin_plugin_order_and_sources(fresh_plugins, monkeypatch):
    monkeypatch.setenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", "1")
    assert plugins.BUILTIN_PLUGINS == ("controlgs_adapter.builtin", "controlgs_adapter.backends.builtin",
                                       "controlgs_adapter.downstream.builtin", "controlgs_adapter.rendering.builtin")
    assert plugins.ENTRY_POINT_GROUP == "controlgs_adapter"
    infos = plugins.plugin_report()
    assert {i.source for i in infos} == {"controlgs-adapter (built-in)"}
    assert list(plugins.schedules()) == ["lens", "resample", "display", "foveation"]


class _Picky(ScaffoldGSBackend):
    """Picky test backend: recognises only models with a ``picky`` attribute.

    A second paragraph that the listing leaves out."""

    name = "picky"

    def matches(self, model):
        return hasattr(model, "picky")


def test_select_backend_names_what_each_backend_looks_for():
    """A backend is described by its name and the first paragraph of its docstring (else its class name);
    a refusal lists the registered backends in the order they are tried, or the chosen one."""
    model = ScaffoldStandIn(4, seed=0)
    assert plugins.select_backend(model).name == "scaffold_gs"  # the first that recognises it
    assert plugins.select_backend(model, "scaffold_gs") is plugins.backends()["scaffold_gs"].obj
    picky = _Picky()
    assert plugins.select_backend(SimpleNamespace(picky=1), picky) is picky  # an instance is used as given
    assert _describe(picky) == "picky: Picky test backend: recognises only models with a ``picky`` attribute"
    assert _describe(type("NoDoc", (ScaffoldGSBackend,), {"name": "nodoc", "__doc__": None})()) == "nodoc: NoDoc"
    listing = "".join(f"\n  - {_describe(info.obj)}" for info in plugins.backends().values())
    assert "scaffold_gs: Scaffold-GS layout" in listing and "mlp_color" in listing

    class NotAModel:
        mlp_opacity = nn.Linear(3, 3)

    with pytest.raises(NoMatchingBackendError) as e:
        plugins.select_backend(NotAModel())
    assert str(e.value).startswith("no registered backend recognises a NotAModel") and str(e.value).endswith(listing)
    for name in ("no_such_family", 5):
        with pytest.raises(NoMatchingBackendError) as e:
            plugins.select_backend(model, name)
        assert str(e.value).startswith(f"backend {name!r} is not registered") and str(e.value).endswith(listing)
    with pytest.raises(NoMatchingBackendError, match=r"scaffold_gs: Scaffold-GS layout.* does not recognise a SimpleNamespace"):
        plugins.select_backend(SimpleNamespace(mlp_cov=nn.Linear(2, 2)), "scaffold_gs")
    with pytest.raises(NoMatchingBackendError, match="picky: Picky test backend.* does not recognise a ScaffoldStandIn"):
        plugins.select_backend(model, picky)
