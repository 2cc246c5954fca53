"""Training beyond one process: data parallelism with ``torch.distributed``.

Launch the unchanged ``controlgs train`` command with ``torchrun``; :func:`init_distributed`
reads torchrun's environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``,
``MASTER_PORT``) and joins the process group with a timeout, so a process that dies makes the
others fail with :class:`DistributedError` instead of hanging. The backend follows the training
device (:func:`default_backend`): NCCL with one GPU per process (``cuda:<LOCAL_RANK>``) for
``--device cuda``, gloo on the CPU otherwise.

Every process (rank) holds a full replica of the adapter. Per step:

* **Global batch.** Every rank draws the whole global batch of (view, state) samples from the
  trainer's generator (same seed, same draws: identical on every rank and equal to a
  single-process run) and renders only the samples ``j`` with ``j % world_size == rank``
  (:meth:`DistContext.shard`). The batch therefore does not depend on the number of processes,
  and the generator state saved in a checkpoint resumes on any number of processes.
* **Gradients** (:meth:`DistContext.sync_gradients`), each sample's loss being divided by the
  global batch size so that the sum over ranks is the batch mean:

  1. one all-reduce (SUM, float64) of a small dense buffer: the gradients of the dense
     parameters (the shared projections), one has-gradient flag per parameter, each rank's count
     of touched condition rows and iteration (one slot per rank) and the loss;
  2. the per-anchor conditions ``[A, M, N]`` are *row-sparse*: a rank only decodes the anchors
     visible in its views, so only rows with a non-zero gradient are sent. Every rank
     all-gathers the (padded to the largest count) row ids ``[k]`` and rows ``[k, M*N]`` and sums
     them with ``index_add`` into a zero gradient, in rank order. With ``exchange="auto"`` the
     table falls back to a dense all-reduce when the padded gather would move as many bytes or more
     (most anchors touched by every rank).

  Afterwards every rank holds the same summed gradients (``None`` where no rank had one, as in
  a single process), and the same optimizer step keeps the replicas identical.
* **Checkpoints** are written by rank 0 only (atomically, :mod:`controlgs_adapter.formats.safetensors`).

Bytes are counted as what one rank sends under the ring algorithms (all-reduce of ``n`` bytes:
``2 (W-1)/W n``; all-gather of ``n`` bytes per rank: ``(W-1) n``); :class:`CommStats` keeps them,
next to what a dense all-reduce of every gradient would have sent.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any, Callable, Iterable, Sequence, TypeVar

import torch
import torch.distributed as dist
from torch import nn

from .errors import ControlGSError, InputValueError

__all__ = ["DistributedError", "CommStats", "DistContext", "init_distributed", "default_backend", "shard_scenes",
           "EXCHANGES", "DEFAULT_TIMEOUT_S"]

T = TypeVar("T")

#: how the row-sparse tables travel: only touched rows, the whole table, or whichever is cheaper
EXCHANGES = ("auto", "sparse", "dense")
#: seconds a collective waits for the other processes (:func:`init_distributed`)
DEFAULT_TIMEOUT_S = 300.0

_TORCHRUN_VARS = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


class DistributedError(ControlGSError, RuntimeError):
    """A collective failed (another process died or timed out) or the ranks disagree."""


@dataclass
class CommStats:
    """Bytes one rank sent in gradient exchanges (ring model, see the module docstring).

    Attributes:
        steps: exchanges counted.
        bytes_sent: total bytes this rank sent.
        dense_bytes: what a dense all-reduce of every gradient would have sent over the same steps.
        rows_touched: row-sparse rows with a non-zero gradient on this rank (what the sparse
            exchange sends).
        last: the most recent step's ``{"bytes_sent", "dense_bytes", "rows", "exchange"}``.
    """

    steps: int = 0
    bytes_sent: int = 0
    dense_bytes: int = 0
    rows_touched: int = 0
    last: dict[str, Any] = field(default_factory=dict)

    def per_step(self) -> tuple[float, float]:
        """Mean ``(bytes_sent, dense_bytes)`` per step."""
        n = max(self.steps, 1)
        return self.bytes_sent / n, self.dense_bytes / n


def _all_reduce_bytes(nbytes: int, world: int) -> int:
    return (2 * (world - 1) * nbytes) // world


@dataclass
class DistContext:
    """Where this process stands in a data-parallel run; the trainer consults it.

    A default ``DistContext()`` is a single process: :meth:`shard` returns everything,
    :meth:`sync_gradients` returns at once and :attr:`is_main` is True.

    Attributes:
        rank, world_size, local_rank: torchrun's ``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``.
        backend: ``"gloo"`` or ``"nccl"`` (None for a single process).
        device: where this rank computes: ``cuda:<local_rank>`` with NCCL, the CPU with gloo; in a
            single process the device :func:`init_distributed` was given (default CPU).
        exchange: how row-sparse gradients travel (one of :data:`EXCHANGES`).
        stats: :class:`CommStats` of the gradient exchanges so far.
        last_checkpoint: ``(path, iteration)`` of the last checkpoint written (by rank 0), for
            error messages.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    exchange: str = "auto"
    stats: CommStats = field(default_factory=CommStats)
    last_checkpoint: tuple[str, int] | None = None
    _owns_group: bool = False

    def __post_init__(self) -> None:
        if self.exchange not in EXCHANGES:
            raise InputValueError(f"exchange must be one of {EXCHANGES}, got {self.exchange!r}")
        if not (0 <= self.rank < self.world_size):
            raise InputValueError(f"need 0 <= rank < world_size, got rank={self.rank}, world_size={self.world_size}")

    # ------------------------------------------------------------------ basics
    @property
    def is_distributed(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        """True on rank 0 (the one that writes files and prints)."""
        return self.rank == 0

    def shard(self, items: Sequence[T]) -> list[T]:
        """This rank's share of ``items``: ``items[rank::world_size]``."""
        return list(items[self.rank::self.world_size])

    def check_batch(self, batch_size: int) -> None:
        """Refuse a global batch smaller than the number of processes (some ranks would idle)."""
        if int(batch_size) < self.world_size:
            raise InputValueError(
                f"the global batch_size ({batch_size}) is smaller than the number of processes ({self.world_size}): "
                f"ranks {batch_size}..{self.world_size - 1} would have no view to render; pass a batch size >= "
                f"{self.world_size} (the same batch size gives the same result on any number of processes)")

    def close(self, *, wait_for_all: bool = True) -> None:
        """Leave the process group if :func:`init_distributed` created it; with ``wait_for_all``
        after a barrier, so that no rank tears its connections down while a peer still uses them
        (gloo can abort a process whose peer vanished mid-teardown)."""
        if self._owns_group and dist.is_initialized():
            if wait_for_all:
                try:
                    self.barrier()
                except DistributedError:
                    pass  # a peer is gone already: nothing left to wait for
            dist.destroy_process_group()
        self._owns_group = False

    def __enter__(self) -> "DistContext":
        return self

    def __exit__(self, exc_type: type | None, *exc: object) -> None:
        self.close(wait_for_all=exc_type is None)  # after an error a peer may never arrive

    # ------------------------------------------------------------------ collectives
    def _failed(self, what: str, step: int | None, e: BaseException) -> DistributedError:
        at = "" if step is None else f" at iteration {step}"
        ck = ("no checkpoint was written yet" if self.last_checkpoint is None else
              f"the last checkpoint, {self.last_checkpoint[0]} (iteration {self.last_checkpoint[1]}), resumes the run "
              "on any number of processes: run the same command again")
        msg = (str(e.args[0]) if e.args else str(e)).strip().splitlines() or [repr(e)]
        return DistributedError(f"rank {self.rank} of {self.world_size}: {what}{at} failed ({type(e).__name__}: "
                                f"{msg[0]}); another process has probably died or stalled past the timeout; {ck}")

    def _run(self, what: str, step: int | None, fn: Callable[..., Any], *args: Any) -> Any:
        try:
            return fn(*args)
        except RuntimeError as e:  # gloo/NCCL errors and timeouts (DistBackendError is a RuntimeError)
            raise self._failed(what, step, e) from e

    def broadcast_parameters(self, parameters: Iterable[torch.Tensor]) -> None:
        """Copy rank 0's values of ``parameters`` to every rank (one flat broadcast)."""
        if not self.is_distributed:
            return
        params = list(parameters)
        if not params:
            return
        with torch.no_grad():
            flat = torch.cat([p.detach().reshape(-1) for p in params])
            self._run("broadcasting the initial parameters", None, dist.broadcast, flat, 0)
            offset = 0
            for p in params:
                p.copy_(flat[offset:offset + p.numel()].view_as(p))
                offset += p.numel()

    def barrier(self) -> None:
        if self.is_distributed:
            self._run("waiting for every rank (barrier)", None, dist.barrier)

    def all_gather_json(self, obj: Any) -> list[Any]:
        """Every rank's JSON-able ``obj``, in rank order (sent as UTF-8 bytes, never pickled)."""
        if not self.is_distributed:
            return [obj]
        data = torch.tensor(list(json.dumps(obj).encode()), dtype=torch.uint8, device=self.device)
        size = torch.tensor([data.numel()], dtype=torch.int64, device=self.device)
        sizes = [torch.zeros_like(size) for _ in range(self.world_size)]
        self._run("gathering results", None, dist.all_gather, sizes, size)
        n = int(max(int(s) for s in sizes))
        padded = torch.zeros(n, dtype=torch.uint8, device=self.device)
        padded[:data.numel()] = data
        out = [torch.zeros_like(padded) for _ in range(self.world_size)]
        self._run("gathering results", None, dist.all_gather, out, padded)
        return [json.loads(bytes(o[:int(s)].tolist()).decode()) for o, s in zip(out, sizes)]

    # ------------------------------------------------------------------ gradients
    def sync_gradients(self, parameters: Iterable[nn.Parameter], *, row_sparse: Iterable[nn.Parameter] = (),
                       loss: float = 0.0, step: int = 0) -> float:
        """Sum every parameter's ``.grad`` over the ranks, in place; return the sum of ``loss``.

        Args:
            parameters: every trainable parameter (same order on every rank).
            row_sparse: those among ``parameters`` whose gradient is non-zero in few rows (dim 0),
                e.g. the per-anchor conditions ``[A, M, N]``: only touched rows travel.
            loss: this rank's share of the batch loss (summed over ranks for logging).
            step: the iteration; every rank must be at the same one (checked: a rank that did not
                load the checkpoint the others resumed from is caught here).

        A ``None`` gradient counts as zero; it stays ``None`` only if it is ``None`` on every rank.
        """
        if not self.is_distributed:
            return float(loss)
        params = list(parameters)
        sparse_ids = {id(p) for p in row_sparse}
        sparse = [p for p in params if id(p) in sparse_ids]
        if len(sparse) != len(sparse_ids):
            raise InputValueError("row_sparse must be a subset of parameters")
        dense = [p for p in params if id(p) not in sparse_ids]
        w, r = self.world_size, self.rank
        device = params[0].device

        # touched rows of the row-sparse tables: ids [k], rows [k, row_numel]
        local = []
        for p in sparse:
            g = p.grad
            if g is None:
                local.append((torch.zeros(0, dtype=torch.long, device=device), p.new_zeros(0, p[0].numel())))
            else:
                g2 = g.reshape(g.shape[0], -1)
                ids = g2.ne(0).any(dim=1).nonzero().squeeze(1)
                local.append((ids, g2.index_select(0, ids)))

        # 1. one all-reduce: dense grads | has-grad flags | counts per rank | step per rank | loss
        n_dense = sum(p.numel() for p in dense)
        buf = torch.zeros(n_dense + len(params) + len(sparse) * w + w + 1, dtype=torch.float64, device=device)
        offset = 0
        for p in dense:
            if p.grad is not None:
                buf[offset:offset + p.numel()] = p.grad.reshape(-1)
            offset += p.numel()
        flags = buf[n_dense:n_dense + len(params)]
        flags.copy_(torch.tensor([float(p.grad is not None) for p in params], dtype=torch.float64))
        counts = buf[n_dense + len(params):n_dense + len(params) + len(sparse) * w].view(len(sparse), w)
        counts[:, r] = torch.tensor([float(ids.numel()) for ids, _ in local], dtype=torch.float64)
        steps = buf[-w - 1:-1]
        steps[r] = float(step)
        buf[-1] = float(loss)
        self._run("the gradient all-reduce", step, dist.all_reduce, buf)
        sent = _all_reduce_bytes(buf.numel() * buf.element_size(), w)
        dense_equiv = _all_reduce_bytes(sum(p.numel() * p.element_size() for p in params), w)

        if bool((steps != steps[0]).any()):
            at = ", ".join(f"rank {i}: {int(s)}" for i, s in enumerate(steps.tolist()))
            raise DistributedError(
                f"the ranks are at different iterations ({at}): a rank resumed from another checkpoint or none; "
                "put the checkpoint on a filesystem that every node shares")

        has_grad = {id(p): bool(f > 0) for p, f in zip(params, flags.tolist())}
        offset = 0
        for p in dense:
            if has_grad[id(p)]:
                p.grad = buf[offset:offset + p.numel()].view_as(p).to(p.dtype).clone()
            else:
                p.grad = None
            offset += p.numel()

        # 2. the row-sparse tables
        rows, exchange = sum(ids.numel() for ids, _ in local), "none"
        for p, (ids, vals), cnt in zip(sparse, local, counts.tolist()):
            if not has_grad[id(p)]:
                p.grad = None
                continue
            cnt = [int(c) for c in cnt]
            k = max(cnt)
            row_bytes = ids.element_size() + vals.shape[1] * vals.element_size()
            sparse_bytes = (w - 1) * k * row_bytes
            dense_bytes = _all_reduce_bytes(p.numel() * p.element_size(), w)
            if k == 0:  # a gradient on some rank, but zero everywhere
                p.grad = torch.zeros_like(p)
                continue
            use_dense = self.exchange == "dense" or (self.exchange == "auto" and sparse_bytes >= dense_bytes)
            if use_dense:
                g = p.grad if p.grad is not None else torch.zeros_like(p)
                g = g.contiguous()
                self._run("the dense condition all-reduce", step, dist.all_reduce, g)
                p.grad = g
                sent += dense_bytes
                exchange = "dense" if exchange in ("none", "dense") else "mixed"
                continue
            pad = k - ids.numel()  # all-gather needs equal sizes; the padding is cut off before the sum
            pad_ids = torch.cat([ids, ids.new_zeros(pad)]) if pad else ids
            pad_vals = torch.cat([vals, vals.new_zeros(pad, vals.shape[1])]) if pad else vals
            all_ids = [torch.empty_like(pad_ids) for _ in range(w)]
            all_vals = [torch.empty_like(pad_vals) for _ in range(w)]
            self._run("the sparse condition all-gather (row ids)", step, dist.all_gather, all_ids, pad_ids)
            self._run("the sparse condition all-gather (rows)", step, dist.all_gather, all_vals, pad_vals)
            if p.grad is None:
                grad = p.new_zeros(p.shape[0], vals.shape[1])
            else:  # the local gradient is zero outside this rank's rows: clear those, no O(A) fill
                grad = p.grad.contiguous().view(p.shape[0], -1).index_fill_(0, ids, 0.0)
            for a, v, c in zip(all_ids, all_vals, cnt):  # rank order: the same sum on every rank
                if c:
                    grad.index_add_(0, a[:c], v[:c])
            p.grad = grad.view_as(p)
            sent += sparse_bytes
            exchange = "sparse" if exchange in ("none", "sparse") else "mixed"

        st = self.stats
        st.steps += 1
        st.bytes_sent += sent
        st.dense_bytes += dense_equiv
        st.rows_touched += rows
        st.last = {"bytes_sent": sent, "dense_bytes": dense_equiv, "rows": rows, "exchange": exchange}
        return float(buf[-1])


def default_backend(device: str | torch.device | None) -> str:
    """The process-group backend that fits the training ``device``: ``"nccl"`` for a CUDA device,
    ``"gloo"`` otherwise (CPU, or ``None``: a caller that names no device trains on CPU; whether
    CUDA is installed does not matter)."""
    return "nccl" if device is not None and torch.device(device).type == "cuda" else "gloo"


def _as_device(device: str | torch.device | None) -> torch.device | None:
    if device is None or isinstance(device, torch.device):
        return device
    try:
        return torch.device(device)
    except (RuntimeError, TypeError) as e:
        raise InputValueError(f"device {device!r} is not a torch device: {e}") from None


def _rank_device(backend: str, device: torch.device | None, local_rank: int) -> torch.device:
    """Where this rank computes: ``cuda:<local_rank>`` with NCCL, the CPU with gloo; a ``device``
    of the other kind is refused (NCCL moves CUDA tensors only; gloo ranks train on the CPU)."""
    if device is not None and (device.type == "cuda") != (backend == "nccl"):
        fix = ("NCCL moves CUDA tensors only: pass a CUDA device (--device cuda) or use gloo (the default on CPU)"
               if backend == "nccl" else
               "gloo ranks train on the CPU: pass --device cpu, or leave the backend to the default (nccl with CUDA)")
        raise InputValueError(f"backend {backend!r} does not fit device {str(device)!r}: {fix}")
    return torch.device("cuda", local_rank) if backend == "nccl" else torch.device("cpu")


def init_distributed(backend: str | None = None, *, device: str | torch.device | None = None,
                     timeout: float = DEFAULT_TIMEOUT_S, exchange: str = EXCHANGES[0]) -> DistContext:
    """The :class:`DistContext` of this process, joining torchrun's process group if launched by it.

    Without torchrun's environment (``WORLD_SIZE`` unset or 1) this is a single process, no group
    is created and the context's device is ``device`` (the CPU when None). Otherwise the group is
    initialised from the environment (``env://``) with ``timeout`` seconds for every collective and
    ``backend`` (default :func:`default_backend` of ``device``: ``"nccl"`` for a CUDA device,
    ``"gloo"`` for the CPU or ``None``). With NCCL this rank computes on ``cuda:<LOCAL_RANK>``
    (the index of a ``device`` such as ``cuda:1`` is not used: every process takes its own GPU),
    with gloo on the CPU. A group that the caller created already is used as it is.

    Raises:
        InputValueError: an unknown backend, exchange or device, a timeout <= 0, or a backend that
            does not fit ``device`` (``"nccl"`` with a CPU device, ``"gloo"`` with a CUDA one).
        DistributedError: torchrun's variables are incomplete, NCCL finds no GPU of its own for this
            process (``LOCAL_RANK`` >= the GPUs visible), or the group cannot be formed.
    """
    if exchange not in EXCHANGES:
        raise InputValueError(f"exchange must be one of {EXCHANGES}, got {exchange!r}")
    if not timeout > 0:
        raise InputValueError(f"timeout must be > 0 seconds, got {timeout!r}")
    want = _as_device(device)
    env = os.environ
    if dist.is_initialized():  # the caller made the group: use it as it is
        rank, world = dist.get_rank(), dist.get_world_size()
        be = dist.get_backend()
        local = int(env.get("LOCAL_RANK", rank))
        return DistContext(rank, world, local, be, _rank_device(be, want, local), exchange)
    if int(env.get("WORLD_SIZE", "1")) <= 1:
        return DistContext(device=want if want is not None else torch.device("cpu"), exchange=exchange)
    missing = [k for k in _TORCHRUN_VARS if k not in env]
    if missing:
        raise DistributedError(f"WORLD_SIZE={env['WORLD_SIZE']} but {missing} are not set: launch with torchrun "
                               "(or set every one of RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT)")
    rank, world, local = int(env["RANK"]), int(env["WORLD_SIZE"]), int(env["LOCAL_RANK"])
    if backend is None:
        backend = default_backend(want)
    if backend not in ("gloo", "nccl"):
        raise InputValueError(f"backend must be 'gloo' or 'nccl', got {backend!r}")
    rank_device = _rank_device(backend, want, local)
    if backend == "nccl":
        gpus = torch.cuda.device_count()
        if local >= gpus:
            fewer = f"start at most {gpus} process(es) per node (torchrun --nproc-per-node {gpus}), or " if gpus else ""
            raise DistributedError(
                f"rank {rank} of {world}: NCCL needs one GPU per process, but this is process LOCAL_RANK={local} of "
                f"its node and this machine has {gpus} GPU(s) visible; {fewer}train on the CPU with gloo (--device cpu)")
        torch.cuda.set_device(rank_device)
    try:
        dist.init_process_group(backend, rank=rank, world_size=world, timeout=timedelta(seconds=float(timeout)),
                                device_id=rank_device if backend == "nccl" else None)
    except (RuntimeError, ValueError) as e:
        raise DistributedError(f"rank {rank} of {world}: could not join the process group at "
                               f"{env['MASTER_ADDR']}:{env['MASTER_PORT']} ({backend}): {e}") from e
    return DistContext(rank, world, local, backend, rank_device, exchange, _owns_group=True)


def shard_scenes(scenes: Sequence[str], ctx: DistContext) -> list[str]:
    """This rank's scenes for many-scenes mode: ``scenes[rank::world_size]`` (each rank trains
    its scenes' adapters independently). Duplicate names are refused."""
    dupes = sorted({s for s in scenes if list(scenes).count(s) > 1})
    if dupes:
        raise InputValueError(f"scenes lists {dupes} more than once")
    if not scenes:
        raise InputValueError("scenes must name at least one scene")
    return ctx.shard(list(scenes))
