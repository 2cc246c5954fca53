"""Automatic mutation sweep (not run in CI): plausible one-line bugs at sampled lines of the library,
each run against the tests that execute that line, and the survivors listed.

1. Record which test executes which line (once per tree state; about 1.5x the suite's time)::

       .venv/bin/coverage run --rcfile=scripts/coverage-contexts.rc -m pytest -q -p no:cacheprovider

2. Sweep files or folders (one mutant per sampled line; ``--all`` for every line)::

       .venv/bin/python scripts/mutation_sweep.py downstream/display.py --sample 30 --seed 1

Mutations: arithmetic / comparison / boolean operator swaps, numeric constants changed, ``not`` dropped,
``min``/``max`` and ``sum``/``mean`` swapped, ``.detach()``/``.clamp(...)``/``.abs()`` dropped, the first
two arguments of a call swapped, a keyword argument dropped, a ``raise`` replaced by ``pass``, an ``if`` test negated. A line that no
test executes (by coverage's record) is run against the test files that name its module (lines run only at
import or in a subprocess); when there are none it is reported UNCOVERED. Tests are run with ``-x`` in a git worktree of HEAD
(committed code only: commit the tests first), at most ``--max-tests`` of them first and, for a survivor,
every test file that holds one of them. A run past ``--timeout`` is reported
``timeout`` and not counted as caught. The sample's first run is the honest figure (docs/testing.md).

Outside a git checkout (a copy of the tree on another machine) the working tree stands for HEAD and is
copied instead of checked out; ``--shard I/N`` runs every N-th chosen mutant from the I-th (parallel runs
of one sample), and ``--deselect FILE`` leaves out the test ids and test files listed in FILE (tests that fail
there without any mutant, files that do not import there), so that a failure is always the mutant's.
"""

from __future__ import annotations

import argparse
import ast
import json
import os
import random
import re
import shutil
import sqlite3
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_BINOP = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult, ast.FloorDiv: ast.Div,
          ast.Pow: ast.Mult, ast.Mod: ast.FloorDiv, ast.BitAnd: ast.BitOr, ast.BitOr: ast.BitAnd,
          ast.LShift: ast.RShift, ast.RShift: ast.LShift}
_CMP = {ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq, ast.NotEq: ast.Eq,
        ast.In: ast.NotIn, ast.NotIn: ast.In, ast.Is: ast.IsNot, ast.IsNot: ast.Is}
_NAMES = {"min": "max", "max": "min", "sum": "mean", "mean": "sum", "any": "all", "all": "any",
          "minimum": "maximum", "maximum": "minimum", "amin": "amax", "amax": "amin", "floor": "ceil", "ceil": "floor"}
_DROPPED = {"detach", "clamp", "clamp_min", "clamp_max", "clip", "abs", "round"}
_QUIET = {"warn", "print", "write", "info", "debug", "warning", "set_description", "set_postfix", "echo"}


@dataclass(frozen=True)
class Mutant:
    path: str  # repository-relative source file
    line: int  # 1-based first line
    end: int  # 1-based last line replaced
    new: str  # replacement text of lines line..end
    what: str


def _seg(lines: list[str], node: ast.AST) -> tuple[int, int, int] | None:
    """(line index, start char, end char) of a one-line node (ast offsets are UTF-8 bytes)."""
    ln, end_ln = getattr(node, "lineno", None), getattr(node, "end_lineno", None)
    if ln is None or ln != end_ln:
        return None
    raw = lines[ln - 1].encode()
    c0 = len(raw[: node.col_offset].decode(errors="replace"))  # type: ignore[attr-defined]
    c1 = len(raw[: node.end_col_offset].decode(errors="replace"))  # type: ignore[attr-defined]
    return ln - 1, c0, c1


def _skipped_ids(tree: ast.AST) -> set[int]:
    """Nodes whose descendants are not mutated: docstrings, annotations, f-strings, messages."""
    skip: set[int] = set()

    def mark(n: ast.AST | None) -> None:
        if n is not None:
            skip.update(id(d) for d in ast.walk(n))

    for n in ast.walk(tree):
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
            mark(n.returns)
            for a in [*n.args.args, *n.args.kwonlyargs, *n.args.posonlyargs, n.args.vararg, n.args.kwarg]:
                if a is not None:
                    mark(a.annotation)
        elif isinstance(n, ast.AnnAssign):
            mark(n.annotation)
        elif isinstance(n, ast.JoinedStr):
            mark(n)
        elif isinstance(n, ast.Call):
            f = n.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if name in _QUIET:
                mark(n)
        elif isinstance(n, ast.If) and isinstance(n.test, ast.Name) and n.test.id == "TYPE_CHECKING":
            mark(n)
        elif isinstance(n, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "__all__" for t in n.targets):
            mark(n)
    return skip


def _in_git() -> bool:
    return subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True).returncode == 0


def mutants_of(path: str, git: bool = True) -> list[Mutant]:
    """Every mutant of one source file (repository-relative ``path``, as committed at HEAD, or as in the
    working tree when ``git`` is false: the tests run in a copy of the same state) that still compiles."""
    src = (subprocess.run(["git", "show", f"HEAD:{path}"], cwd=ROOT, check=True, capture_output=True,
                          text=True).stdout if git else (ROOT / path).read_text())
    lines = src.splitlines(keepends=True)
    tree = ast.parse(src)
    skip = _skipped_ids(tree)
    out: list[Mutant] = []

    def put(node: ast.AST, text: str, what: str) -> None:
        seg = _seg(lines, node)
        if seg is None:
            return
        i, c0, c1 = seg
        new = lines[i][:c0] + text + lines[i][c1:]
        out.append(Mutant(path, i + 1, i + 1, new, what))

    for n in ast.walk(tree):
        if id(n) in skip:
            continue
        if isinstance(n, ast.BinOp) and type(n.op) in _BINOP:
            m = ast.BinOp(n.left, _BINOP[type(n.op)](), n.right)
            put(n, f"({ast.unparse(m)})", f"{type(n.op).__name__} -> {type(m.op).__name__}")
        elif isinstance(n, ast.AugAssign) and type(n.op) in _BINOP:
            m2 = ast.AugAssign(n.target, _BINOP[type(n.op)](), n.value)
            put(n, ast.unparse(m2), f"{type(n.op).__name__}= -> {type(m2.op).__name__}=")
        elif isinstance(n, ast.Compare) and len(n.ops) == 1 and type(n.ops[0]) in _CMP:
            m3 = ast.Compare(n.left, [_CMP[type(n.ops[0])]()], n.comparators)
            put(n, f"({ast.unparse(m3)})", f"{type(n.ops[0]).__name__} -> {type(m3.ops[0]).__name__}")
        elif isinstance(n, ast.BoolOp):
            m4 = ast.BoolOp(ast.Or() if isinstance(n.op, ast.And) else ast.And(), n.values)
            put(n, f"({ast.unparse(m4)})", "and <-> or")
        elif isinstance(n, ast.UnaryOp) and isinstance(n.op, ast.Not):
            put(n, f"({ast.unparse(n.operand)})", "not dropped")
        elif isinstance(n, ast.Constant) and type(n.value) in (int, float, bool):
            v = n.value
            if isinstance(v, bool):
                new = repr(not v)
            elif isinstance(v, int):
                new = repr(1 if v == 0 else 0 if v == 1 else v + 1)
            else:
                new = repr(1.0 if v == 0.0 else v * 2.0)
            put(n, new, f"constant {v!r} -> {new}")
        elif isinstance(n, ast.Call):
            f = n.func
            if isinstance(f, ast.Name) and f.id in _NAMES:
                put(f, _NAMES[f.id], f"{f.id} -> {_NAMES[f.id]}")
            elif isinstance(f, ast.Attribute) and f.attr in _NAMES:
                put(n, f"{ast.unparse(f.value)}.{_NAMES[f.attr]}({', '.join(map(ast.unparse, [*n.args, *n.keywords]))})",
                    f".{f.attr} -> .{_NAMES[f.attr]}")
            elif isinstance(f, ast.Attribute) and f.attr in _DROPPED:
                put(n, f"({ast.unparse(f.value)})", f".{f.attr}(...) dropped")
            if len(n.args) >= 2 and not any(isinstance(a, ast.Starred) for a in n.args[:2]) \
                    and ast.unparse(n.args[0]) != ast.unparse(n.args[1]):
                swapped = ast.Call(n.func, [n.args[1], n.args[0], *n.args[2:]], n.keywords)
                put(n, ast.unparse(swapped), "first two arguments swapped")
            for k, kw in enumerate(n.keywords):
                if kw.arg is not None:
                    fewer = ast.Call(n.func, n.args, n.keywords[:k] + n.keywords[k + 1:])
                    put(n, ast.unparse(fewer), f"keyword {kw.arg}= dropped")
        elif isinstance(n, ast.Raise):
            i = n.lineno - 1
            indent = lines[i][: len(lines[i]) - len(lines[i].lstrip())]
            out.append(Mutant(path, n.lineno, n.end_lineno or n.lineno, f"{indent}pass\n", "raise -> pass"))
        elif isinstance(n, (ast.If, ast.While)) and id(n.test) not in skip:
            seg = _seg(lines, n.test)
            if seg is not None:
                i, c0, c1 = seg
                new = lines[i][:c0] + f"not ({ast.unparse(n.test)})" + lines[i][c1:]
                out.append(Mutant(path, i + 1, i + 1, new, "condition negated"))
    good = []
    for m in out:
        text = "".join(lines[: m.line - 1]) + m.new + "".join(lines[m.end:])
        if text != src:
            try:
                compile(text, path, "exec")
            except SyntaxError:
                continue
            good.append(m)
    return good


def _numbits_to_lines(bits: bytes) -> list[int]:
    """coverage.py's numbits (bit ``k`` of byte ``j``: line ``8 j + k`` ran) as line numbers."""
    return [8 * j + k for j, byte in enumerate(bits) for k in range(8) if byte >> k & 1]


class Coverage:
    """Tests per executed line, read from a coverage data file recorded with per-test contexts (its file
    paths are taken relative to the folder that held them all, so the data serves a copy of the tree)."""

    def __init__(self, data_file: Path) -> None:
        if not data_file.exists():
            raise SystemExit(f"no coverage data at {data_file}: record it first (see this script's docstring)")
        self.db = sqlite3.connect(str(data_file))
        self.contexts = dict(self.db.execute("select id, context from context"))
        recorded = dict(self.db.execute("select path, id from file"))
        root = os.path.commonpath([str(Path(p).parent) for p in recorded]) if recorded else ""
        parts = [Path(p).relative_to(root).parts for p in recorded]
        if parts and all(len(q) > 1 for q in parts) and len({q[0] for q in parts}) == 1 \
                and not (ROOT / parts[0][0]).is_dir():  # one top folder shared by every recorded file
            root = os.path.dirname(root)
        self.files = {str(ROOT / Path(p).relative_to(root)): i for p, i in recorded.items()}
        self.size: dict[str, int] = {}  # lines each test executes: focused (fast) tests are run first
        for ctx, bits in self.db.execute("select context_id, numbits from line_bits"):
            name = self.contexts[ctx]
            self.size[name] = self.size.get(name, 0) + len(_numbits_to_lines(bits))

    def tests_by_line(self, path: str) -> dict[int, set[str]]:
        fid = self.files.get(str(ROOT / path))
        by_line: dict[int, set[str]] = {}
        if fid is None:
            return by_line
        for ctx, bits in self.db.execute("select context_id, numbits from line_bits where file_id = ?", (fid,)):
            for ln in _numbits_to_lines(bits):
                by_line.setdefault(ln, set()).add(self.contexts[ctx])
        return by_line


def _node_id(context: str) -> str | None:
    """``test_x.TestC.test_f`` (coverage's test_function context) -> ``tests/test_x.py::TestC::test_f``."""
    parts = context.split(".")
    if len(parts) < 2 or not (ROOT / "tests" / f"{parts[0]}.py").exists():
        return None
    return f"tests/{parts[0]}.py::" + "::".join(parts[1:])


def _tests_for(m: Mutant, by_line: dict[int, set[str]], size: dict[str, int]) -> list[str]:
    """Node ids of the tests that execute the mutated lines, most focused first; for a line executed
    only at import, the tests that execute the module; for a module only subprocesses run (no test's
    context at all), the test files that name it."""
    ctxs = set().union(*(by_line.get(ln, set()) for ln in range(m.line, m.end + 1)))
    if not any(_node_id(c) for c in ctxs):  # run at import (a default, a constant): the tests that use the module
        ctxs = set().union(*by_line.values())
    named: dict[str, int] = {}
    for c in ctxs:
        if (t := _node_id(c)) is not None:
            named[t] = min(named.get(t, 1 << 30), size.get(c, 0))
    if named:
        return sorted(named, key=lambda t: (named[t], t))
    stem = Path(m.path).stem
    word = re.compile(rf"\b{re.escape(stem)}\b")
    files = sorted((f for f in (ROOT / "tests").glob("test_*.py") if word.search(f.read_text())),
                   key=lambda f: f.stat().st_size)
    return [str(f.relative_to(ROOT)) for f in files[:6]]


def _run(worktree: Path, m: Mutant, tests: list[str], timeout: float, deselect: list[str]) -> tuple[str, str]:
    """Apply ``m`` in ``worktree``, run ``tests`` (those whose file is in HEAD), restore:
    (``caught`` / ``MISSED`` / ``timeout``, the first failure or pytest's last line)."""
    tests = [t for t in tests if (worktree / t.split("::")[0]).exists() and t.split("::")[0] not in deselect]
    if not tests:
        return "MISSED", "none of its tests is in HEAD"
    target = worktree / m.path
    original = target.read_text()
    lines = original.splitlines(keepends=True)
    target.write_text("".join(lines[: m.line - 1]) + m.new + "".join(lines[m.end:]))
    boot = ("import sys, pytest\ntry:\n import __editable___controlgs_adapter_0_1_0_finder as f\n"
            f" f.MAPPING.update({{'controlgs_adapter': {str(worktree / 'controlgs_adapter')!r}, "
            f"'controlgs_adapter.backends': {str(worktree / 'backends')!r}, "
            f"'controlgs_adapter.downstream': {str(worktree / 'downstream')!r}}})\n"
            f"except ImportError:\n sys.path.insert(0, {str(worktree)!r})\n"
            "sys.exit(pytest.main(sys.argv[1:]))")
    skip = [a for t in deselect if "::" in t for a in ("--deselect", t)]  # whole files: left out above
    try:
        for attempt in (tests, sorted({t.split("::")[0] for t in tests})):
            proc = subprocess.run([sys.executable, "-c", boot, "-x", "-q", "-rf", "-p", "no:cacheprovider", *skip, *attempt],
                                  cwd=worktree, capture_output=True, text=True, timeout=timeout)
            if proc.returncode != 4:  # 4: a node id renamed since the coverage record: run whole files
                break
        if proc.returncode in (4, 5):  # usage error / no tests collected: not a verdict
            raise SystemExit(f"pytest could not run {tests[:3]}...: {proc.stdout[-500:]}{proc.stderr[-500:]}")
        failed = [ln.split(" ")[1] for ln in proc.stdout.splitlines() if ln.startswith("FAILED ")]
        return "caught" if proc.returncode else "MISSED", (failed or proc.stdout.strip().splitlines() or [""])[-1]
    except subprocess.TimeoutExpired:
        return "timeout", f"no verdict in {timeout:g} s (not counted as caught)"
    finally:
        target.write_text(original)


def _sources(targets: list[str]) -> list[str]:
    """Repository paths of the targets' Python files (through the package symlinks: the real files, once)."""
    files: dict[str, None] = {}
    for t in targets:
        p = ROOT / t
        if not (p.is_dir() or (p.is_file() and p.suffix == ".py")):
            raise SystemExit(f"mutation_sweep.py: {t}: not a Python file or folder of this repository")
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            if not f.name.startswith("_version"):
                files[str(f.resolve().relative_to(ROOT))] = None
    return list(files)


def _line_range(text: str) -> tuple[int, int]:
    """``A-B`` -> ``(A, B)`` (argparse type: a malformed range is a usage error)."""
    a, sep, b = text.partition("-")
    if not (sep and a.isdigit() and b.isdigit() and int(a) <= int(b)):
        raise argparse.ArgumentTypeError(f"expected A-B with A <= B, got {text!r}")
    return int(a), int(b)


def _shard(text: str) -> tuple[int, int]:
    """``I/N`` -> ``(I, N)`` with 0 <= I < N (argparse type)."""
    i, sep, n = text.partition("/")
    if not (sep and i.isdigit() and n.isdigit() and int(i) < int(n)):
        raise argparse.ArgumentTypeError(f"expected I/N with 0 <= I < N, got {text!r}")
    return int(i), int(n)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("targets", nargs="+", help="source files or folders (repository-relative)")
    ap.add_argument("--sample", type=int, default=20, help="lines sampled over all targets (one mutant each)")
    ap.add_argument("--all", action="store_true", help="every mutant of every line instead of a sample")
    ap.add_argument("--lines", type=_line_range, help="only lines A-B (one target file)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-tests", type=int, default=40, help="tests run first (their whole files for a survivor)")
    ap.add_argument("--also", nargs="*", default=[], help="test files run for every mutant (tests newer than the coverage data)")
    ap.add_argument("--coverage", default=str(ROOT / ".coverage-contexts"), help="coverage data file")
    ap.add_argument("--worktree", help="where the worktree of HEAD goes (default: a new temporary folder)")
    ap.add_argument("--timeout", type=float, default=600.0)
    ap.add_argument("--list", action="store_true", help="only list the chosen mutants")
    ap.add_argument("--json", help="write the results here (rewritten after every mutant)")
    ap.add_argument("--shard", type=_shard, default=(0, 1), help="I/N: every N-th chosen mutant from the I-th")
    ap.add_argument("--deselect", help="a file of test ids or test files (one a line) left out of every run")
    args = ap.parse_args()
    git = _in_git()
    if args.deselect and not Path(args.deselect).is_file():
        ap.error(f"--deselect {args.deselect}: no such file")
    deselect = Path(args.deselect).read_text().split() if args.deselect else []
    cov = Coverage(Path(args.coverage))
    rng = random.Random(args.seed)
    chosen: list[Mutant] = []
    by_line_of: dict[str, dict[int, set[str]]] = {}
    pool: dict[tuple[str, int], list[Mutant]] = {}
    for path in _sources(args.targets):
        by_line_of[path] = cov.tests_by_line(path)
        for m in mutants_of(path, git):
            if args.lines:
                a, b = args.lines
                if not a <= m.line <= b:
                    continue
            pool.setdefault((m.path, m.line), []).append(m)
    if args.all:
        chosen = [m for ms in pool.values() for m in ms]
    else:
        keys = sorted(pool)
        for key in rng.sample(keys, min(args.sample, len(keys))):
            chosen.append(rng.choice(pool[key]))
    chosen = chosen[args.shard[0]::args.shard[1]]  # in the sample's random order: a partial run is a sample too
    if args.list:
        for m in sorted(chosen, key=lambda m: (m.path, m.line)):
            print(f"{m.path}:{m.line}  {m.what}\n    {m.new.strip()}")
        return
    worktree = Path(args.worktree or tempfile.mkdtemp(prefix="sweep-")) / "tree"
    if git:
        subprocess.run(["git", "worktree", "add", "--detach", str(worktree), "HEAD"], cwd=ROOT, check=True,
                       capture_output=True)
    else:
        shutil.copytree(ROOT, worktree, symlinks=True, ignore=shutil.ignore_patterns(".venv", ".git", "__pycache__"))
    results = []
    try:
        for m in chosen:
            t0 = time.perf_counter()
            tests = list(args.also) + _tests_for(m, by_line_of[m.path], cov.size)
            if not tests:
                verdict, tail = "UNCOVERED", "no test executes this line"
            else:
                verdict, tail = _run(worktree, m, tests[: args.max_tests], args.timeout, deselect)
                if verdict == "MISSED":  # whole files: fixtures' lines are recorded under a neighbouring test's name
                    verdict, tail = _run(worktree, m, sorted({t.split("::")[0] for t in tests}), args.timeout, deselect)
            results.append({**asdict(m), "verdict": verdict, "tests": len(tests), "by": tail})
            print(f"{verdict:9s} {time.perf_counter() - t0:6.1f}s {m.path}:{m.line}  {m.what}  [{tail}]\n"
                  f"          {m.new.strip()}", flush=True)
            if args.json:
                Path(args.json).write_text(json.dumps(results, indent=1))
    finally:
        if git:
            subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=ROOT, check=False)
        else:
            shutil.rmtree(worktree.parent, ignore_errors=True)
    n = sum(r["verdict"] == "caught" for r in results)
    slow = sum(r["verdict"] == "timeout" for r in results)
    print(f"caught {n}/{len(results)}" + (f" ({slow} without a verdict in {args.timeout:g} s)" if slow else ""))


if __name__ == "__main__":
    main()
