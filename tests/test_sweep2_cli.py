"""Sweep-2 survivors of the command line and its neighbours: the ablation table reaching the
training config, the sub-command metavar, ``--format``'s choices, ``--dist-timeout`` reaching
``init_distributed``, the LPIPS missing-weights hints, ``side_by_side``'s (eye, gt) order, the
gradient exchange's bookkeeping and the explicit backend kept under torchrun."""

from __future__ import annotations

import argparse
import io
import zipfile
import math

import pytest
import torch
import torch.distributed as dist

from controlgs_adapter import ControlGS, cli
from controlgs_adapter.commands.adapters import train_config
from controlgs_adapter.distributed import DistContext, DistributedError, init_distributed
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.perceptual import LPIPS


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


# ------------------------------------------------------------------------------ parser
def test_usage_names_the_sub_command_as_COMMAND():
    usage = cli.build_parser().format_usage()
    assert "COMMAND" in usage and "{plugins" not in usage, usage


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


# ------------------------------------------------------------------------------ LPIPS hints
_BACKBONE = "(the AlexNet backbone: torchvision's alexnet-owt-7be5be79.pth)"
_HEAD = "(the LPIPS head: the lpips package's weights/v0.1/alex.pth; pip install --no-deps lpips)"


def test_lpips_missing_hints_name_each_missing_part():
    from controlgs_adapter.perceptual import _expected

    shapes = _expected()
    full = {k: torch.zeros(s) for k, s in shapes.items()}
    # nothing given: both parts missing, both hinted
    with pytest.raises(InputValueError) as e:
        LPIPS({}, "w.pth")
    assert str(e.value).startswith("LPIPS weights w.pth: missing [") and _BACKBONE in str(e.value) \
        and _HEAD in str(e.value), str(e.value)
    # only the head missing: the head's hint alone
    with pytest.raises(InputValueError) as e:
        LPIPS({k: v for k, v in full.items() if not k.startswith("lin")}, "w.pth")
    assert _HEAD in str(e.value) and _BACKBONE not in str(e.value), str(e.value)
    # one backbone tensor and one head tensor missing: both hinted
    with pytest.raises(InputValueError) as e:
        LPIPS({k: v for k, v in full.items() if k not in ("conv0.bias", "lin4")}, "w.pth")
    assert str(e.value).startswith("LPIPS weights w.pth: missing ['conv0.bias', 'lin4']") \
        and _BACKBONE in str(e.value) and _HEAD in str(e.value), str(e.value)


# ------------------------------------------------------------------------------ side_by_side scores (eye, gt)
def test_side_by_side_scores_against_the_unclamped_ground_truth(tiny, tmp_path):
    from controlgs_adapter.evaluation import side_by_side
    from controlgs_adapter.metrics import ssim

    scene, model = tiny
    views = scene.data.views("train", first=1)
    cgs = ControlGS.wrap(model, cond_dim=4)
    path = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    cam, gt = views[0]
    bright = gt + 0.5  # a reference brighter than a display shows: only the eye image is clamped to [0, 1]
    assert float(bright.max()) > 1.2
    out = side_by_side(model, path, cam, bright, settings=[(1.0, 0.0)], background=views.background,
                       effects={"lens": True, "resample": True, "display": True})
    for method, row in out["rows"].items():
        _, eye, p, q = row[0]
        assert float(eye.max()) <= 1.0
        mse = float((eye.double() - bright.double()).square().mean())  # float64 PSNR against the unclamped gt
        assert p == pytest.approx(10 * math.log10(1.0 / mse), abs=1e-9), method
        assert q == pytest.approx(float(ssim(eye.double(), bright.double())), abs=1e-9), method
        clamped = float((eye.double() - bright.double().clamp(0, 1)).square().mean())
        assert abs(10 * math.log10(1.0 / clamped) - p) > 0.1  # the clamped reference would score differently


# ------------------------------------------------------------------------------ gradient exchange bookkeeping
def test_dense_exchange_counts_rows_and_bytes_by_hand():
    # a real gloo group of one process; the context claims 2 ranks: the all-reduce then sums this rank's
    # buffer with nothing (as if rank 1 had no gradient), which is all the dense exchange needs
    if dist.is_initialized():
        pytest.skip("a process group already exists in this test process")
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        ctx = DistContext(rank=0, world_size=2, backend="gloo", exchange="dense")
        assert ctx.stats.rows_touched == 0 and ctx.stats.steps == 0
        a = torch.nn.Parameter(torch.zeros(2))
        t = torch.nn.Parameter(torch.zeros(4, 2))
        for step in range(2):
            a.grad = torch.tensor([1.0, 2.0])
            t.grad = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.0], [0.0, -4.0]])  # rows 1 and 3 touched
            loss = ctx.sync_gradients([a, t], row_sparse=[t], loss=0.5, step=0)
            assert loss == 0.5
            assert torch.equal(a.grad, torch.tensor([1.0, 2.0]))
            assert torch.equal(t.grad, torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.0], [0.0, -4.0]]))
        # buffer: 2 dense + 2 flags + 1 table x 2 ranks + 2 steps + loss = 9 float64 = 72 bytes; a ring
        # all-reduce on 2 ranks sends 2 (2 - 1) / 2 n = n bytes; t dense: 8 float32 = 32 bytes;
        # dense equivalent: (2 + 8) float32 = 40 bytes
        assert ctx.stats.last == {"bytes_sent": 72 + 32, "dense_bytes": 40, "rows": 2, "exchange": "dense"}
        assert (ctx.stats.steps, ctx.stats.bytes_sent, ctx.stats.dense_bytes, ctx.stats.rows_touched) == (2, 208, 80, 4)
    finally:
        dist.destroy_process_group()


# ------------------------------------------------------------------------------ the backend named is kept
def test_named_backend_is_not_replaced_by_the_default(monkeypatch):
    # port "not-a-port": a group that tries to form fails at once instead of waiting
    for k, v in zip(("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"),
                    ("0", "2", "0", "127.0.0.1", "not-a-port")):
        monkeypatch.setenv(k, v)
    if dist.is_initialized():
        pytest.skip("a process group already exists in this test process")
    with pytest.raises(InputValueError, match=r"backend 'nccl' does not fit device 'cpu'"):
        init_distributed("nccl", device="cpu", timeout=2.0)
    with pytest.raises(DistributedError, match=r"could not join the process group at 127\.0\.0\.1:not-a-port \(gloo\)"):
        init_distributed(None, device="cpu", timeout=2.0)


# ------------------------------------------------------------------------------ the progress bar follows the terminal
@pytest.mark.skipif(not hasattr(__import__("os"), "openpty"), reason="needs a pseudo-terminal (POSIX)")
def test_training_progress_bar_follows_a_resized_terminal(tiny, monkeypatch):
    # the bar is drawn on a real pseudo-terminal (stderr): 61 columns when the bar starts, widened to
    # 101 while training runs; a bar that follows the terminal (dynamic_ncols) draws its last frame
    # 100 characters wide (tqdm leaves one column: width - 1), a fixed one stays 60 wide
    import fcntl
    import os
    import struct
    import sys
    import termios

    from controlgs_adapter.rendering.protocol import ModelRenderer
    from controlgs_adapter.training import Trainer, TrainConfig

    master, slave = os.openpty()

    def resize(cols: int) -> None:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 25, cols, 0, 0))

    class Resizing(ModelRenderer):
        def render(self, model, camera, visible, background):  # type: ignore[no-untyped-def]
            resize(101)  # the user widens the terminal while a step runs
            return super().render(model, camera, visible, background)

    scene, model = tiny
    resize(61)
    tty = os.fdopen(slave, "w", encoding="utf-8", closefd=False)
    monkeypatch.setattr(sys, "stderr", tty)
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.0),
                effects={"lens": True, "resample": True, "display": True}, renderer=Resizing())
    try:
        t.train(progress=True)
        tty.flush()
        os.set_blocking(master, False)
        out = b""
        while True:
            try:
                chunk = os.read(master, 65536)
            except BlockingIOError:
                break
            if not chunk:
                break
            out += chunk
    finally:
        t.cgs.unwrap()
        monkeypatch.undo()
        tty.close()
        os.close(slave)
        os.close(master)
    text = out.decode("utf-8").replace("\x1b[A", "")
    frames = [f for f in text.replace("\n", "\r").split("\r") if "training ControlGS" in f]
    assert frames and len(frames[0]) == 60, frames  # drawn at the start: 61 - 1
    assert len(frames[-1]) == 100 and "2/2" in frames[-1], frames


# ------------------------------------------------------------------------------ LPIPS weights saved on a GPU
def _as_if_saved_on_cuda(src: bytes) -> bytes:
    """A torch checkpoint whose storages say ``cuda:0`` (what ``torch.save`` writes for GPU tensors):
    the pickled location string ``cpu`` rewritten, every other record copied."""
    zin = zipfile.ZipFile(io.BytesIO(src))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as zout:
        for name in zin.namelist():
            data = zin.read(name)
            if name.endswith("/data.pkl"):
                # protocol-2 BINUNICODE: 'X' + 4-byte little-endian length + UTF-8
                assert b"X\x03\x00\x00\x00cpu" in data
                data = data.replace(b"X\x03\x00\x00\x00cpu", b"X\x06\x00\x00\x00cuda:0")
            zout.writestr(name, data)
    return out.getvalue()


def test_lpips_weights_saved_on_a_gpu_load_onto_the_cpu(tmp_path):
    from controlgs_adapter.perceptual import _read

    weights = {"features.0.weight": torch.arange(6.0).reshape(2, 3), "lin0.model.1.weight": torch.tensor([0.5, -1.0])}
    buf = io.BytesIO()
    torch.save(weights, buf)
    path = tmp_path / "alex.pth"
    path.write_bytes(_as_if_saved_on_cuda(buf.getvalue()))
    got = _read(path)  # map_location="cpu": no GPU needed, whether CUDA is installed or not
    assert sorted(got) == sorted(weights)
    for k, v in weights.items():
        assert got[k].device == torch.device("cpu") and torch.equal(got[k], v), k


def test_training_progress_bar_only_when_asked_and_only_on_rank_0(tiny, capsys):
    from controlgs_adapter.training import Trainer, TrainConfig

    scene, model = tiny
    cheap = {"lens": True, "resample": True, "display": True}

    def bar_shown(progress: bool, dist_ctx: DistContext | None = None) -> bool:
        config = TrainConfig(iterations=1, checkpoint_every=0, psf_fraction=0.0, batch_size=2)
        t = Trainer(model, scene.views("train"), config,
                    effects=cheap, dist=dist_ctx)
        try:
            capsys.readouterr()
            t.train(progress=progress)
        finally:
            t.cgs.unwrap()
        return "training ControlGS" in capsys.readouterr().err

    assert bar_shown(True) and not bar_shown(False)
    # rank 1 of 2 never draws it: a real gloo group of this one process stands in for the job (its
    # collectives see only this rank; one iteration keeps every rank's step equal)
    if dist.is_initialized():
        pytest.skip("a process group already exists in this test process")
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        assert not bar_shown(True, DistContext(rank=1, world_size=2, backend="gloo"))
        assert bar_shown(True, DistContext(rank=0, world_size=2, backend="gloo"))
    finally:
        dist.destroy_process_group()


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
    from _scene_writers import write_blender  # tests/ is on the path (rootdir conftest), as for test_cli_own_scene

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


def test_lpips_weights_never_unpickle_objects_even_when_torch_is_told_to(tmp_path, monkeypatch):
    # TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 turns torch.load's default to full unpickling (code may run);
    # the weights are loaded with weights_only=True named, so a file holding an object is still refused
    from controlgs_adapter.perceptual import _read

    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    path = tmp_path / "alex.pth"
    torch.save({"features.0.weight": torch.ones(2), "extra": argparse.Namespace(x=1)}, path)
    with pytest.raises(InputValueError, match=r"LPIPS weights .*alex\.pth: refused, not a tensor-only checkpoint "
                                              r"\(loaded with torch\.load\(weights_only=True\), which never runs code\)"):
        _read(path)
