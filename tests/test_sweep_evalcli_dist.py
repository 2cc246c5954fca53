"""controlgs_adapter.distributed by hand: the gradient exchange of two real gloo processes (this
test process is rank 0, a child process rank 1) against the float64 sum of both ranks' gradients
written out here, the bytes each exchange reports computed by hand from the ring model, and every
refusal of the module.

All gradient values are multiples of 1/4, so every sum is exact in float32 whatever the order."""

from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from torch import nn

from controlgs_adapter.distributed import (DEFAULT_TIMEOUT_S, EXCHANGES, CommStats, DistContext, DistributedError,
                                           _all_reduce_bytes, init_distributed, shard_scenes)
from controlgs_adapter.errors import InputValueError

HERE = Path(__file__).resolve().parent
_TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


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


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def two_ranks() -> dict[str, object]:
    """Run the protocol as rank 0 here, rank 1 in a child; returns rank 0's observations."""
    port = _free_port()
    env = {**os.environ, "GLOO_SOCKET_IFNAME": "lo", "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "ignore"}
    child = subprocess.Popen([sys.executable, "-c", f"import sys; sys.path.insert(0, {str(HERE)!r}); "
                              f"import test_sweep_evalcli_dist as t; t._child({port})"], env=env,
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
