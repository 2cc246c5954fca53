"""One process of the distributed-training tests (``tests/core/test_distributed.py``), run by torchrun.

    torchrun --nproc_per_node=2 tests/helpers/dist_worker.py FIXTURE OUT --iterations 4 --batch 2 \
        [--checkpoint CK] [--die-at K]

FIXTURE is written by :func:`write_fixture` (a tiny backbone, the training views); OUT receives
the trained adapter's tensors and the loss history (rank 0). ``--die-at K``: every rank prints its
exchange statistics once iteration K is done, then rank 1 kills itself (SIGKILL), to test that
the others stop with an error.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

import torch

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.datasets.memory import posed_images
from controlgs_adapter.distributed import DistContext, init_distributed
from controlgs_adapter.formats.safetensors import load_tensors, save_tensors
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig, Trainer

FIXTURE_KIND = "controlgs_test_dist_fixture"
#: cheap downstream path (no optics) so that a step takes a fraction of a second at 16 px
EFFECTS = {"lens": True, "resample": True, "display": True}


def write_fixture(path: Path, model: NeuralGaussianModel, images: torch.Tensor, cameras: list[Camera],
                  background: torch.Tensor) -> Path:
    tensors = {f"model.{k}": v for k, v in model.state_dict().items()}
    tensors["images"] = images
    tensors["w2c"] = torch.stack([c.world_to_camera for c in cameras])
    tensors["K"] = torch.stack([c.intrinsics for c in cameras])
    tensors["background"] = background
    header = {"num_anchors": model.num_anchors, "feat_dim": model.feat_dim, "n_offsets": model.n_offsets,
              "voxel_size": model.voxel_size, "size": [cameras[0].width, cameras[0].height]}
    return save_tensors(path, tensors, header, kind=FIXTURE_KIND, format_version=1)


def read_fixture(path: Path) -> tuple[NeuralGaussianModel, torch.Tensor, list[Camera], torch.Tensor]:
    t, h = load_tensors(path, kind=FIXTURE_KIND, max_version=1)
    model = NeuralGaussianModel(h["num_anchors"], feat_dim=h["feat_dim"], n_offsets=h["n_offsets"],
                                voxel_size=h["voxel_size"])
    model.load_state_dict({k[len("model."):]: v for k, v in t.items() if k.startswith("model.")})
    w, hh = h["size"]
    cams = [Camera(m, k, w, hh) for m, k in zip(t["w2c"], t["K"])]
    return model, t["images"], cams, t["background"]


def make_trainer(fixture: Path, iterations: int, batch: int, checkpoint: Path | None, dist: DistContext,
                 checkpoint_every: int = 1) -> Trainer:
    model, images, cams, bg = read_fixture(fixture)
    config = TrainConfig(iterations=iterations, batch_size=batch, checkpoint_every=checkpoint_every, seed=0)
    return Trainer(model, posed_images(images, cams, background=bg), config, effects=EFFECTS, checkpoint=checkpoint,
                   dist=dist)


def result_tensors(trainer: Trainer) -> dict[str, torch.Tensor]:
    out = {k: v.detach().clone() for k, v in trainer.cgs.injector.state_dict().items()}
    out["history"] = torch.tensor(trainer.history, dtype=torch.float64)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("fixture", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--iterations", type=int, default=4)
    p.add_argument("--batch", type=int, default=2)
    p.add_argument("--checkpoint", type=Path)
    p.add_argument("--die-at", type=int)
    p.add_argument("--timeout", type=float, default=60.0)
    p.add_argument("--exchange", default="auto")
    args = p.parse_args(argv)
    with init_distributed(device="cpu", timeout=args.timeout, exchange=args.exchange) as ctx:  # trains on CPU
        trainer = make_trainer(args.fixture, args.iterations, args.batch, args.checkpoint, ctx)
        trainer.resume()
        if args.die_at is not None:
            trainer.train(until=args.die_at, progress=False)
            sent, dense = ctx.stats.per_step()
            print(f"rank {ctx.rank} exchange: " + json.dumps({"bytes": sent, "dense_bytes": dense,
                  "rows": ctx.stats.rows_touched / max(ctx.stats.steps, 1), "exchange": ctx.stats.last.get("exchange")}),
                  flush=True)
            if ctx.rank == 1:
                os.kill(os.getpid(), signal.SIGKILL)
        trainer.train(progress=False)
        if ctx.is_main:
            sent, dense = ctx.stats.per_step()
            header = {"bytes": sent, "dense_bytes": dense, "rows": ctx.stats.rows_touched / max(ctx.stats.steps, 1),
                      "exchange": ctx.stats.last.get("exchange")}
            save_tensors(args.out, result_tensors(trainer), header, kind="controlgs_test_dist_result", format_version=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
