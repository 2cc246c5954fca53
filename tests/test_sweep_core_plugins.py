"""Issue 15 s.5 sweep, core area: plug-in autoload switches, entry points skipped when already
registered or blocked, a plug-in that fails after registering, load failures and the reset."""

from __future__ import annotations

import pytest

import controlgs_adapter
from controlgs_adapter import plugins
from controlgs_adapter.errors import PluginLoadError

from test_plugins_third_party import _FakeDistribution, _FakeEntryPoint, _GoodPlugin, _fake_distributions


@pytest.fixture()
def fresh(monkeypatch):
    monkeypatch.delenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", raising=False)
    monkeypatch.delenv("CONTROLGS_STRICT_PLUGINS", raising=False)
    plugins.reset_plugin_manager()
    yield
    plugins.reset_plugin_manager()


class _BadHook:
    """Registers, then fails pluggy's check: a hook implementation no specification knows."""

    @controlgs_adapter.hookimpl
    def controlgs_register_nothing(self):
        return []


@pytest.mark.parametrize("value, loaded", [("", True), ("0", True), ("1", False), ("yes", False)])
def test_autoload_switch(fresh, monkeypatch, value, loaded):
    _fake_distributions(monkeypatch, _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", _GoodPlugin())]))
    monkeypatch.setenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", value)
    assert ("sharpen_test" in plugins.stages()) is loaded
    assert (plugins.get_plugin_manager().get_plugin("acme") is not None) is loaded
    assert "scaffold_gs" in plugins.backends()  # built-ins always


def test_entry_points_already_registered_blocked_or_failing_late(fresh, monkeypatch):
    first, second = _GoodPlugin(), _GoodPlugin()
    _fake_distributions(monkeypatch,
                        _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", first)]),
                        _FakeDistribution("acme-fork", "9.9", [_FakeEntryPoint("acme", second)]),  # same name: skipped
                        _FakeDistribution("late-xr", "0.2", [_FakeEntryPoint("late", _BadHook())]))
    with pytest.warns(RuntimeWarning, match="plug-in 'late' from late-xr 0.2 failed to load") as rec:
        pm = plugins.get_plugin_manager()
    assert len(rec) == 1 and "(skipped; CONTROLGS_STRICT_PLUGINS=1 makes this fatal)" in str(rec[0].message)
    assert pm.get_plugin("acme") is first and plugins.stages()["sharpen_test"].source == "acme-xr 1.2.3"
    assert pm.get_plugin("late") is None  # registered, failed the check, unregistered again
    failures = plugins.load_failures()
    assert len(failures) == 1 and failures[0].startswith("plug-in 'late' from late-xr 0.2 failed to load: ")
    plugins.reset_plugin_manager()
    assert plugins._pm is None and plugins._sources == {} and plugins._failures == []


def test_blocked_entry_point_is_not_loaded(fresh, monkeypatch):
    _fake_distributions(monkeypatch, _FakeDistribution("acme-xr", "1.2.3", [_FakeEntryPoint("acme", _GoodPlugin())]))
    pm = plugins.PluginManager(controlgs_adapter.hookspecs.PROJECT)
    pm.add_hookspecs(controlgs_adapter.hookspecs)
    pm.set_blocked("acme")
    plugins._load_entry_points(pm, strict=True)
    assert pm.get_plugin("acme") is None and pm.is_blocked("acme")
    with pytest.raises(PluginLoadError, match="plug-in 'late' from late-xr 0.2 failed to load"):
        _fake_distributions(monkeypatch, _FakeDistribution("late-xr", "0.2", [_FakeEntryPoint("late", _BadHook())]))
        plugins._load_entry_points(pm, strict=True)


def test_builtin_plugin_order_and_sources(fresh, monkeypatch):
    monkeypatch.setenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", "1")
    assert plugins.BUILTIN_PLUGINS == ("controlgs_adapter.builtin", "controlgs_adapter.backends.builtin",
                                       "controlgs_adapter.downstream.builtin", "controlgs_adapter.rendering.builtin")
    assert plugins.ENTRY_POINT_GROUP == "controlgs_adapter"
    infos = plugins.plugin_report()
    assert {i.source for i in infos} == {"controlgs-adapter (built-in)"}
    assert list(plugins.schedules()) == ["lens", "resample", "display", "foveation"]
    name = plugins.register_plugin(_GoodPlugin())
    assert plugins.stages()["sharpen_test"].plugin == name and plugins.stages()["sharpen_test"].source == "runtime"
    plugins.unregister_plugin(name)
    assert "sharpen_test" not in plugins.stages()
