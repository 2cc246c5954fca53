"""The core's layers (docs/reference/conventions.md, "Layers"): imports only go down, none closes a cycle.

The import graph is built from the source with ``ast``: module-level imports (class bodies, ``try``
and ``if`` blocks included; ``if TYPE_CHECKING:`` blocks left out, they never run), relative imports
resolved, ``from pkg import name`` resolved to the submodule ``pkg.name`` where there is one. It
covers the whole package, ``backends/`` and ``downstream/`` included (through their symlinks).
"""

from __future__ import annotations

import ast
import functools
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import controlgs_adapter

PACKAGE = "controlgs_adapter"
ROOT = Path(controlgs_adapter.__file__).resolve().parent

#: the core modules by layer; a module imports only from its own layer and the ones below
LAYERS: dict[int, tuple[str, ...]] = {
    # 1. foundation: errors, checks, states, file readers that know no model, the splatter, the clock
    1: ("_version", "errors", "checks", "state", "seeding", "lock", "extras", "clock", "injector", "cvvdp_shim", "metrics",
        "losses",
        "formats.safetensors", "formats.torchscript_layers", "formats.torchscript_live", "formats.torchscript",
        "formats.backbone", "formats.decoders", "formats.layout",
        "rendering.splatter"),
    # 2. contracts: import no registry, register nothing
    2: ("backend", "schedules", "rendering.rasterizer", "rendering.renderer", "downstream.stage"),
    # 3. the plug-in system: markers and hook specifications, the manager (select_backend), the rasterizer choice
    3: ("hookspecs", "plugins", "rendering.rasterizers"),
    # 4. the built-ins, registered through the hooks
    4: ("builtin", "rendering.builtin", "backends.builtin", "downstream.builtin"),
    # 5. the wrapper and its file formats
    5: ("lens_frame", "formats.adapter", "formats.checkpoint", "targets", "strengths", "load_plan", "controlgs"),
    # 6. the application
    6: ("rendering.protocol", "distributed", "training", "evaluation", "ablations", "report", "perceptual", "viewer",
        "benchmarking", "cli"),
}
LAYER: dict[str, int] = {f"{PACKAGE}.{m}": n for n, mods in LAYERS.items() for m in mods}


def _source_files() -> dict[str, Path]:
    """Module name -> file, for every module of the package (symlinked folders followed)."""
    out = {}
    for folder, _, files in os.walk(ROOT, followlinks=True):
        for f in files:
            if f.endswith(".py"):
                rel = (Path(folder) / f).relative_to(ROOT).with_suffix("")
                parts = [PACKAGE, *rel.parts]
                if parts[-1] == "__init__":
                    parts.pop()
                out[".".join(parts)] = Path(folder) / f
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return isinstance(test, ast.Name) and test.id == "TYPE_CHECKING" or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


@functools.lru_cache(maxsize=1)
def import_graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """``(module_level, deferred)``: module -> the package's modules it imports when it is imported,
    and -> those it imports inside functions (only when called)."""
    files = _source_files()
    modules = set(files)

    def targets(node: ast.Import | ast.ImportFrom, package: str) -> list[str]:
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(parent + ([node.module] if node.module else []))
            names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        out = []
        for name in names:
            while name and name not in modules:  # `import a.b.c` of a name inside a module
                name = name.rpartition(".")[0]
            if name:
                out.append(name)
        return out

    module_level: dict[str, set[str]] = {}
    deferred: dict[str, set[str]] = {}
    for name, path in files.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        now: set[str] = set()
        later: set[str] = set()

        def visit(nodes: list[ast.stmt], in_function: bool) -> None:
            for node in nodes:
                if isinstance(node, (ast.Import, ast.ImportFrom)):
                    (later if in_function else now).update(targets(node, package))
                elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    visit(node.body, True)
                elif isinstance(node, ast.If) and _is_type_checking(node.test):
                    visit(node.orelse, in_function)  # typing-only imports never run
                else:  # class bodies, if / try / with / for blocks run at import
                    for field in ("body", "orelse", "finalbody"):
                        visit(getattr(node, field, []), in_function)
                    for handler in getattr(node, "handlers", []):
                        visit(handler.body, in_function)

        visit(ast.parse(path.read_text(), str(path)).body, False)
        module_level[name] = now - {name}
        deferred[name] = later - now - {name}
    return module_level, deferred


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as ``[a, b, ..., a]``, or None."""
    state: dict[str, int] = {}  # 1: on the stack, 2: done
    stack: list[str] = []

    def dfs(v: str) -> list[str] | None:
        state[v] = 1
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state and (found := dfs(w)) is not None:
                return found
        stack.pop()
        state[v] = 2
        return None

    for v in sorted(graph):
        if v not in state and (found := dfs(v)) is not None:
            return found
    return None


def _runs_with(name: str) -> set[str]:
    """What importing ``name`` runs besides its own imports: its packages' ``__init__`` files."""
    parts = name.split(".")
    return {".".join(parts[:i]) for i in range(1, len(parts))}


def dependency_order() -> list[str]:
    """The core modules, each after everything it (or a package above it) imports."""
    graph, _ = import_graph()
    order: list[str] = []
    seen: set[str] = set()

    def visit(v: str) -> None:
        seen.add(v)
        for w in sorted(graph.get(v, set()) | _runs_with(v)):
            if w not in seen:
                visit(w)
        order.append(v)

    for v in sorted(LAYER):
        if v not in seen:
            visit(v)
    return [v for v in order if v in LAYER]


def test_every_module_of_the_layer_map_exists():
    graph, _ = import_graph()
    assert sorted(set(LAYER) - set(graph)) == []


def test_no_import_cycle():
    """No cycle among the modules' module-level imports (the core's, and everyone else's)."""
    graph, _ = import_graph()
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or ())


def test_no_function_local_import_dodges_a_cycle():
    """Moving every function-local import of the package's own modules to module level would close
    no cycle: each stays inside its function for another reason (a heavy or optional dependency,
    the command line's start-up), never to dodge a cycle."""
    graph, deferred = import_graph()
    cycle = find_cycle({m: graph[m] | deferred[m] for m in graph})
    assert cycle is None, "a function-local import closes the cycle " + " -> ".join(cycle or ())


def test_core_imports_only_go_down():
    """Every core module that importing a core module loads (through any module, its packages'
    ``__init__`` files included) sits on the same layer or a lower one."""
    graph, _ = import_graph()
    upward = []
    for start, layer in sorted(LAYER.items()):
        paths = {start: [start]}
        todo = [start]
        while todo:
            v = todo.pop()
            for w in sorted(graph.get(v, set()) | _runs_with(v)):
                if w not in paths:
                    paths[w] = paths[v] + [w]
                    todo.append(w)
        upward += [f"{' -> '.join(path)} (layer {layer} -> {LAYER[m]})"
                   for m, path in sorted(paths.items()) if LAYER.get(m, 0) > layer]
    assert upward == [], "imports that go up:\n" + "\n".join(upward)


_IMPORT_ONE_BY_ONE = textwrap.dedent("""
    import importlib, json, sys
    order, layer = json.loads(sys.argv[1]), json.loads(sys.argv[2])
    problems = []
    before = set(sys.modules)
    import controlgs_adapter  # every import below runs it first: its eager names are the foundation's
    preloaded = set(sys.modules) - before
    extra = sorted(m for m in preloaded if layer.get(m, 0) > 1)
    if extra:
        problems.append(f"import controlgs_adapter loads {extra} (above the foundation)")
    for name in order:
        if name in preloaded:
            continue
        if name in sys.modules:
            problems.append(f"{name} was loaded before its turn (an earlier module imports it)")
            continue
        before = set(sys.modules)
        try:
            importlib.import_module(name)
        except Exception as e:
            problems.append(f"import {name}: {type(e).__name__}: {e}")
            continue
        up = sorted(m for m in set(sys.modules) - before if layer.get(m, 0) > layer[name])
        if up:
            problems.append(f"import {name} (layer {layer[name]}) loads {up} from a higher layer")
    print(json.dumps(problems))
""")


def test_core_modules_import_alone_in_dependency_order():
    """In a fresh interpreter, import the core modules one by one in dependency order: each import
    succeeds with only what comes before it loaded, and loads no module of a higher layer."""
    order = dependency_order()
    assert set(order) == set(LAYER)
    env = {**os.environ, "CONTROLGS_DISABLE_PLUGIN_AUTOLOAD": "1"}
    out = subprocess.run([sys.executable, "-c", _IMPORT_ONE_BY_ONE, json.dumps(order), json.dumps(LAYER)],
                         capture_output=True, text=True, env=env, cwd=ROOT.parent, timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    problems = json.loads(out.stdout.strip().splitlines()[-1])
    assert problems == [], "\n".join(problems)
