"""Tests of ``controlgs_adapter.commands.train``: its defaults and option checks (one line, before anything is
written), a run folder's record (a refused or failed run writes nothing, run.json only with its adapters, a
folder of another scene kept as it is, a full disk keeps the old files), seeds and ablations, a user's renderer
and rasterizer, and distributed runs (the process group's options, torchrun)."""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.capture import cropped_capture
import torch
from helpers.banks import random_bank
from helpers.cli_runs import FAST, MODEL, error_line, needs_backbone, snapshot, write_tiny_colmap
from helpers.progress import record_bars
from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp
from safetensors import SafetensorError
from safetensors.torch import load_file

import controlgs_adapter.formats.safetensors as st
from controlgs_adapter import cli, training
from controlgs_adapter.cli import main
from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND
from controlgs_adapter.datasets.detect import FORMATS
from controlgs_adapter.errors import NonFiniteError
from controlgs_adapter.formats.adapter import read_tensors
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.lock import run_lock
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV
from controlgs_adapter.scene import load_builtin_scene
from controlgs_adapter.training import Trainer

#: torchrun's variables
_TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
RUN_TIMEOUT = 80.0  # seconds: far beyond a healthy torchrun run; hitting it means a hang


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A COLMAP capture of the built-in scene (1 test, 5 training views at 24 px)."""
    return write_tiny_colmap(tmp_path_factory.mktemp("scene"))


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory, data: Path) -> Path:
    """A run trained for 2 iterations on the built-in backbone and ``data`` (tests copy it before changing it)."""
    run = tmp_path_factory.mktemp("trained") / "run"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "2", *FAST]) == 0
    return run


def _copy(run: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run, tmp_path / "run"))


def _parse(*argv: str) -> argparse.Namespace:
    return cli.build_parser().parse_args(list(argv))


def _single_process(monkeypatch: pytest.MonkeyPatch) -> None:
    for k in _TORCHRUN:
        monkeypatch.delenv(k, raising=False)


def _torchrun_env(monkeypatch: pytest.MonkeyPatch, *, rank: int = 0, world: int = 2, local: int = 0,
                  port: str = "1") -> None:
    """torchrun's variables for rank ``rank`` of ``world`` (port 1: nothing listens there)."""
    for k, v in zip(_TORCHRUN, (rank, world, local, "127.0.0.1", port)):
        monkeypatch.setenv(k, str(v))


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


#: a user's render module: a renderer and a render function that log their calls, and attributes that do not render
USER_MODULE = '''
from pathlib import Path

LOG = Path(__file__).with_suffix(".calls")


def _log(what):
    with LOG.open("a") as f:
        f.write(what + "\\n")


class CountingRenderer:
    """The model's own prefilter and render, logging each call."""

    def visible(self, model, camera):
        _log("visible")
        return model.visible_anchors(camera)

    def render(self, model, camera, visible, background):
        _log("render")
        return model.render(camera, visible, background).color


renderer = CountingRenderer()


def render_all(model, camera, visible, background):
    _log("function")
    return model.render(camera, visible, background)


def wrong_arguments(model, camera):
    return None


number = 3
'''


def _calls(log):
    return log.read_text().split() if log.is_file() else []


# ----------------------------------------------------------------------------- options

def test_train_defaults():
    a = _parse("train")
    assert (a.out, a.variant, a.resolution, a.test_views, a.optics, a.seed, a.seeds, a.progress) == \
        ("controlgs-run", "ar", None, None, "fast", 0, None, True)
    assert (a.iterations, a.psf_fraction, a.lr, a.cond_dim, a.checkpoint_every, a.effects) == (1000, 0.1, 3e-3, 8, 500, None)
    assert (a.batch_size, a.scenes, a.dist_backend, a.dist_timeout, a.exchange) == (1, None, None, 300.0, "auto")
    assert (a.ablations, a.ablation, a.cache_mib, a.device, a.holdout, a.rasterizer, a.renderer) == \
        (True, [], 1024, "cpu", None, None, None)
    assert (a.model, a.data, a.family, a.model_iteration, a.allow_unquantized, a.white_background, a.images) == \
        (None,) * 7
    assert _parse("train", "--no-ablations").ablations is False
    assert _parse("train", "--ablation", "wo_lens", "--ablation", "state_blind").ablation == ["wo_lens", "state_blind"]


@needs_backbone
@pytest.mark.parametrize("option, value", [
    ("--iterations", "-1"), ("--seed", "-1"), ("--lr", "nan"), ("--lr", "0"), ("--psf-fraction", "1.5"),
    ("--cond-dim", "0"), ("--checkpoint-every", "-2"), ("--batch-size", "0"), ("--seeds", "0"),
    ("--test-views", "0"), ("--resolution", "0"), ("--holdout", "-1"), ("--cache-mib", "-1"),
    ("--effects", "blur"), ("--device", "meta"), ("--device", "cuda:99"), ("--device", "nodevice"),
    ("--lens", "cardbaord"), ("--lens", "no/such/lens.json"),
])
def test_a_refused_option_writes_nothing(tmp_path: Path, data: Path, capsys: pytest.CaptureFixture[str],
                                         option: str, value: str) -> None:
    new = tmp_path / "new"
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(new), "--iterations", "2", *FAST]
    assert main([*argv, option, value]) == 2
    line = error_line(capsys, "train")
    assert line.startswith(f"{option} ") and value in line, line
    assert not new.exists()  # no folder, no lock file, no run.json


@needs_backbone
def test_a_lens_file_that_does_not_load_writes_nothing(tmp_path: Path, data: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    bank = tmp_path / "broken.safetensors"
    bank.write_bytes(b"not a bank")
    new = tmp_path / "new"
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(new), "--iterations", "2", *FAST]
    assert main([*argv, "--lens", str(bank)]) == 2
    assert error_line(capsys, "train").startswith(f"{bank}: not a readable safetensors file")
    assert not new.exists()


@pytest.mark.parametrize("command", ["train", "eval"])
def test_unknown_dataset_format_is_refused_by_argparse(command, capsys):
    with pytest.raises(SystemExit) as e:
        _parse(command, "--format", "nerfstudio")
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "argument --format: invalid choice: 'nerfstudio'" in err, err
    for f in FORMATS:
        assert repr(f) in err, (f, err)
    first = next(iter(FORMATS))
    assert _parse(command, "--format", first).format == first


def test_train_refusals_before_any_loading(capsys, tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    # --scenes trains built-in scenes only (and takes no run-folder lock: each process locks its scenes)
    assert main(["train", "--model", "m", "--data", "d", "--scenes", "ar", "--out", str(blocker / "run")]) == 2
    assert error_line(capsys, "train").startswith("--scenes trains built-in scenes; ")
    # rank 0 takes the run folder's lock (which cannot be made under a file); another rank does not
    assert main(["train", "--model", "m", "--out", str(blocker / "run")]) == 2
    assert str(blocker) in error_line(capsys, "train")
    monkeypatch.setenv("RANK", "1")
    assert main(["train", "--model", "m", "--out", str(blocker / "run")]) == 2
    assert error_line(capsys, "train").startswith("give both --model MODEL_DIR and --data DATA_DIR")
    with pytest.raises(SystemExit) as e:
        main(["train", "--device"])  # argparse's own usage error
    assert e.value.code == 2


@needs_backbone
def test_a_missing_or_wrong_model_and_flipped_cameras_are_one_line(tmp_path, capsys):
    cams, images = cropped_capture(16)
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    assert main(["train", "--model", str(tmp_path), "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    flipped = json.loads((data / "transforms.json").read_text())
    for f in flipped["frames"]:  # camera to world given in OpenCV axes: the scene is behind every camera
        for row in f["transform_matrix"][:3]:
            row[1], row[2] = -row[1], -row[2]
    (data / "transforms.json").write_text(json.dumps(flipped))
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("controlgs train: error: ") for line in err), err
    assert "--model" in err[0] and "not a trained model folder" in err[1] and "flipped" in err[2]


@needs_backbone
@pytest.mark.parametrize("option, expected", [
    (["--rasterizer", "nvdiffrast"], "--rasterizer 'nvdiffrast' is not registered; available: "),
    (["--rasterizer", "gsplat"], "pip install 'controlgs-adapter[gsplat]'"),
    (["--renderer", "no_such_module_xyz:render"], "no module named 'no_such_module_xyz'"),
    (["--renderer", "my_render:missing"], "my_render has no attribute 'missing'"),
    (["--renderer", "my_render:CountingRenderer"], "CountingRenderer is a class"),
    (["--renderer", "my_render:wrong_arguments"], "wrong_arguments does not fit the render protocol"),
    (["--renderer", "my_render:number"], "number does not fit the render protocol"),
    (["--renderer", "my_render"], "--renderer must be MODULE:ATTR or path/to/file.py:ATTR"),
    (["--renderer", "nowhere/render.py:render"], "no such file nowhere/render.py"),
])
def test_bad_rasterizer_or_renderer_is_one_line(tmp_path, data, monkeypatch, capsys, option, expected):
    (tmp_path / "my_render.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)
    code = main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(tmp_path / "run"), "--iterations", "1",
                 *FAST, *option])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and expected in err, err
    if option[1] == "nvdiffrast":
        assert "torch" in err and "gsplat" in err
    assert not (tmp_path / "run" / "controlgs.controlgs.safetensors").exists()


# ----------------------------------------------------------------------------- the run folder's record

def test_train_refuses_a_locked_run_folder(tmp_path, capsys):
    run = tmp_path / "run"
    with run_lock(run):
        assert main(["train", "--out", str(run), "--iterations", "1"]) == 2
        line = error_line(capsys, "train")
    assert f"pid {os.getpid()}" in line and str(run) in line


@needs_backbone
def test_a_run_that_fails_after_the_lock_leaves_no_folder(tmp_path: Path, data: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    new = tmp_path / "a" / "b" / "new"
    assert main(["train", "--model", str(tmp_path / "no_model"), "--data", str(data), "--out", str(new), *FAST]) == 2
    assert str(tmp_path / "no_model") in error_line(capsys, "train")
    assert not (tmp_path / "a").exists()


@needs_backbone
def test_run_json_is_written_only_with_the_adapters(tmp_path: Path, data: Path, trained: Path,
                                                    capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    record = json.loads((trained / "run.json").read_text())
    assert record["iterations"] == 2 and record["adapters"] == ["controlgs"]
    assert (trained / "controlgs.controlgs.safetensors").is_file()

    def diverge(self: Trainer, *args: object, **kwargs: object) -> None:
        raise NonFiniteError("training diverged: the loss is NaN at iteration 1")

    monkeypatch.setattr(Trainer, "train", diverge)
    new = tmp_path / "new"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(new), "--iterations", "2", *FAST]) == 2
    assert "loss is NaN" in error_line(capsys, "train")
    assert not (new / "run.json").exists() and not (new / "controlgs.controlgs.safetensors").exists()

    run = _copy(trained, tmp_path)
    before = snapshot(run)
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "5", *FAST]) == 2
    assert "loss is NaN" in error_line(capsys, "train")
    assert snapshot(run) == before  # the record still says 2 iterations, with the adapter of 2


@needs_backbone
@pytest.mark.parametrize("what", ["--model", "--data", "--effects", "--resolution", "--lens"])
def test_a_run_folder_of_another_scene_is_refused_and_kept(tmp_path: Path, data: Path, trained: Path,
                                                           capsys: pytest.CaptureFixture[str], what: str) -> None:
    run = _copy(trained, tmp_path)
    before = snapshot(run)
    model, scene = MODEL, data
    extra: list[str] = []
    if what == "--model":  # the same backbone in another folder: another model as far as the record goes
        model = Path(shutil.copytree(MODEL, tmp_path / "other_model"))
    elif what == "--data":
        scene = Path(shutil.copytree(data, tmp_path / "other_data"))
    elif what == "--effects":
        extra = ["--effects", "display"]
    elif what == "--lens":
        random_bank(C=5).save(tmp_path / "mine.safetensors")
        extra = ["--lens", str(tmp_path / "mine.safetensors")]
    else:
        extra = ["--resolution", "16"]
    argv = ["train", "--model", str(model), "--data", str(scene), "--out", str(run), "--iterations", "3", *FAST, *extra]
    assert main(argv) == 2
    line = error_line(capsys, "train")
    assert line.startswith(f"--out {run}: ") and f"{what} " in line, line
    if what in ("--model", "--data"):
        recorded = json.loads(before["run.json"])[what[2:]]
        assert recorded in line and str(model if what == "--model" else scene) in line
    assert snapshot(run) == before


@needs_backbone
def test_the_same_scene_trains_on_and_updates_the_record(tmp_path: Path, data: Path, trained: Path) -> None:
    run = _copy(trained, tmp_path)
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3", *FAST]) == 0
    assert json.loads((run / "run.json").read_text())["iterations"] == 3


@needs_backbone
def test_a_broken_run_file_in_the_out_folder_is_refused(tmp_path: Path, data: Path, trained: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    run = _copy(trained, tmp_path)
    (run / "run.json").write_text(json.dumps({**json.loads((run / "run.json").read_text()), "effects": 5}))
    before = snapshot(run)
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3", *FAST]) == 2
    line = error_line(capsys, "train")
    assert str(run / "run.json") in line and "'effects'" in line and "got 5" in line
    assert snapshot(run) == before


@needs_backbone
@pytest.mark.parametrize("error", [OSError(28, "No space left on device"),
                                   SafetensorError("Error while serializing: I/O error: No space left on device")])
def test_a_full_disk_while_writing_is_one_line_and_keeps_the_old_files(
        tmp_path: Path, data: Path, trained: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch, error: Exception) -> None:
    run = _copy(trained, tmp_path)
    before = snapshot(run)
    writes: list[str] = []

    def full_disk(tensors: object, filename: str, metadata: object = None) -> None:
        Path(filename).write_bytes(b"\0" * 64)  # part of the file made it to the disk
        writes.append(filename)
        raise error

    monkeypatch.setattr(st, "save_file", full_disk)
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "4", *FAST,
            "--checkpoint-every", "2"]
    assert main(argv) == 2
    line = error_line(capsys, "train")
    assert f"{run / 'checkpoints' / 'controlgs.ckpt.safetensors'}: write failed: " in line
    assert "No space left on device" in line
    assert writes and not any(Path(w).exists() for w in writes)  # the temporary file is removed
    assert snapshot(run) == before  # the old adapter, checkpoint and record survive


@needs_backbone
def test_full_disk_by_file_size_limit_in_a_real_write(tmp_path: Path, data: Path, trained: Path) -> None:
    """The same through the kernel: ``RLIMIT_FSIZE`` below the checkpoint's size in a child process."""
    run = _copy(trained, tmp_path)
    before = snapshot(run)
    limit = len(before["controlgs.controlgs.safetensors"]) // 2
    code = ("import resource, signal, sys\n"
            "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
            f"resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))\n"
            "from controlgs_adapter.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3", *FAST]
    # -B: under the limit the interpreter would leave truncated bytecode caches behind
    done = subprocess.run([sys.executable, "-B", "-c", code, *argv], capture_output=True, text=True, timeout=300,
                          env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "PYTHONDONTWRITEBYTECODE": "1"})
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(err) == 1, done.stderr
    assert err[0].startswith(f"controlgs train: error: {run}") and "write failed: " in err[0], err
    assert snapshot(run) == before
    assert not list(run.rglob("*.tmp"))


# ----------------------------------------------------------------------------- seeds and ablations

@needs_backbone
def test_seeds_train_each_seed_on_a_users_scene(tmp_path):
    """``--seeds 2 --seed 5`` on ``--model/--data`` trains seed-5/ and seed-6/ with their own seeds: each
    adapter equals the one a single run with that ``--seed`` writes (and the two differ)."""
    cams, images = cropped_capture(16)
    data = write_colmap(tmp_path / "colmap", cams, images)
    common = ["--model", str(MODEL), "--data", str(data), "--iterations", "2", *FAST]
    assert main(["train", *common, "--out", str(tmp_path / "multi"), "--seeds", "2", "--seed", "5"]) == 0
    assert main(["train", *common, "--out", str(tmp_path / "single"), "--seed", "6"]) == 0
    name = "controlgs.controlgs.safetensors"
    five = read_tensors(tmp_path / "multi" / "seed-5" / name)
    six = read_tensors(tmp_path / "multi" / "seed-6" / name)
    alone = read_tensors(tmp_path / "single" / name)
    assert five.keys() == six.keys() == alone.keys()
    assert all(torch.equal(six[k], alone[k]) for k in six)
    assert not all(torch.equal(five[k], six[k]) for k in five)


@needs_backbone
def test_train_built_in_with_two_seeds_and_one_ablation(tmp_path, monkeypatch, capsys):
    """``controlgs train --seeds 2 --seed 5 --ablation wo_lens`` on the built-in scene: ControlGS and only the
    chosen ablation, per seed in ``seed-<s>/``, each seed its own training; run.json records the run."""
    _single_process(monkeypatch)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "run"
    assert main(["train", "--out", str(out), "--iterations", "1", "--resolution", "16", "--effects", "display",
                     "--checkpoint-every", "0", "--no-progress", "--seeds", "2", "--seed", "5",
                     "--ablation", "wo_lens"]) == 0
    want = [out / f"seed-{s}" / f"{n}.controlgs.safetensors" for s in (5, 6) for n in ("controlgs", "wo_lens")]
    assert capsys.readouterr().out.splitlines()[-4:] == [f"{p.name.split('.')[0]}: {p}" for p in want]
    record = json.loads((out / "run.json").read_text())
    assert {k: record[k] for k in ("variant", "effects", "iterations", "seed", "seeds", "adapters")} == \
        {"variant": "ar", "effects": ["display"], "iterations": 1, "seed": 5, "seeds": 2, "adapters": ["controlgs", "wo_lens"]}
    a, b = (load_file(out / f"seed-{s}" / "controlgs.controlgs.safetensors") for s in (5, 6))
    assert any(not torch.equal(a[k], b[k]) for k in a)


@needs_backbone
def test_train_many_scenes_mode(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "runs"
    assert main(["train", "--scenes", "ar", "--out", str(out), "--iterations", "1", "--resolution", "16",
                 "--no-ablations", "--effects", "display", "--checkpoint-every", "0", "--no-progress",
                 "--seeds", "2", "--seed", "5"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    want = [out / "ar" / f"seed-{s}" / "controlgs.controlgs.safetensors" for s in (5, 6)]
    assert lines[-2:] == [f"[rank 0] ar controlgs: {p}" for p in want]
    assert all(p.is_file() for p in want) and not (out / "run.json").exists()


# ----------------------------------------------------------------------------- a user's renderer and rasterizer

@needs_backbone
def test_user_renderer_and_rasterizer_train_and_evaluate(tmp_path, data, monkeypatch):
    pytest.importorskip("matplotlib")  # eval's report
    module = tmp_path / "my_render.py"
    module.write_text(USER_MODULE)
    log = module.with_suffix(".calls")
    monkeypatch.setenv(RASTERIZER_ENV, "gsplat")  # ignored by a run that passes --rasterizer torch; fatal on CPU otherwise
    run, report = tmp_path / "run", tmp_path / "report"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3",
                 *FAST, "--rasterizer", "torch", "--renderer", f"{module}:renderer"]) == 0
    record = json.loads((run / "run.json").read_text())
    assert record["renderer"] == f"{module.resolve()}:renderer" and record["rasterizer"] == "torch"
    trained = _calls(log)
    assert trained.count("render") == 3 and trained.count("visible") == 3  # one render per training step

    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress"]) == 2
    assert _calls(log) == trained  # the run's renderer is not run without the user's say
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress",
                 "--trust-run-renderer"]) == 0
    evaluated = _calls(log)[len(trained):]
    assert evaluated.count("render") > 20  # the grid's renders (4 x 5 states, baselines) went through it
    info = json.loads((report / "results.json").read_text())["info"]
    assert info["renderer"] == record["renderer"] and info["rasterizer"] == "torch"

    # without the recorded choice the environment's gsplat applies, and cannot render on the CPU
    (run / "run.json").write_text(json.dumps({**record, "rasterizer": "auto"}))
    assert main(["eval", "--run", str(run), "--out", str(report), "--test-views", "1", "--no-progress",
                 "--trust-run-renderer"]) == 2


@needs_backbone
def test_a_render_function_from_the_current_folder(tmp_path, data, monkeypatch, capsys):
    (tmp_path / "my_render_fn.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)  # MODULE:ATTR is found in the current folder, as `python -m` would
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(tmp_path / "run"), "--iterations", "2",
                 *FAST, "--renderer", "my_render_fn:render_all"]) == 0
    assert _calls(tmp_path / "my_render_fn.calls") == ["function", "function"]
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["renderer"] == "my_render_fn:render_all" and record["rasterizer"] == "auto"


# ----------------------------------------------------------------------------- distributed training

@pytest.mark.parametrize("value, shown", [("0", "0.0"), ("-2.5", "-2.5")])
def test_train_dist_timeout_reaches_init_distributed(value, shown, tmp_path, capsys, monkeypatch):
    _single_process(monkeypatch)
    rc = main(["train", "--out", str(tmp_path / "run"), "--dist-timeout", value, "--iterations", "1",
                   "--no-ablations", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"controlgs train: error: timeout must be > 0 seconds, got {shown}"], err
    assert not (tmp_path / "run" / "controlgs.controlgs.safetensors").exists()


@needs_backbone
@pytest.mark.parametrize("exchange", ["dense", "sparse"])
def test_train_records_the_exchange_that_reached_the_process_group(exchange, tmp_path, monkeypatch):
    _single_process(monkeypatch)
    out = tmp_path / "run"
    assert main(["train", "--out", str(out), "--iterations", "1", "--no-ablations", "--no-progress",
                     "--resolution", "16", "--effects", "display", "--exchange", exchange]) == 0
    record = json.loads((out / "run.json").read_text())
    # one process: no process group (backend None); the exchange is the one init_distributed was given
    assert record["distributed"] == {"processes": 1, "backend": None, "exchange": exchange}


@needs_backbone
def test_train_on_your_own_scene_records_the_exchange(tmp_path, monkeypatch, capsys):
    model = MODEL
    _single_process(monkeypatch)
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    data = write_blender(tmp_path / "data", scene.test_cameras + scene.train_cameras,
                         list(torch.cat([scene.test_images, scene.train_images])), test=[0])
    out = tmp_path / "run"
    assert main(["train", "--model", str(model), "--data", str(data), "--out", str(out), "--iterations", "1",
                     "--no-ablations", "--no-progress", "--effects", "display", "--checkpoint-every", "0",
                     "--exchange", "dense"]) == 0
    record = json.loads((out / "run.json").read_text())
    assert record["family"] == "scaffold_gs"
    assert record["distributed"] == {"processes": 1, "backend": None, "exchange": "dense"}


def test_train_command_passes_its_device(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # a GPU machine, as far as the old rule knew
    _torchrun_env(monkeypatch, port="not-a-port")
    # default --device cpu: gloo (the group then fails to form on the bad port, naming the backend)
    assert main(["train", "--out", str(tmp_path / "a"), "--dist-timeout", "2"]) == 2
    assert "could not join the process group at 127.0.0.1:not-a-port (gloo)" in capsys.readouterr().err
    assert main(["train", "--out", str(tmp_path / "b"), "--dist-backend", "nccl"]) == 2
    err = capsys.readouterr().err
    assert "controlgs train: error: backend 'nccl' does not fit device 'cpu'" in err


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (--device cuda is refused without it)")
def test_train_command_with_cuda_and_too_many_processes_per_node(monkeypatch, tmp_path, capsys):
    gpus = torch.cuda.device_count()
    _torchrun_env(monkeypatch, rank=gpus, world=gpus + 2, local=gpus)
    assert main(["train", "--out", str(tmp_path / "a"), "--device", "cuda"]) == 2
    assert f"this machine has {gpus} GPU(s) visible" in capsys.readouterr().err


@needs_backbone
def test_controlgs_train_command_under_torchrun(tmp_path, monkeypatch):
    """The unchanged `controlgs train` under torchrun (2 processes, dense condition exchange)
    writes the adapter once and it equals the single-process command's with the same global batch
    and seed."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    common = ["train", "--resolution", "16", "--iterations", "2", "--batch-size", "2", "--checkpoint-every", "1", "--no-ablations",
              "--exchange", "dense", "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "one")]) == 0
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore",
           "XDG_CACHE_HOME": str(tmp_path / "cache")}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--nnodes=1", "--nproc_per_node=2",
                           "--master_addr=127.0.0.1", f"--master_port={_free_port()}", "--max_restarts=0",
                           "-m", "controlgs_adapter.cli", *common, "--out", str(tmp_path / "two")],
                          env=env, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert proc.stdout.count("controlgs: ") == 1  # only rank 0 reports (and writes)
    name = "controlgs.controlgs.safetensors"
    want, _ = load_tensors(tmp_path / "one" / name, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    got, _ = load_tensors(tmp_path / "two" / name, kind=ADAPTER_KIND, max_version=ADAPTER_FORMAT_VERSION)
    assert set(got) == set(want) and want["conditions"].abs().max() > 0
    for k in want:
        torch.testing.assert_close(got[k], want[k], rtol=1e-5, atol=1e-6, msg=lambda m: f"{k}: {m}")


@pytest.mark.parametrize("option", ["--iterations", "--cond-dim", "--checkpoint-every", "--test-views", "--batch-size"])
def test_a_count_beyond_int64_is_one_line(tmp_path: Path, data: Path, capsys: pytest.CaptureFixture[str],
                                          option: str) -> None:
    new = tmp_path / "new"
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(new), *FAST]
    assert main([*argv, option, "9" * 400]) == 2
    line = error_line(capsys, "train")
    assert line.startswith(f"{option} must be an integer in ") and "401 digits" in line, line
    assert not new.exists()


def test_train_with_seeds_and_ablations_names_each_bar(tmp_path, monkeypatch):
    """``controlgs train --seeds 2 --ablation wo_lens``: four trainings, each bar titled with its place in the
    job, its method and seed, and showing the whole job's time left."""
    from controlgs_adapter.cli import main

    bars = record_bars(monkeypatch, training)
    assert main(["train", "--out", str(tmp_path / "run"), "--resolution", "16", "--iterations", "2", "--seeds", "2",
                 "--ablation", "wo_lens", "--effects", "resample,display", "--checkpoint-every", "0"]) == 0
    assert [b.desc for b in bars] == ["[1/4] training ControlGS, seed 0", "[2/4] training w/o Lens, seed 0",
                                      "[3/4] training ControlGS, seed 1", "[4/4] training w/o Lens, seed 1"]
    assert all(b.total == b.n == 2 and b.closed for b in bars)
    lefts = [p["total left"] for b in bars for p in b.postfixes]
    assert len(lefts) == 8 and all(re.fullmatch(r"~\d+s", v) for v in lefts), lefts
