"""Mutation sweep 5, batch 7: behaviours that a plausible one-line bug changed and no test observed (the
integer-factor average pool of area_resample on non-square frames, Trainer.seconds before training, the
start of ladder_len's FFT-size ladder, init_distributed with a sub-second timeout). See docs/testing.md."""

from __future__ import annotations

import time

import pytest
import torch

from controlgs_adapter.distributed import init_distributed
from controlgs_adapter.downstream.optics.resampled import fast_len, ladder_len
from controlgs_adapter.downstream.resample import area_resample

_TORCHRUN = ("RANK", "WORLD_SIZE", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT")


# ----------------------------------------------------------------------------- area_resample: integer factors
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("k", [3, 5])
def test_integer_factor_on_a_non_square_frame_is_the_exact_block_mean(k, dtype):
    """``area_resample`` docstring: at an integer factor k dividing both H and W (non-square frames
    included) each output is its k x k block's sum / (k * k), the correctly rounded mean when the sum is
    exact. 8-bit pixel values on a 3k x 4k frame: the reference is the float64 block mean (exact sums of
    at most 64 values < 256) rounded once to ``dtype``."""
    g = torch.Generator().manual_seed(k)
    x = torch.randint(0, 256, (2, 3, 3 * k, 4 * k), generator=g).to(dtype)
    ref = x.double().reshape(2, 3, 3, k, 4, k).sum(dim=(3, 5)) / (k * k)
    out = area_resample(x, float(k))
    assert out.shape == (2, 3, 3, 4) and out.dtype == dtype
    assert torch.equal(out, ref.to(dtype))


# ----------------------------------------------------------------------------- Trainer.seconds
def test_trainer_seconds_is_zero_before_training_then_the_wall_time_of_train():
    """``Trainer`` docstring: ``seconds`` is the wall time of the last ``train()`` call, 0.0 before the
    first; after ``train()`` it lies between 0 and the wall time measured around the call."""
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.training import TrainConfig, Trainer

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=2)
    t = Trainer(model.eval(), scene.views("train"), TrainConfig(iterations=1, checkpoint_every=0),
                effects={"resample": True})
    try:
        assert t.seconds == 0.0 and t.iteration == 0
        t0 = time.perf_counter()
        t.train(progress=False)
        wall = time.perf_counter() - t0
        assert t.iteration == 1 and 0.0 < t.seconds <= wall
    finally:
        t.cgs.unwrap()


# ----------------------------------------------------------------------------- ladder_len: where the ladder starts
def test_ladder_starts_at_8_and_pads_at_most_20_percent_above_it():
    """``ladder_len`` docstring: the ladder starts at 8 (every n <= 8 gives 8); above that n is padded by at
    most 20 % (10 -> 12). By hand: the ladder from 8 by steps of 1.12 is 8, 8.96 -> 9, 10.04 -> 11 -> 12
    (the next 7-smooth size), 11.24 -> 12, 12.59 -> 13 -> 14, 14.10 -> 15, 15.79 -> 16, 17.68 -> 18, ..."""
    assert [ladder_len(n) for n in range(1, 19)] == [8] * 8 + [9, 12, 12, 12, 14, 14, 15, 16, 18, 18]
    for n in range(8, 16385):
        m = ladder_len(n)
        assert n <= m <= 1.2 * n and fast_len(m) == m, (n, m)
    assert ladder_len(10) == 12  # the 20 % case


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
