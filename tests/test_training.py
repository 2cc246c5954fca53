"""Trainer: only adapter parameters change, sampling follows the paper, resume is exact."""

import math

import pytest
import torch

pytest.importorskip("skimage")

from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import FileFormatError, InputValueError
from controlgs_adapter.state import RuntimeState
from controlgs_adapter.training import DEFAULT_EFFECTS, TrainConfig, Trainer, modules_for

EFFECTS = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}



def _trainer(tiny, tmp_path=None, **cfg):
    scene, model = tiny
    config = TrainConfig(**{"iterations": 6, "checkpoint_every": 0, "psf_fraction": 0.34, **cfg})
    return Trainer(model, scene.views("train"), config, effects=EFFECTS,
                   checkpoint=None if tmp_path is None else tmp_path / "ckpt.safetensors")


def test_resume_is_exact(tiny, tmp_path):
    straight = _trainer(tiny)
    straight.train(progress=False)
    want = {k: v.clone() for k, v in straight.cgs.injector.state_dict().items()}
    losses = list(straight.history)
    straight.cgs.unwrap()

    first = _trainer(tiny, tmp_path)
    first.train(until=4, progress=False)  # "interrupted" after 4 of 6 iterations; checkpoint written
    first.cgs.unwrap()
    second = _trainer(tiny, tmp_path)
    assert second.resume() and second.iteration == 4
    second.train(progress=False)
    got = second.cgs.injector.state_dict()
    second.cgs.unwrap()
    assert second.history == losses
    for k in want:
        assert torch.equal(want[k], got[k]), k
    assert any(float(v.abs().max()) > 0 for k, v in want.items() if k.startswith("conditions")), "conditions never moved"


def test_only_the_adapter_trains_and_phases(tiny):
    scene, model = tiny
    before = {k: v.clone() for k, v in model.state_dict().items()}
    t = _trainer(tiny, iterations=3)
    assert [t.optics_mode(i) for i in range(3)] == ["distortion", "distortion", "fast"]
    t.train(progress=False)
    t.cgs.unwrap()
    for k, v in model.state_dict().items():
        assert torch.equal(before[k], v), k


def test_each_step_runs_the_optics_in_its_phase_mode(tiny):
    t = _trainer(tiny, iterations=3, psf_mode="exact")  # psf_fraction 0.34 of 3: the last step in the PSF phase
    modes = []
    for _ in range(3):
        t.step()
        modes.append(t.pipeline["optics"].mode)
    t.cgs.unwrap()
    assert modes == ["distortion", "distortion", "exact"]


class _ModelessOptics(Stage):
    """A third-party optics stage with no ``mode``."""

    name = "optics"
    order = 50.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        return image


def test_an_optics_stage_without_modes_is_refused_before_training(tiny):
    scene, model = tiny
    with pytest.raises(InputValueError, match="PSFOptics.*_ModelessOptics"):
        Trainer(model, scene.views("train"), TrainConfig(iterations=2, checkpoint_every=0),
                effects={"resample": True, "optics": _ModelessOptics()})
    t = _trainer(tiny)  # the wrap was rolled back: a model still wrapped is refused (LifecycleError)
    t.cgs.unwrap()


def test_state_sampling_follows_the_paper(tiny):
    t = _trainer(tiny)
    draws = [t.sample() for _ in range(400)]
    t.cgs.unwrap()
    d = torch.tensor([s.downsample for _, s in draws])
    rho = torch.tensor([s.power_saving for _, s in draws])
    assert float(d.min()) >= 1.0 and float(d.max()) <= 8.0 and float(rho.max()) <= 0.8
    # log-uniform: log2 d is uniform on [0, 3] (mean 1.5, var 0.75); rho uniform on [0, 0.8]
    assert abs(float(torch.log2(d).mean()) - 1.5) < 0.15 and abs(float(torch.log2(d).var()) - 0.75) < 0.15
    assert abs(float(rho.mean()) - 0.4) < 0.04
    views = {v for v, _ in draws}
    assert views == set(range(len(tiny[0].train_cameras)))


def test_modules_follow_the_effects_and_errors():
    assert modules_for(DEFAULT_EFFECTS) == ("lens", "resample", "display")
    assert modules_for({"resample": True, "oled": True}) == ("resample",)
    assert modules_for({"optics": True, "display": False}) == ("lens",)
    with pytest.raises(InputValueError, match="max_power_saving"):
        TrainConfig(max_power_saving=1.0)


def test_checkpoint_from_another_config_is_refused(tiny, tmp_path):
    t = _trainer(tiny, tmp_path, iterations=1)
    t.train(progress=False)
    t.cgs.unwrap()
    other = _trainer(tiny, tmp_path, iterations=1, lr=1e-2)
    with pytest.raises(FileFormatError, match="lr"):
        other.resume()
    other.cgs.unwrap()


def test_checkpoint_from_other_views_is_refused_and_views_are_checked(tiny, tmp_path):
    scene, model = tiny
    t = _trainer(tiny, tmp_path, iterations=1)
    t.train(progress=False)
    t.cgs.unwrap()
    config = TrainConfig(iterations=1, checkpoint_every=0, psf_fraction=0.34)
    other = Trainer(model, scene.views("test"), config, effects=EFFECTS, checkpoint=tmp_path / "ckpt.safetensors")
    with pytest.raises(FileFormatError, match=r"ckpt\.safetensors.*other views"):
        other.resume()
    other.cgs.unwrap()
    with pytest.raises(InputValueError, match="views must be"):
        Trainer(model, scene.train_images, config, effects=EFFECTS)


def test_views_of_any_size_and_a_plain_sequence(tiny):
    """Non-square views of different sizes train; a plain list with a background is a dataset too."""
    from controlgs_adapter.datasets.memory import tensor_frames
    from controlgs_adapter.datasets.base import PosedImages

    scene, model = tiny
    frames = tensor_frames(scene.train_images, scene.train_cameras)
    crops = [PosedImages(frames, resolution=12).cameras[0], scene.train_cameras[1]]

    class Plain(list):
        background = scene.background

    views = Plain([(crops[0], PosedImages(frames, resolution=12).image(0)), (crops[1], scene.train_images[1])])
    t = Trainer(model, views, TrainConfig(iterations=2, checkpoint_every=0), effects={"resample": True, "display": True})
    t.train(progress=False)
    t.cgs.unwrap()
    assert len(t.history) == 2 and all(math.isfinite(v) for v in t.history)
