"""Tests of ``controlgs_adapter.commands.eval``: its defaults, the seed folders it evaluates, a run's report
(numbers, files, timings), and what it refuses in one line before any work, writing nothing: a renderer the run
names unless named again or trusted, a hand-edited run file (naming the file and the field), bad options and
outputs, seed folders of different adapters."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers.cli_runs import MARKER_MODULE, error_line, needs_backbone, snapshot, timings_within, untrained_run

import controlgs_adapter.commands.eval as eval_command
from controlgs_adapter import cli
from controlgs_adapter.cli import main
from controlgs_adapter.commands.eval import seed_folders
from controlgs_adapter.errors import InputValueError

#: a built-in AR run trained through the display stage alone
RECORD = {"variant": "ar", "effects": ["display"], "iterations": 7, "seed": 0, "seeds": 1, "adapters": ["controlgs"],
          "rasterizer": "auto", "renderer": None}
FAST = ["--resolution", "16", "--test-views", "1", "--no-progress"]
DEEP = "[" * 100_000 + "]" * 100_000


class _Stop(Exception):
    """Ends a command once it has got as far as a test needs."""


@pytest.fixture(scope="module")
def base_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return untrained_run(tmp_path_factory.mktemp("base") / "run", RECORD)


def _run(base: Path, tmp_path: Path, **record: Any) -> Path:
    """A copy of ``base`` whose run.json is :data:`RECORD` updated with ``record``."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "controlgs.controlgs.safetensors").write_bytes((base / "controlgs.controlgs.safetensors").read_bytes())
    (run / "run.json").write_text(json.dumps({**RECORD, **record}))
    return run


def _seed_run(tmp_path: Path, seeds: dict[str, tuple[str, ...]]) -> Path:
    """A run folder with empty adapter files ``folder/<name>.controlgs.safetensors`` (their presence is checked
    before any load)."""
    run = tmp_path / "run"
    for folder, names in seeds.items():
        (run / folder).mkdir(parents=True, exist_ok=True)
        for n in names:
            (run / folder / f"{n}.controlgs.safetensors").write_text("")
    return run


# ----------------------------------------------------------------------------- options and seed folders

def test_eval_defaults() -> None:
    e = cli.build_parser().parse_args(["eval"])
    assert (e.run, e.out, e.effects, e.lpips_weights, e.optics, e.seed, e.seeds, e.func.__module__) == \
        ("controlgs-run", None, None, None, "fast", 0, None, "controlgs_adapter.commands.eval")
    assert cli.build_parser().parse_args(["eval", "--lpips-weights", "a", "b"]).lpips_weights == ["a", "b"]
    assert cli.build_parser().parse_args(["eval", "--no-progress"]).progress is False


def test_seed_folders(tmp_path: Path) -> None:
    """No seed folders: the run folder itself; else every ``seed-<int>`` folder, by seed; ``--seeds N`` names N
    folders from ``--seed`` (one: the run folder); ``--seeds`` must be an int >= 1."""
    assert seed_folders(tmp_path, 5, None) == [(5, tmp_path)]
    for name in ("seed-2", "seed--1", "seed-10", "seed-x", "seed-"):
        (tmp_path / name).mkdir()
    (tmp_path / "seed-7").write_text("")  # a file, not a folder
    assert seed_folders(tmp_path, 0, None) == [(-1, tmp_path / "seed--1"), (2, tmp_path / "seed-2"),
                                               (10, tmp_path / "seed-10")]
    assert seed_folders(tmp_path, 2, 1) == [(2, tmp_path)]
    assert seed_folders(tmp_path, -1, 2) == [(-1, tmp_path / "seed--1"), (0, tmp_path / "seed-0")]
    assert seed_folders(tmp_path, 3, 2) == [(3, tmp_path / "seed-3"), (4, tmp_path / "seed-4")]
    for bad in (0, -2, True, 1.5):
        with pytest.raises(InputValueError, match=rf"--seeds .*got {bad!r}"):
            seed_folders(tmp_path, 0, bad)  # type: ignore[arg-type]


def test_seed_folders_of_different_adapters_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _seed_run(tmp_path, {"seed-1": ("controlgs",), "seed-2": ("controlgs", "wo_lens")})
    assert main(["eval", "--run", str(run)]) == 2
    assert error_line(capsys, "eval").startswith(f"{run}: the seed folders hold different adapters "
                                                  "(seed-1: controlgs; seed-2: controlgs, wo_lens)")
    run = _seed_run(tmp_path / "no-controlgs", {"seed-1": ("controlgs",), "seed-2": ("wo_lens",)})
    assert main(["eval", "--run", str(run)]) == 2
    assert "seed-2: no controlgs.controlgs.safetensors" in error_line(capsys, "eval")
    run = _seed_run(tmp_path / "one", {".": ()})
    assert main(["eval", "--run", str(run)]) == 2  # one seed: the run folder itself is named
    assert error_line(capsys, "eval").startswith(f"{run}: no controlgs.controlgs.safetensors")


# ----------------------------------------------------------------------------- refusals before any work

@needs_backbone
@pytest.mark.parametrize("value", ["0", "-3"])
def test_test_views_below_one_is_refused(base_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                         value: str) -> None:
    run, report = _run(base_run, tmp_path), tmp_path / "report"
    assert main(["eval", "--run", str(run), "--out", str(report), "--resolution", "16", "--no-progress",
                 "--test-views", value]) == 2
    line = error_line(capsys, "eval")
    assert line.startswith("--test-views ") and f"got {value}" in line
    assert not report.exists()


@needs_backbone
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


@needs_backbone
@pytest.mark.parametrize("device", ["meta", "cuda:99"])
def test_a_device_that_cannot_hold_data_is_one_line(base_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                    device: str) -> None:
    run, report = _run(base_run, tmp_path), tmp_path / "report"
    assert main(["eval", "--run", str(run), "--out", str(report), *FAST, "--device", device]) == 2
    assert error_line(capsys, "eval").startswith(f"--device {device}: ")
    assert not report.exists()


@needs_backbone
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


@needs_backbone
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


# ----------------------------------------------------------------------------- a run's report

@needs_backbone
def test_eval_of_a_built_in_run(tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """The files it writes and prints, the info it records (the run's effects, iterations and seed), the paper's grid
    of the first test views, an untrained adapter equal to the SS-backbone, and load / eval times that are parts of
    the command's own time."""
    pytest.importorskip("matplotlib")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    run = untrained_run(tmp_path / "run", {**RECORD, "seed": 3})  # an untrained (zero) adapter: the backbone
    out = tmp_path / "report"
    t0 = time.perf_counter()
    assert main(["eval", "--run", str(run), "--out", str(out), "--resolution", "16", "--test-views", "2",
                 "--no-progress"]) == 0
    wall = time.perf_counter() - t0
    printed = capsys.readouterr().out.split()
    assert printed == [str(out / f) for f in ("results.json", "heatmap.png", "comparison.png",
                                              "condition_response.png", "report.md")]
    data = json.loads((out / "results.json").read_text())
    info = data["info"]
    assert (info["resolution"], info["test_views"], info["seeds"], info["adapters"], info["effects"]) == \
        (16, 2, 1, ["controlgs"], ["display"])  # the effects of run.json
    assert (info["optics"], info["device"], info["rasterizer"], info["renderer"]) == ("fast", "cpu", "auto", None)
    assert (info["iterations"], info["seed"], info["test_sizes"]) == (7, 3, ["16x16"])
    assert "lpips_weights" not in info and info["eval_s"] > 0
    timings_within(info, ("load_s", "eval_s"), wall)
    assert set(data["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    ss = torch.tensor(data["methods"]["ss"]["psnr"]["per_view"])
    assert ss.shape == (4, 5, 2)  # the paper's grid, the first 2 test views
    # a zero adapter renders the backbone: the same numbers as the SS-backbone
    assert data["methods"]["controlgs"]["psnr"]["per_view"] == data["methods"]["ss"]["psnr"]["per_view"]
    md = (out / "report.md").read_text()
    assert "averaged over the 2 test views and the 20 run-time settings" in md
    assert "Run: test_views = 2, seed = 3, scene = builtin-ar, resolution = 16, optics = fast" in md


# ----------------------------------------------------------------------------- optional packages




# ----------------------------------------------------------------------------- the foveation axis
FOVEATED = "lens,resample,display,oled,foveation"


@needs_backbone
def test_eval_of_a_foveated_run_writes_the_band_tables(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """train --effects ...,foveation --ablation wo_foveation, then eval --gazes: results.json holds the axis (the
    gazes asked, the three settings, SS-backbone, ideal, ControlGS and w/o foveation, per band); report.md a table
    per gaze. The untrained w/o foveation adapter lacks the foveation module."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    run, out = tmp_path / "run", tmp_path / "report"
    assert main(["train", "--out", str(run), "--iterations", "2", "--resolution", "16", "--effects", FOVEATED,
                 "--ablation", "wo_foveation", "--no-progress", "--checkpoint-every", "0"]) == 0
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import load_builtin_backbone

    model = load_builtin_backbone("ar")
    for name, has in (("controlgs", True), ("wo_foveation", False)):
        cgs = ControlGS.load(run / f"{name}.controlgs.safetensors", model)
        assert ("foveation" in cgs.modules) is has
        cgs.unwrap()
    capsys.readouterr()
    assert main(["eval", "--run", str(run), "--out", str(out), "--resolution", "16", "--test-views", "1",
                 "--no-progress", "--gazes", "0,0", "10,0"]) == 0
    data = json.loads((out / "results.json").read_text())
    assert data["info"]["effects"] == sorted(FOVEATED.split(","))
    fov = data["foveation"]
    assert fov["gazes"] == [[0.0, 0.0], [10.0, 0.0]] and fov["settings"] == [[1.0, 0.0], [2.0, 0.4], [8.0, 0.8]]
    assert list(fov["methods"]) == ["ss", "ideal", "controlgs", "wo_foveation"]
    assert set(fov["methods"]["ss"]) == {f"{k}{b}" for k in ("psnr", "ssim") for b in ("", "_foveal", "_parafoveal",
                                                                                        "_periphery")}
    assert torch.tensor(fov["methods"]["controlgs"]["psnr"]["per_view"]).shape == (2, 3, 1)
    md = (out / "report.md").read_text()
    assert md.count("| Method | All | Foveal (< 5°) | Parafoveal (5-15°) | Periphery (≥ 15°) |") == 2
    assert "Gaze (10°, 0°):" in md and "| w/o Foveation |" in md


def test_gazes_outside_the_field_or_malformed_are_one_line(base_run: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    run = _run(base_run, tmp_path, effects=FOVEATED.split(","))
    before = snapshot(run)
    for gazes, want in ((["40,0"], "--gazes: gaze (40, 0) deg is outside the lens's field"),
                        (["0;0"], "--gazes takes AZ,EL pairs of degrees")):
        assert main(["eval", "--run", str(run), *FAST, "--gazes", *gazes]) == 2
        assert error_line(capsys, "eval").startswith(want)
    assert snapshot(run) == before
