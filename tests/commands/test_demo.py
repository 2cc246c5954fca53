"""``controlgs demo`` checks its options and ``--out`` before taking the report folder's lock: a
refused demo creates no folder."""

from __future__ import annotations

from pathlib import Path

import pytest

from controlgs_adapter.cli import main
from helpers.cli_runs import error_line


@pytest.mark.parametrize("option, value", [("--iterations", "-1"), ("--seed", "-1"), ("--lr", "nan"),
                                           ("--test-views", "0"), ("--seeds", "0"), ("--effects", "blur")])
def test_a_refused_demo_creates_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str,
                                        value: str) -> None:
    out = tmp_path / "report"
    assert main(["demo", "--out", str(out), "--no-progress", option, value]) == 2
    line = error_line(capsys, "demo")
    assert line.startswith(f"{option} ") and value in line, line
    assert not out.exists()


def test_an_out_that_is_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["demo", "--out", str(taken), "--no-progress"]) == 2
    assert error_line(capsys, "demo") == f"--out {taken}: is a file; expected a folder to write into"
    assert taken.read_text() == "mine"
