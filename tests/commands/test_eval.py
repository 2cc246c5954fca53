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
from helpers.cli_runs import MARKER_MODULE, error_line, needs_backbone, snapshot, untrained_run

import controlgs_adapter.commands.eval as eval_command
from controlgs_adapter.cli import main

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


import time
import types

import torch

from controlgs_adapter import ControlGS, cli
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_backbone

pytest.importorskip("matplotlib")

pytest.importorskip("skimage")



def _eval_run(tmp_path: Path, seeds: dict[str, tuple[str, ...]]) -> Path:
    run = tmp_path / "run"
    for folder, names in seeds.items():
        (run / folder).mkdir(parents=True, exist_ok=True)
        for n in names:
            (run / folder / f"{n}.controlgs.safetensors").write_text("")  # checked for presence before any load
    return run


def test_eval_seed_folders(tmp_path: Path) -> None:
    from controlgs_adapter.commands.eval import seed_folders

    assert seed_folders(tmp_path, 5, None) == [(5, tmp_path)]  # no seed folders: the run folder itself
    for name in ("seed-2", "seed--1", "seed-10", "seed-x", "seed-"):
        (tmp_path / name).mkdir()
    (tmp_path / "seed-7").write_text("")  # a file, not a folder
    assert seed_folders(tmp_path, 0, None) == [(-1, tmp_path / "seed--1"), (2, tmp_path / "seed-2"),
                                               (10, tmp_path / "seed-10")]
    assert seed_folders(tmp_path, 2, 1) == [(2, tmp_path)]
    assert seed_folders(tmp_path, -1, 2) == [(-1, tmp_path / "seed--1"), (0, tmp_path / "seed-0")]


def test_eval_refuses_seed_folders_with_different_adapters(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _eval_run(tmp_path, {"seed-1": ("controlgs",), "seed-2": ("controlgs", "wo_lens")})
    assert cli.main(["eval", "--run", str(run)]) == 2
    assert (f"{run}: the seed folders hold different adapters (seed-1: controlgs; seed-2: controlgs, wo_lens)"
            in capsys.readouterr().err)
    run = _eval_run(tmp_path / "one", {".": ()})
    assert cli.main(["eval", "--run", str(run)]) == 2  # one seed: the run folder itself is named
    assert f"controlgs eval: error: {run}: no controlgs.controlgs.safetensors" in capsys.readouterr().err


needs_backbone_2 = pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                    reason="built-in backbone not baked")


# ------------------------------------------------------------------------------ eval / demo timings
def _timings_within(info: dict[str, Any], keys: tuple[str, ...], wall: float) -> None:
    """The reported durations (seconds, one decimal) are each >= 0 and together at most the command's
    wall time (measured around it here), allowing for the rounding of each."""
    got = [info[k] for k in keys]
    assert all(isinstance(v, float) and v >= 0 for v in got), info
    assert sum(got) <= wall + 0.05 * len(keys), (got, wall)


@needs_backbone_2
def test_eval_reported_times_are_parts_of_its_run(tmp_path, monkeypatch, capsys):
    """``controlgs eval`` reports ``load_s`` / ``eval_s`` in results.json's info: the time of loading
    and of the grid evaluation, both within the command's own time."""
    pytest.importorskip("matplotlib")
    from controlgs_adapter import ControlGS
    from controlgs_adapter.scene import load_builtin_backbone

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    run = tmp_path / "run"
    run.mkdir()
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    t0 = time.perf_counter()
    assert cli.main(["eval", "--run", str(run), "--resolution", "16", "--test-views", "1", "--effects", "display",
                     "--no-progress"]) == 0
    wall = time.perf_counter() - t0
    info = json.loads((run / "results.json").read_text())["info"]
    _timings_within(info, ("load_s", "eval_s"), wall)
    assert info["eval_s"] > 0 and (info["test_views"], info["effects"]) == (1, ["display"])


def _err(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {command}: error: "), err
    return err[0][len(f"controlgs {command}: error: "):]


def test_commands_that_do_not_need_the_missing_extra(capsys, monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "skimage", types.ModuleType("skimage"))
    # eval needs matplotlib only: it goes on to its own check of the run folder
    assert cli.main(["eval", "--run", str(tmp_path)]) == 2
    assert _err(capsys, "eval") == (f"{tmp_path}: no controlgs.controlgs.safetensors (train one with "
                                    f"`controlgs train --out {tmp_path}`)")
    # optics figures needs neither
    assert cli.main(["optics", "figures", "--prescription", str(tmp_path / "none.json")]) == 2
    assert _err(capsys, "optics") == f"--prescription {tmp_path / 'none.json'}: no such file"
    monkeypatch.setitem(sys.modules, "matplotlib", types.ModuleType("matplotlib"))
    assert cli.main(["eval", "--run", str(tmp_path)]) == 2
    assert _err(capsys, "eval").startswith("controlgs eval (the report's plots) needs matplotlib")


# ------------------------------------------------------------------------------ helpers
def test_seed_folders(tmp_path):
    from controlgs_adapter.commands.eval import seed_folders

    assert seed_folders(tmp_path, 4, None) == [(4, tmp_path)]
    for name in ("seed-3", "seed-12", "seed--1", "seed-x"):
        (tmp_path / name).mkdir()
    (tmp_path / "seed-7").write_text("")  # a file, not a seed folder
    assert seed_folders(tmp_path, 0, None) == [(-1, tmp_path / "seed--1"), (3, tmp_path / "seed-3"),
                                               (12, tmp_path / "seed-12")]
    assert seed_folders(tmp_path, 3, 2) == [(3, tmp_path / "seed-3"), (4, tmp_path / "seed-4")]
    assert seed_folders(tmp_path, 3, 1) == [(3, tmp_path)]
    for bad in (0, -2, True, 1.5):
        with pytest.raises(InputValueError, match="--seeds must be an int >= 1"):
            seed_folders(tmp_path, 0, bad)  # type: ignore[arg-type]


def test_eval_of_a_built_in_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    run.mkdir()
    cgs = ControlGS.wrap(load_builtin_backbone("ar"), cond_dim=2)  # an untrained (zero) adapter: the backbone
    cgs.save(run / "controlgs.controlgs.safetensors")
    cgs.unwrap()
    (run / "run.json").write_text(json.dumps({"variant": "ar", "effects": ["display"], "iterations": 7, "seed": 3,
                                              "seeds": 1, "adapters": ["controlgs"], "rasterizer": "auto",
                                              "renderer": None}))
    out = tmp_path / "report"
    assert main(["eval", "--run", str(run), "--out", str(out), "--resolution", "16", "--test-views", "2",
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out.split()
    assert printed == [str(out / f) for f in ("results.json", "heatmap.png", "comparison.png",
                                              "condition_response.png", "report.md")]
    data = json.loads((out / "results.json").read_text())
    info = data["info"]
    assert (info["resolution"], info["test_views"], info["seeds"], info["adapters"], info["effects"]) == \
        (16, 2, 1, ["controlgs"], ["display"])  # the effects of run.json
    assert (info["optics"], info["device"], info["rasterizer"], info["renderer"]) == ("fast", "cpu", "auto", None)
    assert (info["iterations"], info["seed"], info["test_sizes"]) == (7, 3, ["16x16"])
    assert "lpips_weights" not in info and info["load_s"] >= 0 and info["eval_s"] > 0
    assert set(data["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    ss = torch.tensor(data["methods"]["ss"]["psnr"]["per_view"])
    assert ss.shape == (4, 5, 2)  # the paper's grid, the first 2 test views
    # a zero adapter renders the backbone: the same numbers as the SS-backbone
    assert data["methods"]["controlgs"]["psnr"]["per_view"] == data["methods"]["ss"]["psnr"]["per_view"]
    md = (out / "report.md").read_text()
    assert "averaged over the 2 test views and the 20 run-time settings" in md
    assert "Run: test_views = 2, seed = 3, scene = builtin-ar, resolution = 16, optics = fast" in md


def test_cli_eval_needs_matplotlib_only(tmp_path, monkeypatch, capsys):
    """eval's table entry names matplotlib alone: without scikit-image it goes on (to its own error)."""
    from controlgs_adapter.cli import main

    monkeypatch.setitem(sys.modules, "skimage", None)
    assert main(["eval", "--run", str(tmp_path / "no-run"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("controlgs eval: error: ") and "scikit-image" not in err and "no-run" in err, err


def test_cli_import_errors_outside_the_table_are_one_line(tmp_path, monkeypatch, capsys):
    """A package missing at the command's own import (not in REQUIRES) and a broken install (a name
    missing from a module) each end in one line and exit code 2, never a traceback."""
    import controlgs_adapter.report as report
    from controlgs_adapter.cli import main

    pytest.importorskip("matplotlib")
    argv = ["eval", "--run", str(tmp_path / "run"), "--out", str(tmp_path / "out")]
    with monkeypatch.context() as mp:
        mp.setitem(sys.modules, "controlgs_adapter.report", None)
        assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == ("controlgs eval: error: needs the Python package 'controlgs_adapter.report', which is not installed "
                   "(pip install 'controlgs-adapter[demo]' installs the optional ones)\n"), err
    monkeypatch.delattr(report, "write_report")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("controlgs eval: error: cannot import name 'write_report' from 'controlgs_adapter.report'"), err
    assert err.endswith(" (pip install 'controlgs-adapter[demo]' installs the optional ones)\n") and err.count("\n") == 1


pytestmark = [pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                reason="built-in backbone not baked"), pytest.mark.filterwarnings("ignore::DeprecationWarning")]
