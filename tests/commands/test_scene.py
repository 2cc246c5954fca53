"""``controlgs scene build-backbone`` / ``export`` check ``--out`` and their numbers before the work:
a file in the way is one line and the backbone is never trained."""

from __future__ import annotations

from pathlib import Path

import pytest

import controlgs_adapter.scene as scene_module
from controlgs_adapter.cli import main
from helpers.cli_runs import error_line


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work started")

    monkeypatch.setattr(scene_module, "build_builtin_backbone", refuse)
    monkeypatch.setattr(scene_module, "load_builtin_scene", refuse)


@pytest.mark.parametrize("action", ["build-backbone", "export"])
def test_out_in_the_way_is_refused_before_the_work(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None,
                                                   action: str) -> None:
    existing = tmp_path / "taken"
    existing.write_text("mine")
    assert main(["scene", action, "--out", str(existing)]) == 2
    assert error_line(capsys, "scene") == f"--out {existing}: is a file; expected a folder to write into"
    assert main(["scene", action, "--out", str(existing / "below")]) == 2
    assert error_line(capsys, "scene") == f"--out {existing / 'below'}: {existing} is a file, not a folder"
    assert existing.read_text() == "mine" and sorted(p.name for p in tmp_path.iterdir()) == ["taken"]


def test_export_refuses_a_file_where_a_split_folder_goes(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         no_work: None) -> None:
    (tmp_path / "test").write_text("mine")
    assert main(["scene", "export", "--out", str(tmp_path)]) == 2
    assert error_line(capsys, "scene").startswith(f"--out {tmp_path / 'test'}: is a file")
    assert not (tmp_path / "train").exists()


@pytest.mark.parametrize("option, value", [("--iterations", "0"), ("--resolution", "-8"), ("--max-anchors", "0"),
                                           ("--n-offsets", "0"), ("--seed", "-1")])
def test_build_backbone_numbers_are_checked_first(tmp_path: Path, capsys: pytest.CaptureFixture[str], no_work: None,
                                                  option: str, value: str) -> None:
    assert main(["scene", "build-backbone", "--out", str(tmp_path / "bb"), option, value]) == 2
    line = error_line(capsys, "scene")
    assert line.startswith(f"{option} must be an integer") and line.endswith(f"got {value}")
    assert not (tmp_path / "bb").exists()
