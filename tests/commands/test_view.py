"""``controlgs view --run RUN`` loads a run without running its code: a renderer RUN/run.json names is
used only when named again (``--renderer``) or trusted (``--trust-run-renderer``); a hand-edited run
file and bad options are one line before the viewer is built. The server's loop is replaced: what
is checked is the session the command builds."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from controlgs_adapter.cli import main
from controlgs_adapter.viewer.server import ViewerServer
from helpers.cli_runs import MARKER_MODULE, error_line, needs_backbone, snapshot, untrained_run

pytestmark = needs_backbone
RECORD = {"variant": "ar", "effects": ["display"], "iterations": 7, "seed": 0, "seeds": 1, "adapters": ["controlgs"],
          "rasterizer": "auto"}
FAST = ["--threads", "1", "--resolution", "16", "--test-views", "1"]


@pytest.fixture
def served(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The sessions the command would have served (serve_forever returns at once)."""
    sessions: list[Any] = []

    def record(self: ViewerServer, poll_interval: float = 0.5) -> None:
        sessions.append(self.session)

    monkeypatch.setattr(ViewerServer, "serve_forever", record)
    return sessions


@pytest.fixture(scope="module")
def marked_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, str]:
    """A built-in run whose run.json names a renderer file that leaves a marker when its code runs."""
    root = tmp_path_factory.mktemp("view")
    (root / "view_marker.py").write_text(MARKER_MODULE)
    spec = f"{root / 'view_marker.py'}:renderer"
    return untrained_run(root / "run", {**RECORD, "renderer": spec}), root / "view_marker.ran", spec


def test_the_run_renderer_is_not_run_without_the_users_say(marked_run: tuple[Path, Path, str], served: list[Any],
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    run, marker, spec = marked_run
    marker.unlink(missing_ok=True)
    before = snapshot(run)
    assert main(["view", "--run", str(run), *FAST]) == 2
    line = error_line(capsys, "view")
    assert str(run / "run.json") in line and f"--renderer {spec}" in line and "--trust-run-renderer" in line, line
    assert not marker.exists() and served == [] and snapshot(run) == before


@pytest.mark.parametrize("how", [["--trust-run-renderer"], ["--renderer", "SPEC"]])
def test_the_run_renderer_is_used_when_trusted_or_named(marked_run: tuple[Path, Path, str], served: list[Any],
                                                        capsys: pytest.CaptureFixture[str], how: list[str]) -> None:
    run, marker, spec = marked_run
    marker.unlink(missing_ok=True)
    assert main(["view", "--run", str(run), *FAST, *[spec if a == "SPEC" else a for a in how]]) == 0
    assert marker.exists()
    (session,) = served
    assert type(session.renderer).__name__ == "OwnRenderer" and session.methods[-1] == "controlgs"
    assert "serving on http://127.0.0.1:" in capsys.readouterr().out


@pytest.mark.parametrize("record, field", [({**RECORD, "effects": 5}, "'effects'"),
                                           ({**RECORD, "resolution": -4}, "'resolution'"),
                                           ([RECORD], "a JSON list")])
def test_a_hand_edited_run_file_is_one_line(tmp_path: Path, served: list[Any], capsys: pytest.CaptureFixture[str],
                                            record: Any, field: str) -> None:
    run = untrained_run(tmp_path / "run")
    (run / "run.json").write_text(json.dumps(record))
    assert main(["view", "--run", str(run), *FAST]) == 2
    line = error_line(capsys, "view")
    assert line.startswith(f"{run / 'run.json'}: ") and field in line, line
    assert served == []


@pytest.mark.parametrize("option, value", [("--test-views", "0"), ("--test-views", "-3"), ("--resolution", "0"),
                                           ("--device", "meta"), ("--cache-mib", "-1")])
def test_a_bad_option_is_one_line_before_loading(tmp_path: Path, served: list[Any], capsys: pytest.CaptureFixture[str],
                                                 option: str, value: str) -> None:
    run = untrained_run(tmp_path / "run", RECORD)
    assert main(["view", "--run", str(run), *FAST, option, value]) == 2
    line = error_line(capsys, "view")
    assert line.startswith(f"{option} ") and value in line, line
    assert served == []
