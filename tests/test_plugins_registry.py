"""The registry calls hooks through pluggy (wrappers and tracing see them) and never serves a
stale lookup after a registration change."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from controlgs_adapter import hookimpl, plugins
from controlgs_adapter.backends.scaffold_gs import ScaffoldGSBackend


@pytest.fixture()
def pm(monkeypatch):
    monkeypatch.setenv("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", "1")
    plugins.reset_plugin_manager()
    yield plugins.get_plugin_manager()
    plugins.reset_plugin_manager()


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
