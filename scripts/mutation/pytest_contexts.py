"""pytest plug-in for the coverage run of scripts/mutation/run.sh: names coverage.py's dynamic context after
each test's node id (what tests executed which line) and writes the baseline outcome and duration of every
test to $MUTATION_BASELINE (JSON), so that tests already failing on the unmutated code are never selected.

    coverage run --data-file=... -m pytest -p pytest_contexts      (scripts/mutation on PYTHONPATH)
"""

from __future__ import annotations

import json
import os

import coverage
import pytest

_durations: dict[str, float] = {}
_failed: set[str] = set()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    cov = coverage.Coverage.current()
    if cov is not None:
        cov.switch_context(item.nodeid)
    yield
    if cov is not None:
        cov.switch_context("")


def pytest_runtest_logreport(report):
    _durations[report.nodeid] = _durations.get(report.nodeid, 0.0) + report.duration
    if report.failed:
        _failed.add(report.nodeid)


def pytest_sessionfinish(session, exitstatus):
    path = os.environ.get("MUTATION_BASELINE")
    if path:
        with open(path, "w", encoding="utf-8") as f:
            json.dump({"durations": _durations, "failed": sorted(_failed)}, f)
