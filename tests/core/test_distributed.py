"""Tests of ``controlgs_adapter.distributed``: the process context (ranks, sharding, backend and device
choice, refusals), the gradient exchange between two real gloo ranks (sums, bytes counted from the buffer layout), a
dead or late peer, and a torchrun job that loses a rank and resumes from its checkpoint on one process."""

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
from helpers.gradient_exchange import protocol, summed_gradients
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
from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.training import Trainer

TESTS = Path(__file__).resolve().parents[1]
WORKER = TESTS / "helpers" / "dist_worker.py"
ITERATIONS, BATCH, DIE_AT = 2, 2, 1
ATOL, RTOL = 1e-6, 1e-5
RUN_TIMEOUT = 80.0  # seconds: far beyond a healthy run; hitting it means a hang
TORCHRUN_VARIABLES = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")
CHILD_ENV = {"GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _torchrun_env(monkeypatch: pytest.MonkeyPatch, *, rank: int = 0, world: int = 2, local: int = 0,
                  port: str = "1") -> None:
    """torchrun's variables for rank ``rank`` of ``world`` (port 1: nothing listens there)."""
    for k, v in zip(TORCHRUN_VARIABLES, (rank, world, local, "127.0.0.1", port)):
        monkeypatch.setenv(k, str(v))


def _no_torchrun(monkeypatch: pytest.MonkeyPatch) -> None:
    for k in TORCHRUN_VARIABLES:
        monkeypatch.delenv(k, raising=False)


@pytest.fixture
def one_process_group():
    """A real gloo group of this one process (its collectives see only this rank)."""
    if dist.is_initialized():
        pytest.skip("a process group already exists in this test process")
    dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
    try:
        yield
    finally:
        dist.destroy_process_group()


# ---------------------------------------------------------------------------------------- torchrun
def _torchrun(nproc: int, *args: str, nodes: int = 1) -> tuple[list[subprocess.CompletedProcess], float]:
    """Run the worker under torchrun: ``nodes`` agents (one per simulated node, all on loopback)
    of ``nproc`` processes each. Returns each agent's completed process and the wall time."""
    env = {**os.environ, **CHILD_ENV}
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
    with torch.random.fork_rng(devices=[]):
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


def test_killed_rank_errors_and_checkpoint_resumes_on_one_process(fixture_path, reference, tmp_path):
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
    assert f"{ck} (iteration {DIE_AT})" in node0.stdout  # the checkpoint that resumes the run
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


# ---------------------------------------------------------------------------------------- two real ranks
RANK1_PROTOCOL = (f"import sys; sys.path.insert(0, {str(TESTS)!r}); "
                  "from helpers.gradient_exchange import rank1; rank1(int(sys.argv[1]))")


@pytest.fixture(scope="module")
def two_ranks() -> dict[str, object]:
    """Run the exchange protocol as rank 0 here, rank 1 in a child; returns rank 0's observations."""
    with pytest.MonkeyPatch.context() as mp, peer_rank(mp, RANK1_PROTOCOL):
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
            out.update(protocol(ctx))
            ctx.close()
            out["after_close"] = (dist.is_initialized(), ctx._owns_group)
        finally:
            if dist.is_initialized():
                dist.destroy_process_group()
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
    mine, theirs = got["grads"]
    assert mine == theirs  # every rank holds the same gradients
    for n, w in summed_gradients().items():
        if w is None:
            assert mine[n] is None, n
        else:
            assert mine[n] is not None, n
            assert torch.equal(torch.tensor(mine[n], dtype=torch.float64), w), n
    assert got["dtypes"] == {n: "torch.float32" for n in "actuvx"}
    # v had a (zero) gradient on both ranks: a zero tensor, not None; w had none anywhere: None
    assert mine["v"] == [[0.0, 0.0]] * 3 and mine["w"] is None and mine["b"] is None


def test_bytes_sent_by_each_exchange(two_ranks):
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


_RANK1_PARTLY_ZERO_ROW = """
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
    with peer_rank(monkeypatch, _RANK1_PARTLY_ZERO_ROW), init_distributed("gloo", timeout=60.0, exchange="sparse") as ctx:
        t = torch.nn.Parameter(torch.zeros(3, 2))
        t.grad = torch.tensor([[0.5, 0.0], [0.0, 0.0], [0.0, 0.0]])
        ctx.sync_gradients([t], row_sparse=[t], step=2)
        last = dict(ctx.stats.last)
    assert torch.equal(t.grad, torch.tensor([[0.5, 0.0], [0.0, 0.0], [0.0, -1.0]]))
    assert last["rows"] == 1 and last["exchange"] == "sparse"


_RANK1_ON_THE_CPU = """
import os, sys
from controlgs_adapter.distributed import init_distributed
os.environ.update(RANK="1", WORLD_SIZE="2", LOCAL_RANK="1", MASTER_ADDR="127.0.0.1", MASTER_PORT=sys.argv[1])
with init_distributed(timeout=30.0) as ctx:
    seen = [ctx.backend, str(ctx.device), ctx.all_gather_json(ctx.rank)]
    assert seen == ["gloo", "cpu", [0, 1]], seen
"""


def test_two_ranks_without_a_device_form_a_gloo_group_on_the_cpu(monkeypatch):
    # on a machine with one GPU a default of (nccl, cuda:<LOCAL_RANK>) would put rank 1 on a GPU that does
    # not exist; here both ranks join gloo and exchange on the CPU
    with peer_rank(monkeypatch, _RANK1_ON_THE_CPU), init_distributed(timeout=30.0) as ctx:
        mine = [ctx.backend, str(ctx.device), ctx.all_gather_json(ctx.rank)]
        assert ctx._owns_group and (ctx.rank, ctx.world_size, ctx.local_rank) == (0, 2, 0)
    assert mine == ["gloo", "cpu", [0, 1]]


_RANK1_LEAVES_LATE = """
import os, sys, time
from pathlib import Path
from controlgs_adapter.distributed import init_distributed
os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": sys.argv[1]})
with init_distributed("gloo", timeout=60.0) as ctx:
    ctx.barrier()
    time.sleep(0.5)
    Path(%r).write_text("rank 1 is leaving")
"""


def test_leaving_a_dist_context_normally_waits_for_every_rank(monkeypatch, tmp_path):
    """``DistContext.close`` / ``__exit__`` (docs: "after a barrier, so that no rank tears its connections
    down while a peer still uses them"): on a normal exit rank 0 waits for rank 1, which writes a file
    0.5 s after the last common barrier, just before it leaves: the file is there once rank 0 is out of its
    context."""
    leaving = tmp_path / "leaving"
    with peer_rank(monkeypatch, _RANK1_LEAVES_LATE % str(leaving)):
        with init_distributed("gloo", timeout=60.0) as ctx:
            ctx.barrier()
        assert leaving.read_text() == "rank 1 is leaving"


_RANK_THAT_LOSES_ITS_PEER = """
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


def test_a_dead_peer_is_reported_with_the_collective_and_iteration():
    """When the other process dies, each collective fails with a message naming this rank, what it was
    doing and (for the gradient exchange) the iteration, so that the user knows where the run stopped."""
    port = str(_free_port())
    env = {**os.environ, **CHILD_ENV}
    procs = [subprocess.Popen([sys.executable, "-c", _RANK_THAT_LOSES_ITS_PEER, r, port], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for r in ("0", "1")]
    (out0, _), _ = (p.communicate(timeout=120) for p in procs)
    msgs = json.loads(out0.strip().splitlines()[-1])
    assert msgs["gather"].startswith("rank 0 of 2: gathering results failed ("), msgs
    assert msgs["sync"].startswith("rank 0 of 2: the gradient all-reduce at iteration 7 failed ("), msgs
    assert "no checkpoint was written yet" in msgs["sync"]


# ---------------------------------------------------------------------------------------- one process
def test_single_process_shortcuts(monkeypatch):
    """Without torchrun (or with WORLD_SIZE=1) the context is rank 0 of 1 on the CPU, forms no group, and
    every collective is a no-op: parameters and gradients stay, the loss comes back, nothing is counted."""
    assert DEFAULT_TIMEOUT_S == 300.0 and EXCHANGES == ("auto", "sparse", "dense")
    for world in (None, "1"):
        _no_torchrun(monkeypatch)
        if world is not None:
            monkeypatch.setenv("WORLD_SIZE", world)
        ctx = init_distributed()
        assert (ctx.rank, ctx.world_size, ctx.local_rank, ctx.backend, ctx.device, ctx.exchange, ctx._owns_group) == \
            (0, 1, 0, None, torch.device("cpu"), "auto", False)
        assert ctx.is_main and not ctx.is_distributed
        p = nn.Parameter(torch.tensor([1.0, 2.0]))
        ctx.broadcast_parameters([p])
        ctx.barrier()
        assert torch.equal(p.detach(), torch.tensor([1.0, 2.0]))
        assert ctx.all_gather_json({"a": [1, 2]}) == [{"a": [1, 2]}]
        assert ctx.sync_gradients([p], loss=0.5, step=3) == 0.5 and p.grad is None
        p.grad = torch.ones(2)
        assert ctx.sync_gradients([p], loss=2.5) == 2.5 and torch.equal(p.grad, torch.ones(2))
        assert ctx.stats.steps == 0
        with ctx as same:
            assert same is ctx
        ctx.close()
        assert not ctx._owns_group
    assert init_distributed(exchange="dense").exchange == "dense"


def test_single_process_keeps_the_device_and_any_positive_timeout(monkeypatch):
    """The device named is kept (no GPU needed: nothing is allocated, no group formed); a timeout is any
    positive number of seconds, a sub-second one included."""
    _no_torchrun(monkeypatch)
    assert init_distributed().device == torch.device("cpu")
    ctx = init_distributed(device="cuda:1")
    assert (ctx.world_size, ctx.backend, ctx.device, ctx._owns_group) == (1, None, torch.device("cuda", 1), False)
    assert init_distributed(device=torch.device("meta")).device == torch.device("meta")
    with pytest.raises(InputValueError, match="device 'gpu'"):
        init_distributed(device="gpu")
    for timeout in (0.25, 1.0, 1.5):
        ctx = init_distributed(device="cpu", timeout=timeout)
        assert (ctx.world_size, ctx.device) == (1, torch.device("cpu"))


def test_init_refusals_name_the_argument(monkeypatch):
    with pytest.raises(InputValueError, match="exchange .*'fast'"):
        init_distributed(exchange="fast")
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(InputValueError, match=f"timeout .*got {bad!r}"):
            init_distributed(device="cpu", timeout=bad)
    monkeypatch.setenv("WORLD_SIZE", "2")
    for k in ("RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(k, raising=False)
    with pytest.raises(DistributedError, match=r"WORLD_SIZE=2 .*'RANK'"):
        init_distributed()
    for k, v in (("RANK", "0"), ("LOCAL_RANK", "0"), ("MASTER_ADDR", "127.0.0.1")):
        monkeypatch.setenv(k, v)
    with pytest.raises(DistributedError, match=r"WORLD_SIZE=2 .*\['MASTER_PORT'\]"):
        init_distributed()
    monkeypatch.setenv("MASTER_PORT", "1")
    with pytest.raises(InputValueError, match="backend .*'mpi'"):
        init_distributed("mpi")
    with pytest.raises(InputValueError, match="backend .*'mpi'"):
        init_distributed("mpi", device="cpu")
    assert not dist.is_initialized()


@pytest.mark.parametrize("device, backend", [
    ("cuda", "nccl"), ("cuda:1", "nccl"), (torch.device("cuda", 3), "nccl"),
    ("cpu", "gloo"), (torch.device("cpu"), "gloo"), (None, "gloo"), ("meta", "gloo"),
])
@pytest.mark.parametrize("cuda_installed", [False, True])
def test_default_backend_follows_the_device_not_whether_cuda_is_installed(monkeypatch, device, backend, cuda_installed):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda_installed)
    assert default_backend(device) == backend


def test_a_backend_that_does_not_fit_the_device_is_refused(monkeypatch):
    _torchrun_env(monkeypatch)
    with pytest.raises(InputValueError, match=r"backend 'nccl' .*device 'cpu'"):
        init_distributed("nccl", device="cpu")
    with pytest.raises(InputValueError, match=r"backend 'gloo' .*device 'cuda:0'"):
        init_distributed("gloo", device="cuda:0")


def test_a_group_that_cannot_form_names_where_and_the_backend_tried(monkeypatch):
    """No device named: gloo, even where CUDA is installed, and a backend named is not replaced by the
    default (port "not-a-port": the group fails at once instead of waiting)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    _torchrun_env(monkeypatch, port="not-a-port")
    if dist.is_initialized():
        pytest.skip("a process group already exists in this test process")
    for backend, device in ((None, None), (None, "cpu"), ("gloo", None)):
        with pytest.raises(DistributedError, match=r"^rank 0 of 2: .*127\.0\.0\.1:not-a-port \(gloo\)"):
            init_distributed(backend, device=device, timeout=2.0)
    with pytest.raises(InputValueError, match=r"backend 'nccl' .*device 'cpu'"):
        init_distributed("nccl", device="cpu", timeout=2.0)
    assert not dist.is_initialized()


def test_nccl_without_a_gpu_of_its_own_is_refused(monkeypatch):
    # LOCAL_RANK = the number of GPUs visible: one process too many on any machine
    gpus = torch.cuda.device_count()
    _torchrun_env(monkeypatch, rank=gpus, world=gpus + 2, local=gpus)
    for args, kw in (((), {"device": "cuda"}), (("nccl",), {})):  # nccl named, or the default for a CUDA device
        with pytest.raises(DistributedError, match=rf"^rank {gpus} of {gpus + 2}: NCCL .*LOCAL_RANK={gpus}") as e:
            init_distributed(*args, **kw)
        msg = str(e.value)
        assert f"{gpus} GPU(s)" in msg and "--device cpu" in msg
        assert (f"--nproc-per-node {gpus}" in msg) == (gpus > 0)


def test_an_existing_one_process_gloo_group_is_used_as_it_is(one_process_group):
    """A group the caller made is used as it is, checked against the device, and left to its owner."""
    for device in (None, "cpu"):
        ctx = init_distributed(device=device)
        assert (ctx.backend, ctx.device, ctx._owns_group) == ("gloo", torch.device("cpu"), False)
    with pytest.raises(InputValueError, match="backend 'gloo' .*device 'cuda'"):
        init_distributed(device="cuda")
    ctx = init_distributed(exchange="dense")
    assert (ctx.rank, ctx.world_size, ctx.backend, ctx.device, ctx.exchange) == (0, 1, "gloo", torch.device("cpu"), "dense")
    assert isinstance(ctx, DistContext) and ctx.is_main and not ctx.is_distributed
    p = torch.nn.Parameter(torch.zeros(2, 3))
    p.grad = torch.arange(6.0).reshape(2, 3)
    assert ctx.sync_gradients([p], row_sparse=[p], loss=1.5, step=4) == 1.5
    assert torch.equal(p.grad, torch.arange(6.0).reshape(2, 3))  # one rank: the sum is its own gradient
    ctx.close()  # not its group: left for its owner
    assert dist.is_initialized()


def test_dense_exchange_counts_rows_and_bytes(one_process_group):
    # the context claims 2 ranks in a group of one: the all-reduce then sums this rank's buffer with nothing
    # (as if rank 1 had no gradient), which is all the dense exchange needs
    ctx = DistContext(rank=0, world_size=2, backend="gloo", exchange="dense")
    assert ctx.stats.rows_touched == 0 and ctx.stats.steps == 0
    a = torch.nn.Parameter(torch.zeros(2))
    t = torch.nn.Parameter(torch.zeros(4, 2))
    for _ in range(2):
        a.grad = torch.tensor([1.0, 2.0])
        t.grad = torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.0], [0.0, -4.0]])  # rows 1 and 3 touched
        assert ctx.sync_gradients([a, t], row_sparse=[t], loss=0.5, step=0) == 0.5
        assert torch.equal(a.grad, torch.tensor([1.0, 2.0]))
        assert torch.equal(t.grad, torch.tensor([[0.0, 0.0], [3.0, 0.0], [0.0, 0.0], [0.0, -4.0]]))
    # buffer: 2 dense + 2 flags + 1 table x 2 ranks + 2 steps + loss = 9 float64 = 72 bytes; a ring
    # all-reduce on 2 ranks sends 2 (2 - 1) / 2 n = n bytes; t dense: 8 float32 = 32 bytes;
    # dense equivalent: (2 + 8) float32 = 40 bytes
    assert ctx.stats.last == {"bytes_sent": 72 + 32, "dense_bytes": 40, "rows": 2, "exchange": "dense"}
    assert (ctx.stats.steps, ctx.stats.bytes_sent, ctx.stats.dense_bytes, ctx.stats.rows_touched) == (2, 208, 80, 4)


# ---------------------------------------------------------------------------------------- the context
def test_distributed_context_refusals():
    for rank, world in ((-1, 2), (2, 2), (0, 0), (1, 1), (3, 3)):
        with pytest.raises(InputValueError, match=f"rank={rank}, world_size={world}"):
            DistContext(rank=rank, world_size=world)
    assert DistContext(rank=1, world_size=2).is_main is False
    assert DistContext(rank=1, world_size=2).is_distributed is True
    for bad in ("ring", "fast"):
        with pytest.raises(InputValueError, match=f"exchange .*'{bad}'"):
            DistContext(exchange=bad)
    ctx = DistContext(rank=0, world_size=4)
    ctx.check_batch(4)  # equal is enough: one view per rank
    DistContext(rank=2, world_size=3).check_batch(3)
    with pytest.raises(InputValueError, match=r"batch_size \(3\) .*\(4\).*ranks 3\.\.3"):
        ctx.check_batch(3)
    with pytest.raises(InputValueError, match=r"batch_size \(2\) .*\(3\)"):
        DistContext(rank=0, world_size=3).check_batch(2)
    a, b = nn.Parameter(torch.zeros(2)), nn.Parameter(torch.zeros(2, 2))
    with pytest.raises(InputValueError, match="row_sparse"):  # refused before any collective
        DistContext(rank=0, world_size=2).sync_gradients([a], row_sparse=[b])


@pytest.mark.parametrize("world", [1, 2, 3, 5])
def test_shards_of_a_batch_and_of_scenes_partition_it_round_robin(world):
    """Rank r takes items r, r + W, r + 2W ...: every item on exactly one rank, in order."""
    items = [f"s{i}" for i in range(7)]
    shards = [DistContext(rank=r, world_size=world).shard(items) for r in range(world)]
    assert shards == [[items[i] for i in range(r, 7, world)] for r in range(world)]
    assert sorted(x for s in shards for x in s) == sorted(items)
    assert [shard_scenes(items, DistContext(rank=r, world_size=world)) for r in range(world)] == shards
    with pytest.raises(InputValueError, match=r"\['s1'\] more than once"):
        shard_scenes(["s0", "s1", "s1"], DistContext(rank=0, world_size=world))


def test_shard_and_shard_scenes_examples():
    assert DistContext(rank=2, world_size=3).shard("abcdefg") == ["c", "f"]
    assert DistContext(rank=0, world_size=3).shard(list(range(7))) == [0, 3, 6]
    assert DistContext(rank=1, world_size=3).shard(list(range(7))) == [1, 4]
    assert shard_scenes(["ar", "vr"], DistContext(rank=1, world_size=3)) == ["vr"]
    assert shard_scenes(["a", "b", "c"], DistContext(rank=1, world_size=2)) == ["b"]
    assert shard_scenes(["ar"], DistContext(rank=1, world_size=2)) == []
    with pytest.raises(InputValueError, match="scenes .*at least one scene"):
        shard_scenes([], DistContext())
    with pytest.raises(InputValueError, match=r"\['vr'\] more than once"):
        shard_scenes(["vr", "ar", "vr"], DistContext())


@pytest.mark.parametrize("world", [1, 2, 3, 4, 8])
def test_all_reduce_bytes_is_the_ring_volume(world):
    """A ring all-reduce sends 2 (W - 1) / W of the buffer per process (reduce-scatter + all-gather), floored."""
    for nbytes in (0, 4, 7, 10, 100, 4096, 123_456):
        assert _all_reduce_bytes(nbytes, world) == (2 * (world - 1) * nbytes) // world
    assert _all_reduce_bytes(1200, world) == {1: 0, 2: 1200, 3: 1600, 4: 1800, 8: 2100}[world]
    assert _all_reduce_bytes(100, world) == {1: 0, 2: 100, 3: 133, 4: 150, 8: 175}[world]
    assert _all_reduce_bytes(10, 3) == 13 and _all_reduce_bytes(7, 2) == 7  # floor(13.33); n on two ranks


def test_comm_stats_per_step():
    assert CommStats().per_step() == (0.0, 0.0)  # no step: no division by zero
    assert CommStats(steps=4, bytes_sent=10, dense_bytes=30).per_step() == (2.5, 7.5)
    assert CommStats(steps=1, bytes_sent=3, dense_bytes=5).per_step() == (3.0, 5.0)


def test_failure_message_names_rank_step_and_checkpoint():
    ctx = DistContext(rank=1, world_size=3)

    def broken() -> None:
        raise RuntimeError("Connection closed by peer\nmore detail")

    with pytest.raises(DistributedError) as e:
        ctx._run("the gradient all-reduce", 12, broken)
    msg = str(e.value)
    assert msg.startswith("rank 1 of 3: the gradient all-reduce at iteration 12 failed (RuntimeError: "
                          "Connection closed by peer)")
    assert "no checkpoint was written yet" in msg and "more detail" not in msg
    assert isinstance(e.value.__cause__, RuntimeError)
    ctx.last_checkpoint = ("run/ck.safetensors", 40)
    msg = str(ctx._failed("waiting", None, RuntimeError("")))
    assert "waiting failed (RuntimeError: RuntimeError(''))" in msg and "iteration 4" not in msg.split(";")[0]
    assert "run/ck.safetensors (iteration 40)" in msg
    # other errors pass through unchanged
    with pytest.raises(ValueError):
        ctx._run("x", None, lambda: (_ for _ in ()).throw(ValueError("no")))
    assert ctx._run("x", None, lambda a, b: a + b, 2, 3) == 5
