"""``controlgs train`` keeps a run folder's record true: a refused or failed run writes nothing (no
folder, no lock file, no run.json), run.json is written once the adapters are saved, a folder trained
on another model or dataset is refused with its record and adapters unchanged, and a failed
checkpoint or adapter write is one line with the old files intact."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from safetensors import SafetensorError

from controlgs_adapter.cli import main
from controlgs_adapter.errors import NonFiniteError
from helpers.cli_runs import FAST, MODEL, error_line, needs_backbone, snapshot, write_tiny_colmap

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
