"""``controlgs demo`` checks its options and ``--out`` before taking the report folder's lock: a
refused demo creates no folder."""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cli_runs import error_line

from controlgs_adapter.cli import main


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


import argparse
import json
import os
import subprocess
import sys
import time
import types
from typing import Any, Callable

import torch

from controlgs_adapter import cli
from controlgs_adapter.errors import ControlGSError, InputValueError, RunLockedError
from controlgs_adapter.evaluation import GridResult
from controlgs_adapter.lock import run_lock
from controlgs_adapter.report import markdown_tables
from controlgs_adapter.scene import builtin_backbone_dir

pytest.importorskip("skimage")

pytest.importorskip("matplotlib")



ROOT = Path(__file__).resolve().parents[2]


def _raises(fn: Callable[[], Any], error: type[BaseException] | tuple[type[BaseException], ...], *names: str) -> str:
    """Call ``fn``; it must raise ``error`` (a ControlGSError) whose message holds every one of ``names``."""
    with pytest.raises(error) as info:
        fn()
    assert isinstance(info.value, ControlGSError), type(info.value)
    msg = str(info.value)
    for n in names:
        assert n in msg, f"{n!r} not in {msg!r}"
    return msg


# ============================================================================ CLI
def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process: exit code 2, exactly one line on stderr, no traceback; returns it."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ============================================================================ run-folder lock
_HOLDER = """
import sys, time
from controlgs_adapter.lock import run_lock
with run_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def test_cli_unwritable_out_is_one_line(tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root writes anywhere")
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    assert "ro" in _cli(["demo", "--out", str(ro / "report")], capsys)


def test_run_folder_lock_refuses_a_second_process_naming_the_holder(tmp_path, capsys):
    run = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", _HOLDER, str(run)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "held"
        msg = _raises(lambda: run_lock(run).__enter__(), RunLockedError, str(run), f"pid {holder.pid}")
        assert "since" in msg
        line = _cli(["demo", "--out", str(run)], capsys)  # the CLI too: one line naming the holder
        assert f"pid {holder.pid}" in line
        second = subprocess.run([sys.executable, "-c", _HOLDER, str(run)], capture_output=True, text=True, cwd=ROOT,
                                timeout=120)
        assert second.returncode != 0 and f"pid {holder.pid}" in second.stderr
    finally:
        holder.kill()  # SIGKILL: the kernel drops the lock, the stale .lock file does not block
        holder.wait()
    with run_lock(run):
        assert json.loads((run / ".lock").read_text())["pid"] == os.getpid()


def test_cli_reports_bad_input_without_traceback(capsys, tmp_path):
    assert main(["demo", "--resolution", "0", "--out", str(tmp_path / "unused")]) == 2
    err = capsys.readouterr().err
    assert "resolution" in err and "Traceback" not in err


@pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(), reason="built-in backbone not baked")
def test_tiny_demo_writes_the_report(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "report"
    rc = main(["demo", "--out", str(out), "--resolution", "16", "--iterations", "2", "--psf-fraction", "0.5",
               "--test-views", "1", "--checkpoint-every", "1", "--no-progress", "--no-ablations"])
    assert rc == 0
    for name in ("results.json", "report.md", "heatmap.png", "comparison.png", "condition_response.png",
                 "controlgs.controlgs.safetensors"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    data = json.loads((out / "results.json").read_text())
    assert set(data["methods"]) == {"no_ss", "ss", "ideal", "controlgs"}
    for m in data["methods"].values():
        grid = torch.tensor(m["psnr"]["grid"], dtype=torch.float64)
        assert grid.shape == (4, 5) and bool(torch.isfinite(grid).all())
        assert m["psnr"]["mean"] == pytest.approx(float(grid.mean()), rel=1e-9)
    assert data["info"]["iterations"] == 2
    back = GridResult.from_json(data)
    assert back.mean("controlgs", "psnr") == data["methods"]["controlgs"]["psnr"]["mean"]


GRID = ((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8))


def _seed_result(seed: int, values: dict[str, float]) -> GridResult:
    """Every view and cell of a method holds one known PSNR (so its overall mean is that number)."""
    per_view = {m: {"psnr": torch.full((4, 5, 2), v, dtype=torch.float64)} for m, v in values.items()}
    return GridResult(*GRID, per_view, info={"seed": seed})


def test_seed_folders_and_pooling_checks(tmp_path):
    from controlgs_adapter.commands.demo import seed_runs
    from controlgs_adapter.commands.eval import seed_folders

    assert seed_runs(tmp_path, 3, None) == [(3, tmp_path)]
    assert seed_runs(tmp_path, 3, 2) == [(3, tmp_path / "seed-3"), (4, tmp_path / "seed-4")]
    with pytest.raises(InputValueError, match="--seeds"):
        seed_runs(tmp_path, 0, 0)
    assert seed_folders(tmp_path, 0, None) == [(0, tmp_path)]
    for s in (10, 2):
        (tmp_path / f"seed-{s}").mkdir()
    assert seed_folders(tmp_path, 0, None) == [(2, tmp_path / "seed-2"), (10, tmp_path / "seed-10")]
    with pytest.raises(InputValueError, match="pooled"):
        markdown_tables([_seed_result(0, {"ss": 1.0}), _seed_result(1, {"controlgs": 1.0})])


needs_backbone = pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                    reason="built-in backbone not baked")


# ------------------------------------------------------------------------------ eval / demo timings
def _timings_within(info: dict[str, Any], keys: tuple[str, ...], wall: float) -> None:
    """The reported durations (seconds, one decimal) are each >= 0 and together at most the command's
    wall time (measured around it here), allowing for the rounding of each."""
    got = [info[k] for k in keys]
    assert all(isinstance(v, float) and v >= 0 for v in got), info
    assert sum(got) <= wall + 0.05 * len(keys), (got, wall)


@needs_backbone
def test_demo_with_two_seeds(tmp_path, monkeypatch, capsys):
    """``controlgs demo --seeds 2 --seed 5``: one adapter per seed in ``seed-5/`` and ``seed-6/``, each trained
    with its own seed (they differ); the options reach the evaluation (``--resolution``, ``--test-views``)
    and info records them; the reported phase times are parts of the command's wall time."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("skimage")
    from safetensors.torch import load_file

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "report"
    t0 = time.perf_counter()
    assert cli.main(["demo", "--out", str(out), "--resolution", "16", "--iterations", "1", "--test-views", "1",
                     "--effects", "display", "--checkpoint-every", "0", "--no-ablations", "--no-progress",
                     "--seeds", "2", "--seed", "5"]) == 0
    wall = time.perf_counter() - t0
    a, b = (load_file(out / f"seed-{s}" / "controlgs.controlgs.safetensors") for s in (5, 6))
    assert a.keys() == b.keys() and any(not torch.equal(a[k], b[k]) for k in a)
    data = json.loads((out / "results.json").read_text())
    info = data["info"]
    assert (info["resolution"], info["test_views"], info["seeds"], info["seed"], info["iterations"]) == (16, 1, 2, 5, 1)
    assert info["test_sizes"] == ["16x16"]
    _timings_within(info, ("load_s", "train_s", "eval_s", "figures_s"), wall)
    assert info["train_s"] > 0 and info["eval_s"] > 0


def _parse(*argv: str) -> argparse.Namespace:
    return cli.build_parser().parse_args(list(argv))


def _err(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {command}: error: "), err
    return err[0][len(f"controlgs {command}: error: "):]


def test_demo_view_scene_optics_bench_defaults():
    d = _parse("demo")
    assert (d.out, d.ablations, d.iterations, d.resolution, d.variant) == ("report", True, 1000, None, "ar")
    v = _parse("view")
    assert (v.run, v.port, v.iterations, v.threads, v.resolution, v.test_views) == (None, 0, 150, None, None, None)
    b = _parse("scene", "build-backbone", "--out", "o")
    assert (b.variant, b.resolution, b.iterations, b.max_anchors, b.n_offsets, b.seed) == ("ar", 128, 1500, 3000, 5, 0)
    x = _parse("scene", "export", "--out", "o")
    assert (x.variant, x.resolution, x.scene_command) == ("ar", 128, "export")
    o = _parse("optics", "build-bank")
    assert (o.out, tuple(o.grid), o.psf_size, o.pupil_samples, o.min_pitch_px, o.prescription) == \
        (Path("psf_bank.safetensors"), (30, 30), 33, 192, 0.125, None)
    c = _parse("optics", "bench")
    assert (c.sizes, c.radiometry, c.tols, c.repeat, c.scaling, c.zone, c.exact_max, c.threads, c.out) == \
        (["256", "512", "1024", "576x1024"], ["radiance", "energy"], [0.02], 3, True, 5, 1024, 2, None)
    assert _parse("optics", "bench", "--doc").out == Path("docs") and _parse("optics", "bench", "--no-scaling").scaling is False
    w = _parse("optics", "fit-prewarp", "--out", "l.safetensors")
    assert (w.bank, w.size, w.modes, w.radiometry) == (None, 256, ["distortion", "exact"], "radiance")
    n = _parse("bench")
    assert (n.out, n.resolution, n.iterations, n.test_views, n.quick, n.variant, n.seed) == \
        (None, 96, None, None, False, "ar", 0)
    assert _parse("bench", "--doc").out == Path("docs") / "benchmarks.md"
    assert _parse("plugins").strict is False
    assert cli.COMMANDS == ("plugins", "optics", "scene", "backbone", "train", "eval", "demo", "bench", "view")


@pytest.mark.parametrize("argv, needs", [
    (["demo", "--out", "{d}/r"], "controlgs demo (the built-in scene and the report's plots) needs scikit-image"),
    (["optics", "bench"], "controlgs optics bench (the optics benchmark's test image and plot) needs scikit-image"),
    (["scene", "export", "--out", "{d}/x"], "controlgs scene export (exporting the built-in scene's views as PNG) "
                                            "needs scikit-image"),
])
def test_optional_dependencies_per_command_and_action(capsys, monkeypatch, tmp_path, argv, needs):
    """A stand-in module without a file counts as missing (extras.py): the command stops before its
    work with the extra to install."""
    monkeypatch.setitem(sys.modules, "skimage", types.ModuleType("skimage"))
    assert cli.main([a.replace("{d}", str(tmp_path)) for a in argv]) == 2
    assert _err(capsys, argv[0]) == f"{needs}, which is not installed: pip install 'controlgs-adapter[demo]'"
    assert not (tmp_path / "r").exists()


_DEMO_HINT = "which is not installed: pip install 'controlgs-adapter[demo]'"


@pytest.mark.parametrize("argv,blocked,purpose,missing", [
    (["demo"], "skimage", "controlgs demo (the built-in scene and the report's plots)", "scikit-image"),
    (["optics", "bench"], "skimage", "controlgs optics bench (the optics benchmark's test image and plot)",
     "scikit-image"),
    (["scene", "export"], "skimage", "controlgs scene export (exporting the built-in scene's views as PNG)",
     "scikit-image"),
    (["eval", "--run", "RUN"], "matplotlib", "controlgs eval (the report's plots)", "matplotlib"),
    (["demo"], "matplotlib", "controlgs demo (the built-in scene and the report's plots)", "matplotlib"),
])
def test_cli_refuses_a_missing_extra_before_any_work(tmp_path, monkeypatch, capsys, argv, blocked, purpose, missing):
    from controlgs_adapter.cli import main

    monkeypatch.setitem(sys.modules, blocked, None)  # ``import <blocked>`` raises ImportError
    out = tmp_path / "out"
    argv = [str(tmp_path / "run") if a == "RUN" else a for a in argv] + ["--out", str(out)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"controlgs {argv[0]}: error: {purpose} needs {missing}, {_DEMO_HINT}", err
    assert not out.exists()


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
