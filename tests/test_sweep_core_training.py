"""Issue 15 s.5 sweep, core area: TrainConfig's documented defaults and bounds, the effects ->
modules map, views fingerprints, the optics phase switch, state sampling branches, the training
loop's checkpoint cadence and the Trainer's refusals, pinned by hand."""

from __future__ import annotations

import math

import pytest
import torch

pytest.importorskip("skimage")

from controlgs_adapter import ControlGS  # noqa: E402
from controlgs_adapter.errors import InputValueError  # noqa: E402
from controlgs_adapter.losses import LossWeights  # noqa: E402
from controlgs_adapter.state import Camera  # noqa: E402
from controlgs_adapter.training import (DEFAULT_EFFECTS, TrainConfig, Trainer, modules_for, view_cameras,  # noqa: E402
                                        views_fingerprint)

FAST = {"resample": True, "display": True}  # no lens/optics: the cheapest pipeline that trains two modules


def test_train_config_defaults_are_the_papers():
    c = TrainConfig()
    assert (c.iterations, c.lr, c.modules, c.cond_dim, c.state_blind) == (10_000, 3e-3, None, 8, False)
    assert (c.max_downsample, c.max_power_saving, c.psf_fraction, c.psf_mode) == (8.0, 0.8, 0.1, "fast")
    assert (c.checkpoint_every, c.seed, c.batch_size) == (500, 0, 1) and c.loss == LossWeights()
    assert c.as_header() == {"iterations": 10_000, "lr": 3e-3, "modules": None, "cond_dim": 8, "state_blind": False,
                             "max_downsample": 8.0, "max_power_saving": 0.8, "psf_fraction": 0.1, "psf_mode": "fast",
                             "loss": {"l1": 0.8, "ssim": 0.2, "mse": 10.0, "lpips": 0.0}, "checkpoint_every": 500,
                             "seed": 0, "batch_size": 1}
    h = TrainConfig(modules=["lens", "display"]).as_header()
    assert h["modules"] == ["lens", "display"] and TrainConfig(modules=["lens"]).modules == ("lens",)


@pytest.mark.parametrize("name, value", [("iterations", 0), ("lr", 1e3), ("lr", 1e-12), ("cond_dim", 1),
                                         ("max_downsample", 1.0), ("max_downsample", 1e4), ("max_power_saving", 0.0),
                                         ("max_power_saving", 0.999), ("psf_fraction", 0.0), ("psf_fraction", 1.0),
                                         ("checkpoint_every", 0), ("seed", 2**63 - 1), ("batch_size", 1),
                                         ("psf_mode", "exact"), ("state_blind", True)])
def test_train_config_accepts_its_bounds(name, value):
    assert getattr(TrainConfig(**{name: value}), name) == value


@pytest.mark.parametrize("name, value, words", [
    ("lr", 1001.0, "TrainConfig.lr must be a finite number in (0, 1000], got 1001.0"),
    ("max_downsample", 10001.0, "TrainConfig.max_downsample must be a finite number in [1, 10000], got 10001.0"),
    ("seed", 2**63, "TrainConfig.seed must be an integer in [0, 9.22337e+18]"),
    ("batch_size", 0, "TrainConfig.batch_size must be an integer in [1, inf), got 0"),
    ("cond_dim", 0, "TrainConfig.cond_dim must be an integer in [1, inf), got 0"),
    ("max_power_saving", 1.0, "TrainConfig.max_power_saving must be a finite number in [0, 1), got 1.0"),
    ("psf_fraction", 1.5, "TrainConfig.psf_fraction must be a finite number in [0, 1], got 1.5"),
    ("iterations", -1, "TrainConfig.iterations must be an integer in [0, inf), got -1"),
    ("state_blind", 1, "TrainConfig.state_blind must be a bool, got 1"),
    ("psf_mode", "distortion", "TrainConfig.psf_mode must be 'fast' or 'exact', got 'distortion'"),
    ("loss", None, "TrainConfig.loss must be a LossWeights, got NoneType"),
    ("modules", ("lens", 2), "TrainConfig.modules must be None or a sequence of module names, got ('lens', 2)"),
    ("modules", {"lens"}, "TrainConfig.modules must be None or a sequence of module names"),
])
def test_train_config_refusals_by_message(name, value, words):
    with pytest.raises(InputValueError) as e:
        TrainConfig(**{name: value})
    assert str(e.value).startswith(words)


def test_effects_to_modules():
    assert DEFAULT_EFFECTS == {"lens": True, "resample": True, "display": True, "oled": True, "optics": True}
    assert modules_for(DEFAULT_EFFECTS) == ("lens", "resample", "display")
    assert modules_for({"optics": {"mode": "fast"}}) == ("lens",)  # an options dict switches a stage on
    assert modules_for({"lens": True, "optics": False}) == ("lens",)
    assert modules_for({"lens": None, "optics": None, "resample": False, "display": 0.5}) == ("display",)
    assert modules_for({"display": True, "resample": True}) == ("resample", "display")  # the library's order
    assert modules_for({"oled": True, "foveation": True}) == ()


class _Views(list):
    """(camera, image) pairs with a background."""

    background = None


def _cam(w=8, h=6, tx=0.0):
    w2c = torch.eye(4)
    w2c[0, 3] = tx
    return Camera(w2c, torch.tensor([[10.0, 0, w / 2], [0, 10.0, h / 2], [0, 0, 1]]), w, h)


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


@pytest.fixture
def trainer(tiny):
    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=10, psf_fraction=0.25, checkpoint_every=2, seed=3),
                effects=FAST)
    yield t
    t.cgs.unwrap()


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


@pytest.mark.parametrize("effects, fixed", [({"resample": True}, "power_saving"), ({"display": True}, "downsample")])
def test_states_of_stages_that_are_off_stay_neutral(tiny, effects, fixed):
    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=1, checkpoint_every=0), effects=effects)
    try:
        states = [t.sample()[1] for _ in range(20)]
        neutral = {"power_saving": 0.0, "downsample": 1.0}[fixed]
        assert all(getattr(s, fixed) == neutral for s in states)
        other = "downsample" if fixed == "power_saving" else "power_saving"
        assert len({getattr(s, other) for s in states}) == 20
    finally:
        t.cgs.unwrap()


@pytest.mark.parametrize("fraction, want", [(0.0, ["distortion"] * 4), (1.0, ["exact"] * 4),
                                            (0.5, ["distortion", "distortion", "exact", "exact"])])
def test_optics_phase_switch_ends(tiny, fraction, want):
    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=4, psf_fraction=fraction, psf_mode="exact",
                                                         checkpoint_every=0), effects=FAST)
    try:
        assert [t.optics_mode(i) for i in range(4)] == want
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
    for args, kw, words in [((views, {"iterations": 1}), {}, "config must be a TrainConfig, got dict"),
                            ((views, TrainConfig()), {"effects": {"oled": True}},
                             "no condition module to train: the effects ['oled'] call for none"),
                            ((_Views(), TrainConfig()), {}, "views must be a non-empty dataset"),
                            ((torch.zeros(2, 3, 4, 4), TrainConfig()), {}, "got Tensor")]:
        with pytest.raises(InputValueError) as e:
            Trainer(model, *args, **kw)
        assert words in str(e.value)
        assert ControlGS.attached(model) is None


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
    sample from the same generator state, before the adapter moves)."""
    from controlgs_adapter.losses import image_loss
    from controlgs_adapter.rendering.protocol import render_view

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
        t.generator.set_state(rng)
        got = t.step()
        assert math.isclose(got, sum(losses) / 2, rel_tol=1e-5) and t.history == [got] and t.iteration == 1
        assert bool(t.cgs.injector.conditions.detach().any())  # the optimizer moved the adapter
        from controlgs_adapter.distributed import DistContext

        t.dist = DistContext(rank=1, world_size=2)  # a replica: remembers the checkpoint, rank 0 writes it
        assert t.save_checkpoint(tmp_path / "r1.safetensors") == tmp_path / "r1.safetensors"
        assert not (tmp_path / "r1.safetensors").exists() and t.dist.last_checkpoint == (str(tmp_path / "r1.safetensors"), 1)
        assert t.resume() is False  # no file at checkpoint_path yet
        t.checkpoint_path = None
        assert t.resume() is False
    finally:
        t.cgs.unwrap()


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
        inits.append({k: v.clone() for k, v in t.cgs.injector.state_dict().items()})
        assert t.checkpoint_state().effects == ["display", "resample"]  # stages switched on, sorted
        t.cgs.unwrap()
    assert all(torch.equal(inits[0][k], inits[1][k]) for k in inits[0])
    assert not torch.equal(inits[0]["projections.display.d8.weight"], inits[2]["projections.display.d8.weight"])


def test_step_refuses_a_view_whose_image_size_differs_from_its_camera(tiny):
    scene, model = tiny
    cam, image = scene.views("train")[0]

    class Views(list):
        background = scene.background

    t = Trainer(model, Views([(cam, image[:, :8, :8])]), TrainConfig(iterations=1, checkpoint_every=0), effects=FAST)
    try:
        with pytest.raises(InputValueError, match=rf"view 0: image is \[3, 8, 8\], its camera renders "
                                                  rf"\[3, {cam.height}, {cam.width}\]"):
            t.step()
    finally:
        t.cgs.unwrap()


def test_a_parameter_that_becomes_non_finite_stops_training(tiny):
    """rho is always 0 (max_power_saving 0): the display strength is 0, its projection gets no gradient and
    Adam leaves it as it is; an Inf planted there passes the loss check and is caught by the parameter check."""
    from controlgs_adapter.errors import NonFiniteError

    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=2, checkpoint_every=0, modules="display",
                                                         max_power_saving=0.0, lr=0.02), effects=FAST)
    try:
        with torch.no_grad():
            t.cgs.injector.projections["display"]["d8"].weight[0, 0] = float("inf")
        with pytest.raises(NonFiniteError) as e:
            t.step()
        assert str(e.value) == ("training diverged at iteration 0: parameter(s) ['projections.display.d8.weight'] became "
                                "NaN/Inf (lr 0.02); the last good checkpoint was kept, this state not written")
        assert t.iteration == 0 and t.history == []
    finally:
        t.cgs.unwrap()


def test_a_module_never_active_in_the_sampled_states_trains_without_error(tiny):
    """max_downsample 1: d = 1 always, log2 d = 0, the resample strength is 0 in every state: the loss has no
    gradient (it raised torch's 'does not require grad' before); steps record the loss, the adapter stays."""
    scene, model = tiny
    t = Trainer(model, scene.views("train"), TrainConfig(iterations=2, checkpoint_every=0, modules="resample",
                                                         max_downsample=1.0), effects=FAST)
    try:
        before = {k: v.clone() for k, v in t.cgs.injector.state_dict().items()}
        t.train(progress=False)
        assert t.iteration == 2 and len(t.history) == 2 and all(math.isfinite(v) and v > 0 for v in t.history)
        assert all(torch.equal(before[k], v) for k, v in t.cgs.injector.state_dict().items())
    finally:
        t.cgs.unwrap()
