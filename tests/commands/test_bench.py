"""``controlgs bench`` checks ``--out`` and its numbers before measuring anything."""

from __future__ import annotations

from pathlib import Path

import pytest

import controlgs_adapter.commands.bench as bench_command
from controlgs_adapter.cli import main
from helpers.cli_runs import error_line


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the measurements started")

    monkeypatch.setattr(bench_command, "run_bench", refuse)


def test_out_that_cannot_be_written_is_refused_first(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     no_work: None) -> None:
    assert main(["bench", "--out", str(tmp_path)]) == 2
    assert error_line(capsys, "bench") == f"--out {tmp_path}: is a folder; expected the path of a file to write"
    blocker = tmp_path / "blocker"
    blocker.write_text("mine")
    assert main(["bench", "--out", str(blocker / "bench.md")]) == 2
    assert error_line(capsys, "bench") == f"--out {blocker / 'bench.md'}: {blocker} is a file, not a folder"
    assert blocker.read_text() == "mine"


@pytest.mark.parametrize("option, value", [("--test-views", "0"), ("--resolution", "0"), ("--iterations", "-1"),
                                           ("--seed", "-2")])
def test_numbers_are_checked_first(capsys: pytest.CaptureFixture[str], no_work: None, option: str, value: str) -> None:
    assert main(["bench", option, value]) == 2
    line = error_line(capsys, "bench")
    assert line.startswith(f"{option} must be an integer") and line.endswith(f"got {value}")
