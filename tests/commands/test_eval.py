"""``controlgs eval --run RUN`` reads RUN/run.json without running code: a renderer the run names is
used only when named again (``--renderer``) or trusted (``--trust-run-renderer``); a hand-edited run
file is refused in one line naming the file and the field; ``--test-views`` below 1 and an ``--out``
that cannot be written are refused before any work. A refused eval writes no report."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import pytest

import controlgs_adapter.commands.eval as eval_command
from controlgs_adapter.cli import main
from helpers.cli_runs import MARKER_MODULE, error_line, needs_backbone, snapshot, untrained_run

pytestmark = needs_backbone
#: a built-in AR run trained through the display stage alone
RECORD = {"variant": "ar", "effects": ["display"], "iterations": 7, "seed": 0, "seeds": 1, "adapters": ["controlgs"],
          "rasterizer": "auto", "renderer": None}
FAST = ["--resolution", "16", "--test-views", "1", "--no-progress"]


@pytest.fixture(scope="module")
def base_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return untrained_run(tmp_path_factory.mktemp("base") / "run", RECORD)


def _run(base: Path, tmp_path: Path, **record: Any) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "controlgs.controlgs.safetensors").write_bytes((base / "controlgs.controlgs.safetensors").read_bytes())
    (run / "run.json").write_text(json.dumps({**RECORD, **record}))
    return run


@pytest.mark.parametrize("kind", ["file", "module"])
def test_a_run_renderer_runs_only_when_named_or_trusted(base_run: Path, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str],
                                                        monkeypatch: pytest.MonkeyPatch, kind: str) -> None:
    code = tmp_path / "code"
    code.mkdir()
    (code / "run_marker.py").write_text(MARKER_MODULE)
    marker = code / "run_marker.ran"
    if kind == "file":
        spec = f"{code / 'run_marker.py'}:renderer"
    else:  # MODULE:ATTR is looked up in the current folder too
        spec = "run_marker:renderer"
        monkeypatch.chdir(code)
    run, report = _run(base_run, tmp_path, renderer=spec), tmp_path / "report"
    before = snapshot(run)

    assert main(["eval", "--run", str(run), "--out", str(report), *FAST]) == 2
    line = error_line(capsys, "eval")
    assert str(run / "run.json") in line and f"--renderer {spec}" in line and "--trust-run-renderer" in line, line
    assert not marker.exists() and not report.exists() and snapshot(run) == before

    try:
        assert main(["eval", "--run", str(run), "--out", str(report), *FAST, "--trust-run-renderer"]) == 0
        assert marker.exists()
        assert json.loads((report / "results.json").read_text())["info"]["renderer"] == spec

        marker.unlink()
        sys.modules.pop("run_marker", None)
        used: list[Any] = []

        def stop(*args: object, renderer: Any = None, **kwargs: object) -> None:
            used.append(renderer)
            raise _Stop

        monkeypatch.setattr(eval_command, "evaluate_seeds", stop)
        with pytest.raises(_Stop):  # named again on the command line: loaded and handed to the evaluation
            main(["eval", "--run", str(run), "--out", str(tmp_path / "report2"), *FAST, "--renderer", spec])
        assert marker.exists() and type(used[0]).__name__ == "OwnRenderer"
    finally:
        sys.modules.pop("run_marker", None)


class _Stop(Exception):
    """Ends a command once it has got as far as a test needs."""


DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize("text, field, shown", [
    (json.dumps({**RECORD, "effects": 5}), "'effects'", "got 5"),
    (json.dumps({**RECORD, "effects": ["blur"]}), "'effects'", "got ['blur']"),
    (json.dumps({**RECORD, "resolution": "16"}), "'resolution'", "got '16'"),
    (json.dumps({**RECORD, "resolution": 0}), "'resolution'", "got 0"),
    (json.dumps({**RECORD, "holdout": True}), "'holdout'", "got True"),
    (json.dumps({**RECORD, "model": 3, "data": "d"}), "'model'", "got 3"),
    (json.dumps({**RECORD, "family": ["scaffold_gs"]}), "'family'", "got ['scaffold_gs']"),
    (json.dumps({**RECORD, "format": "ply"}), "'format'", "got 'ply'"),
    (json.dumps({**RECORD, "renderer": 7}), "'renderer'", "got 7"),
    (json.dumps({**RECORD, "rasterizer": {"name": "torch"}}), "'rasterizer'", "got {'name': 'torch'}"),
    (json.dumps({**RECORD, "rasterizer": "nvdiffrast"}), "'rasterizer'", "'nvdiffrast' is not registered"),
    (json.dumps({**RECORD, "seeds": 0}), "'seeds'", "got 0"),
    (json.dumps({**RECORD, "distributed": [1]}), "'distributed'", "got [1]"),
    (json.dumps({**RECORD, "white_background": "yes"}), "'white_background'", "got 'yes'"),
    (json.dumps([RECORD]), "a JSON list, expected an object", ""),
    ("{not json", "not a controlgs run file", ""),
    (DEEP, "not a controlgs run file", ""),
])
def test_a_hand_edited_run_file_is_one_line_naming_file_and_field(base_run: Path, tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str],
                                                                   text: str, field: str, shown: str) -> None:
    run, report = _run(base_run, tmp_path), tmp_path / "report"
    (run / "run.json").write_text(text)
    before = snapshot(run)
    assert main(["eval", "--run", str(run), "--out", str(report), *FAST]) == 2
    line = error_line(capsys, "eval")
    assert line.startswith(f"{run / 'run.json'}: ") and field in line and shown in line, line
    assert len(line) < 400  # the value is shortened, never the whole file
    assert not report.exists() and snapshot(run) == before


@pytest.mark.parametrize("value", ["0", "-3"])
def test_test_views_below_one_is_refused(base_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         value: str) -> None:
    run, report = _run(base_run, tmp_path), tmp_path / "report"
    assert main(["eval", "--run", str(run), "--out", str(report), "--resolution", "16", "--no-progress",
                 "--test-views", value]) == 2
    line = error_line(capsys, "eval")
    assert line.startswith("--test-views ") and f"got {value}" in line
    assert not report.exists()


def test_an_out_that_is_a_file_is_refused_before_the_evaluation(base_run: Path, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str],
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    def no_work(*args: object, **kwargs: object) -> None:
        raise AssertionError("the evaluation started")

    monkeypatch.setattr(eval_command, "evaluate_seeds", no_work)
    run, report = _run(base_run, tmp_path), tmp_path / "report"
    report.write_text("mine")
    assert main(["eval", "--run", str(run), "--out", str(report), *FAST]) == 2
    assert error_line(capsys, "eval").startswith(f"--out {report}: is a file")
    assert report.read_text() == "mine"
    assert main(["eval", "--run", str(run), "--out", str(report / "sub"), *FAST]) == 2
    assert error_line(capsys, "eval") == f"--out {report / 'sub'}: {report} is a file, not a folder"


@pytest.mark.parametrize("device", ["meta", "cuda:99"])
def test_a_device_that_cannot_hold_data_is_one_line(base_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                    device: str) -> None:
    run, report = _run(base_run, tmp_path), tmp_path / "report"
    assert main(["eval", "--run", str(run), "--out", str(report), *FAST, "--device", device]) == 2
    assert error_line(capsys, "eval").startswith(f"--device {device}: ")
    assert not report.exists()
