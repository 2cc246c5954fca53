"""Numerics and training pieces by hand: the splatter on a wide image with off-screen and border
Gaussians, a background and small chunk limits against the float64 reference; box emission to a
non-integer size; the trainer's ``until``, checkpoint cadence and option checks; refusals of the
splatter, optics stage, PSF bank, process context and injector, each naming its argument."""

from __future__ import annotations

import math

import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.distributed import DistContext
from controlgs_adapter.downstream.oled import oled_emission
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.stage import PSFOptics, psf_optics
from controlgs_adapter.errors import InputValueError, LifecycleError, ShapeError
from controlgs_adapter.rendering import splatter
from controlgs_adapter.rendering.splatter import rasterize
from controlgs_adapter.rendering.splatter_reference import rasterize_reference
from controlgs_adapter.state import Camera
from controlgs_adapter.training import TrainConfig, Trainer

from scaffold_standin import ScaffoldStandIn, make_camera

F64 = torch.float64


# ----------------------------------------------------------------------------- splatter


def _wide_scene():
    """A 37 x 11 camera (unrotated, principal point off-centre) and Gaussians placed by pixel: inside,
    straddling each border, entirely off-screen below and right, and one behind the near plane."""
    w, h = 37, 11
    k = torch.tensor([[30.0, 0, 17.3], [0, 28.0, 5.9], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, w, h)
    # (u, v) pixel positions and depths
    uv = torch.tensor([[5.0, 5.0], [18.0, 10.6], [36.4, 3.0], [-0.5, 7.0], [20.0, -0.4], [18.0, 12.5],
                       [45.0, 5.0], [9.0, 2.0], [30.0, 8.0], [18.0, 5.0]], dtype=F64)
    z = torch.tensor([2.0, 1.5, 3.0, 2.5, 1.2, 2.0, 2.0, 4.0, 0.15, 3.5], dtype=F64)
    x = (uv[:, 0] - 17.3) / 30.0 * z
    y = (uv[:, 1] - 5.9) / 28.0 * z
    means = torch.stack([x, y, z], -1)
    g = torch.Generator().manual_seed(3)
    scales = 0.02 + 0.05 * torch.rand(10, 3, generator=g, dtype=F64)
    rot = torch.randn(10, 4, generator=g, dtype=F64)
    opac = 0.3 + 0.69 * torch.rand(10, generator=g, dtype=F64)
    colors = torch.rand(10, 3, generator=g, dtype=F64)
    return cam, (means, scales, rot, opac, colors)


@pytest.mark.parametrize("limits", [None, (40, 64)])
def test_wide_image_borders_background_and_small_chunks_match_the_reference(limits, monkeypatch):
    cam, scene = _wide_scene()
    if limits is not None:  # chunks of a few tiles, passes of a few pairs
        monkeypatch.setattr(splatter, "_KEY_LIMIT", limits[0])
        monkeypatch.setattr(splatter, "_PAIR_BUDGET", limits[1])
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=F64)
    for t_min in (0.0, 0.3):
        got = rasterize(*scene, cam, bg, tile_size=4, transmittance_min=t_min)
        ref = rasterize_reference(*scene, cam, bg, transmittance_min=t_min)
        for name in ("color", "alpha", "depth"):
            assert torch.allclose(getattr(got, name), getattr(ref, name), atol=1e-10), (name, t_min)
        assert torch.equal(got.visible, ref.visible)
    # visibility by hand: off-screen right (45, 5) and behind the near plane (z = 0.15) are not visible
    assert not got.visible[6] and not got.visible[8] and got.visible[[0, 1, 7, 9]].all()
    # where nothing is drawn the pixel is the background colour exactly, with T = 1 - alpha elsewhere
    empty = got.alpha[0] == 0
    assert empty.any() and torch.equal(got.color[:, empty], bg[:, None].expand(3, int(empty.sum())))


def test_background_is_weighted_by_the_remaining_transmittance_by_hand():
    """One Gaussian at the principal point, opacity 0.5: the centre pixel has alpha 0.5 exp(-m/2)
    (m its Mahalanobis distance, the low-pass included), colour c alpha + bg (1 - alpha)."""
    w = h = 5
    k = torch.tensor([[10.0, 0, 2.5], [0, 10.0, 2.5], [0, 0, 1]], dtype=F64)
    cam = Camera(torch.eye(4, dtype=F64), k, w, h)
    s = 0.05
    out = rasterize(torch.tensor([[0.0, 0.0, 1.0]], dtype=F64), torch.full((1, 3), s, dtype=F64),
                    torch.tensor([[1.0, 0, 0, 0]], dtype=F64), torch.tensor([0.5], dtype=F64),
                    torch.tensor([[1.0, 0.0, 0.0]], dtype=F64), cam, torch.tensor([0.0, 1.0, 0.0], dtype=F64))
    var = (10.0 * s) ** 2 + 0.3  # px^2: (f s / z)^2 + low-pass, isotropic
    a = 0.5  # the centre pixel (2.5, 2.5) sits on the mean
    assert math.isclose(float(out.alpha[0, 2, 2]), a, rel_tol=1e-12)
    assert torch.allclose(out.color[:, 2, 2], torch.tensor([a, 1 - a, 0.0], dtype=F64), atol=1e-12)
    a1 = 0.5 * math.exp(-0.5 * 1.0 / var)  # one pixel to the right
    assert torch.allclose(out.color[:, 2, 3], torch.tensor([a1, 1 - a1, 0.0], dtype=F64), atol=1e-12)


@pytest.mark.parametrize("t_min", [1.0, -0.1, 1.5, "0.1"])
def test_transmittance_min_outside_0_1_is_refused(t_min):
    cam, scene = _wide_scene()
    with pytest.raises(InputValueError, match="transmittance_min"):
        rasterize(*scene, cam, transmittance_min=t_min)


# ----------------------------------------------------------------------------- box emission


def test_box_emission_to_a_non_integer_size_by_hand_and_refusals():
    img = torch.arange(2 * 3, dtype=F64).reshape(1, 2, 3).expand(3, 2, 3)
    out = oled_emission(img, (3, 5))
    # simulation pixel i shows display pixel floor((i + 0.5) n / S): rows 2 -> 3: [0, 1, 1]; cols 3 -> 5: [0, 0, 1, 2, 2]
    want = img[:, [0, 1, 1]][:, :, [0, 0, 1, 2, 2]]
    assert torch.equal(out, want)
    for size in ((2, 2), (1, 3), (1, 2)):  # either side smaller than the image
        with pytest.raises(ShapeError, match="size"):
            oled_emission(img, size)


# ----------------------------------------------------------------------------- optics bank and stage


def _bank(L: int = 3, **over) -> PSFBank:
    G, K = 2, 3
    psf = torch.zeros(L, G, G, K, K, dtype=F64)
    psf[..., 1, 1] = 1.0  # delta PSFs
    c = torch.linspace(-1, 1, 3, dtype=F64)
    cy, cx = torch.meshgrid(c, c, indexing="ij")
    f = torch.tensor([-0.5, 0.5], dtype=F64)
    args = dict(psf=psf, psf_pitch_mm=torch.full((L, G, G), 0.1, dtype=F64), field_x=f, field_y=f,
                chief=torch.stack([cx, cy], -1).expand(L, 3, 3, 2).clone(), chief_x=c, chief_y=c,
                wavelengths_nm=(656.0, 550.0, 486.0, 420.0)[:L], display_mm=(10.0, 10.0))
    args.update(over)
    return PSFBank(**args)


def test_optics_needs_three_wavelengths_and_a_positive_zone():
    image = torch.rand(3, 8, 8, dtype=F64)
    with pytest.raises(InputValueError, match="3 wavelengths"):
        psf_optics(image, _bank(4), "distortion")
    with pytest.raises(InputValueError, match="zone"):
        PSFOptics(_bank(), zone=0)
    psf_optics(image, _bank(3), "distortion")  # the same bank with three wavelengths is taken


def test_psf_bank_refuses_negative_taps_and_transmission_above_one():
    psf = _bank().psf.clone()
    psf[0, 0, 0, 0, 0], psf[0, 0, 0, 1, 1] = -0.01, 1.01  # still sums to 1
    with pytest.raises(InputValueError, match="non-negative"):
        _bank(psf=psf)
    psf[0, 0, 0, 0, 0], psf[0, 0, 0, 1, 1] = -1e-4, 1.0 + 1e-4  # rounding-size negatives are kept
    _bank(psf=psf)
    for t in (1.5, -0.2):  # checked when the bank is made
        with pytest.raises(InputValueError, match="transmission"):
            _bank(meta={"transmission": torch.full((3, 2, 2), t).tolist()})
    assert torch.equal(_bank(meta={"transmission": [[[0.25] * 2] * 2] * 3}).transmission, torch.full((3, 2, 2), 0.25, dtype=F64))


# ----------------------------------------------------------------------------- process context, injector


@pytest.mark.parametrize("rank, world", [(1, 1), (2, 2), (-1, 2)])
def test_rank_outside_the_world_is_refused(rank, world):
    with pytest.raises(InputValueError, match="rank"):
        DistContext(rank=rank, world_size=world)


def test_nested_conditioned_blocks_are_refused():
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model)
    try:
        with cgs.conditioned(RuntimeState(downsample=2.0), camera=cam):
            model.decode(model.decoder_input(cam.center))  # the outer block is used
            with pytest.raises(LifecycleError, match="already inside"):
                with cgs.conditioned(RuntimeState(), camera=cam):
                    pass
    finally:
        cgs.unwrap()


# ----------------------------------------------------------------------------- trainer


def test_psf_mode_other_than_fast_or_exact_is_refused():
    for mode in ("distortion", "slow"):
        with pytest.raises(InputValueError, match="psf_mode"):
            TrainConfig(psf_mode=mode)


@pytest.fixture(scope="module")
def tiny():
    pytest.importorskip("skimage")
    from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
    from controlgs_adapter.scene import load_builtin_scene

    scene = load_builtin_scene("ar", 16, views=2, test_every=2, samples=2)
    xyz, rgb = scene.points(0.25)
    model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.35, color_fit_steps=5)
    return scene, model.eval()


class _RecordingTrainer(Trainer):
    """The real trainer, recording the iteration at which each checkpoint is written."""

    def save_checkpoint(self, path):
        self.saved_at = [*getattr(self, "saved_at", []), self.iteration]
        return super().save_checkpoint(path)


def test_checkpoint_cadence_and_until_past_the_end(tiny, tmp_path):
    scene, model = tiny
    config = TrainConfig(iterations=5, checkpoint_every=2)
    t = _RecordingTrainer(model, scene.views("train"), config, effects={"resample": True},
                          checkpoint=tmp_path / "c.safetensors")
    try:
        t.train(until=50, progress=False)  # until beyond iterations stops at iterations
        assert t.iteration == 5 and len(t.history) == 5
        assert t.saved_at == [2, 4, 5]  # every 2nd iteration, then at the end
        # without a display stage every state has rho = 0; d = max_d ** u0 from the same draws
        g = torch.Generator().manual_seed(config.seed)
        t.generator.manual_seed(config.seed)
        for _ in range(20):
            view = int(torch.randint(len(t.views), (1,), generator=g))
            u = torch.rand(2, generator=g, dtype=F64)
            got_view, state = t.sample()
            assert got_view == view and state.power_saving == 0.0
            assert state.downsample == pytest.approx(config.max_downsample ** float(u[0]), rel=1e-12)
    finally:
        t.cgs.unwrap()


# ----------------------------------------------------------------------------- ray tracer


def test_slab_rays_clip_at_the_semi_diameter_and_extend_back_to_the_image_plane():
    """A plane-parallel slab of semi-diameter 2 mm: a ray from the axis with slope u meets the first
    surface at height u d (d the object distance); it passes iff that height (and its exit height)
    is within 2 mm. Its backward extension crosses the image plane at exit + u (z_image - z_exit)."""
    from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription, cauchy_index
    from controlgs_adapter.downstream.optics.raytrace import trace

    spec = dict(CARDBOARD, surfaces=[
        {"radius_mm": None, "thickness_mm": 5.0, "after": {"nd": 1.6, "vd": 40.0}, "semi_diameter_mm": 2.0},
        {"radius_mm": None, "thickness_mm": 10.0, "after": "air", "semi_diameter_mm": 2.0}])
    rx = Prescription(spec)
    d = rx.object_distance
    u = torch.tensor([0.5, 1.5, 2.5, -1.7]).double().numpy() / d  # first-surface heights 0.5, 1.5, 2.5, -1.7 mm
    _, _, X, _, ok = trace(rx, 550.0, 0.0, 0.0, u, 0.0)
    n = cauchy_index(1.6, 40.0, 550.0)
    slope_glass = torch.tan(torch.asin(torch.from_numpy(u / (1 + u * u) ** 0.5) / n)).numpy()
    exit_x = u * d + slope_glass * 5.0
    assert ok.tolist() == [bool(abs(h) <= 2.0) for h in exit_x]
    assert ok.tolist() == [True, True, False, True]
    want_X = exit_x + u * (rx.image_z - (d + 5.0))
    assert abs(X - want_X).max() < 1e-9


# ----------------------------------------------------------------------------- pipeline sizes


def test_pipeline_refuses_an_image_larger_than_native_and_a_reference_at_another_size():
    from controlgs_adapter.downstream.oled import OLEDEmission
    from controlgs_adapter.downstream.pipeline import Pipeline

    p = Pipeline([OLEDEmission()])
    img = torch.rand(3, 4, 6, dtype=F64)
    state = RuntimeState(downsample=2.0)
    for native in ((3, 6), (4, 5)):  # either side smaller than the image
        with pytest.raises(ShapeError, match="larger than the native size"):
            p(img, state, native_size=native)
    with pytest.raises(ShapeError, match="reference must be at native_size"):
        p(img, state, reference=torch.rand(3, 8, 12, dtype=F64), native_size=(8, 11))
    # the native size taken from the reference: box emission to it (display pixel floor((i + 0.5) n / S))
    out = p(img, state, reference=torch.rand(3, 8, 9, dtype=F64))
    assert torch.allclose(out, img[:, [0, 0, 1, 1, 2, 2, 3, 3]][:, :, [0, 1, 1, 2, 3, 3, 4, 5, 5]], atol=1e-12)
