"""Public keyword options at non-default values, each checked by hand (brute force, float64, or the
formula written out): metric data ranges and windows, loss weights (function and module), schedule
endpoints, the 'stretch' placement, display mapping with other coefficients, stages called without a
context, the trainer's state-sampling ranges and batch size."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter import RuntimeState
from controlgs_adapter.downstream.placement import image_region, to_display
from controlgs_adapter.losses import ImageLoss, LossWeights, image_loss
from controlgs_adapter.metrics import gaussian_window, psnr, ssim
from controlgs_adapter.schedules import DisplaySchedule, FoveationSchedule, LensSchedule, ResampleSchedule

D = torch.float64


def _images(h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(3, h, w, generator=g, dtype=D)
    y = (x + 0.2 * torch.randn(3, h, w, generator=g, dtype=D)).clamp(0, 1)
    return x, y


def _ssim_by_hand(x: torch.Tensor, y: torch.Tensor, data_range: float, size: int, sigma: float) -> float:
    """Brute-force SSIM: every valid window position, Gaussian weights g(u) g(v), exp(-r^2 / 2 sigma^2)
    normalised, c1 = (0.01 L)^2, c2 = (0.03 L)^2, mean over channels and positions."""
    r = [i - (size - 1) / 2 for i in range(size)]
    g = [math.exp(-t * t / (2 * sigma * sigma)) for t in r]
    g = [v / sum(g) for v in g]
    w = torch.tensor([[a * b for b in g] for a in g], dtype=D)
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    vals = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - size + 1):
            for j in range(x.shape[2] - size + 1):
                px, py = x[c, i:i + size, j:j + size], y[c, i:i + size, j:j + size]
                mx, my = (w * px).sum(), (w * py).sum()
                vx, vy = (w * px * px).sum() - mx * mx, (w * py * py).sum() - my * my
                cxy = (w * px * py).sum() - mx * my
                vals.append(float((2 * mx * my + c1) * (2 * cxy + c2) / ((mx * mx + my * my + c1) * (vx + vy + c2))))
    return sum(vals) / len(vals)


@pytest.mark.parametrize("data_range,size,sigma", [(1.0, 11, 1.5), (255.0, 7, 2.0), (2.0, 5, 0.8)])
def test_ssim_options_by_hand(data_range, size, sigma):
    x, y = _images(12, 14, 1)
    x, y = x * data_range, y * data_range
    got = float(ssim(x, y, data_range=data_range, window_size=size, sigma=sigma))
    assert got == pytest.approx(_ssim_by_hand(x, y, data_range, size, sigma), rel=1e-10, abs=1e-12)


def test_gaussian_window_options_by_hand():
    got = gaussian_window(5, 0.7, dtype=D)
    want = torch.tensor([math.exp(-(i - 2) ** 2 / (2 * 0.49)) for i in range(5)], dtype=D)
    torch.testing.assert_close(got, want / want.sum(), rtol=1e-14, atol=0)


def test_psnr_batch_and_data_range_by_hand():
    x, y = _images(5, 6, 2)
    xb, yb = torch.stack([x, y]) * 4.0, torch.stack([y, y * 0.5]) * 4.0
    got = psnr(xb, yb, data_range=4.0)
    want = [10 * math.log10(16.0 / float(((a - b) ** 2).mean())) for a, b in zip(xb, yb)]
    torch.testing.assert_close(got, torch.tensor(want, dtype=D), rtol=1e-12, atol=0)


@pytest.mark.parametrize("weights", [LossWeights(l1=0.3, ssim=0.5, mse=2.0), LossWeights(l1=0.0, ssim=0.0, mse=1.0),
                                     LossWeights(l1=1.0, ssim=1.0, mse=0.0)])
def test_image_loss_weights_by_hand(weights):
    x, y = _images(12, 13, 3)
    got = float(image_loss(x[None], y[None], weights))
    d = (x - y).flatten().tolist()
    want = (weights.l1 * sum(abs(v) for v in d) / len(d) + weights.mse * sum(v * v for v in d) / len(d)
            + weights.ssim * (1.0 - _ssim_by_hand(x, y, 1.0, 11, 1.5)))
    assert got == pytest.approx(want, rel=1e-10)
    assert float(ImageLoss(weights)(x[None], y[None])) == pytest.approx(want, rel=1e-10)  # the module form


def test_schedule_endpoints_by_hand():
    """clamp((alpha - lo) / (hi - lo), 0, 1) at non-default lo/hi, inverted included."""
    rs = ResampleSchedule(lo=1.0, hi=2.0)
    for d, want in ((2.0, 0.0), (2 ** 1.5, 0.5), (2 ** 1.75, 0.75), (8.0, 1.0), (1.0, 0.0)):
        got = rs.strength(RuntimeState(downsample=d), rows=2, dtype=D)
        assert got.tolist() == pytest.approx([want, want], abs=1e-12), d
    ds = DisplaySchedule(lo=0.2, hi=0.6)
    assert float(ds.strength(RuntimeState(power_saving=0.5), rows=1, dtype=D)) == pytest.approx(0.75)
    inv = DisplaySchedule(lo=0.8, hi=0.0)
    assert float(inv.strength(RuntimeState(power_saving=0.2), rows=1, dtype=D)) == pytest.approx(0.75)
    assert float(inv.strength(RuntimeState(power_saving=0.9), rows=1, dtype=D)) == 0.0
    lens = LensSchedule(lo=0.5, hi=1.0)
    xy = torch.tensor([[0.3, 0.4], [0.45, -0.6], [0.6, 0.8], [3.0, 4.0], [0.1, 0.0], [math.inf, math.inf]], dtype=D)
    assert lens.strength(RuntimeState(), xy, dtype=D).tolist() == pytest.approx([0.0, 0.5, 1.0, 1.0, 0.0, 1.0])
    fov = FoveationSchedule(lo=0.1, hi=0.6)
    xy = torch.tensor([[0.4, 0.2], [0.1, -0.2], [-0.2, -0.6]], dtype=D)  # distances 0.5, 0, 0.5 from the gaze
    assert fov.strength(RuntimeState(gaze=(0.1, -0.2)), xy, dtype=D).tolist() == pytest.approx([0.8, 0.0, 0.8])
    assert fov.strength(RuntimeState(), xy, dtype=D).tolist() == [0.0, 0.0, 0.0]  # no gaze: eccentricity 0
    moved = lens.with_endpoints(hi=2.0)
    assert (moved.lo, moved.hi) == (0.5, 2.0)


def test_stretch_and_fit_placement_by_hand():
    """A 30 x 50 image on a 24 x 18 mm display. 'stretch': the whole display, pitch 24/50 by 18/30 mm,
    positions unchanged. 'fit': width-limited, pitch 0.48 mm both ways, 14.4 mm tall = 0.8 of the display."""
    s = image_region(30, 50, (24.0, 18.0), "stretch")
    assert (s.half_x, s.half_y, s.size_mm) == (1.0, 1.0, (24.0, 18.0))
    assert s.pitch_mm == pytest.approx((0.48, 0.6))
    f = image_region(30, 50, (24.0, 18.0), "fit")
    assert (f.half_x, f.half_y) == pytest.approx((1.0, 0.8)) and f.pitch_mm == pytest.approx((0.48, 0.48))
    assert f.size_mm == pytest.approx((24.0, 14.4)) and f.bounds_mm == pytest.approx((-12.0, 12.0, -7.2, 7.2))
    tall = image_region(50, 20, (24.0, 18.0), "fit")  # height-limited: pitch 18/50, 7.2 mm wide = 0.3 of the display
    assert (tall.half_x, tall.half_y) == pytest.approx((0.3, 1.0)) and tall.pitch_mm == pytest.approx((0.36, 0.36))
    xy = torch.tensor([[0.5, -0.5], [-1.0, 1.0]], dtype=D)
    assert torch.equal(to_display(xy, 30, 50, "stretch", (24.0, 18.0)), xy)
    torch.testing.assert_close(to_display(xy, 30, 50, "fit", (24.0, 18.0)), torch.tensor([[0.5, -0.4], [-1.0, 0.8]], dtype=D))
    torch.testing.assert_close(to_display(xy, 50, 20, "fit", (24.0, 18.0)), torch.tensor([[0.15, -0.5], [-0.3, 1.0]], dtype=D))


def test_trainer_samples_states_from_the_configured_ranges_by_hand():
    """max_downsample / max_power_saving / seed off their defaults: each draw is (randint view,
    d = max_d ** u0, rho = max_rho * u1) from the seeded generator, as the docstring says."""
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.training import TrainConfig, Trainer

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


@pytest.mark.parametrize("brighten", [True, False])
@pytest.mark.parametrize("rho", [0.0, 0.3])
def test_display_mapping_with_other_coefficients_and_a_smaller_reference_by_hand(brighten, rho):
    """Panel coefficients (0.5, 2, 1), a 2 x 3 reference for a 4 x 5 image: P(X) = sum_c w_c mean(max(X_c, 0)),
    scale = (1 - rho) P(ref) / P(image) (at most 1 without brighten), output clipped to [0, 1]; the stats
    hold the scale, the target, the output's power and the fraction of values clipped."""
    from controlgs_adapter.downstream.display import display_mapping_with_stats

    w = (0.5, 2.0, 1.0)
    g = torch.Generator().manual_seed(4)
    image = torch.rand(3, 4, 5, generator=g, dtype=D) * 1.2 - 0.1  # some values < 0 and > 1
    ref = torch.rand(3, 2, 3, generator=g, dtype=D) * 1.6  # brighter than the image: brighten decides

    def power(x: torch.Tensor) -> float:
        return sum(w[c] * sum(max(v, 0.0) for v in x[c].flatten().tolist()) / x[c].numel() for c in range(3))

    target = (1 - rho) * power(ref)
    scale = target / power(image)
    assert scale > 1.0
    if not brighten:
        scale = min(scale, 1.0)
    dimmed = image * scale
    want = dimmed.clamp(0, 1)
    out, stats = display_mapping_with_stats(image, rho, ref, coefficients=w, brighten=brighten)
    torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    assert float(stats["scale"]) == pytest.approx(scale, rel=1e-12)
    assert float(stats["power_target"]) == pytest.approx(target, rel=1e-12)
    assert float(stats["power"]) == pytest.approx(power(want), rel=1e-12)
    n_clipped = sum(1 for v in dimmed.flatten().tolist() if v < 0 or v > 1)
    assert float(stats["clipped_fraction"]) == pytest.approx(n_clipped / dimmed.numel(), rel=1e-12)


def test_batch_loss_is_the_mean_of_its_samples():
    """batch_size=2: the first step's loss is the mean of the losses of the first two (view, state) draws,
    each measured by a batch_size=1 trainer with the same seed (its first two steps; lr 1e-12 so that its
    first update leaves the second loss as at initialisation)."""
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.training import TrainConfig, Trainer

    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=2).eval()
    effects = {"resample": True, "display": True}
    losses = {}
    for batch, iterations in ((2, 1), (1, 2)):
        t = Trainer(model, scene.views("train"), TrainConfig(iterations=iterations, checkpoint_every=0, lr=1e-12, seed=3,
                                                             batch_size=batch), effects=effects)
        try:
            t.train(progress=False)
            losses[batch] = list(t.history)
        finally:
            t.cgs.unwrap()
    assert losses[1][0] != pytest.approx(losses[1][1], rel=1e-3)  # two different draws
    assert losses[2][0] == pytest.approx((losses[1][0] + losses[1][1]) / 2, rel=1e-5)


def test_stages_used_as_plain_modules_take_the_image_size_as_native():
    """A stage called without a context on a 12 x 20 image: resampling by 4 gives 3 x 5, each output pixel
    the mean of its 4 x 4 block (by hand); the OLED stage keeps the size."""
    from controlgs_adapter.downstream.oled import OLEDEmission
    from controlgs_adapter.downstream.resample import AreaResample

    g = torch.Generator().manual_seed(5)
    image = torch.rand(3, 12, 20, generator=g, dtype=D)
    out = AreaResample()(image, RuntimeState(downsample=4.0))
    want = torch.stack([torch.stack([torch.stack([image[c, 4 * i:4 * i + 4, 4 * j:4 * j + 4].mean() for j in range(5)])
                                     for i in range(3)]) for c in range(3)])
    torch.testing.assert_close(out, want, rtol=1e-12, atol=1e-12)
    assert OLEDEmission()(image, RuntimeState()).shape == (3, 12, 20)
