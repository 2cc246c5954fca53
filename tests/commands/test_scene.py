"""Tests of ``controlgs_adapter.commands.scene``: ``build-backbone`` and ``export`` (their defaults, what they write,
and the outputs and numbers they refuse in one line before the work)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers.cli_runs import error_line

import controlgs_adapter.scene as scene_module
from controlgs_adapter.cli import build_parser, main


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work started")

    monkeypatch.setattr(scene_module, "build_builtin_backbone", refuse)
    monkeypatch.setattr(scene_module, "load_builtin_scene", refuse)


# ----------------------------------------------------------------------------- options

def test_scene_defaults_and_help(capsys) -> None:
    """``build-backbone`` needs an explicit ``--out``; ``scene --help`` names its actions."""
    b = build_parser().parse_args(["scene", "build-backbone", "--out", "o"])
    assert (b.variant, b.resolution, b.iterations, b.max_anchors, b.n_offsets, b.seed) == ("ar", 128, 1500, 3000, 5, 0)
    x = build_parser().parse_args(["scene", "export", "--out", "o"])
    assert (x.variant, x.resolution, x.scene_command) == ("ar", 128, "export")
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["scene", "build-backbone"])
    assert e.value.code == 2 and "--out" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["scene", "--help"])
    assert e.value.code == 0
    usage = capsys.readouterr().out.split("\n\n")[0]
    assert usage.split() == ["usage:", "controlgs", "scene", "[-h]", "ACTION", "..."]


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


@pytest.mark.parametrize("argv", [
    ["scene", "build-backbone", "--iterations", "9" * 400], ["scene", "build-backbone", "--max-anchors", "9" * 400],
    ["scene", "export", "--resolution", "9" * 400],
])
def test_a_count_beyond_int64_is_one_line_before_the_work(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          argv: list[str]) -> None:
    out = tmp_path / "out"
    assert main([*argv, "--out", str(out)]) == 2
    line = error_line(capsys, "scene")
    assert line.startswith(f"{argv[2]} must be an integer in ") and "401 digits" in line, line  # the value, shortened
    assert not out.exists()


# ----------------------------------------------------------------------------- what the actions write

def test_scene_build_backbone_exits_zero_and_writes_the_backbone(tmp_path, monkeypatch, capsys):
    """``controlgs scene build-backbone`` (docs/reference/cli.md) bakes the backbone into ``--out`` and, having done
    so, exits with status 0 (a script or CI job checks it), with the settings given in build.json."""
    out = tmp_path / "bb"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    rc = main(["scene", "build-backbone", "--resolution", "16", "--iterations", "1", "--max-anchors", "20",
               "--n-offsets", "2", "--out", str(out)])
    assert rc == 0
    assert f"backbone written to {out}" in capsys.readouterr().out
    info = json.loads((out / "build.json").read_text())
    assert (info["variant"], info["resolution"], info["iterations"], info["n_offsets"]) == ("ar", 16, 1, 2)
    assert 0 < info["anchors"] <= 20


def test_scene_export_writes_every_view(tmp_path, capsys, monkeypatch):
    matplotlib_image = pytest.importorskip("matplotlib.image")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the export renders through the scene cache
    assert main(["scene", "export", "--resolution", "16", "--out", str(tmp_path)]) == 0
    assert len(list((tmp_path / "cache" / "controlgs-adapter" / "scene").iterdir())) == 1
    scene = scene_module.load_builtin_scene("ar", 16, cache=True)
    n_train, n_test = len(scene.train_images), len(scene.test_images)
    assert capsys.readouterr().out.strip().endswith(f"{n_train} train and {n_test} test views written to {tmp_path}")
    assert sorted(p.name for p in (tmp_path / "train").iterdir()) == [f"{i:03d}.png" for i in range(n_train)]
    assert sorted(p.name for p in (tmp_path / "test").iterdir()) == [f"{i:03d}.png" for i in range(n_test)]
    for split, images in (("train", scene.train_images), ("test", scene.test_images)):
        for i in (0, len(images) - 1):
            png = matplotlib_image.imread(tmp_path / split / f"{i:03d}.png")[..., :3]
            assert png.shape == (16, 16, 3)
            # 8-bit PNG: within one level (matplotlib rounds x * 255 down or to nearest)
            assert float(abs(png - images[i].permute(1, 2, 0).numpy()).max()) <= 1 / 255 + 1e-6


# ----------------------------------------------------------------------------- report files


