"""``controlgs train`` keeps a run folder's record true: a refused or failed run writes nothing (no
folder, no lock file, no run.json), run.json is written once the adapters are saved, a folder trained
on another model or dataset is refused with its record and adapters unchanged, and a failed
checkpoint or adapter write is one line with the old files intact."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from helpers.cli_runs import FAST, MODEL, error_line, needs_backbone, snapshot, write_tiny_colmap
from safetensors import SafetensorError

from controlgs_adapter.cli import main
from controlgs_adapter.errors import NonFiniteError

pytestmark = needs_backbone


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_colmap(tmp_path_factory.mktemp("scene"))


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory, data: Path) -> Path:
    """A run trained for 2 iterations on the built-in backbone and ``data`` (tests copy it before changing it)."""
    run = tmp_path_factory.mktemp("trained") / "run"
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "2", *FAST]) == 0
    return run


def _copy(run: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(run, tmp_path / "run"))


@pytest.mark.parametrize("option, value", [
    ("--iterations", "-1"), ("--seed", "-1"), ("--lr", "nan"), ("--lr", "0"), ("--psf-fraction", "1.5"),
    ("--cond-dim", "0"), ("--checkpoint-every", "-2"), ("--batch-size", "0"), ("--seeds", "0"),
    ("--test-views", "0"), ("--resolution", "0"), ("--holdout", "-1"), ("--cache-mib", "-1"),
    ("--effects", "blur"), ("--device", "meta"), ("--device", "cuda:99"), ("--device", "nodevice"),
])
def test_a_refused_option_writes_nothing(tmp_path: Path, data: Path, capsys: pytest.CaptureFixture[str],
                                         option: str, value: str) -> None:
    new = tmp_path / "new"
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(new), "--iterations", "2", *FAST]
    assert main([*argv, option, value]) == 2
    line = error_line(capsys, "train")
    assert line.startswith(f"{option} ") and value in line, line
    assert not new.exists()  # no folder, no lock file, no run.json


def test_a_run_that_fails_after_the_lock_leaves_no_folder(tmp_path: Path, data: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    new = tmp_path / "a" / "b" / "new"
    assert main(["train", "--model", str(tmp_path / "no_model"), "--data", str(data), "--out", str(new), *FAST]) == 2
    assert str(tmp_path / "no_model") in error_line(capsys, "train")
    assert not (tmp_path / "a").exists()


def test_run_json_is_written_only_with_the_adapters(tmp_path: Path, data: Path, trained: Path,
                                                    capsys: pytest.CaptureFixture[str],
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    from controlgs_adapter.training import Trainer

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


@pytest.mark.parametrize("what", ["--model", "--data", "--effects", "--resolution"])
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


def test_the_same_scene_trains_on_and_updates_the_record(tmp_path: Path, data: Path, trained: Path) -> None:
    run = _copy(trained, tmp_path)
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3", *FAST]) == 0
    assert json.loads((run / "run.json").read_text())["iterations"] == 3


def test_a_broken_run_file_in_the_out_folder_is_refused(tmp_path: Path, data: Path, trained: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    run = _copy(trained, tmp_path)
    (run / "run.json").write_text(json.dumps({**json.loads((run / "run.json").read_text()), "effects": 5}))
    before = snapshot(run)
    assert main(["train", "--model", str(MODEL), "--data", str(data), "--out", str(run), "--iterations", "3", *FAST]) == 2
    line = error_line(capsys, "train")
    assert str(run / "run.json") in line and "'effects'" in line and "got 5" in line
    assert snapshot(run) == before


@pytest.mark.parametrize("error", [OSError(28, "No space left on device"),
                                   SafetensorError("Error while serializing: I/O error: No space left on device")])
def test_a_full_disk_while_writing_is_one_line_and_keeps_the_old_files(
        tmp_path: Path, data: Path, trained: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch, error: Exception) -> None:
    import controlgs_adapter.formats.safetensors as st

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


def test_full_disk_by_file_size_limit_in_a_real_write(tmp_path: Path, data: Path, trained: Path) -> None:
    """The same through the kernel: ``RLIMIT_FSIZE`` below the checkpoint's size in a child process."""
    import subprocess
    import sys

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


import argparse
import os
import socket
import subprocess
import sys
from typing import Any

import torch
from helpers.scene_writers import write_blender, write_colmap, write_instant_ngp

from controlgs_adapter import cli
from controlgs_adapter.cli import build_parser
from controlgs_adapter.commands.adapters import train_config
from controlgs_adapter.commands.common import check_line
from controlgs_adapter.controlgs import ADAPTER_KIND
from controlgs_adapter.distributed import init_distributed
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.lock import run_lock
from controlgs_adapter.rendering.rasterizers import RASTERIZER_ENV
from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig

pytest.importorskip("skimage")

pytest.importorskip("matplotlib")



# ============================================================================ CLI
def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run the CLI in-process: exit code 2, exactly one line on stderr, no traceback; returns it."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_train_refuses_a_locked_run_folder(tmp_path, capsys):
    run = tmp_path / "run"
    with run_lock(run):
        line = _cli(["train", "--out", str(run), "--iterations", "1"], capsys)
    assert f"pid {os.getpid()}" in line and str(run) in line


MODEL_2 = builtin_backbone_dir("ar")


# cheap downstream path (the PSF optics cost ~0.5 s per image whatever its size)
FAST_2 = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0"]


def _capture(size: int = 32, crop: tuple[int, int] | None = None) -> tuple[list[Camera], list[torch.Tensor]]:
    """8 views of the built-in scene (view 0 is the test view in every format); ``crop = (w, h)``
    cuts a centred window out of each image with matching intrinsics."""
    scene = load_builtin_scene("ar", size, views=8, test_every=8, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    images = list(torch.cat([scene.test_images, scene.train_images]))
    if crop is None:
        return cams, images
    w, h = crop
    x0, y0 = (size - w) // 2, (size - h) // 2
    out = []
    for c in cams:
        k = c.intrinsics.clone()
        k[0, 2] -= x0
        k[1, 2] -= y0
        out.append(Camera(c.world_to_camera, k, w, h))
    return out, [img[:, y0:y0 + h, x0:x0 + w].contiguous() for img in images]


def test_user_errors_are_one_line(tmp_path, capsys):
    cams, images = _capture(16)
    data = write_instant_ngp(tmp_path / "ngp", cams, images)
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    assert main(["train", "--model", str(tmp_path), "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    flipped = json.loads((data / "transforms.json").read_text())
    for f in flipped["frames"]:  # camera to world given in OpenCV axes: the scene is behind every camera
        for row in f["transform_matrix"][:3]:
            row[1], row[2] = -row[1], -row[2]
    (data / "transforms.json").write_text(json.dumps(flipped))
    assert main(["train", "--model", str(MODEL_2), "--data", str(data), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(line.startswith("controlgs train: error: ") for line in err), err
    assert "--model" in err[0] and "not a trained model folder" in err[1] and "flipped" in err[2]


def test_seeds_train_each_seed_on_a_users_scene(tmp_path):
    """``--seeds 2 --seed 5`` on ``--model/--data`` trains seed-5/ and seed-6/ with their own seeds: each
    adapter equals the one a single run with that ``--seed`` writes (and the two differ)."""
    from controlgs_adapter.formats.adapter import read_tensors

    cams, images = _capture(16)
    data = write_colmap(tmp_path / "colmap", cams, images)
    common = ["--model", str(MODEL_2), "--data", str(data), "--iterations", "2", "--no-ablations", *FAST_2]
    assert main(["train", *common, "--out", str(tmp_path / "multi"), "--seeds", "2", "--seed", "5"]) == 0
    assert main(["train", *common, "--out", str(tmp_path / "single"), "--seed", "6"]) == 0
    name = "controlgs.controlgs.safetensors"
    five = read_tensors(tmp_path / "multi" / "seed-5" / name)
    six = read_tensors(tmp_path / "multi" / "seed-6" / name)
    alone = read_tensors(tmp_path / "single" / name)
    assert five.keys() == six.keys() == alone.keys()
    assert all(torch.equal(six[k], alone[k]) for k in six)
    assert not all(torch.equal(five[k], six[k]) for k in five)


def _ns(**kw: Any) -> argparse.Namespace:
    return argparse.Namespace(**kw)


# ---------------------------------------------------------------- the scene-check line
def test_check_line_by_hand() -> None:
    report = {"format": "colmap", "source": "/d", "splits": {"train": 7, "test": 1}, "points": 12,
              "in_front": {"a": 0.9, "b": 0.1, "c": 0.5, "d": 0.7}, "blind": ["b"]}
    assert check_line(report) == ("scene check: colmap /d: 7 train, 1 test views, image sizes match their cameras; "
                                  "the model's 12 anchors are in view of 3/4 cameras (median 70% inside the image)")
    report.update(format=None, in_front={})
    assert check_line(report) == "scene check: dataset /d: 7 train, 1 test views, image sizes match their cameras"


# ---------------------------------------------------------------- exit codes
def test_cli_exit_codes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main([]) == 0
    assert "usage: controlgs" in capsys.readouterr().out
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert cli.main(["train", "--out", str(blocker / "run"), "--model", "m"]) == 2  # lock folder under a file
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("controlgs train: error: ") and str(blocker) in err[0]
    with pytest.raises(SystemExit) as e:
        cli.main(["train", "--device"])  # argparse's own usage error
    assert e.value.code == 2


# ---------------------------------------------------------------- defaults of a user scene
def test_user_scene_defaults_every_8th_view_held_out(tmp_path: Path) -> None:
    from helpers.scene_writers import write_colmap

    from controlgs_adapter.commands.common import load_user_scene
    from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene

    model = builtin_backbone_dir("ar")
    if not (model / "point_cloud").is_dir():
        pytest.skip("built-in backbone not baked")
    scene = load_builtin_scene("ar", 16, views=9, test_every=9, samples=1)
    cams = scene.test_cameras + scene.train_cameras
    write_colmap(tmp_path / "data", cams, list(torch.cat([scene.test_images, scene.train_images])))
    args = _ns(model=str(model), data=str(tmp_path / "data"), family=None, model_iteration=None, allow_unquantized=None,
               format=None, images=None, holdout=None, white_background=None, resolution=None, device="cpu")
    user = load_user_scene(args)
    assert [f.name for f in user.data.splits["test"]] == ["v00.png", "v08.png"]  # 9 views, every 8th: 0 and 8
    assert len(user.data.splits["train"]) == 7 and user.family == "scaffold_gs"
    rec = user.record(args, iterations=3)
    assert rec["holdout"] == 8 and rec["model"] == str(model.resolve()) and rec["data"] == str((tmp_path / "data").resolve())
    assert (rec["allow_unquantized"], rec["white_background"], rec["format"], rec["iterations"]) == (False, False, "colmap", 3)


def test_cli_error_with_a_newline_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """torch's message repeats the raw device string: the CLI still prints one line."""
    assert cli.main(["train", "--model", "m", "--data", "d", "--out", str(tmp_path / "r"), "--device", "cu\nda"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("controlgs train: error: --device 'cu\\nda': "), err


MODEL_3 = builtin_backbone_dir("ar")


FAST_3 = ["--effects", "resample,display", "--no-progress", "--checkpoint-every", "0", "--no-ablations"]


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


@pytest.fixture(scope="module")
def data_2(tmp_path_factory):
    scene = load_builtin_scene("ar", 24, views=6, test_every=6, samples=1)
    root = tmp_path_factory.mktemp("scene")
    return write_colmap(root / "colmap", scene.test_cameras + scene.train_cameras,
                        list(scene.test_images) + list(scene.train_images))


def _calls(log):
    return log.read_text().split() if log.is_file() else []


def test_user_renderer_and_rasterizer_train_and_evaluate(tmp_path, data_2, monkeypatch):
    module = tmp_path / "my_render.py"
    module.write_text(USER_MODULE)
    log = module.with_suffix(".calls")
    monkeypatch.setenv(RASTERIZER_ENV, "gsplat")  # ignored by a run that passes --rasterizer torch; fatal on CPU otherwise
    run, report = tmp_path / "run", tmp_path / "report"
    assert main(["train", "--model", str(MODEL_3), "--data", str(data_2), "--out", str(run), "--iterations", "3",
                 "--resolution", "24", *FAST_3, "--rasterizer", "torch", "--renderer", f"{module}:renderer"]) == 0
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


def test_a_render_function_from_the_current_folder(tmp_path, data_2, monkeypatch, capsys):
    (tmp_path / "my_render_fn.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)  # MODULE:ATTR is found in the current folder, as `python -m` would
    assert main(["train", "--model", str(MODEL_3), "--data", str(data_2), "--out", str(tmp_path / "run"), "--iterations", "2",
                 "--resolution", "24", *FAST_3, "--renderer", "my_render_fn:render_all"]) == 0
    assert _calls(tmp_path / "my_render_fn.calls") == ["function", "function"]
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert record["renderer"] == "my_render_fn:render_all" and record["rasterizer"] == "auto"


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
def test_bad_rasterizer_or_renderer_is_one_line(tmp_path, data_2, monkeypatch, capsys, option, expected):
    (tmp_path / "my_render.py").write_text(USER_MODULE)
    monkeypatch.chdir(tmp_path)
    code = main(["train", "--model", str(MODEL_3), "--data", str(data_2), "--out", str(tmp_path / "run"), "--iterations", "1",
                 "--resolution", "24", *FAST_3, *option])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and expected in err, err
    if option[1] == "nvdiffrast":
        assert "torch" in err and "gsplat" in err
    assert not (tmp_path / "run" / "controlgs.controlgs.safetensors").exists()


def test_cli_training_defaults_come_from_train_config() -> None:
    import inspect
    from dataclasses import replace

    from controlgs_adapter.ablations import ABLATIONS
    from controlgs_adapter.commands.adapters import DEMO_ITERATIONS, train_config
    from controlgs_adapter.training import TrainConfig

    base = replace(TrainConfig(), iterations=DEMO_ITERATIONS)  # the one documented exception: a CPU-sized demo
    for cmd in ("demo", "train"):
        args = build_parser().parse_args([cmd])
        assert train_config(args, "controlgs") == base, cmd
        for name, (modules, blind) in ABLATIONS.items():
            assert train_config(args, name) == replace(base, modules=modules, state_blind=blind), (cmd, name)
    args = build_parser().parse_args(["train"])
    defaults = inspect.signature(init_distributed).parameters
    assert (args.dist_timeout, args.exchange) == (defaults["timeout"].default, defaults["exchange"].default)


def test_cli_training_options_reach_train_config() -> None:
    from dataclasses import replace

    from controlgs_adapter.commands.adapters import train_config

    args = build_parser().parse_args(["train", "--iterations", "7", "--lr", "0.02", "--cond-dim", "3", "--psf-fraction",
                                      "0.25", "--optics", "exact", "--checkpoint-every", "2", "--seed", "5",
                                      "--batch-size", "4"])
    want = TrainConfig(iterations=7, lr=0.02, cond_dim=3, psf_fraction=0.25, psf_mode="exact", checkpoint_every=2,
                       seed=5, batch_size=4)
    assert train_config(args, "controlgs") == want
    assert train_config(args, "controlgs", seed=9) == replace(want, seed=9)


ATOL, RTOL = 1e-6, 1e-5


RUN_TIMEOUT = 80.0  # seconds: far beyond a healthy run; hitting it means a hang


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _backbone_baked() -> bool:
    from controlgs_adapter.scene import builtin_backbone_dir

    return (builtin_backbone_dir("ar") / "point_cloud").is_dir()


@pytest.mark.skipif(not _backbone_baked(), reason="built-in backbone not baked")
def test_controlgs_train_command_under_torchrun(tmp_path, monkeypatch):
    """The unchanged `controlgs train` under torchrun (2 processes, dense condition exchange)
    writes the adapter once and it equals the single-process command's with the same global batch
    and seed."""
    from controlgs_adapter.cli import main
    from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION

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
        torch.testing.assert_close(got[k], want[k], rtol=RTOL, atol=ATOL, msg=lambda m: f"{k}: {m}")


def _parse(*argv: str) -> argparse.Namespace:
    return cli.build_parser().parse_args(list(argv))


# ------------------------------------------------------------------------------ ablations (paper Tbl. 4)
def test_ablation_configs_follow_the_paper_table():
    # Tbl. 4: each "w/o X" drops one module and stays state-aware; only "w/o State-Aware" is blind
    a = _parse("train")
    want = {"controlgs": (None, False),  # None: the modules the effects call for (TrainConfig's default)
            "wo_lens": (("resample", "display"), False),
            "wo_display": (("lens", "resample"), False),
            "wo_resample": (("lens", "display"), False),
            "state_blind": (("lens", "resample", "display"), True)}
    for name, (modules, blind) in want.items():
        c = train_config(a, name)
        assert (c.modules, c.state_blind) == (modules, blind), name


@pytest.mark.parametrize("command", ["train", "eval"])
def test_unknown_dataset_format_is_refused_by_argparse(command, capsys):
    from controlgs_adapter.datasets.detect import FORMATS

    with pytest.raises(SystemExit) as e:
        _parse(command, "--format", "nerfstudio")
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "argument --format: invalid choice: 'nerfstudio'" in err, err
    for f in FORMATS:
        assert repr(f) in err, (f, err)
    first = next(iter(FORMATS))
    assert _parse(command, "--format", first).format == first


@pytest.mark.parametrize("value, shown", [("0", "0.0"), ("-2.5", "-2.5")])
def test_train_dist_timeout_reaches_init_distributed(value, shown, tmp_path, capsys, monkeypatch):
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    rc = cli.main(["train", "--out", str(tmp_path / "run"), "--dist-timeout", value, "--iterations", "1",
                   "--no-ablations", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"controlgs train: error: timeout must be > 0 seconds, got {shown}"], err
    assert not (tmp_path / "run" / "controlgs.controlgs.safetensors").exists()


# ------------------------------------------------------------------------------ run.json records how the run was spread
@pytest.mark.parametrize("exchange", ["dense", "sparse"])
def test_train_records_the_exchange_that_reached_the_process_group(exchange, tmp_path, monkeypatch):
    import json

    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    out = tmp_path / "run"
    assert cli.main(["train", "--out", str(out), "--iterations", "1", "--no-ablations", "--no-progress",
                     "--resolution", "16", "--effects", "display", "--exchange", exchange]) == 0
    record = json.loads((out / "run.json").read_text())
    # one process: no process group (backend None); the exchange is the one init_distributed was given
    assert record["distributed"] == {"processes": 1, "backend": None, "exchange": exchange}


def test_train_on_your_own_scene_records_the_exchange(tmp_path, monkeypatch, capsys):
    import json

    pytest.importorskip("skimage")

    from controlgs_adapter.scene import builtin_backbone_dir, load_builtin_scene

    model = builtin_backbone_dir("ar")
    if not (model / "point_cloud").is_dir():
        pytest.skip("built-in backbone not baked")
    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    data = write_blender(tmp_path / "data", scene.test_cameras + scene.train_cameras,
                         list(torch.cat([scene.test_images, scene.train_images])), test=[0])
    out = tmp_path / "run"
    assert cli.main(["train", "--model", str(model), "--data", str(data), "--out", str(out), "--iterations", "1",
                     "--no-ablations", "--no-progress", "--effects", "display", "--checkpoint-every", "0",
                     "--exchange", "dense"]) == 0
    record = json.loads((out / "run.json").read_text())
    assert record["family"] == "scaffold_gs"
    assert record["distributed"] == {"processes": 1, "backend": None, "exchange": "dense"}


_TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def _torchrun_env(monkeypatch: pytest.MonkeyPatch, *, rank: int = 0, world: int = 2, local: int = 0,
                  port: str = "1") -> None:
    """torchrun's variables for rank ``rank`` of ``world`` (port 1: nothing listens there)."""
    for k, v in zip(_TORCHRUN, (rank, world, local, "127.0.0.1", port)):
        monkeypatch.setenv(k, str(v))


# ------------------------------------------------------------------------------ the command
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


needs_backbone_2 = pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                    reason="built-in backbone not baked")


# ------------------------------------------------------------------------------ train_adapters
def test_train_adapters_resume_messages(tiny, tmp_path, capsys):
    """``train_adapters`` resumes from the run's checkpoint: a fresh run says nothing about resuming, a
    second run of the same length says where it resumes (and nothing else), a shorter one also says that
    it keeps what was trained; ``trained`` receives the iterations actually trained."""
    from controlgs_adapter.commands.adapters import train_adapters

    scene, model = tiny
    views = scene.views("train")

    def args(iterations: int) -> Any:
        return cli.build_parser().parse_args(["train", "--iterations", str(iterations), "--checkpoint-every", "1",
                                              "--effects", "display", "--no-progress", "--cond-dim", "2"])

    trained: dict[str, int] = {}
    paths = train_adapters(views, model, tmp_path, args(2), ["controlgs"], trained=trained)
    assert paths == {"controlgs": tmp_path / "controlgs.controlgs.safetensors"} and paths["controlgs"].is_file()
    assert trained == {"controlgs": 2} and capsys.readouterr().out == ""
    train_adapters(views, model, tmp_path, args(2), ["controlgs"], trained=trained)
    assert capsys.readouterr().out.splitlines() == ["controlgs: resuming at iteration 2"]
    train_adapters(views, model, tmp_path, args(1), ["controlgs"], trained=trained)
    assert capsys.readouterr().out.splitlines() == [
        "controlgs: resuming at iteration 2",
        "controlgs: the checkpoint is already at iteration 2 > --iterations 1; keeping what was trained"]
    assert trained == {"controlgs": 2}


@needs_backbone_2
def test_train_built_in_with_two_seeds_and_one_ablation(tmp_path, monkeypatch, capsys):
    """``controlgs train --seeds 2 --seed 5 --ablation wo_lens`` on the built-in scene: ControlGS and only the
    chosen ablation, per seed in ``seed-<s>/``, each seed its own training; run.json records the run."""
    from safetensors.torch import load_file

    for k in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    out = tmp_path / "run"
    assert cli.main(["train", "--out", str(out), "--iterations", "1", "--resolution", "16", "--effects", "display",
                     "--checkpoint-every", "0", "--no-progress", "--seeds", "2", "--seed", "5",
                     "--ablation", "wo_lens"]) == 0
    want = [out / f"seed-{s}" / f"{n}.controlgs.safetensors" for s in (5, 6) for n in ("controlgs", "wo_lens")]
    assert capsys.readouterr().out.splitlines()[-4:] == [f"{p.name.split('.')[0]}: {p}" for p in want]
    record = json.loads((out / "run.json").read_text())
    assert {k: record[k] for k in ("variant", "effects", "iterations", "seed", "seeds", "adapters")} == \
        {"variant": "ar", "effects": ["display"], "iterations": 1, "seed": 5, "seeds": 2, "adapters": ["controlgs", "wo_lens"]}
    a, b = (load_file(out / f"seed-{s}" / "controlgs.controlgs.safetensors") for s in (5, 6))
    assert any(not torch.equal(a[k], b[k]) for k in a)


def _err(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"controlgs {command}: error: "), err
    return err[0][len(f"controlgs {command}: error: "):]


# ------------------------------------------------------------------------------ defaults
def test_train_and_eval_defaults():
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
    e = _parse("eval")
    assert (e.run, e.out, e.effects, e.lpips_weights, e.optics, e.seed, e.seeds, e.func.__module__) == \
        ("controlgs-run", None, None, None, "fast", 0, None, "controlgs_adapter.commands.eval")
    assert _parse("eval", "--lpips-weights", "a", "b").lpips_weights == ["a", "b"]
    assert _parse("eval", "--no-progress").progress is False


def test_train_config_of_each_adapter():
    from controlgs_adapter.commands.adapters import DEMO_ITERATIONS, train_config

    assert DEMO_ITERATIONS == 1000
    a = _parse("train", "--iterations", "12", "--lr", "0.5", "--cond-dim", "3", "--psf-fraction", "0.25",
               "--optics", "exact", "--checkpoint-every", "4", "--seed", "9", "--batch-size", "2")
    c = train_config(a, "controlgs")
    assert (c.iterations, c.lr, c.cond_dim, c.psf_fraction, c.psf_mode, c.checkpoint_every, c.seed, c.batch_size) == \
        (12, 0.5, 3, 0.25, "exact", 4, 9, 2)
    assert (c.modules, c.state_blind) == (None, False)
    assert (train_config(a, "wo_lens").modules, train_config(a, "wo_lens").state_blind) == (("resample", "display"), False)
    assert train_config(a, "wo_display").modules == ("lens", "resample")
    assert (train_config(a, "state_blind").modules, train_config(a, "state_blind").state_blind) == \
        (("lens", "resample", "display"), True)
    assert train_config(a, "controlgs", seed=5).seed == 5 and train_config(a, "controlgs", seed=0).seed == 0
    demo = _parse("demo")  # no --batch-size: TrainConfig's
    assert train_config(demo, "controlgs").batch_size == 1 and train_config(demo, "controlgs").iterations == 1000


def test_train_refusals_before_any_loading(capsys, tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    # --scenes trains built-in scenes only (and takes no run-folder lock: each process locks its scenes)
    assert cli.main(["train", "--model", "m", "--data", "d", "--scenes", "ar", "--out", str(blocker / "run")]) == 2
    assert _err(capsys, "train") == "--scenes trains built-in scenes; it does not combine with --model/--data"
    # rank 0 takes the run folder's lock (which cannot be made under a file); another rank does not
    assert cli.main(["train", "--model", "m", "--out", str(blocker / "run")]) == 2
    assert str(blocker) in _err(capsys, "train")
    monkeypatch.setenv("RANK", "1")
    assert cli.main(["train", "--model", "m", "--out", str(blocker / "run")]) == 2
    assert _err(capsys, "train") == "give both --model MODEL_DIR and --data DATA_DIR (or neither, for the built-in scene)"


def test_train_many_scenes_mode(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "runs"
    assert main(["train", "--scenes", "ar", "--out", str(out), "--iterations", "1", "--resolution", "16",
                 "--no-ablations", "--effects", "display", "--checkpoint-every", "0", "--no-progress",
                 "--seeds", "2", "--seed", "5"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    want = [out / "ar" / f"seed-{s}" / "controlgs.controlgs.safetensors" for s in (5, 6)]
    assert lines[-2:] == [f"[rank 0] ar controlgs: {p}" for p in want]
    assert all(p.is_file() for p in want) and not (out / "run.json").exists()


pytestmark = [pytest.mark.skipif(not (MODEL / "point_cloud").is_dir(), reason="built-in backbone not baked"), pytest.mark.skipif(not (builtin_backbone_dir("ar") / "point_cloud").is_dir(),
                                reason="built-in backbone not baked")]


@pytest.mark.parametrize("option", ["--iterations", "--cond-dim", "--checkpoint-every", "--test-views", "--batch-size"])
def test_a_count_beyond_int64_is_one_line(tmp_path: Path, data: Path, capsys: pytest.CaptureFixture[str],
                                          option: str) -> None:
    new = tmp_path / "new"
    argv = ["train", "--model", str(MODEL), "--data", str(data), "--out", str(new), *FAST]
    assert main([*argv, option, "9" * 400]) == 2
    line = error_line(capsys, "train")
    assert line.startswith(f"{option} must be an integer in ") and "401 digits" in line, line
    assert not new.exists()
