"""cosmic-ray's test command (scripts/mutation/cosmic-ray.toml): run the tests that executed the mutated lines.

cosmic-ray has just rewritten one file of the scratch copy made by scripts/mutation/run.sh (a git repository of
its own). This finds the changed lines with ``git diff``, looks up which tests executed them in the coverage
data that run.sh recorded with one context per test (scripts/mutation/pytest_contexts.py), drops the tests that
already failed on the unmutated code, and runs the most focused of them (fewest library lines executed, then
fastest) with ``pytest -x``. Exit status 0: the mutant survived; anything else: it was killed.

A mutated continuation line is looked up under its statement's first line, where coverage.py files it. Lines
that only run at import (module constants, signatures, decorators) carry no test context: those mutants get the
tests that executed any line of the file. A file no test executes: nothing to run, the mutant survives.

    python scripts/mutation/select_tests.py            # cosmic-ray's test command, in the scratch copy
    python scripts/mutation/select_tests.py --index    # once, after the coverage run (run.sh)

Environment: MUTATION_WORK (run.sh's folder: coverage.db, baseline.json, focus.json),
MUTATION_MAX_TESTS (default 60).
"""

from __future__ import annotations

import ast
import json
import os
import re
import subprocess
import sys
from pathlib import Path

from coverage import CoverageData

WORK = Path(os.environ.get("MUTATION_WORK", "..")).resolve()
TREE = Path.cwd().resolve()
PACKAGES = ("controlgs_adapter", "backends", "downstream")  # module-path of cosmic-ray.toml


def _data() -> CoverageData:
    data = CoverageData(basename=str(WORK / "coverage.db"))
    data.read()
    return data


def build_index() -> None:
    """focus.json: for each test, how many library lines it executed (the fewer, the more focused)."""
    data = _data()
    size: dict[str, int] = {}
    for path in data.measured_files():
        for contexts in data.contexts_by_lineno(path).values():
            for ctx in contexts:
                if ctx:
                    size[ctx] = size.get(ctx, 0) + 1
    (WORK / "focus.json").write_text(json.dumps(size), encoding="utf-8")
    print(f"{len(size)} tests executed lines of {len(data.measured_files())} files")


def changed_lines() -> dict[str, set[int]]:
    """{path relative to the tree: line numbers of the unmutated file that the mutation touched}."""
    diff = subprocess.run(["git", "diff", "-U0", "--no-color", "--no-ext-diff", "--", *PACKAGES], capture_output=True,
                          text=True, check=True, cwd=TREE).stdout
    out: dict[str, set[int]] = {}
    path = None
    for line in diff.splitlines():
        if line.startswith("--- a/"):
            path = line[6:]
        elif line.startswith("@@") and path:
            m = re.match(r"@@ -(\d+)(?:,(\d+))? \+", line)
            start, count = int(m.group(1)), int(m.group(2) or 1)
            out.setdefault(path, set()).update(range(start, start + count) if count else (start, start + 1))
    return out


def statement_starts(rel: str) -> dict[int, int]:
    """{line: first line of the innermost statement that spans it} for the unmutated file."""
    source = subprocess.run(["git", "show", f"HEAD:{rel}"], capture_output=True, text=True, check=True, cwd=TREE).stdout
    starts: dict[int, int] = {}
    for node in ast.walk(ast.parse(source)):  # outer statements first: inner ones overwrite their lines
        if isinstance(node, ast.stmt):
            for n in range(node.lineno, (node.end_lineno or node.lineno) + 1):
                if starts.get(n, 0) <= node.lineno:
                    starts[n] = node.lineno
    return starts


def main() -> int:
    if sys.argv[1:] == ["--index"]:
        build_index()
        return 0
    changes = changed_lines()
    if not changes:
        print("no mutation in the tree: nothing to run")
        return 0
    data = _data()
    baseline = json.loads((WORK / "baseline.json").read_text(encoding="utf-8"))
    failed, durations = set(baseline["failed"]), baseline["durations"]
    focus = json.loads((WORK / "focus.json").read_text(encoding="utf-8"))
    tests: set[str] = set()
    how = "the mutated lines"
    for rel, lines in changes.items():
        by_line = data.contexts_by_lineno(str((TREE / rel).resolve()))
        starts = statement_starts(rel)
        # coverage.py files a statement under its first line: a mutated continuation line is looked up there
        tests.update(c for n in lines for c in by_line.get(n) or by_line.get(starts.get(n, n), ()) if c)
    if not tests:
        how = "a line of the mutated file (none executed the mutated lines: they run at import, or never)"
        for rel in changes:
            for contexts in data.contexts_by_lineno(str((TREE / rel).resolve())).values():
                tests.update(c for c in contexts if c)
    tests -= failed
    where = ", ".join(f"{rel}:{min(lines)}" for rel, lines in changes.items())
    if not tests:
        print(f"no test executes {where}: survived untested")
        return 0
    cap = int(os.environ.get("MUTATION_MAX_TESTS", "60"))
    chosen = sorted(tests, key=lambda t: (focus.get(t, 1 << 30), durations.get(t, 0.0), t))[:cap]
    print(f"ran {len(chosen)} of {len(tests)} tests that executed {how} ({where})", flush=True)
    env = dict(os.environ)
    # a test's own child processes (CLI, distributed ranks) import the mutated copy too, not the editable install
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(TREE), env.get("PYTHONPATH", "")) if p)
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "--no-header", "--tb=line", "-p", "no:cacheprovider",
           *chosen]
    return subprocess.run(cmd, cwd=TREE, env=env).returncode


if __name__ == "__main__":
    sys.exit(main())
