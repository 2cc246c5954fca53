"""Data-parallel training with torch.distributed: 2 CPU processes (gloo over loopback) started by
torchrun must reproduce single-process training with the same global batch and seed; a killed
rank must end the run with an error (not a hang) and leave a checkpoint that resumes on another
number of processes to the uninterrupted result.

Tolerance (docs/distributed.md): adapter parameters within 1e-6 absolute (+1e-5 relative), loss
history within 1e-6 relative. Measured: bit-identical for 2 processes and a batch of 2 (each
gradient element is one sum of two terms, whichever the order); 7.8e-8 in the conditions for a
batch of 4 after 3 iterations.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest
import torch

from controlgs_adapter.distributed import DistContext, DistributedError, init_distributed, shard_scenes
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.formats.safetensors import load_tensors

sys.path.insert(0, str(Path(__file__).parent))
import _dist_worker as worker  # noqa: E402

WORKER = Path(__file__).parent / "_dist_worker.py"
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
    from controlgs_adapter.training import Trainer

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


def _backbone_baked() -> bool:
    from controlgs_adapter.scene import builtin_backbone_dir

    return (builtin_backbone_dir("ar") / "point_cloud").is_dir()


@pytest.mark.skipif(not _backbone_baked(), reason="built-in backbone not baked")
def test_controlgs_train_command_under_torchrun(tmp_path, monkeypatch):
    """The unchanged `controlgs train` under torchrun (2 processes, dense condition exchange)
    writes the adapter once and it equals the single-process command's with the same global batch
    and seed."""
    from controlgs_adapter.cli import main
    from controlgs_adapter.controlgs import ADAPTER_FORMAT_VERSION, ADAPTER_KIND

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
