"""The process-group backend and each rank's device follow the training device
(:func:`controlgs_adapter.distributed.default_backend`), not whether CUDA is installed: a CPU run
under torchrun on a GPU machine uses gloo on the CPU, ``--device cuda`` uses NCCL with one GPU per
process, and the combinations that cannot work are refused before any group is formed.

Everything here runs without a GPU; the two-process test (this process rank 0, a child rank 1)
forms a real gloo group with the default backend, which on a GPU machine was NCCL before the fix."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from typing import Iterator

import pytest
import torch
import torch.distributed as dist

from controlgs_adapter.cli import main
from controlgs_adapter.distributed import DistributedError, default_backend, init_distributed
from controlgs_adapter.errors import InputValueError

_TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def _torchrun_env(monkeypatch: pytest.MonkeyPatch, *, rank: int = 0, world: int = 2, local: int = 0,
                  port: str = "1") -> None:
    """torchrun's variables for rank ``rank`` of ``world`` (port 1: nothing listens there)."""
    for k, v in zip(_TORCHRUN, (rank, world, local, "127.0.0.1", port)):
        monkeypatch.setenv(k, str(v))


@pytest.fixture(autouse=True)
def _no_group_left() -> Iterator[None]:
    if dist.is_initialized():
        pytest.skip("a process group already exists in this test process")
    yield
    assert not dist.is_initialized(), "a test left a process group behind"


# ------------------------------------------------------------------------------ the one rule
@pytest.mark.parametrize("device, backend", [
    ("cuda", "nccl"), ("cuda:1", "nccl"), (torch.device("cuda", 3), "nccl"),
    ("cpu", "gloo"), (torch.device("cpu"), "gloo"), (None, "gloo"), ("meta", "gloo"),
])
def test_default_backend_follows_the_device(device, backend):
    assert default_backend(device) == backend


def test_default_backend_ignores_whether_cuda_is_installed(monkeypatch):
    # the old rule was "nccl when torch.cuda.is_available()": pretend CUDA is there
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert default_backend(None) == "gloo" and default_backend("cpu") == "gloo"
    assert default_backend("cuda") == "nccl"


# ------------------------------------------------------------------------------ one process
def test_single_process_keeps_the_device_it_is_given(monkeypatch):
    for k in _TORCHRUN:
        monkeypatch.delenv(k, raising=False)
    assert init_distributed().device == torch.device("cpu")
    ctx = init_distributed(device="cuda:1")  # no GPU needed: nothing is allocated, no group formed
    assert (ctx.world_size, ctx.backend, ctx.device, ctx._owns_group) == (1, None, torch.device("cuda", 1), False)
    assert init_distributed(device=torch.device("meta")).device == torch.device("meta")
    with pytest.raises(InputValueError, match="device 'gpu' is not a torch device"):
        init_distributed(device="gpu")


# ------------------------------------------------------------------------------ refusals under torchrun
def test_a_backend_that_does_not_fit_the_device_is_refused(monkeypatch):
    _torchrun_env(monkeypatch)
    with pytest.raises(InputValueError, match=r"backend 'nccl' does not fit device 'cpu': NCCL moves CUDA tensors only"):
        init_distributed("nccl", device="cpu")
    with pytest.raises(InputValueError, match=r"backend 'gloo' does not fit device 'cuda:0': gloo ranks train on the CPU"):
        init_distributed("gloo", device="cuda:0")
    with pytest.raises(InputValueError, match="backend must be 'gloo' or 'nccl', got 'mpi'"):
        init_distributed("mpi", device="cpu")


def test_nccl_without_a_gpu_of_its_own_is_refused(monkeypatch):
    # LOCAL_RANK = the number of GPUs visible: one process too many on any machine (0 GPUs here)
    gpus = torch.cuda.device_count()
    _torchrun_env(monkeypatch, rank=gpus, world=gpus + 2, local=gpus)
    fewer = rf"start at most {gpus} process\(es\) per node \(torchrun --nproc-per-node {gpus}\), or " if gpus else ""
    want = (rf"^rank {gpus} of {gpus + 2}: NCCL needs one GPU per process, but this is process LOCAL_RANK={gpus} of "
            rf"its node and this machine has {gpus} GPU\(s\) visible; {fewer}train on the CPU with gloo "
            rf"\(--device cpu\)$")
    with pytest.raises(DistributedError, match=want):
        init_distributed(device="cuda")  # the default backend for a CUDA device: nccl
    with pytest.raises(DistributedError, match=want):
        init_distributed("nccl")  # no device named: NCCL's rank device, cuda:<LOCAL_RANK>


def test_gloo_is_the_default_on_cpu_even_where_cuda_is_installed(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    _torchrun_env(monkeypatch, port="not-a-port")  # the group cannot form: the error names the backend tried
    for device in (None, "cpu"):
        with pytest.raises(DistributedError, match=r"could not join the process group at 127\.0\.0\.1:not-a-port \(gloo\)"):
            init_distributed(device=device, timeout=2.0)


# ------------------------------------------------------------------------------ an existing group
def test_an_existing_gloo_group_is_checked_against_the_device():
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        for device in (None, "cpu"):
            ctx = init_distributed(device=device)
            assert (ctx.backend, ctx.device, ctx._owns_group) == ("gloo", torch.device("cpu"), False)
        with pytest.raises(InputValueError, match="backend 'gloo' does not fit device 'cuda'"):
            init_distributed(device="cuda")
    finally:
        dist.destroy_process_group()


# ------------------------------------------------------------------------------ two real processes
_CHILD = """
import json, os, sys
from controlgs_adapter.distributed import init_distributed
os.environ.update(RANK="1", WORLD_SIZE="2", LOCAL_RANK="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=sys.argv[1])
with init_distributed(timeout=30.0) as ctx:
    print(json.dumps([ctx.backend, str(ctx.device), ctx.all_gather_json(ctx.rank)]))
"""


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_two_ranks_without_a_device_form_a_gloo_group_on_the_cpu(monkeypatch):
    # on a machine with one GPU the old default (nccl, cuda:<LOCAL_RANK>) put rank 1 on a GPU that
    # does not exist; here both ranks join gloo and exchange on the CPU
    port = _free_port()
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    child = subprocess.Popen([sys.executable, "-c", _CHILD, str(port)], env=env, stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    _torchrun_env(monkeypatch, port=str(port))
    monkeypatch.setenv("GLOO_SOCKET_IFNAME", "lo")
    try:
        with init_distributed(timeout=30.0) as ctx:
            mine = [ctx.backend, str(ctx.device), ctx.all_gather_json(ctx.rank)]
            assert ctx._owns_group and (ctx.rank, ctx.world_size, ctx.local_rank) == (0, 2, 0)
        out, _ = child.communicate(timeout=60)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == 0, out
    assert mine == ["gloo", "cpu", [0, 1]]
    assert json.loads(out.strip().splitlines()[-1]) == ["gloo", "cpu", [0, 1]]


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
