"""The plug-in manager (pluggy), following pytest's model.

Built-in backends, stages, schedules and rasterizers are plug-in modules listed in :data:`BUILTIN_PLUGINS`,
registered through the same hooks a third party uses. Installed plug-ins come from the
entry-point group ``controlgs_adapter``; one that fails to load is reported (name and
distribution) and skipped, unless strict mode is on (``strict=True`` or
``CONTROLGS_STRICT_PLUGINS=1``), where it raises :class:`PluginLoadError`.
``CONTROLGS_DISABLE_PLUGIN_AUTOLOAD=1`` skips entry points entirely.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import os
from dataclasses import dataclass
from typing import Any, Callable

import pluggy

from . import hookspecs
from .backend import Backend
from .errors import NoMatchingBackendError, PluginLoadError, warn_user

__all__ = [
    "BUILTIN_PLUGINS", "ENTRY_POINT_GROUP", "PluginInfo", "PluginManager", "get_plugin_manager", "register_plugin",
    "unregister_plugin", "backends", "stages", "schedules", "rasterizers", "plugin_report", "load_failures", "reset_plugin_manager",
    "select_backend",
]

ENTRY_POINT_GROUP = "controlgs_adapter"
BUILTIN_DIST = "controlgs-adapter (built-in)"

#: Modules of built-in plug-ins, registered in this order (later ones are called first by pluggy).
BUILTIN_PLUGINS: tuple[str, ...] = (
    "controlgs_adapter.builtin",
    "controlgs_adapter.backends.builtin",
    "controlgs_adapter.downstream.builtin",
    "controlgs_adapter.rendering.builtin",
)


@dataclass(frozen=True)
class PluginInfo:
    """What one registered item is and where it comes from."""

    kind: str  # "backend" | "stage" | "schedule" | "rasterizer"
    name: str
    plugin: str  # the plug-in's registered name
    source: str  # distribution "name version", "controlgs-adapter (built-in)" or "runtime"
    obj: Any


class PluginManager(pluggy.PluginManager):
    """pluggy's manager plus the registry's lookup cache, which every registration change drops
    (``register``, ``unregister``, ``set_blocked``), so a plain ``pm.register(obj)`` is seen by the
    next :func:`backends` / :func:`stages` / ... call."""

    def __init__(self, project_name: str) -> None:
        super().__init__(project_name)
        self.lookup_cache: dict[str, dict[str, PluginInfo]] = {}

    def register(self, plugin: Any, name: str | None = None) -> str | None:
        self.lookup_cache.clear()
        return super().register(plugin, name=name)

    def unregister(self, plugin: Any | None = None, name: str | None = None) -> Any | None:
        self.lookup_cache.clear()
        return super().unregister(plugin, name=name)

    def set_blocked(self, name: str) -> None:
        self.lookup_cache.clear()
        super().set_blocked(name)


_pm: PluginManager | None = None
_sources: dict[str, str] = {}
_failures: list[str] = []


def _strict_default() -> bool:
    return os.environ.get("CONTROLGS_STRICT_PLUGINS", "") not in ("", "0")


def get_plugin_manager(*, strict: bool | None = None) -> PluginManager:
    """The process-wide plug-in manager (built on first use)."""
    global _pm
    if _pm is None:
        strict = _strict_default() if strict is None else strict
        pm = PluginManager(hookspecs.PROJECT)
        pm.add_hookspecs(hookspecs)
        for mod in BUILTIN_PLUGINS:
            pm.register(importlib.import_module(mod), name=mod)
            _sources[mod] = BUILTIN_DIST
        if os.environ.get("CONTROLGS_DISABLE_PLUGIN_AUTOLOAD", "") in ("", "0"):
            _load_entry_points(pm, strict)
        _pm = pm
    return _pm


def reset_plugin_manager() -> None:
    """Forget the manager, run-time plug-ins and load failures: the next use rebuilds it (and reads
    the entry points again). For tests and long-running hosts that install plug-ins."""
    global _pm
    _pm = None
    _sources.clear()
    _failures.clear()


def _load_entry_points(pm: pluggy.PluginManager, strict: bool) -> None:
    for dist in importlib.metadata.distributions():
        for ep in dist.entry_points:
            if ep.group != ENTRY_POINT_GROUP or pm.get_plugin(ep.name) is not None or pm.is_blocked(ep.name):
                continue
            dist_name = f"{dist.metadata['name']} {dist.version}"
            try:
                pm.register(ep.load(), name=ep.name)
                pm.check_pending()
            except Exception as e:  # noqa: BLE001 - a broken plug-in must not break the host
                msg = f"plug-in {ep.name!r} from {dist_name} failed to load: {type(e).__name__}: {e}"
                if strict:
                    raise PluginLoadError(msg) from e
                if pm.get_plugin(ep.name) is not None:
                    pm.unregister(name=ep.name)
                _failures.append(msg)
                warn_user(msg + " (skipped; CONTROLGS_STRICT_PLUGINS=1 makes this fatal)", RuntimeWarning)
                continue
            _sources[ep.name] = dist_name


def register_plugin(plugin: Any, name: str | None = None) -> str:
    """Register a plug-in object or module at run time; returns its registered name."""
    pm = get_plugin_manager()
    registered = pm.register(plugin, name=name)
    if registered is None:
        raise PluginLoadError(f"plug-in {name or plugin!r} is blocked")
    pm.check_pending()
    _sources[registered] = "runtime"
    return registered


def unregister_plugin(name: str) -> None:
    """Remove a run-time registered plug-in by name."""
    get_plugin_manager().unregister(name=name)
    _sources.pop(name, None)


def load_failures() -> list[str]:
    """Messages of installed plug-ins that failed to load (non-strict mode)."""
    get_plugin_manager()
    return list(_failures)


def _attributed(pm: PluginManager, hook_name: str) -> list[tuple[str, Any]]:
    """Call the hook through pluggy (so hook wrappers and tracing apply) and pair each result with
    the plug-in that returned it, in call order (last registered first, ``trylast`` built-ins last)."""
    caller = getattr(pm.hook, hook_name)
    impls = [i for i in reversed(caller.get_hookimpls()) if not (i.hookwrapper or i.wrapper)]
    results = caller()
    if len(results) == len(impls):
        return [(pm.get_name(i.plugin) or repr(i.plugin), r) for i, r in zip(impls, results)]
    # some implementation returned None (pluggy drops those): attribute plug-in by plug-in, still through pluggy
    out: list[tuple[str, Any]] = []
    plugins = [i.plugin for i in impls]
    for impl in impls:
        sub = pm.subset_hook_caller(hook_name, remove_plugins=[p for p in plugins if p is not impl.plugin])
        out += [(pm.get_name(impl.plugin) or repr(impl.plugin), r) for r in sub()]
    return out


def _collect(kind: str, hook_name: str, key: Callable[[Any], str]) -> dict[str, PluginInfo]:
    pm = get_plugin_manager()
    cached = pm.lookup_cache.get(kind)
    if cached is not None:
        return cached
    out: dict[str, PluginInfo] = {}
    for plugin_name, objs in _attributed(pm, hook_name):
        source = _sources.get(plugin_name, "runtime")
        for obj in objs or ():
            name = key(obj)
            prev = out.get(name)
            if prev is not None:
                if source == BUILTIN_DIST and prev.source != BUILTIN_DIST:
                    warn_user(f"{kind} {name!r} from {prev.plugin} ({prev.source}) replaces the built-in", UserWarning)
                    continue
                raise PluginLoadError(
                    f"{kind} {name!r} is registered twice: by {prev.plugin} ({prev.source}) and {plugin_name} ({source})"
                )
            out[name] = PluginInfo(kind, name, plugin_name, source, obj)
    pm.lookup_cache[kind] = out
    return out


def backends() -> dict[str, PluginInfo]:
    """Registered backends by name, in the order ``ControlGS.wrap`` tries them."""
    return _collect("backend", "controlgs_register_backends", lambda b: b.name)


def _describe(backend: Backend) -> str:
    """``name: first paragraph of the backend's docstring`` (what the backend looks for)."""
    para = (type(backend).__doc__ or "").strip().split("\n\n")[0]
    return f"{backend.name}: {' '.join(para.split()).rstrip('.') or type(backend).__qualname__}"


def select_backend(model: Any, backend: str | Backend | None = None) -> Backend:
    """The backend that adapts ``model``: ``backend`` itself (an instance), the registered backend
    of that name, or (None) the first registered one whose ``matches(model)`` is true, in
    :func:`backends` order (plug-ins before built-ins).

    Raises:
        NoMatchingBackendError: no registered backend recognises the model, the named one is not
            registered, or the chosen one does not recognise the model (listing the registered ones).
    """
    if isinstance(backend, Backend):
        chosen = backend
    else:
        registered = {name: info.obj for name, info in backends().items()}
        listing = "".join(f"\n  - {_describe(b)}" for b in registered.values()) or " none"
        if backend is None:
            for b in registered.values():
                if b.matches(model):
                    return b
            raise NoMatchingBackendError(
                f"no registered backend recognises a {type(model).__name__}; registered backends (tried in this order):{listing}"
            )
        if backend not in registered:
            raise NoMatchingBackendError(f"backend {backend!r} is not registered; registered backends:{listing}")
        chosen = registered[backend]
    if not chosen.matches(model):
        raise NoMatchingBackendError(f"backend {_describe(chosen)} does not recognise a {type(model).__name__}")
    return chosen


def stages() -> dict[str, PluginInfo]:
    """Registered downstream stage classes by name."""
    return _collect("stage", "controlgs_register_stages", lambda s: s.name)


def schedules() -> dict[str, PluginInfo]:
    """Registered strength schedules by module name."""
    return _collect("schedule", "controlgs_register_schedules", lambda s: s.name)


def rasterizers() -> dict[str, PluginInfo]:
    """Registered rasterizers by name, in the order the automatic choice tries them."""
    return _collect("rasterizer", "controlgs_register_rasterizers", lambda r: r.name)


def plugin_report() -> list[PluginInfo]:
    """Everything registered, for ``controlgs plugins``."""
    return [*backends().values(), *stages().values(), *schedules().values(), *rasterizers().values()]
