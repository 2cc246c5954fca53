"""Tests of ``controlgs_adapter.training``: the training configuration and its refusals, the trainer (setup,
view/state sampling, optics phases, steps, batches, renderers, non-finite inputs and divergence, host
syncs), its checkpoints (cadence, exact resume, damaged or foreign files), and its progress bars
(the terminal width, rank 0 only, a job of several trainings)."""

from __future__ import annotations

import collections
import copy
import math
import os
import re
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import pytest
import torch
import torch.distributed as dist
from helpers.banks import affine_bank, random_bank
from helpers.rawfiles import write_raw
from torch.utils._python_dispatch import TorchDispatchMode

from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.controlgs import ControlGS
from controlgs_adapter.datasets.memory import posed_images
from controlgs_adapter.distributed import DistContext
from controlgs_adapter.downstream.bank_maps import BankMap
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.stage import Stage, StageContext
from controlgs_adapter.errors import ControlGSError, FileFormatError, InputValueError, NonFiniteError
from controlgs_adapter.formats.checkpoint import CHECKPOINT_KIND
from controlgs_adapter.formats.safetensors import load_tensors
from controlgs_adapter.lens_frame import LensFrame
from controlgs_adapter.losses import LossWeights, image_loss
from controlgs_adapter.rendering.protocol import FunctionRenderer, ModelRenderer, render_view
from controlgs_adapter.scene import load_builtin_scene
from controlgs_adapter.state import Camera, RuntimeState
from controlgs_adapter.training import (
    DEFAULT_EFFECTS,
    TrainConfig,
    Trainer,
    TrainingJob,
    modules_for,
    view_cameras,
    views_fingerprint,
)

pytest.importorskip("skimage")  # the built-in scene

#: no lens/optics: the cheapest pipeline that trains two modules
FAST = {"resample": True, "display": True}
#: every stage, the optics in its distortion-only mode
FULL = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}


def _trainer(tiny, *, effects=FULL, views=None, checkpoint=None, renderer=None, **cfg) -> Trainer:
    """A trainer of the tiny backbone on its training views: 2 iterations, no periodic checkpoint and no
    PSF phase unless ``cfg`` says otherwise."""
    scene, model = tiny
    config = TrainConfig(**{"iterations": 2, "checkpoint_every": 0, "psf_fraction": 0.0, **cfg})
    return Trainer(model, scene.views("train") if views is None else views, config, effects=effects,
                   checkpoint=checkpoint, renderer=renderer)


def _adapter(t: Trainer) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in t.cgs.injector.state_dict().items()}


class _Views(list):
    """(camera, image) pairs with a background."""

    background = None


def _cam(w=8, h=6, tx=0.0):
    w2c = torch.eye(4)
    w2c[0, 3] = tx
    return Camera(w2c, torch.tensor([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]]), w, h)


@pytest.fixture
def trainer(tiny):
    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=10, psf_fraction=0.25, checkpoint_every=2, seed=3),
                effects=FAST)
    yield t
    t.cgs.unwrap()


# ============================================================================ the configuration
def test_train_config_defaults_are_the_papers():
    c = TrainConfig()
    assert (c.iterations, c.lr, c.modules, c.cond_dim, c.state_blind) == (10_000, 3e-3, None, 8, False)
    assert (c.max_downsample, c.max_power_saving, c.psf_fraction, c.psf_mode) == (8.0, 0.8, 0.1, "fast")
    assert (c.checkpoint_every, c.seed, c.batch_size) == (500, 0, 1) and c.loss == LossWeights()
    assert c.as_header() == {"iterations": 10_000, "lr": 3e-3, "modules": None, "cond_dim": 8, "state_blind": False,
                             "max_downsample": 8.0, "max_power_saving": 0.8, "psf_fraction": 0.1, "psf_mode": "fast",
                             "loss": {"l1": 0.8, "ssim": 0.2, "mse": 10.0, "lpips": 0.0}, "checkpoint_every": 500,
                             "seed": 0, "batch_size": 1, "lens_conditioning": None, "gaze_jitter_deg": 0.0}
    h = TrainConfig(modules=["lens", "display"]).as_header()
    assert h["modules"] == ["lens", "display"] and TrainConfig(modules=["lens"]).modules == ("lens",)
    assert TrainConfig(modules="lens").modules == ("lens",)  # one module name is one module


@pytest.mark.parametrize("name, value", [("iterations", 0), ("lr", 1e3), ("lr", 1e-12), ("cond_dim", 1),
                                         ("max_downsample", 1.0), ("max_downsample", 1e4), ("max_power_saving", 0.0),
                                         ("max_power_saving", 0.999), ("psf_fraction", 0.0), ("psf_fraction", 1.0),
                                         ("checkpoint_every", 0), ("seed", 2**63 - 1), ("batch_size", 1),
                                         ("psf_mode", "exact"), ("state_blind", True)])
def test_train_config_accepts_its_bounds(name, value):
    assert getattr(TrainConfig(**{name: value}), name) == value


CONFIG_REFUSALS = [
    ("lr", math.inf), ("lr", math.nan), ("lr", 0.0), ("lr", -1e-3), ("lr", "fast"), ("lr", None), ("lr", 1001.0),
    ("iterations", -1), ("iterations", 1.5), ("iterations", "10"), ("iterations", True),
    ("cond_dim", 0), ("cond_dim", 8.0), ("max_downsample", 0.5), ("max_downsample", math.inf),
    ("max_downsample", 10001.0), ("max_power_saving", 1.0), ("max_power_saving", -0.1), ("psf_fraction", 2.0),
    ("psf_fraction", 1.5), ("psf_fraction", math.nan), ("psf_mode", "slow"), ("psf_mode", "distortion"),
    ("batch_size", 0), ("checkpoint_every", -1), ("seed", -1), ("seed", 2.5), ("seed", 2**63), ("state_blind", "yes"),
    ("state_blind", 1), ("loss", {"l1": 1.0}), ("loss", None), ("modules", [1, 2]), ("modules", 7),
    ("modules", ("lens", 2)), ("modules", {"lens"}),
]


@pytest.mark.parametrize("name, value", CONFIG_REFUSALS, ids=[f"{n}={v!r}" for n, v in CONFIG_REFUSALS])
def test_train_config_refusals_name_the_field_and_value(name, value):
    shown = type(value).__name__ if name == "loss" else repr(value)  # a loss that is not a LossWeights: its type
    with pytest.raises(InputValueError, match=rf"^TrainConfig\.{name} .*got {re.escape(shown)}$"):
        TrainConfig(**{name: value})


def test_effects_to_modules():
    assert DEFAULT_EFFECTS == {"lens": True, "resample": True, "display": True, "oled": True, "optics": True}
    assert modules_for(DEFAULT_EFFECTS) == ("lens", "resample", "display")
    assert modules_for({"optics": {"mode": "fast"}}) == ("lens",)  # an options dict switches a stage on
    assert modules_for({"lens": True, "optics": False}) == ("lens",)
    assert modules_for({"optics": True, "display": False}) == ("lens",)
    assert modules_for({"lens": None, "optics": None, "resample": False, "display": 0.5}) == ("display",)
    assert modules_for({"display": True, "resample": True}) == ("resample", "display")  # the library's order
    assert modules_for({"resample": True, "oled": True}) == ("resample",)
    assert modules_for({"oled": True, "foveation": True}) == ("foveation",)


def test_views_fingerprint_and_cameras():
    views = _Views([(_cam(), None), (_cam(tx=0.5), None)])
    assert [c.world_to_camera[0, 3].item() for c in view_cameras(views)] == [0.0, 0.5]
    fp = views_fingerprint(views)
    assert len(fp) == 16 and int(fp, 16) >= 0
    assert views_fingerprint(_Views([(_cam(), None), (_cam(tx=0.5 + 1e-8), None)])) == fp  # rounded to 6 decimals
    assert views_fingerprint(_Views([(_cam(), None), (_cam(tx=0.5 + 1e-5), None)])) != fp
    assert views_fingerprint(_Views([(_cam(), None), (_cam(w=10, tx=0.5), None)])) != fp  # sizes count
    shifted = _cam(tx=0.5)
    shifted.intrinsics[0, 0] += 1e-6  # intrinsics are rounded to 4 decimals
    assert views_fingerprint(_Views([(_cam(), None), (shifted, None)])) == fp
    shifted.intrinsics[0, 0] += 1e-3
    assert views_fingerprint(_Views([(_cam(), None), (shifted, None)])) != fp
    assert views_fingerprint(_Views([(_cam(tx=0.5), None), (_cam(), None)])) != fp  # and the order
    views.cameras = [_cam(tx=0.5)]  # a listed camera set is read instead of the views
    assert view_cameras(views)[0].world_to_camera[0, 3].item() == 0.5 and views_fingerprint(views) != fp
    views.fingerprint = lambda: 12345  # the dataset's own identity wins
    assert views_fingerprint(views) == "12345"


# ============================================================================ the trainer: setup and sampling
def test_trainer_setup_and_sampling_branches(trainer, tiny):
    scene, model = tiny
    assert trainer.cgs.modules == ("resample", "display") and trainer.cgs.injector.cond_dim == 8
    assert trainer.iteration == 0 and trainer.history == [] and trainer.checkpoint_path is None
    assert trainer.optimizer.param_groups[0]["lr"] == 3e-3
    assert torch.equal(trainer.background, scene.background.to(trainer.device))
    # round(10 * (1 - 0.25)) = round(7.5) = 8: iterations 0..7 distortion-only, 8 and 9 with the PSF
    assert [trainer.optics_mode(i) for i in (0, 7, 8, 9)] == ["distortion", "distortion", "fast", "fast"]
    draws = [trainer.sample()[1] for _ in range(50)]
    assert all(1.0 <= s.downsample <= 8.0 and 0.0 <= s.power_saving <= 0.8 for s in draws)
    assert max(s.downsample for s in draws) > 4.0 and max(s.power_saving for s in draws) > 0.6
    # the same seed draws the same sequence from a fresh generator: (view, state) from torch's CPU generator
    g = torch.Generator().manual_seed(3)
    view = int(torch.randint(len(trainer.views), (1,), generator=g))
    u = torch.rand(2, generator=g, dtype=torch.float64)
    trainer.generator.manual_seed(3)
    v, s = trainer.sample()
    assert v == view and s.downsample == math.exp(float(u[0]) * math.log(8.0)) and s.power_saving == float(u[1]) * 0.8


def test_gaze_is_sampled_in_the_field_and_jittered_for_the_adapter(tiny):
    """With a foveation stage the gaze is the direction (through the lens) of a display position drawn
    after d and rho; the adapter is conditioned on it offset by at most gaze_jitter_deg; the foveation
    module trains and moves."""
    scene, model = tiny
    config = TrainConfig(iterations=1, checkpoint_every=0, seed=4, gaze_jitter_deg=2.0, lr=0.1)
    t = Trainer(model, scene.views("train"), config, effects={"foveation": True, "resample": True})
    try:
        assert t.cgs.modules == ("resample", "foveation")
        angles = t.pipeline["foveation"].angles
        g = torch.Generator().manual_seed(config.seed)
        offsets = []
        for _ in range(10):
            torch.randint(len(t.views), (1,), generator=g)
            torch.rand(2, generator=g, dtype=torch.float64)
            xy = torch.rand(2, generator=g, dtype=torch.float64) * 2 - 1
            _, state = t.sample()
            assert state.gaze == pytest.approx(tuple(angles.directions(xy).tolist()), abs=1e-12) and angles.in_field(state.gaze)
            cond = t.conditioning_state(state)
            torch.rand(2, generator=g, dtype=torch.float64)  # the jitter's draw
            offsets.append(math.dist(cond.gaze, state.gaze))
            assert (cond.downsample, cond.power_saving) == (state.downsample, state.power_saving)
        assert max(offsets) <= 2.0 and len(set(offsets)) > 5
        before = _adapter(t)
        t.step()
        assert any(not torch.equal(before[k], v) for k, v in t.cgs.injector.state_dict().items())
    finally:
        t.cgs.unwrap()
    with pytest.raises(InputValueError, match=r"TrainConfig\.gaze_jitter_deg"):
        TrainConfig(gaze_jitter_deg=-1.0)


@pytest.mark.parametrize("effects", [{"resample": True}, {"display": True}], ids=["resample", "display"])
def test_states_of_stages_that_are_off_stay_neutral(tiny, effects):
    """Without a display stage every state has rho = 0, without a resample stage d = 1; the other follows the
    same draws as always (d = max_d ** u0, rho = u1 max_rho), 20 different values in 20 draws."""
    scene, model = tiny
    config = TrainConfig(iterations=1, checkpoint_every=0, seed=3)
    t = Trainer(model, scene.views("train"), config, effects=effects)
    try:
        g = torch.Generator().manual_seed(config.seed)
        t.generator.manual_seed(config.seed)
        states = []
        for _ in range(20):
            view = int(torch.randint(len(t.views), (1,), generator=g))
            u = torch.rand(2, generator=g, dtype=torch.float64)
            got_view, state = t.sample()
            assert got_view == view
            d = config.max_downsample ** float(u[0]) if "resample" in effects else 1.0
            assert state.downsample == pytest.approx(d, rel=1e-12)
            assert state.power_saving == (float(u[1]) * config.max_power_saving if "display" in effects else 0.0)
            states.append(state)
        varying = "downsample" if "resample" in effects else "power_saving"
        assert len({getattr(s, varying) for s in states}) == 20
    finally:
        t.cgs.unwrap()


def test_state_sampling_follows_the_paper(tiny):
    t = _trainer(tiny, iterations=6, psf_fraction=0.34)
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


def test_projection_init_follows_the_seed_not_the_global_generator(tiny):
    scene, model = tiny
    views = scene.views("train")
    inits = []
    for seed in (4, 4, 5):
        torch.manual_seed(100 + len(inits))  # the global generator differs every time
        before = torch.random.get_rng_state()
        t = Trainer(model, views, TrainConfig(iterations=1, seed=seed, modules="display"),
                    effects={**FAST, "oled": False, "lens": None})
        assert torch.equal(torch.random.get_rng_state(), before)  # and is left as it was
        inits.append(_adapter(t))
        assert t.checkpoint_state().effects == ["display", "resample"]  # stages switched on, sorted
        t.cgs.unwrap()
    assert all(torch.equal(inits[0][k], inits[1][k]) for k in inits[0])
    assert not torch.equal(inits[0]["projections.display.d8.weight"], inits[2]["projections.display.d8.weight"])


class _ModelessOptics(Stage):
    """A third-party optics stage with no ``mode``."""

    name = "optics"
    order = 50.0

    def process(self, image: torch.Tensor, state: RuntimeState, ctx: StageContext) -> torch.Tensor:
        return image


def test_the_trainer_simulates_the_lens_it_is_given(tiny):
    """``lens=``: the optics stage holds that lens's bank and the lens stage follows its chief rays (no fitted
    LUT: with a warning); the default is the shipped Cardboard bank."""
    scene, model = tiny
    bank = random_bank(C=9, pincushion=0.05)
    with pytest.warns(UserWarning, match="no fitted pre-warp LUT"):
        t = Trainer(model, scene.views("train"), TrainConfig(iterations=1, psf_fraction=0.0), effects=FULL, lens=bank)
    try:
        assert t.pipeline["optics"].bank is bank
        assert isinstance(t.pipeline["lens"].map, BankMap) and t.pipeline["lens"].map.bank is bank
        assert math.isfinite(t.step())
    finally:
        t.cgs.unwrap()
    t = _trainer(tiny)
    try:
        assert t.pipeline["optics"].bank is PSFBank.default()
    finally:
        t.cgs.unwrap()


def test_trainer_refusals_leave_the_model_unwrapped(tiny):
    scene, model = tiny
    views = scene.views("train")
    t = Trainer(model, views, TrainConfig(cond_dim=3, lr=0.25, state_blind=True, modules="display"), effects=FAST)
    try:  # the config reaches the wrap and the optimizer
        assert t.cgs.injector.cond_dim == 3 and t.cgs.state_blind and t.cgs.modules == ("display",)
        assert t.optimizer.param_groups[0]["lr"] == 0.25
        assert {id(p) for p in t.optimizer.param_groups[0]["params"]} == {id(p) for p in t.cgs.trainable_parameters()}
    finally:
        t.cgs.unwrap()
    for args, kw, pattern in [((views, {"iterations": 1}), {}, r"^config .*got dict"),
                              ((views, TrainConfig()), {"effects": {"oled": True}}, r"no condition module.*\['oled'\]"),
                              ((_Views(), TrainConfig()), {}, r"^views .*got _Views"),
                              ((torch.zeros(2, 3, 4, 4), TrainConfig()), {}, r"^views .*got Tensor"),
                              ((scene.train_images, TrainConfig()), {}, r"^views .*got Tensor"),
                              ((views, TrainConfig(iterations=2)), {"effects": {"resample": True, "optics": _ModelessOptics()}},
                               "PSFOptics.*_ModelessOptics")]:
        with pytest.raises(InputValueError, match=pattern):
            Trainer(model, *args, **kw)
        assert ControlGS.attached(model) is None
    with pytest.raises(ControlGSError):  # a stage's own refusal
        Trainer(model, views, TrainConfig(iterations=1), effects={"lens": True, "resample": {"bogus": 1}, "display": True})
    assert ControlGS.attached(model) is None


# ============================================================================ optics phases
@pytest.mark.parametrize("fraction, iterations, mode, want", [
    (0.0, 4, "exact", ["distortion"] * 4), (1.0, 4, "exact", ["exact"] * 4),
    (0.5, 4, "exact", ["distortion", "distortion", "exact", "exact"]),
    (0.34, 3, "fast", ["distortion", "distortion", "fast"]),
])
def test_optics_phase_switch_ends(tiny, fraction, iterations, mode, want):
    t = _trainer(tiny, effects=FAST, iterations=iterations, psf_fraction=fraction, psf_mode=mode)
    try:
        assert [t.optics_mode(i) for i in range(iterations)] == want
    finally:
        t.cgs.unwrap()


def test_each_step_runs_the_optics_in_its_phase_mode(tiny):
    t = _trainer(tiny, iterations=3, psf_fraction=0.34, psf_mode="exact")  # the last step in the PSF phase
    modes = []
    try:
        for _ in range(3):
            t.step()
            modes.append(t.pipeline["optics"].mode)
    finally:
        t.cgs.unwrap()
    assert modes == ["distortion", "distortion", "exact"]


# ============================================================================ steps and the training loop
def test_only_the_adapter_trains(tiny):
    scene, model = tiny
    before = {k: v.clone() for k, v in model.state_dict().items()}
    t = _trainer(tiny, iterations=3, psf_fraction=0.34)
    t.train(progress=False)
    t.cgs.unwrap()
    for k, v in model.state_dict().items():
        assert torch.equal(before[k], v), k


def test_train_loop_checkpoint_cadence_until_and_state(trainer, tmp_path, monkeypatch):
    written = []
    save = trainer.save_checkpoint

    def recording(path):
        written.append(trainer.iteration)
        return save(path)

    monkeypatch.setattr(trainer, "save_checkpoint", recording)
    trainer.checkpoint_path = tmp_path / "c.safetensors"
    trainer.generator.manual_seed(3)
    trainer.train(until=5, progress=False)
    assert trainer.iteration == 5 and written == [2, 4, 5]  # every 2 iterations, and at the end
    assert len(trainer.history) == 5 and all(math.isfinite(v) and v > 0 for v in trainer.history)
    assert trainer.seconds > 0
    trainer.train(until=100, progress=False)  # clamped to config.iterations
    assert trainer.iteration == 10 and written == [2, 4, 5, 6, 8, 10, 10]
    state = trainer.checkpoint_state()
    assert state.iteration == 10 and state.modules == ["resample", "display"] and state.effects == ["display", "resample"]
    assert state.fingerprint == trainer.cgs.fingerprint and state.data == trainer.data_fingerprint
    assert state.history == trainer.history
    trainer.checkpoint_path = None
    trainer.train(progress=False)  # nothing left to do, nothing written
    assert written[-1] == 10 and len(written) == 7


def test_a_batch_step_is_the_mean_of_its_samples_losses(tiny, tmp_path):
    """step() with batch_size 2: the loss is (l_a + l_b) / 2 over the two sampled (view, state) pairs, each
    rendered, passed through the pipeline and compared with its own ground truth (computed here sample by
    sample from the same generator state, before the adapter moves); a replica (rank 1) remembers the
    checkpoint but does not write it."""
    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=2, batch_size=2, checkpoint_every=0, seed=5),
                effects=FAST, checkpoint=tmp_path / "none.safetensors")
    try:
        rng = t.generator.get_state()
        pairs = [t.sample() for _ in range(2)]
        assert pairs[0] != pairs[1]
        losses = []
        with torch.no_grad():
            for view, state in pairs:
                cam, gt = t.views[view]
                image = render_view(t.cgs, model, cam, state, t.background, renderer=t.renderer)
                losses.append(float(image_loss(t.pipeline(image, state, reference=gt), gt, t.config.loss)))
        assert losses[0] != pytest.approx(losses[1], rel=1e-3)  # two different draws
        t.generator.set_state(rng)
        got = t.step()
        assert math.isclose(got, sum(losses) / 2, rel_tol=1e-5) and t.history == [got] and t.iteration == 1
        assert bool(t.cgs.injector.conditions.detach().any())  # the optimizer moved the adapter
        t.dist = DistContext(rank=1, world_size=2)  # a replica: remembers the checkpoint, rank 0 writes it
        assert t.save_checkpoint(tmp_path / "r1.safetensors") == tmp_path / "r1.safetensors"
        assert not (tmp_path / "r1.safetensors").exists() and t.dist.last_checkpoint == (str(tmp_path / "r1.safetensors"), 1)
        assert t.resume() is False  # no file at checkpoint_path yet
        t.checkpoint_path = None
        assert t.resume() is False
    finally:
        t.cgs.unwrap()


def test_a_user_renderer_gets_the_same_training(tiny):
    """A function renderer doing what the model's own does, and an object following the render protocol,
    train to the same adapter, bit for bit."""
    own = FunctionRenderer(lambda m, c, v, bg: m.render(c, v, bg), visible=lambda m, c: m.visible_anchors(c))

    class Obj:
        def visible(self, m, c):
            return m.visible_anchors(c)

        def render(self, m, c, v, bg):
            return m.render(c, v, bg).color

    runs = []
    for renderer in (None, own, Obj()):
        t = _trainer(tiny, renderer=renderer, iterations=3, psf_fraction=0.34)
        t.train(progress=False)
        runs.append((list(t.history), _adapter(t)))
        t.cgs.unwrap()
    for history, state in runs[1:]:
        assert history == runs[0][0]
        assert all(torch.equal(state[k], runs[0][1][k]) for k in state)


class _HostSyncs(TorchDispatchMode):
    """Counts ``aten._local_scalar_dense`` (a tensor value read on the host: ``.item()``,
    ``float(t)``, ``bool(t)``), each with the library frames that asked for it."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[list[str]] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        if func.overloadpacket is torch.ops.aten._local_scalar_dense:
            frames = [f for f in traceback.extract_stack()[:-1] if "site-packages" not in f.filename]
            self.calls.append([f"{f.filename}:{f.name}: {f.line}" for f in frames])
        return func(*args, **(kwargs or {}))


def test_training_step_host_syncs(tiny):
    """Host syncs of one training step outside the loss log: the view/state sampling (a CPU
    generator) and Adam's step counters are host tensors on any device; the pure-torch splatter's
    own input checks are the rasterizer's (gsplat has none). Everything else: at most 2 (now 1:
    the parameter check)."""
    t = _trainer(tiny, iterations=3, psf_fraction=0.34)
    try:
        t.step()
        for i in range(len(t.views)):  # steady state: a view's image is checked (one sync) on its first read only
            t.load_view(i)
        with _HostSyncs() as mode:
            t.step()
    finally:
        t.cgs.unwrap()
    kinds = collections.Counter()
    for stack in mode.calls:
        where = " ".join(stack)
        kind = ("sampling" if ":sample:" in where else "optimizer" if "optimizer.step()" in where else
                "rasterizer" if "controlgs_adapter/rendering/splatter.py" in where else
                "loss log" if stack[-1].endswith("value += float(loss.detach())  # the loss log: the step's one device "
                                                 "sync besides the check below") else "step")
        kinds[kind] += 1
    assert kinds["loss log"] == 1 and kinds["step"] <= 2, dict(kinds)


def test_training_with_oled_off_scores_the_display_pixels_as_boxes_at_full_size(tiny):
    """With the ``oled`` stage off the eye image stays at the display size S/d; the trainer compares it with
    the ground truth as box pixels at S (how the viewer shows and scores it), so a run with oled off
    trains exactly like one with oled on when nothing follows the oled stage (it is that box emission)."""
    losses = []
    for oled in (True, False):
        t = _trainer(tiny, effects={"resample": True, "display": True, "oled": oled}, iterations=4, seed=3,
                     max_downsample=4.0, psf_fraction=0.1)
        try:
            losses += [t.step() for _ in range(4)]
        finally:
            t.cgs.unwrap()
    on, off = losses[:4], losses[4:]
    assert all(math.isfinite(v) for v in on)
    assert off == pytest.approx(on, rel=1e-6, abs=0)


def test_views_of_any_size_and_a_plain_sequence(tiny):
    """Non-square views of different sizes train; a plain list with a background is a dataset too."""
    from controlgs_adapter.datasets.base import PosedImages
    from controlgs_adapter.datasets.memory import tensor_frames

    scene, model = tiny
    frames = tensor_frames(scene.train_images, scene.train_cameras)
    crops = [PosedImages(frames, resolution=12).cameras[0], scene.train_cameras[1]]

    class Plain(list):
        background = scene.background

    views = Plain([(crops[0], PosedImages(frames, resolution=12).image(0)), (crops[1], scene.train_images[1])])
    t = Trainer(model, views, TrainConfig(iterations=2, checkpoint_every=0), effects=FAST)
    t.train(progress=False)
    t.cgs.unwrap()
    assert len(t.history) == 2 and all(math.isfinite(v) for v in t.history)


def test_step_refuses_a_view_whose_image_size_differs_from_its_camera(tiny):
    scene, model = tiny
    cam, image = scene.views("train")[0]

    class Views(list):
        background = scene.background

    t = _trainer(tiny, effects=FAST, views=Views([(cam, image[:, :8, :8])]), iterations=1)
    try:
        with pytest.raises(InputValueError, match=rf"^view 0: .*\[3, 8, 8\].*\[3, {cam.height}, {cam.width}\]"):
            t.step()
    finally:
        t.cgs.unwrap()


def test_a_module_never_active_in_the_sampled_states_trains_without_error(tiny):
    """max_downsample 1: d = 1 always, log2 d = 0, the resample strength is 0 in every state: the loss has no
    gradient; steps record the loss, the adapter stays."""
    t = _trainer(tiny, effects=FAST, modules="resample", max_downsample=1.0)
    try:
        before = _adapter(t)
        t.train(progress=False)
        assert t.iteration == 2 and len(t.history) == 2 and all(math.isfinite(v) and v > 0 for v in t.history)
        assert all(torch.equal(before[k], v) for k, v in t.cgs.injector.state_dict().items())
    finally:
        t.cgs.unwrap()


def test_a_model_with_a_degenerate_gaussian_trains(tiny):
    """One anchor's Gaussians with scales of about 1e20 (a float32 2D covariance would overflow): the steps
    keep every adapter tensor finite."""
    scene, model = tiny
    model = copy.deepcopy(model)
    cam = scene.test_cameras[0]
    with torch.no_grad():
        g = model.decode(cam, model.visible_anchors(cam))
        model._scaling[int(g.anchor_of[g.opacities.argmax()]), 3:] = math.log(1e20)
    t = _trainer((scene, model), effects=FAST, iterations=3)
    try:
        t.train(progress=False)
        assert len(t.history) == 3 and all(math.isfinite(v) for v in t.history)
        assert all(bool(torch.isfinite(p).all()) for p in t.cgs.trainable_parameters())
    finally:
        t.cgs.unwrap()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU available in this run: a training step on CUDA not run")
def test_a_training_step_runs_on_cuda(tiny):
    scene, model = tiny
    model = copy.deepcopy(model).to("cuda")
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=2, checkpoint_every=0))
    assert t.device.type == "cuda" and t.cgs.injector.conditions.is_cuda
    t.train(progress=False)
    assert all(torch.isfinite(torch.tensor(t.history)))
    t.cgs.unwrap()


# ============================================================================ non-finite images, gradients, losses
class _CountingViews:
    """Views whose images are made on first read (a lazily loading dataset), counting the loads."""

    def __init__(self, views, bad: int, value: float) -> None:
        self.inner, self.bad, self.value, self.loads = views, bad, value, []
        self.background = views.background
        self.cameras = views.cameras

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i):
        self.loads.append(i)
        cam, img = self.inner[i]
        if i == self.bad:
            img = img.clone()
            img[1, 0, 0] = self.value
        return cam, img


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_non_finite_image_is_refused_at_its_first_load_naming_the_view(tiny, value):
    scene, model = tiny
    base = scene.views("train")
    cams = [base[i][0] for i in range(len(base))]
    imgs = [base[i][1].clone() for i in range(len(base))]
    imgs[1][0, 2, 3] = value
    views = posed_images(imgs, cams, background=base.background, name="train")
    t = _trainer(tiny, effects=FAST, views=views, iterations=50)
    try:
        t.load_view(0)  # a finite view passes
        with pytest.raises(InputValueError, match=r"^view 1 \('train/0001'\): .*1 NaN/Inf"):
            t.load_view(1)
        with pytest.raises(InputValueError, match=r"^view 1 \('train/0001'\)"):
            t.train(progress=False)  # stops at the first draw of view 1, before its loss is taken
        assert len(t.history) < 50 and all(math.isfinite(v) for v in t.history)
    finally:
        t.cgs.unwrap()


def test_lazily_loaded_views_are_checked_when_first_read_and_only_then(tiny):
    scene, _ = tiny
    views = _CountingViews(scene.views("train"), bad=2, value=math.nan)
    t = _trainer(tiny, effects=FAST, views=views)
    try:
        assert views.loads == []  # building the trainer loads no image
        t.load_view(0)
        t.load_view(0)
        assert views.loads == [0, 0]
        assert t._checked_views == {0}
        with pytest.raises(InputValueError, match=r"^view 2: .*1 NaN/Inf"):
            t.load_view(2)
        assert 2 not in t._checked_views  # refused again on the next read
        with pytest.raises(InputValueError, match=r"^view 2:"):
            t.load_view(2)
    finally:
        t.cgs.unwrap()


def test_finite_views_train_and_are_each_checked_once(tiny):
    scene, _ = tiny
    t = _trainer(tiny, effects=FAST)
    try:
        t.train(progress=False)
        assert len(t.history) == 2 and all(math.isfinite(v) for v in t.history)
        assert t._checked_views and t._checked_views <= set(range(len(scene.views("train"))))
    finally:
        t.cgs.unwrap()


class _NanGradient(torch.autograd.Function):
    """Identity forward; a NaN gradient backward (a render whose backward breaks down at a finite loss)."""

    @staticmethod
    def forward(ctx, x):
        return x.clone()

    @staticmethod
    def backward(ctx, grad):
        return torch.full_like(grad, math.nan)


def test_nan_gradients_at_a_finite_loss_are_named_as_the_cause_not_the_learning_rate(tiny):
    def nan_backward(m, camera, visible, background):
        return _NanGradient.apply(m.render(camera, visible, background).color)

    renderer = FunctionRenderer(nan_backward, visible=lambda m, c: m.visible_anchors(c))
    t = _trainer(tiny, effects=FAST, renderer=renderer, lr=1e-3, psf_fraction=0.1)
    try:
        with pytest.raises(NonFiniteError, match=r"^training diverged at iteration 0: .*NaN/Inf gradients of "
                                                 r"\['conditions'") as e:
            t.step()
        assert "lr 0.001" not in str(e.value)
    finally:
        t.cgs.unwrap()


def test_a_parameter_that_becomes_non_finite_stops_training(tiny):
    """rho is always 0 (max_power_saving 0): the display strength is 0, its projection gets no gradient and
    Adam leaves it as it is; an Inf planted there passes the loss check and is caught by the parameter check,
    which names it and the learning rate; nothing is recorded."""
    t = _trainer(tiny, effects=FAST, modules="display", max_power_saving=0.0, lr=0.02, psf_fraction=0.1)
    try:
        with torch.no_grad():
            t.cgs.injector.projections["display"]["d8"].weight[0, 0] = float("inf")
        with pytest.raises(NonFiniteError, match=r"^training diverged at iteration 0: .*"
                                                 r"\['projections\.display\.d8\.weight'\].*\(lr 0\.02\)"):
            t.step()
        assert t.iteration == 0 and t.history == []
    finally:
        t.cgs.unwrap()


def test_training_stops_at_the_first_non_finite_loss_keeping_the_last_checkpoint(tiny, tmp_path, monkeypatch):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(tiny, checkpoint=path, iterations=4, checkpoint_every=2)
    try:
        t.train(until=2, progress=False)
        good = path.read_bytes()
        monkeypatch.setattr("controlgs_adapter.training.image_loss", lambda *a, **k: torch.tensor(math.nan, requires_grad=True))
        with pytest.raises(NonFiniteError, match="iteration 2") as e:
            t.train(progress=False)
        assert "loss" in str(e.value)
        assert path.read_bytes() == good, "the bad state must not be written"
        assert all(bool(torch.isfinite(p).all()) for p in t.cgs.trainable_parameters())
    finally:
        t.cgs.unwrap()


# ============================================================================ checkpoints
def test_resume_is_exact(tiny, tmp_path):
    straight = _trainer(tiny, iterations=6, psf_fraction=0.34)
    straight.train(progress=False)
    want = _adapter(straight)
    losses = list(straight.history)
    straight.cgs.unwrap()

    first = _trainer(tiny, checkpoint=tmp_path / "ckpt.safetensors", iterations=6, psf_fraction=0.34)
    first.train(until=4, progress=False)  # "interrupted" after 4 of 6 iterations; checkpoint written
    first.cgs.unwrap()
    second = _trainer(tiny, checkpoint=tmp_path / "ckpt.safetensors", iterations=6, psf_fraction=0.34)
    assert second.resume() and second.iteration == 4
    second.train(progress=False)
    got = second.cgs.injector.state_dict()
    second.cgs.unwrap()
    assert second.history == losses
    for k in want:
        assert torch.equal(want[k], got[k]), k
    assert any(float(v.abs().max()) > 0 for k, v in want.items() if k.startswith("conditions")), "conditions never moved"


@pytest.mark.parametrize("other, named", [
    ({"effects": {k: v for k, v in FULL.items() if k != "oled"}}, r"stages .*'oled'"),  # same modules, a stage off
    ({"lr": 1e-2}, "lr"),
    ({"views": "test"}, "other views"),
    ({"lens": "compact"}, "another lens"),
], ids=["stages", "config", "views", "lens"])
def test_a_checkpoint_of_another_run_is_refused_naming_what_differs(tiny, tmp_path, other, named):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(tiny, checkpoint=path, iterations=1)
    t.train(progress=False)
    t.cgs.unwrap()
    kw = dict(other)
    if kw.get("views") == "test":
        kw["views"] = tiny[0].views("test")
    refused = _trainer(tiny, checkpoint=path, iterations=1, **kw) if "lens" not in kw else Trainer(
        tiny[1], tiny[0].views("train"), TrainConfig(iterations=1, checkpoint_every=0, psf_fraction=0.0), effects=FULL,
        checkpoint=path, lens=kw["lens"])
    try:
        with pytest.raises(FileFormatError, match=rf"run\.ckpt\.safetensors.*{named}"):
            refused.resume()
        assert refused.iteration == 0 and refused.history == []
    finally:
        refused.cgs.unwrap()


def _damage(path: Path, header: dict[str, Any] | None = None, tensors: dict[str, Any] | None = None,
            drop: tuple[str, ...] = (), nan: str | None = None) -> None:
    """Rewrite the checkpoint at ``path`` with header fields or tensors changed, dropped or set to NaN."""
    t, h = load_tensors(path, kind=CHECKPOINT_KIND, max_version=1)
    if nan is not None:
        t[nan] = t[nan].clone()
        t[nan].view(-1)[0] = math.nan
    h = {k: v for k, v in h.items() if k not in ("kind", "format_version", "library_version")}
    h.update(header or {})
    t.update(tensors or {})
    for k in drop:
        h.pop(k, None)
        t.pop(k, None)
    write_raw(path, t, h, kind=CHECKPOINT_KIND)


CKPT_CASES = [
    ("rng missing", {"drop": ("rng",)}, "rng"),
    ("rng float", {"tensors": {"rng": torch.zeros(5056)}}, "rng"),
    ("rng short", {"tensors": {"rng": torch.zeros(3, dtype=torch.uint8)}}, "rng"),
    ("param_groups missing", {"drop": ("param_groups",)}, "param_groups"),
    ("param_groups []", {"header": {"param_groups": []}}, "param_groups"),
    ("param_groups wrong params", {"header": {"param_groups": [{"params": [7, 8], "lr": 0.003}]}}, "param_groups"),
    ("param_groups a string", {"header": {"param_groups": "x"}}, "param_groups"),
    ("param_groups of numbers", {"header": {"param_groups": [1]}}, "param_groups"),
    ("param_groups without params", {"header": {"param_groups": [{"lr": 0.003}]}}, "param_groups"),
    ("iteration 'x'", {"header": {"iteration": "x"}}, "iteration"),
    ("iteration -1", {"header": {"iteration": -1}}, "iteration"),
    ("iteration missing", {"drop": ("iteration",)}, "iteration"),
    ("history [nan]", {"header": {"history": [None]}}, "history"),
    ("config a list", {"header": {"config": [1]}}, "config"),
    ("NaN condition", {"nan": "adapter.conditions"}, "NaN"),
    ("NaN Adam state", {"nan": "optimizer.0.exp_avg"}, "NaN"),
    ("adapter tensor missing", {"drop": ("adapter.conditions",)}, "adapter"),
    ("unexpected tensor", {"tensors": {"extra": torch.zeros(1)}}, "extra"),
    ("optimizer key malformed", {"tensors": {"optimizer.x": torch.zeros(1)}}, "optimizer.x"),
    ("optimizer shape", {"tensors": {"optimizer.0.exp_avg": torch.zeros(1)}}, "optimizer.0.exp_avg"),
]


@pytest.mark.parametrize("damage, name", [c[1:] for c in CKPT_CASES], ids=[c[0] for c in CKPT_CASES])
def test_a_damaged_checkpoint_is_refused_naming_the_file_and_field(tiny, tmp_path, damage, name):
    path = tmp_path / "run.ckpt.safetensors"
    t = _trainer(tiny, checkpoint=path)
    try:
        t.train(until=1, progress=False)
    finally:
        t.cgs.unwrap()
    _damage(path, **damage)
    fresh = _trainer(tiny, checkpoint=path)
    try:
        with pytest.raises(FileFormatError) as e:
            fresh.resume()
        assert "run.ckpt.safetensors" in str(e.value) and name in str(e.value), str(e.value)
        assert fresh.iteration == 0
    finally:
        fresh.cgs.unwrap()


# ============================================================================ progress
@pytest.mark.skipif(not hasattr(os, "openpty"), reason="needs a pseudo-terminal (POSIX)")
def test_training_progress_bar_follows_a_resized_terminal(tiny, monkeypatch):
    # the bar is drawn on a real pseudo-terminal (stderr): 61 columns when the bar starts, widened to
    # 101 while training runs; a bar that follows the terminal draws its last frame the full width less
    # one column (100), a fixed one stays at 60
    import fcntl
    import struct
    import termios

    master, slave = os.openpty()

    def resize(cols: int) -> None:
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 25, cols, 0, 0))

    class Resizing(ModelRenderer):
        def render(self, model, camera, visible, background):  # type: ignore[no-untyped-def]
            resize(101)  # the user widens the terminal while a step runs
            return super().render(model, camera, visible, background)

    resize(61)
    tty = os.fdopen(slave, "w", encoding="utf-8", closefd=False)
    monkeypatch.setattr(sys, "stderr", tty)
    t = _trainer(tiny, effects={"lens": True, "resample": True, "display": True}, renderer=Resizing())
    try:
        t.train(progress=True)
        tty.flush()
        os.set_blocking(master, False)
        out = b""
        while True:
            try:
                chunk = os.read(master, 65536)
            except BlockingIOError:
                break
            if not chunk:
                break
            out += chunk
    finally:
        t.cgs.unwrap()
        monkeypatch.undo()
        tty.close()
        os.close(slave)
        os.close(master)
    text = out.decode("utf-8").replace("\x1b[A", "")
    frames = [f for f in text.replace("\n", "\r").split("\r") if "training ControlGS" in f]
    assert frames and len(frames[0]) == 60, frames  # drawn at the start: 61 - 1
    assert len(frames[-1]) == 100 and "2/2" in frames[-1], frames


def test_training_progress_bar_only_when_asked_and_only_on_rank_0(tiny, capsys):
    def bar_shown(progress: bool, dist_ctx: DistContext | None = None) -> bool:
        scene, model = tiny
        config = TrainConfig(iterations=1, checkpoint_every=0, psf_fraction=0.0, batch_size=2)
        t = Trainer(model, scene.views("train"), config, effects={"lens": True, "resample": True, "display": True},
                    dist=dist_ctx)
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


def test_a_job_titles_its_trainings_and_estimates_the_whole_job():
    job = TrainingJob(4, 10)
    assert job.remaining() is None and job.remaining_text() == "?"  # nothing ran yet
    assert job.start("training ControlGS, seed 0") == "[1/4] training ControlGS, seed 0"
    for _ in range(5):
        job.step(2.0)
    # 5 of 40 iterations done at 2 s each: 35 left, about 70 s
    assert job.remaining() == pytest.approx(70.0) and job.remaining_text() == "~1m10s"
    for _ in range(5):
        job.step(2.0)
    assert job.start("training w/o Lens, seed 0", already=4) == "[2/4] training w/o Lens, seed 0"
    # a resumed checkpoint's 4 iterations count as done and are not timed: 40 - 14 = 26 left at 2 s
    assert job.remaining() == pytest.approx(52.0)
    job.start("c")
    job.start("d")
    assert job.start("beyond") == "[4/4] beyond"  # never counts past N
    assert TrainingJob(1, 1).remaining_text() == "?"
    for bad in ((0, 10), (2, -1)):
        with pytest.raises(InputValueError):
            TrainingJob(*bad)
    # the time left reads in seconds, minutes and hours
    for iterations, text in ((46, "~45s"), (3601, "~1h00m")):
        job = TrainingJob(1, iterations)
        job.step(1.0)
        assert job.remaining_text() == text


@pytest.mark.parametrize("name", ["iterations", "cond_dim", "checkpoint_every", "batch_size"])
def test_train_config_counts_fit_int64(name: str) -> None:
    with pytest.raises(InputValueError, match=f"TrainConfig.{name} must be an integer in"):
        TrainConfig(**{name: 10**400})
    assert getattr(TrainConfig(**{name: 2**40}), name) == 2**40


D = F64 = torch.float64


# ------------------------------------------------------------------- the trainer on the reference model
def test_trainer_samples_states_from_the_configured_ranges_by_hand():
    """max_downsample / max_power_saving / seed off their defaults: each draw is (randint view,
    d = max_d ** u0, rho = max_rho * u1) from the seeded generator, as the docstring says."""
    pytest.importorskip("skimage")
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=2)
    views = scene.views("train")
    config = TrainConfig(iterations=1, checkpoint_every=0, max_downsample=3.0, max_power_saving=0.5, seed=11)
    t = Trainer(model.eval(), views, config, effects={"resample": True, "display": True})
    try:
        g = torch.Generator().manual_seed(11)
        for _ in range(50):
            view = int(torch.randint(len(views), (1,), generator=g))
            u = torch.rand(2, generator=g, dtype=D)
            got_view, state = t.sample()
            assert got_view == view
            assert state.downsample == pytest.approx(3.0 ** float(u[0]), rel=1e-12)
            assert state.power_saving == pytest.approx(0.5 * float(u[1]), rel=1e-12)
    finally:
        t.cgs.unwrap()


def test_a_trainer_starts_in_its_first_iterations_optics_mode():
    """Before any step the pipeline's optics stage is in iteration 0's mode (``distortion`` while
    ``psf_fraction`` leaves iterations to it), and the switch to ``psf_mode`` comes at its iteration."""
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    torch.manual_seed(0)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=5)
    effects = {"lens": True, "resample": True, "display": True, "oled": True, "optics": {"mode": "distortion"}}
    config = TrainConfig(iterations=2, checkpoint_every=0, psf_fraction=0.5, psf_mode="exact")
    t = Trainer(model.eval(), scene.views("train"), config, effects=effects)
    try:
        assert [t.optics_mode(i) for i in (0, 1)] == ["distortion", "exact"]
        assert t.pipeline["optics"].mode == "distortion"
        t.step()
        assert t.pipeline["optics"].mode == "distortion"
        t.step()
        assert t.pipeline["optics"].mode == "exact"
    finally:
        t.cgs.unwrap()


def test_trainer_seconds_is_zero_before_training_then_the_wall_time_of_train():
    """``Trainer`` docstring: ``seconds`` is the wall time of the last ``train()`` call, 0.0 before the
    first; after ``train()`` it lies between 0 and the wall time measured around the call."""
    pytest.importorskip("skimage")
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


def test_the_trainer_wraps_with_the_lens_frame_of_its_optics_else_its_pre_warp_bank(tiny):
    decentred = affine_bank([[0.75, 0.125], [-0.25, 1.5]], [0.0625, -0.125], axis=(0.25, -0.125))
    want = LensFrame.from_bank(decentred)
    for effects in ({"resample": True, "optics": {"bank": decentred, "mode": "distortion"}},
                    {"resample": True, "lens": LensPrewarp(BankMap(decentred))}):
        t = _trainer(tiny, effects=effects, cond_dim=4)
        assert t.cgs.lens_frame == want and t.cgs.lens_frame.mode == "xy"
        t.cgs.unwrap()
    t = _trainer(tiny, cond_dim=4)  # the shipped Cardboard optics: the centred radius frame
    assert t.cgs.lens_frame == LensFrame()
    t.cgs.unwrap()


@pytest.mark.parametrize("mode", ["radius", "xy"])
def test_lens_conditioning_overrides_the_frame_the_lens_calls_for(tiny, mode):
    """TrainConfig.lens_conditioning: Cardboard's centred frame conditioned on (x, y) on request, a decentred lens on
    its radius about the axis; an ablation without the lens module trains as before."""
    decentred = affine_bank([[0.75, 0.125], [-0.25, 1.5]], [0.0625, -0.125], axis=(0.25, -0.125))
    for bank in (None, decentred):
        effects = None if bank is None else {"resample": True, "optics": {"bank": bank, "mode": "distortion"}}
        t = _trainer(tiny, effects=effects, cond_dim=4, lens_conditioning=mode)
        frame = t.cgs.lens_frame
        t.cgs.unwrap()
        assert frame.mode == mode
        assert frame.axis == (LensFrame.from_bank(bank).axis if bank is not None else (0.0, 0.0))
    t = _trainer(tiny, cond_dim=4, lens_conditioning=mode, modules=("resample",))
    assert "lens" not in t.cgs.modules
    t.cgs.unwrap()


def test_lens_conditioning_must_be_a_known_frame():
    with pytest.raises(InputValueError, match="lens_conditioning"):
        TrainConfig(lens_conditioning="polar")
