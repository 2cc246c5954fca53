"""Tests of ``controlgs_adapter.downstream.foveation``: the MAR model against a hand-computed sampling-rate
map on an analytic lens, the exact foveal plateau, identity at no cost when off, gradients, a gaze outside
the field. The stage contract is checked in ``test_stage_contract.py``."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from helpers.banks import radial_lens_bank

from controlgs_adapter.downstream.foveation import PRESETS, Foveation, FoveationModel, _blend, foveation, pixel_savings
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.visual_angles import VisualAngles, angle_to
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.state import RuntimeState

K, S = 0.2, 12.0 * 15.0 / 600.0  # the analytic lens of helpers.banks.radial_lens_bank: tan(angle) = S q


@pytest.fixture(scope="module")
def angles() -> VisualAngles:
    return VisualAngles.of_bank(radial_lens_bank(K))


def _hand_level(n: int, model: FoveationModel) -> torch.Tensor:
    """log2(ppd / rate) of an n x n image, gaze on the axis, by hand: eccentricity atan(S |q|), ppd from
    the map's Jacobian (as in test_visual_angles), rate = min(ppd, 1 / (omega0 + m e))."""
    c = (2 * torch.arange(n, dtype=torch.float64) + 1) / n - 1
    py, px = torch.meshgrid(c, c, indexing="ij")
    r2 = px ** 2 + py ** 2
    qx, qy = px * (1 + K * r2), py * (1 + K * r2)
    ecc = torch.atan(S * torch.sqrt(qx ** 2 + qy ** 2)).rad2deg()
    det = (math.degrees(1) * S) ** 2 / ((1 + (S * qx) ** 2) * (1 + (S * qy) ** 2)) * (1 + K * r2) * (1 + 3 * K * r2) * (2 / n) ** 2
    ppd = det.rsqrt()
    rate = torch.minimum(ppd, 1 / (model.omega0 + model.slope * ecc))
    if model.max_scale is not None:
        rate = torch.maximum(rate, ppd / model.max_scale)
    return torch.log2(ppd / rate)


@pytest.mark.parametrize("preset", ["guenter-0.022", "level-4x", "level-16x"])
def test_the_level_map_is_the_mar_model_by_hand(angles, preset):
    model = PRESETS[preset]
    assert model is not None
    n = 512  # ppd ~ 13 at the centre: the foveal plateau and a periphery at up to 3 levels
    got = Foveation(preset, angles=angles).level(n, n, (0.0, 0.0))
    want = _hand_level(n, model)
    assert torch.allclose(got, want, atol=3e-3, rtol=0)
    assert float(want.min()) == 0.0 and float(want.max()) >= 1.0
    if model.max_scale is not None:
        assert float(got.max()) == pytest.approx(math.log2(model.max_scale), abs=1e-9)


def test_inside_the_foveal_plateau_the_output_is_the_input_exactly(angles):
    x = torch.rand(2, 3, 128, 128, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    stage = Foveation(FoveationModel(slope=0.3), angles=angles)
    gaze = (4.0, -3.0)
    level = stage.level(128, 128, gaze)
    y = stage(x, RuntimeState(gaze=gaze))
    plateau = level == 0
    assert 0 < int(plateau.sum()) < 128 * 128 // 2
    assert torch.equal(y[..., plateau], x[..., plateau])
    assert float((y - x)[..., ~plateau].abs().amax()) > 0.05


def test_a_uniform_level_is_the_mip_level_reconstructed():
    """Where the level is exactly 1, the output is the 2 x 2 box-filtered image upsampled bilinearly."""
    x = torch.rand(1, 3, 16, 16, dtype=torch.float64)
    y = _blend(x, torch.ones(16, 16, dtype=torch.float64), 3)
    box = x.reshape(1, 3, 8, 2, 8, 2).mean((3, 5))
    assert torch.allclose(y, F.interpolate(box, size=(16, 16), mode="bilinear", align_corners=False), atol=1e-12)


def test_identity_and_no_compute_when_off(angles):
    x = torch.rand(3, 8, 8)
    for stage, state in ((Foveation(angles=angles), RuntimeState()),                 # no gaze, not fixed
                         (Foveation("off", angles=angles), RuntimeState(gaze=(1.0, 2.0))),
                         (Foveation(None, angles=angles, fixed=True), RuntimeState())):
        assert stage.is_identity(state) and stage(x, state) is x and stage._maps == {}
    assert foveation(x, None, angles=angles) is x and foveation(x, (1.0, 2.0), preset="off") is x
    p = Pipeline.from_config({"foveation": {"angles": angles}, "lens": True, "oled": False})
    assert p.names == ["foveation", "lens"] and Foveation.order < LensPrewarp.order
    assert p.active(RuntimeState()) == ["lens"] and p.active(RuntimeState(gaze=(0.0, 0.0))) == ["foveation", "lens"]


def test_fixed_foveation_is_centred_on_the_lens_axis(angles):
    x = torch.rand(3, 64, 64, dtype=torch.float64)
    fixed = Foveation(FoveationModel(slope=0.3), angles=angles, fixed=True)
    assert not fixed.is_identity(RuntimeState())
    assert torch.equal(fixed(x, RuntimeState()), fixed(x, RuntimeState(gaze=(0.0, 0.0))))
    assert not torch.equal(fixed(x, RuntimeState()), fixed(x, RuntimeState(gaze=(8.0, 0.0))))


def test_gradcheck_of_the_stage(angles):
    x = torch.rand(3, 12, 10, dtype=torch.float64, requires_grad=True)
    stage = Foveation(FoveationModel(slope=1.0), angles=angles)
    assert float(stage.level(12, 10, (3.0, 2.0)).max()) > 1.0  # several levels blend
    assert torch.autograd.gradcheck(lambda t: stage(t, RuntimeState(gaze=(3.0, 2.0))), (x,))


def test_a_gaze_outside_the_lens_field_is_refused():
    stage = Foveation()
    with pytest.raises(InputValueError, match=r"^gaze \(25, -2\) deg is outside the lens's field"):
        stage(torch.rand(3, 8, 8), RuntimeState(gaze=(25.0, -2.0)))
    with pytest.raises(InputValueError, match=r"^foveation preset must be one of"):
        Foveation("level-3x")


def test_pixel_savings_order_of_the_presets():
    stage = Foveation(bank=PSFBank.default())
    unit, ppd, _ = stage.maps(1024, 1024)
    ecc = angle_to(unit, (0.0, 0.0))
    f = {name: pixel_savings(ecc, ppd, m) for name, m in PRESETS.items() if m is not None}
    assert 1 > f["guenter-0.022"] > f["guenter-0.0275"] and f["level-4x"] > f["level-16x"]
    assert f["level-4x"] >= 0.25 and f["level-16x"] >= 1 / 16


def test_the_stage_measures_through_the_runs_lens():
    """effects_for_lens hands the foveation stage the lens's bank (unless its options name one): the compact
    lens's field and pixels per degree differ from Cardboard's."""
    from controlgs_adapter.downstream.optics.lenses import effects_for_lens, load_lens

    compact = load_lens("compact").bank
    effects = effects_for_lens({"foveation": {"preset": "level-4x"}, "oled": False}, "compact")
    assert effects["foveation"]["preset"] == "level-4x" and torch.equal(effects["foveation"]["bank"].chief, compact.chief)
    stage = Pipeline.from_config(effects)["foveation"]
    assert isinstance(stage, Foveation) and stage.model == PRESETS["level-4x"]
    want = VisualAngles.of_bank(compact).pixels_per_degree(32, 32)
    assert torch.equal(stage.maps(32, 32)[1], want)
    assert not torch.allclose(want, VisualAngles.of_bank(PSFBank.default()).pixels_per_degree(32, 32), rtol=0.05)
    kept = {"angles": VisualAngles.of_bank(PSFBank.default())}
    assert effects_for_lens({"foveation": kept}, "compact")["foveation"] is kept
