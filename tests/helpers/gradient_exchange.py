"""A fixed two-rank scenario of the gradient exchange: parameters whose gradients are dense, row-sparse,
zero, missing on one rank or on both, and the calls both ranks make in the same order (gather, broadcast,
the three exchanges, a refused exchange at different iterations). Rank 1 runs :func:`rank1` in a child
process; rank 0 runs :func:`protocol` and checks what it returns."""

from __future__ import annotations

import os

import torch
from torch import nn

from controlgs_adapter.distributed import DistContext, DistributedError, init_distributed


def _rows(shape: tuple[int, ...], rows: list[int], seed: int) -> torch.Tensor:
    """A gradient of ``shape`` that is non-zero (multiples of 1/4 in [-2, 2], never 0) in ``rows`` only."""
    g = torch.zeros(shape)
    gen = torch.Generator().manual_seed(seed)
    for r in rows:
        v = torch.randint(1, 9, shape[1:], generator=gen).float() / 4.0
        sign = torch.randint(0, 2, shape[1:], generator=gen).float() * 2 - 1
        g[r] = v * sign
    return g


def scenario(rank: int) -> tuple[list[nn.Parameter], list[nn.Parameter], dict[str, nn.Parameter]]:
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


def summed_gradients() -> dict[str, torch.Tensor | None]:
    """The gradients summed over both ranks in float64: None where no rank had one."""
    _, _, p0 = scenario(0)
    _, _, p1 = scenario(1)
    out: dict[str, torch.Tensor | None] = {}
    for n in p0:
        grads = [g.double() for g in (p0[n].grad, p1[n].grad) if g is not None]
        out[n] = sum(grads[1:], grads[0]) if grads else None
    return out


def protocol(ctx: DistContext) -> dict[str, object]:
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
        params, sparse, named = scenario(ctx.rank)
        loss = ctx.sync_gradients(params, row_sparse=sparse, loss=1.5 if ctx.rank == 0 else 2.25, step=7)
        grads = {n: None if q.grad is None else q.grad.tolist() for n, q in named.items()}
        out[exchange] = {"loss": loss, "grads": ctx.all_gather_json(grads), "last": dict(ctx.stats.last),
                         "dtypes": {n: str(q.grad.dtype) for n, q in named.items() if q.grad is not None}}
    out["stats"] = (ctx.stats.steps, ctx.stats.bytes_sent, ctx.stats.dense_bytes, ctx.stats.rows_touched)
    params, sparse, _ = scenario(ctx.rank)
    try:  # a rank at another iteration (resumed from another checkpoint) is caught by every rank
        ctx.sync_gradients(params, row_sparse=sparse, step=3 + ctx.rank)
        out["mismatch"] = None
    except DistributedError as e:
        out["mismatch"] = str(e)
    ctx.barrier()
    return out


def rank1(port: int) -> None:
    """Rank 1 of the scenario (run in a child process)."""
    os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1",
                       "MASTER_PORT": str(port)})
    with init_distributed("gloo", timeout=30.0, exchange="sparse") as ctx:
        protocol(ctx)
