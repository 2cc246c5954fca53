"""``controlgs optics build-bank`` / ``fit-prewarp`` / ``bench`` check ``--out`` before the work: a
folder where the file goes or a file in the way of its folder is one line, and nothing is traced."""

from __future__ import annotations

from pathlib import Path

import pytest

from controlgs_adapter.cli import main
from helpers.cli_runs import error_line


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    import controlgs_adapter.downstream.optics.bench as bench
    import controlgs_adapter.downstream.optics.generate as generate
    import controlgs_adapter.downstream.prewarp_fit as prewarp_fit

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work started")

    monkeypatch.setattr(generate, "build_bank", refuse)
    monkeypatch.setattr(prewarp_fit, "fit_bank_prewarp", refuse)
    monkeypatch.setattr(bench, "run", refuse)


@pytest.mark.parametrize("action", [["build-bank"], ["fit-prewarp"]])
def test_a_file_output_under_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None,
                                               action: list[str]) -> None:
    blocker = tmp_path / "blocker"
    blocker.write_text("mine")
    out = blocker / "bank.safetensors"
    assert main(["optics", *action, "--out", str(out)]) == 2
    assert error_line(capsys, "optics") == f"--out {out}: {blocker} is a file, not a folder"
    assert main(["optics", *action, "--out", str(tmp_path)]) == 2
    assert error_line(capsys, "optics") == f"--out {tmp_path}: is a folder; expected the path of a file to write"
    assert blocker.read_text() == "mine"


def test_bench_out_that_is_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None) -> None:
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert main(["optics", "bench", "--sizes", "16", "--out", str(taken)]) == 2
    assert error_line(capsys, "optics") == f"--out {taken}: is a file; expected a folder to write into"
    assert taken.read_text() == "mine"
