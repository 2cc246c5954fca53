"""Tests of ``controlgs_adapter.commands.scene``: ``build-backbone`` and ``export`` (their defaults, what they write,
and the outputs and numbers they refuse in one line before the work)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from helpers.cli_runs import error_line

import controlgs_adapter.scene as scene_module
from controlgs_adapter.cli import build_parser, main
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import IDEAL, GridResult
from controlgs_adapter.report import read_results, write_report

GRID = ((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8))
D, P = (1.0, 2.0), (0.0, 0.5)
#: [D, P] grids of each method (the mean over the two views, which are the grid -/+ 1 dB, -/+ 0.01)
PSNR = {"no_ss": [[20, 21], [17, 15]], "ss": [[20, 22], [18, 16]], "controlgs": [[21, 21], [19, 18]],
        IDEAL: [[25, 20], [22, 15]], "wo_lens": [[18.75] * 2] * 2, "wo_display": [[19.25] * 2] * 2}
FLIP = {"no_ss": [[0.3] * 2] * 2, "ss": [[0.2] * 2] * 2, "controlgs": [[0.1, 0.25], [0.15, 0.1]],
        IDEAL: [[0.05] * 2] * 2, "wo_lens": [[0.18] * 2] * 2, "wo_display": [[0.22] * 2] * 2}


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError("the work started")

    monkeypatch.setattr(scene_module, "build_builtin_backbone", refuse)
    monkeypatch.setattr(scene_module, "load_builtin_scene", refuse)


def _constructed(methods=("no_ss", "ss", IDEAL, "controlgs"), offset: float = 0.0, views: int = 2) -> GridResult:
    g = torch.Generator().manual_seed(3)
    base = {"no_ss": 18.0, "ss": 20.0, IDEAL: 22.0, "controlgs": 21.0, "wo_lens": 20.9}
    per_view = {m: {"psnr": base[m] + offset + 0.1 * torch.rand(4, 5, views, generator=g, dtype=torch.float64),
                    "ssim": torch.rand(4, 5, views, generator=g, dtype=torch.float64),
                    "flip": torch.rand(4, 5, views, generator=g, dtype=torch.float64)} for m in methods}
    return GridResult(*GRID, per_view)


def _views(grid: list[list[float]], spread: float) -> torch.Tensor:
    g = torch.tensor(grid, dtype=torch.float64)
    return torch.stack([g - spread, g + spread], dim=-1)  # [D, P, 2]


def _result(methods=tuple(PSNR), offset: float = 0.0, info=None) -> GridResult:
    per_view = {m: {"psnr": _views(PSNR[m], 1.0) + offset, "flip": _views(FLIP[m], 0.01)} for m in methods}
    return GridResult(D, P, per_view, info=dict(info or {}))


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

def test_write_report_files_and_results_json(tmp_path: Path):
    r = _result(("ss", "controlgs"), info={"test_views": 2, "seed": 3})
    img = torch.rand(3, 8, 8)
    comparison = {"gt": img, "settings": [(1.0, 0.0), (8.0, 0.8)],
                  "rows": {"ss": [(img, img, 20.0, 0.5)] * 2, "controlgs": [(img, img, 21.0, 0.6)] * 2}}
    response = {"resample": [("d=1", img), ("d=2", img)], "lens": [("off", img)]}
    paths = write_report(tmp_path / "a", r, info={"scene": "x"}, comparison=comparison, response=response)
    assert [p.name for p in paths] == ["results.json", "heatmap.png", "comparison.png", "condition_response.png",
                                       "report.md"]
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths)
    data = json.loads((tmp_path / "a" / "results.json").read_text())
    assert data["info"] == {"test_views": 2, "seed": 3, "scene": "x"}  # the run's info with the call's merged in
    assert read_results(data) == [GridResult.from_json(data)]
    md = (tmp_path / "a" / "report.md").read_text()
    assert md.endswith("\n## Figures\n\n![ControlGS minus SS-backbone and minus the ideal render per setting](heatmap.png)"
                       "\n\n![rendered and eye-space images at two settings](comparison.png)\n\n"
                       "![condition response: one condition varies, the others are off](condition_response.png)\n")
    assert "Run: test_views = 2, seed = 3, scene = x" in md
    # no SS-backbone: no heatmap; no figures at all: no Figures section
    paths = write_report(tmp_path / "b", _result(("controlgs", "no_ss")))
    assert [p.name for p in paths] == ["results.json", "report.md"]
    assert "## Figures" not in (tmp_path / "b" / "report.md").read_text()


def test_write_report_of_several_seeds(tmp_path: Path):
    runs = [_result(("ss", "controlgs"), info={"seed": s, "test_views": 2}) for s in (4, 9)]
    runs[1].per_view["ss"]["psnr"] += 1.0
    write_report(tmp_path, runs, info={"scene": "x"})
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["info"] == {"test_views": 2, "scene": "x"} and data["seeds"] == [4, 9]
    assert data["summary"]["ss"]["psnr"]["per_seed"] == [19.0, 20.0]
    assert [r.info["seed"] for r in read_results(data)] == [4, 9] and read_results(data) == runs
    for bad in ({"runs": []}, {"runs": {"a": 1}}):
        with pytest.raises(InputValueError, match="'runs' must be a non-empty list"):
            read_results(bad)


def test_ideal_row_in_results_json_and_report(tmp_path):
    r = _constructed()
    r.per_view["controlgs"]["psnr"][3, 4] = r.per_view[IDEAL]["psnr"][3, 4] + 0.5  # one cell above the bound
    write_report(tmp_path, r, info={"scene": "test"})
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["methods"][IDEAL]["psnr"]["mean"] == pytest.approx(r.mean(IDEAL, "psnr"), rel=1e-12)
    md = (tmp_path / "report.md").read_text()
    assert f"| Ideal render (GT through E_s) | {r.mean(IDEAL, 'psnr'):.2f} |" in md  # a row, never bold
    assert "PSNR of Ideal render (GT through E_s):" in md and "PSNR of ControlGS minus Ideal render" in md
    assert "ControlGS is above that bound in 1/20 settings" in md
    assert "LPIPS was not computed" in md and "--lpips-weights" in md
    assert (tmp_path / "heatmap.png").stat().st_size > 0
    assert read_results(data)[0] == GridResult.from_json(data)
