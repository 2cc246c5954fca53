"""Tests of ``controlgs_adapter.distributed``."""

from __future__ import annotations

import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import helpers.dist_worker as worker
import pytest
import torch
import torch.distributed as dist
from helpers.two_ranks import peer_rank
from torch import nn

from controlgs_adapter.distributed import (
    DEFAULT_TIMEOUT_S,
    EXCHANGES,
    CommStats,
    DistContext,
    DistributedError,
    _all_reduce_bytes,
    default_backend,
    init_distributed,
    shard_scenes,
)
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.training import TrainConfig, Trainer

WORKER = Path(__file__).resolve().parents[1] / "helpers" / "dist_worker.py"


ITERATIONS, BATCH, DIE_AT = 2, 2, 1


ATOL, RTOL = 1e-6, 1e-5


RUN_TIMEOUT = 80.0  # seconds: far beyond a healthy run; hitting it means a hang


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(nproc: int, *args: str, nodes: int = 1) -> tuple[list[subprocess.CompletedProcess], float]:
    """Run the worker under torchrun: ``nodes`` agents (one per simulated node, all on loopback)
    of ``nproc`` processes each. Returns each agent's completed process and the wall time."""
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    port = _free_port()
    t0 = time.perf_counter()
    logs = [tempfile.TemporaryFile("w+") for _ in range(nodes)]
    agents = [subprocess.Popen([sys.executable, "-m", "torch.distributed.run", f"--nnodes={nodes}", f"--node_rank={n}",
                                f"--nproc_per_node={nproc}", "--master_addr=127.0.0.1", f"--master_port={port}",
                                "--max_restarts=0", str(WORKER), *args],
                               env=env, stdout=logs[n], stderr=subprocess.STDOUT, text=True)
              for n in range(nodes)]
    try:
        codes = [a.wait(timeout=max(RUN_TIMEOUT - (time.perf_counter() - t0), 1.0)) for a in agents]
    finally:
        for a in agents:
            if a.poll() is None:
                a.kill()
    done = []
    for a, code, log in zip(agents, codes, logs):
        log.seek(0)
        done.append(subprocess.CompletedProcess(a.args, code, log.read(), ""))
        log.close()
    return done, time.perf_counter() - t0


@pytest.fixture(scope="module")
def fixture_path(tmp_path_factory) -> Path:
    """A tiny backbone on the built-in scene plus FAR anchors that no view sees (as in a large
    scene, where each view touches a fraction of the anchors)."""
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", resolution=16, views=6, test_every=3, samples=1)
    xyz, rgb = scene.points(spacing=0.3)
    g = torch.stack(torch.meshgrid(*[torch.arange(8.0)] * 3, indexing="ij"), -1).reshape(-1, 3)  # [512, 3]
    far = 50.0 + 0.3 * g
    torch.manual_seed(0)
    model = NeuralGaussianModel.from_points(torch.cat([xyz, far]), feat_dim=8, n_offsets=2, voxel_size=0.3)
    with torch.no_grad():  # features that make anchors emit (zero features emit nothing)
        model._anchor_feat.copy_(0.5 * torch.randn(model._anchor_feat.shape, generator=torch.Generator().manual_seed(1)))
    assert not any(bool(model.visible_anchors(c)[-len(far):].any()) for c in scene.train_cameras)
    return worker.write_fixture(tmp_path_factory.mktemp("dist") / "fixture.safetensors", model,
                                scene.train_images, scene.train_cameras, scene.background)


@pytest.fixture(scope="module")
def reference(fixture_path) -> dict[int, dict[str, torch.Tensor]]:
    """Uninterrupted single-process training, same global batch and seed: results after
    ``DIE_AT`` and after ``ITERATIONS`` iterations."""
    trainer = worker.make_trainer(fixture_path, ITERATIONS, BATCH, None, DistContext())
    trainer.train(until=DIE_AT, progress=False)
    early = worker.result_tensors(trainer)
    trainer.train(progress=False)
    return {DIE_AT: early, ITERATIONS: worker.result_tensors(trainer)}


def _assert_same(got: dict[str, torch.Tensor], ref: dict[str, torch.Tensor]) -> None:
    assert set(got) == set(ref)
    for k in ref:
        if k == "history":
            torch.testing.assert_close(got[k], ref[k], rtol=1e-6, atol=0.0, msg="loss history differs")
        else:
            torch.testing.assert_close(got[k], ref[k], rtol=RTOL, atol=ATOL, msg=lambda m: f"{k}: {m}")


# ---------------------------------------------------------------------------------------- torchrun
def test_killed_rank_errors_and_checkpoint_resumes_on_one_process(fixture_path, reference, tmp_path):
    from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND

    ck = tmp_path / "run.ckpt.safetensors"
    out = tmp_path / "never.safetensors"
    # two "nodes" (torchrun agents) of one process each: rank 1's node loses its process, rank 0
    # learns it only through the failing collective (its agent cannot see the other node)
    (node0, node1), seconds = _torchrun(1, str(fixture_path), str(out), f"--iterations={ITERATIONS}",
                                        f"--batch={BATCH}", f"--checkpoint={ck}", f"--die-at={DIE_AT}", "--timeout=30",
                                        nodes=2)
    assert node0.returncode != 0 and node1.returncode != 0 and seconds < RUN_TIMEOUT
    assert not out.exists()
    assert "SIGKILL" in node1.stdout, node1.stdout[-4000:]  # torchrun names the dead rank
    assert "DistributedError: rank 0 of 2" in node0.stdout, node0.stdout[-4000:]
    assert f"{ck} (iteration {DIE_AT}), resumes the run" in node0.stdout
    # only touched condition rows travelled (auto picked the sparse exchange): fewer rows than
    # anchors (the far ones are never seen) and fewer bytes than a dense all-reduce
    stats = json.loads(node0.stdout.split("rank 0 exchange: ", 1)[1].splitlines()[0])
    assert stats["exchange"] == "sparse"
    assert 0 < stats["rows"] <= reference[ITERATIONS]["conditions"].shape[0] - 512
    assert 0 < stats["bytes"] < stats["dense_bytes"]
    # rank 0 wrote the checkpoint of the last completed iteration, atomically (no stray temp file),
    # and it holds what one process computes in DIE_AT iterations
    assert [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")] == []
    tensors, header = load_tensors(ck, kind=CHECKPOINT_KIND, max_version=99)
    assert header["iteration"] == DIE_AT
    early = reference[DIE_AT]
    for k in ("conditions", "projections.lens.d8.weight"):
        torch.testing.assert_close(tensors[f"adapter.{k}"], early[k], rtol=RTOL, atol=ATOL)
    # resume on ONE process: the same result as the uninterrupted run
    trainer: Trainer = worker.make_trainer(fixture_path, ITERATIONS, BATCH, ck, DistContext())
    assert trainer.resume() and trainer.iteration == DIE_AT
    trainer.train(progress=False)
    _assert_same(worker.result_tensors(trainer), reference[ITERATIONS])


# ---------------------------------------------------------------------------------------- in-process
def test_single_process_context_without_torchrun(monkeypatch):
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    ctx = init_distributed()
    assert (ctx.rank, ctx.world_size, ctx.is_main, ctx.is_distributed) == (0, 1, True, False)
    p = torch.nn.Parameter(torch.zeros(3))
    p.grad = torch.ones(3)
    assert ctx.sync_gradients([p], loss=2.5) == 2.5 and torch.equal(p.grad, torch.ones(3))


def test_incomplete_torchrun_environment_is_refused(monkeypatch):
    monkeypatch.setenv("WORLD_SIZE", "2")
    for k in ("RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    with pytest.raises(DistributedError, match="RANK"):
        init_distributed()


def test_sharding_covers_the_batch_once():
    items = list(range(7))
    shards = [DistContext(rank=r, world_size=3).shard(items) for r in range(3)]
    assert sorted(sum(shards, [])) == items and shards[1] == [1, 4]
    with pytest.raises(InputValueError, match="batch_size"):
        DistContext(rank=0, world_size=3).check_batch(2)
    assert shard_scenes(["a", "b", "c"], DistContext(rank=1, world_size=2)) == ["b"]
    with pytest.raises(InputValueError, match="more than once"):
        shard_scenes(["a", "a"], DistContext())
    with pytest.raises(InputValueError, match="exchange"):
        DistContext(exchange="fast")
    with pytest.raises(InputValueError, match="rank"):
        DistContext(rank=2, world_size=2)


@pytest.mark.parametrize("rank, world", [(1, 1), (2, 2), (-1, 2)])
def test_rank_outside_the_world_is_refused(rank, world):
    with pytest.raises(InputValueError, match="rank"):
        DistContext(rank=rank, world_size=world)


@pytest.mark.parametrize("world", [1, 2, 3, 4, 8])
def test_all_reduce_bytes_is_the_ring_volume(world):
    """A ring all-reduce sends 2 (W - 1) / W of the buffer per process (reduce-scatter + all-gather)."""
    from controlgs_adapter.distributed import _all_reduce_bytes

    for nbytes in (0, 4, 4096, 123_456):
        assert _all_reduce_bytes(nbytes, world) == (2 * (world - 1) * nbytes) // world
    assert _all_reduce_bytes(1200, world) == {1: 0, 2: 1200, 3: 1600, 4: 1800, 8: 2100}[world]


@pytest.mark.parametrize("world", [1, 2, 3, 5])
def test_shards_of_a_batch_and_of_scenes_partition_it_round_robin(world):
    """Rank r takes items r, r + W, r + 2W ...: every item on exactly one rank, in order."""
    from controlgs_adapter.distributed import DistContext, shard_scenes

    items = [f"s{i}" for i in range(7)]
    shards = [DistContext(rank=r, world_size=world).shard(items) for r in range(world)]
    assert shards == [[items[i] for i in range(r, 7, world)] for r in range(world)]
    assert sorted(x for s in shards for x in s) == sorted(items)
    assert [shard_scenes(items, DistContext(rank=r, world_size=world)) for r in range(world)] == shards
    with pytest.raises(InputValueError, match=r"\['s1'\] more than once"):
        shard_scenes(["s0", "s1", "s1"], DistContext(rank=0, world_size=world))


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


def test_training_progress_bar_only_when_asked_and_only_on_rank_0(tiny, capsys):
    from controlgs_adapter.training import Trainer

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


_TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


def _torchrun_env(monkeypatch: pytest.MonkeyPatch, *, rank: int = 0, world: int = 2, local: int = 0,
                  port: str = "1") -> None:
    """torchrun's variables for rank ``rank`` of ``world`` (port 1: nothing listens there)."""
    for k, v in zip(_TORCHRUN, (rank, world, local, "127.0.0.1", port)):
        monkeypatch.setenv(k, str(v))


# ------------------------------------------------------------------------------ two real processes
_CHILD = """
import json, os, sys
from controlgs_adapter.distributed import init_distributed
os.environ.update(RANK="1", WORLD_SIZE="2", LOCAL_RANK="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=sys.argv[1])
with init_distributed(timeout=30.0) as ctx:
    print(json.dumps([ctx.backend, str(ctx.device), ctx.all_gather_json(ctx.rank)]))
"""


def _free_port_2() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


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


def test_two_ranks_without_a_device_form_a_gloo_group_on_the_cpu(monkeypatch):
    # on a machine with one GPU the old default (nccl, cuda:<LOCAL_RANK>) put rank 1 on a GPU that
    # does not exist; here both ranks join gloo and exchange on the CPU
    port = _free_port_2()
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


# ------------------------------------------------------------------------------ a peer that died
_RANK = """
import json, os, sys, time, torch
from torch import nn
from controlgs_adapter.distributed import DistributedError, init_distributed
rank, port = sys.argv[1], sys.argv[2]
os.environ.update({"RANK": rank, "WORLD_SIZE": "2", "LOCAL_RANK": rank, "MASTER_ADDR": "127.0.0.1",
                   "MASTER_PORT": port})
ctx = init_distributed("gloo", timeout=5.0)
if rank == "1":
    os._exit(0)  # dies without a word
time.sleep(1.0)
out = {}
try:
    ctx.all_gather_json({"a": 1})
except DistributedError as e:
    out["gather"] = str(e)
p = nn.Parameter(torch.zeros(2))
p.grad = torch.ones(2)
try:
    ctx.sync_gradients([p], step=7)
except DistributedError as e:
    out["sync"] = str(e)
print(json.dumps(out))
os._exit(0)
"""


def test_a_dead_peer_is_reported_with_the_collective_and_iteration(tmp_path):
    """When the other process dies, each collective fails with a message naming this rank, what it was
    doing and (for the gradient exchange) the iteration, so that the user knows where the run stopped."""
    import json
    import os
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = str(s.getsockname()[1])
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    procs = [subprocess.Popen([sys.executable, "-c", _RANK, r, port], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for r in ("0", "1")]
    (out0, err0), _ = (p.communicate(timeout=120) for p in procs)
    msgs = json.loads(out0.strip().splitlines()[-1])
    assert msgs["gather"].startswith("rank 0 of 2: gathering results failed ("), msgs
    assert msgs["sync"].startswith("rank 0 of 2: the gradient all-reduce at iteration 7 failed ("), msgs
    assert "no checkpoint was written yet" in msgs["sync"]


# ------------------------------------------------------------------------------ distributed
_RANK1 = """
import os, sys, torch
from torch import nn
from controlgs_adapter.distributed import init_distributed
os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": sys.argv[1]})
with init_distributed("gloo", timeout=60.0, exchange="sparse") as ctx:
    t = nn.Parameter(torch.zeros(3, 2))
    t.grad = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, -1.0]])
    ctx.sync_gradients([t], row_sparse=[t], step=2)
"""


def test_sparse_exchange_sends_rows_that_are_only_partly_non_zero(monkeypatch):
    """A row of a row-sparse gradient is "touched" when any of its entries is non-zero: two real gloo ranks
    whose only gradient rows are half zero ([0.5, 0] on rank 0, [0, -1] on rank 1) end with their sum,
    not with a zero gradient, and each rank counts its one row."""
    from controlgs_adapter.distributed import init_distributed

    with peer_rank(monkeypatch, _RANK1), init_distributed("gloo", timeout=60.0, exchange="sparse") as ctx:
        t = torch.nn.Parameter(torch.zeros(3, 2))
        t.grad = torch.tensor([[0.5, 0.0], [0.0, 0.0], [0.0, 0.0]])
        ctx.sync_gradients([t], row_sparse=[t], step=2)
        last = dict(ctx.stats.last)
    assert torch.equal(t.grad, torch.tensor([[0.5, 0.0], [0.0, 0.0], [0.0, -1.0]]))
    assert last["rows"] == 1 and last["exchange"] == "sparse"


# ----------------------------------------------------------------------------- distributed: a normal exit waits
_LATE_RANK1 = """
import os, sys, time
from controlgs_adapter.distributed import init_distributed
os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": sys.argv[1]})
with init_distributed("gloo", timeout=60.0) as ctx:
    ctx.barrier()
    time.sleep(0.6)
"""


def test_leaving_a_dist_context_normally_waits_for_every_rank(monkeypatch):
    """``DistContext.close`` / ``__exit__`` (docs: "after a barrier, so that no rank tears its connections
    down while a peer still uses them"): on a normal exit rank 0 waits for rank 1, which leaves 0.6 s
    later, so rank 0's exit takes about 0.6 s, not an instant."""
    from controlgs_adapter.distributed import init_distributed

    with peer_rank(monkeypatch, _LATE_RANK1):
        with init_distributed("gloo", timeout=60.0) as ctx:
            ctx.barrier()
            start = time.perf_counter()
        waited = time.perf_counter() - start
    assert waited >= 0.5, f"rank 0 left after {waited:.3f} s without waiting for rank 1"


# ----------------------------------------------------------------------------- init_distributed: timeout
def test_a_sub_second_timeout_is_accepted(monkeypatch):
    """``init_distributed`` docstring: a timeout <= 0 is refused; any positive number of seconds is valid,
    a sub-second one included (a single process: no group is formed, nothing waits)."""
    from controlgs_adapter.errors import InputValueError

    for k in _TORCHRUN:
        monkeypatch.delenv(k, raising=False)
    for timeout in (0.25, 1.0, 1.5):
        ctx = init_distributed(device="cpu", timeout=timeout)
        assert (ctx.world_size, ctx.device) == (1, torch.device("cpu"))
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(InputValueError, match="timeout must be > 0 seconds"):
            init_distributed(device="cpu", timeout=bad)


HERE = Path(__file__).resolve().parent


# ------------------------------------------------------------------------------ the scenario
def _rows(shape: tuple[int, ...], rows: list[int], seed: int) -> torch.Tensor:
    """A gradient of ``shape`` that is non-zero (multiples of 1/4 in [-2, 2], never 0) in ``rows`` only."""
    g = torch.zeros(shape)
    gen = torch.Generator().manual_seed(seed)
    for r in rows:
        v = torch.randint(1, 9, shape[1:], generator=gen).float() / 4.0
        sign = torch.randint(0, 2, shape[1:], generator=gen).float() * 2 - 1
        g[r] = v * sign
    return g


def _scenario(rank: int) -> tuple[list[nn.Parameter], list[nn.Parameter], dict[str, nn.Parameter]]:
    """Parameters with rank ``rank``'s gradients: (params, row_sparse, by name).

    dense: a (both ranks), b (no rank), c (rank 1 only); row-sparse: t (rows {1, 4} | {0, 4, 5}),
    u (rank 0 None, rank 1 rows {2, 3}), v (a zero gradient on both), w (None on both), x [2, 1]
    (row 0 on rank 0, row 1 on rank 1: too small for the sparse exchange to pay under "auto")."""
    p = {n: nn.Parameter(torch.zeros(s)) for n, s in
         (("a", (3, 2)), ("b", (4,)), ("c", (2,)), ("t", (6, 2, 3)), ("u", (5, 2)), ("v", (3, 2)), ("w", (4, 2)),
          ("x", (2, 1)))}
    p["a"].grad = _rows((3, 2), [0, 1, 2], 10 + rank)
    p["c"].grad = torch.tensor([1.5, -2.0]) if rank == 1 else None
    p["t"].grad = _rows((6, 2, 3), [1, 4] if rank == 0 else [0, 4, 5], 20 + rank)
    p["u"].grad = None if rank == 0 else _rows((5, 2), [2, 3], 31)
    p["v"].grad = torch.zeros(3, 2)
    p["x"].grad = torch.tensor([[0.25], [0.0]]) if rank == 0 else torch.tensor([[0.0], [-0.5]])
    params = [p[n] for n in "abctuvwx"]
    return params, [p[n] for n in "tuvwx"], p


def _want() -> dict[str, torch.Tensor | None]:
    """The summed gradients in float64: None where no rank had one."""
    _, _, p0 = _scenario(0)
    _, _, p1 = _scenario(1)
    out: dict[str, torch.Tensor | None] = {}
    for n in p0:
        g0, g1 = p0[n].grad, p1[n].grad
        out[n] = None if g0 is None and g1 is None else \
            sum(g.double() for g in (g0, g1) if g is not None)  # type: ignore[assignment]
    return out


def _protocol(ctx: DistContext) -> dict[str, object]:
    """The calls both ranks make in the same order; returns what rank 0 checks."""
    out: dict[str, object] = {}
    out["gathered"] = ctx.all_gather_json({"rank": ctx.rank, "text": "é" * (3 * ctx.rank + 1)})
    # broadcast: rank 0's values reach every rank
    bp = [nn.Parameter(torch.full((2, 2), float(ctx.rank + 1))), nn.Parameter(torch.arange(3.0) * (ctx.rank + 1))]
    ctx.broadcast_parameters(bp)
    ctx.broadcast_parameters([])  # nothing to send: returns (no collective)
    out["broadcast"] = ctx.all_gather_json([q.detach().tolist() for q in bp])
    for exchange in ("sparse", "dense", "auto"):
        ctx.exchange = exchange
        params, sparse, named = _scenario(ctx.rank)
        loss = ctx.sync_gradients(params, row_sparse=sparse, loss=1.5 if ctx.rank == 0 else 2.25, step=7)
        grads = {n: None if q.grad is None else q.grad.tolist() for n, q in named.items()}
        out[exchange] = {"loss": loss, "grads": ctx.all_gather_json(grads), "last": dict(ctx.stats.last),
                         "dtypes": {n: str(q.grad.dtype) for n, q in named.items() if q.grad is not None}}
    out["stats"] = (ctx.stats.steps, ctx.stats.bytes_sent, ctx.stats.dense_bytes, ctx.stats.rows_touched)
    params, sparse, _ = _scenario(ctx.rank)
    try:  # a rank at another iteration (resumed from another checkpoint) is caught by every rank
        ctx.sync_gradients(params, row_sparse=sparse, step=3 + ctx.rank)
        out["mismatch"] = None
    except DistributedError as e:
        out["mismatch"] = str(e)
    ctx.barrier()
    return out


def _child(port: int) -> None:
    """Rank 1 (run in a child process)."""
    os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1",
                       "MASTER_PORT": str(port)})
    with init_distributed("gloo", timeout=30.0, exchange="sparse") as ctx:
        _protocol(ctx)


def _free_port_3() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def two_ranks() -> dict[str, object]:
    """Run the protocol as rank 0 here, rank 1 in a child; returns rank 0's observations."""
    port = _free_port_3()
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    child = subprocess.Popen([sys.executable, "-c", f"import sys; sys.path[:0] = [{str(HERE)!r}, {str(HERE.parent)!r}]; "
                              f"import {Path(__file__).stem} as t; t.{_child.__name__}({port})"], env=env,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    saved = {k: os.environ.get(k) for k in _TORCHRUN}
    os.environ.update({"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
                       "MASTER_PORT": str(port)})
    try:
        ctx = init_distributed("gloo", timeout=30.0, exchange="sparse")
        out: dict[str, object] = {"ctx": (ctx.rank, ctx.world_size, ctx.local_rank, ctx.backend, ctx.device.type,
                                          ctx.is_distributed, ctx.is_main, ctx._owns_group)}
        # a group the caller made is used as it is (and is not the context's to destroy)
        joined = init_distributed(exchange="dense")
        out["joined"] = (joined.rank, joined.world_size, joined.local_rank, joined.backend, joined.exchange,
                         joined._owns_group)
        joined.close()
        out["still_initialized"] = dist.is_initialized()
        out.update(_protocol(ctx))
        ctx.close()
        out["after_close"] = (dist.is_initialized(), ctx._owns_group)
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        log, _ = child.communicate(timeout=60)
    assert child.returncode == 0, log
    return out


def test_two_ranks_join_and_gather(two_ranks):
    assert two_ranks["ctx"] == (0, 2, 0, "gloo", "cpu", True, True, True)
    assert two_ranks["joined"] == (0, 2, 0, "gloo", "dense", False)
    assert two_ranks["still_initialized"] is True
    assert two_ranks["after_close"] == (False, False)
    # rank order, UTF-8 of unequal lengths (2 and 8 bytes of "é"), never pickled
    assert two_ranks["gathered"] == [{"rank": 0, "text": "é"}, {"rank": 1, "text": "éééé"}]
    assert two_ranks["broadcast"] == [[[[1.0, 1.0], [1.0, 1.0]], [0.0, 1.0, 2.0]]] * 2


@pytest.mark.parametrize("exchange", ["sparse", "dense", "auto"])
def test_gradients_are_the_sum_over_ranks(two_ranks, exchange):
    got = two_ranks[exchange]
    assert got["loss"] == 3.75  # 1.5 + 2.25
    want = _want()
    mine, theirs = got["grads"]
    assert mine == theirs  # every rank holds the same gradients
    for n, w in want.items():
        if w is None:
            assert mine[n] is None, n
        else:
            assert mine[n] is not None, n
            assert torch.equal(torch.tensor(mine[n], dtype=torch.float64), w), n
    assert got["dtypes"] == {n: "torch.float32" for n in "actuvx"}
    # v had a (zero) gradient on both ranks: a zero tensor, not None; w had none anywhere: None
    assert mine["v"] == [[0.0, 0.0]] * 3 and mine["w"] is None and mine["b"] is None


def test_bytes_by_hand(two_ranks):
    # the all-reduce buffer: 12 dense values (a 6, b 4, c 2) + 8 flags + 5 tables x 2 ranks + 2 steps + loss
    # = 33 float64 = 264 bytes; a ring all-reduce on 2 ranks sends 2 (2-1)/2 n = n bytes.
    # t [6, 2, 3]: 3 rows at most (rank 1), a row is an int64 id + 6 float32 = 32 bytes -> 96 sparse, 144 dense;
    # u [5, 2]: 2 rows x (8 + 8) = 32 sparse, 40 dense; v: zero everywhere, nothing sent; w: no gradient;
    # x [2, 1]: 1 row x (8 + 4) = 12 sparse, 8 dense (auto takes the dense one).
    # dense equivalent: 74 float32 values = 296 bytes.
    assert two_ranks["sparse"]["last"] == {"bytes_sent": 264 + 96 + 32 + 12, "dense_bytes": 296, "rows": 3,
                                           "exchange": "sparse"}
    assert two_ranks["dense"]["last"] == {"bytes_sent": 264 + 144 + 40 + 8, "dense_bytes": 296, "rows": 3,
                                          "exchange": "dense"}
    assert two_ranks["auto"]["last"] == {"bytes_sent": 264 + 96 + 32 + 8, "dense_bytes": 296, "rows": 3,
                                         "exchange": "mixed"}
    # three exchanges counted (the refused one raised before counting); rank 0 touched t {1, 4} + x {0}
    assert two_ranks["stats"] == (3, 404 + 456 + 400, 3 * 296, 9)


def test_ranks_at_different_iterations_are_refused(two_ranks):
    msg = two_ranks["mismatch"]
    assert msg is not None and "rank 0: 3, rank 1: 4" in msg and "different iterations" in msg


# ------------------------------------------------------------------------------ in one process
def test_all_reduce_bytes_ring_model_by_hand():
    assert _all_reduce_bytes(100, 4) == 150  # 2 * 3 / 4 * 100
    assert _all_reduce_bytes(100, 1) == 0
    assert _all_reduce_bytes(7, 2) == 7
    assert _all_reduce_bytes(10, 3) == 13  # floor(2 * 2 * 10 / 3) = floor(13.33)


def test_comm_stats_per_step():
    assert CommStats().per_step() == (0.0, 0.0)  # no step: no division by zero
    assert CommStats(steps=4, bytes_sent=10, dense_bytes=30).per_step() == (2.5, 7.5)
    assert CommStats(steps=1, bytes_sent=3, dense_bytes=5).per_step() == (3.0, 5.0)


def test_defaults_and_single_process_shortcuts(monkeypatch):
    assert DEFAULT_TIMEOUT_S == 300.0 and EXCHANGES == ("auto", "sparse", "dense")
    monkeypatch.setenv("WORLD_SIZE", "1")
    ctx = init_distributed()
    assert (ctx.rank, ctx.world_size, ctx.local_rank, ctx.backend, ctx.device, ctx.exchange, ctx._owns_group) == \
        (0, 1, 0, None, torch.device("cpu"), "auto", False)
    assert init_distributed(exchange="dense").exchange == "dense"
    # nothing travels in one process: parameters and gradients stay, the loss comes back
    p = nn.Parameter(torch.tensor([1.0, 2.0]))
    ctx.broadcast_parameters([p])
    ctx.barrier()
    assert torch.equal(p.detach(), torch.tensor([1.0, 2.0]))
    assert ctx.all_gather_json({"a": [1, 2]}) == [{"a": [1, 2]}]
    assert ctx.sync_gradients([p], loss=0.5, step=3) == 0.5 and p.grad is None
    assert ctx.stats.steps == 0
    with ctx as same:
        assert same is ctx
    ctx.close()
    assert not ctx._owns_group


def test_distributed_context_refusals():
    for rank, world in ((-1, 2), (2, 2), (0, 0), (1, 1)):
        with pytest.raises(InputValueError, match=f"rank={rank}, world_size={world}"):
            DistContext(rank=rank, world_size=world)
    assert DistContext(rank=1, world_size=2).is_main is False
    assert DistContext(rank=1, world_size=2).is_distributed is True
    with pytest.raises(InputValueError, match="exchange must be one of"):
        DistContext(exchange="ring")
    ctx = DistContext(rank=0, world_size=4)
    ctx.check_batch(4)  # equal is enough
    with pytest.raises(InputValueError, match=r"batch_size \(3\) is smaller than the number of processes \(4\)"):
        ctx.check_batch(3)
    with pytest.raises(InputValueError, match=r"ranks 3\.\.3 would have no view"):
        ctx.check_batch(3)


def test_row_sparse_must_be_among_the_parameters():
    ctx = DistContext(rank=0, world_size=2)  # refused before any collective
    a, b = nn.Parameter(torch.zeros(2)), nn.Parameter(torch.zeros(2, 2))
    with pytest.raises(InputValueError, match="row_sparse must be a subset"):
        ctx.sync_gradients([a], row_sparse=[b])


def test_shard_and_shard_scenes():
    assert DistContext(rank=2, world_size=3).shard("abcdefg") == ["c", "f"]
    assert DistContext(rank=0, world_size=3).shard(list(range(7))) == [0, 3, 6]
    assert shard_scenes(["ar", "vr"], DistContext(rank=1, world_size=3)) == ["vr"]
    assert shard_scenes(["ar"], DistContext(rank=1, world_size=2)) == []
    with pytest.raises(InputValueError, match="at least one scene"):
        shard_scenes([], DistContext())
    with pytest.raises(InputValueError, match=r"\['vr'\] more than once"):
        shard_scenes(["vr", "ar", "vr"], DistContext())


def test_failure_message_names_rank_step_and_checkpoint():
    ctx = DistContext(rank=1, world_size=3)

    def broken() -> None:
        raise RuntimeError("Connection closed by peer\nmore detail")

    with pytest.raises(DistributedError) as e:
        ctx._run("the gradient all-reduce", 12, broken)
    msg = str(e.value)
    assert msg.startswith("rank 1 of 3: the gradient all-reduce at iteration 12 failed (RuntimeError: "
                          "Connection closed by peer); another process")
    assert "no checkpoint was written yet" in msg and "more detail" not in msg
    assert isinstance(e.value.__cause__, RuntimeError)
    ctx.last_checkpoint = ("run/ck.safetensors", 40)
    msg = str(ctx._failed("waiting", None, RuntimeError("")))
    assert "waiting failed (RuntimeError: RuntimeError(''))" in msg and "iteration 4" not in msg.split(";")[0]
    assert "the last checkpoint, run/ck.safetensors (iteration 40), resumes the run" in msg
    # other errors pass through unchanged
    with pytest.raises(ValueError):
        ctx._run("x", None, lambda: (_ for _ in ()).throw(ValueError("no")))
    assert ctx._run("x", None, lambda a, b: a + b, 2, 3) == 5


def test_init_refusals(monkeypatch):
    with pytest.raises(InputValueError, match="exchange must be one of"):
        init_distributed(exchange="fast")
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(InputValueError, match="timeout must be > 0"):
            init_distributed(timeout=bad)
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "0")
    monkeypatch.setenv("LOCAL_RANK", "0")
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    monkeypatch.delenv("MASTER_PORT", raising=False)
    with pytest.raises(DistributedError, match=r"WORLD_SIZE=2 but \['MASTER_PORT'\] are not set"):
        init_distributed()
    monkeypatch.setenv("MASTER_PORT", "1")
    with pytest.raises(InputValueError, match="backend must be 'gloo' or 'nccl', got 'mpi'"):
        init_distributed("mpi")
    monkeypatch.setenv("MASTER_PORT", "not-a-port")  # the group cannot be formed: one error naming where
    with pytest.raises(DistributedError, match=r"rank 0 of 2: could not join the process group at 127\.0\.0\.1:not-a-port \(gloo\)"):
        init_distributed("gloo", timeout=2.0)
    assert not dist.is_initialized()


def test_init_distributed_refusals_name_the_argument(monkeypatch):
    from controlgs_adapter.distributed import init_distributed

    with pytest.raises(InputValueError, match="exchange must be one of .*'fast'"):
        init_distributed(exchange="fast")
    for timeout in (0.0, -1.0, float("nan")):
        with pytest.raises(InputValueError, match="timeout must be > 0 seconds"):
            init_distributed(timeout=timeout)
    env = {"RANK": "0", "WORLD_SIZE": "2", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": "1"}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    with pytest.raises(InputValueError, match="backend must be 'gloo' or 'nccl', got 'mpi'"):
        init_distributed("mpi")


def test_shard_scenes_refuses_an_empty_list_and_batch_equal_to_world_is_fine():
    from controlgs_adapter.distributed import DistContext, shard_scenes

    with pytest.raises(InputValueError, match="scenes must name at least one scene"):
        shard_scenes([], DistContext())
    DistContext(rank=2, world_size=3).check_batch(3)  # the bound: one view per rank
    with pytest.raises(InputValueError, match=r"need 0 <= rank < world_size, got rank=3, world_size=3"):
        DistContext(rank=3, world_size=3)


def test_an_existing_one_process_gloo_group_is_used_as_it_is():
    import torch.distributed as dist

    from controlgs_adapter.distributed import DistContext, init_distributed

    if not dist.is_available() or dist.is_initialized():
        pytest.skip("torch.distributed unavailable or a group already exists in this process")
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        ctx = init_distributed(exchange="dense")
        assert (ctx.rank, ctx.world_size, ctx.backend, ctx.device, ctx.exchange) == (0, 1, "gloo", torch.device("cpu"), "dense")
        assert isinstance(ctx, DistContext) and ctx.is_main and not ctx.is_distributed
        p = torch.nn.Parameter(torch.zeros(2, 3))
        p.grad = torch.arange(6.0).reshape(2, 3)
        assert ctx.sync_gradients([p], row_sparse=[p], loss=1.5, step=4) == 1.5
        assert torch.equal(p.grad, torch.arange(6.0).reshape(2, 3))  # one rank: the sum is its own gradient
        ctx.close()  # not its group: left for its owner
        assert dist.is_initialized()
    finally:
        dist.destroy_process_group()
