"""Injection strengths of a wrapped model: the schedules of its modules (checked before the model
changes) and their values for a run-time state at each anchor's position on the display, against a
float64 pinhole projection and the schedules' equations in plain Python."""

from __future__ import annotations

import math
from typing import Any

import pytest
import torch
from helpers.banks import affine_bank, radial_lens_bank
from helpers.scaffold_standin import ScaffoldStandIn, make_camera
from helpers.strength_oracle import STATES, cardboard_eccentricity, reference_strengths
from helpers.wrapping import assert_unchanged, decode, model_record, refusing_stand_in
from hypothesis import given, settings
from hypothesis import strategies as st

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.visual_angles import VisualAngles
from controlgs_adapter.downstream.placement import to_display
from controlgs_adapter.errors import InputValueError


def test_strengths_by_hand():
    """lambda = log2(d) / 3 (resample), rho / 0.8 (display), |p| / sqrt(2) clamped (lens) with p the
    anchor's position on the display, in the order of the wrapped modules; every module is listed,
    zeros included."""
    model, cam = ScaffoldStandIn(), make_camera()
    cgs = ControlGS.wrap(model, modules=("resample", "display", "lens"), cond_dim=4)
    lam = cgs.strengths(RuntimeState(downsample=2.0, power_saving=0.3), cam)
    assert list(lam) == ["resample", "display", "lens"]
    assert torch.allclose(lam["resample"].double(), torch.full((40,), 1 / 3, dtype=torch.float64), atol=1e-7)
    assert torch.allclose(lam["display"].double(), torch.full((40,), 0.375, dtype=torch.float64), atol=1e-7)
    p = to_display(cam.normalized_screen(model.get_anchor.detach()).double(), cam.height, cam.width, cgs.placement)
    want = (p.norm(dim=1) / math.sqrt(2)).clamp(0, 1)
    assert torch.allclose(lam["lens"].double(), want, atol=1e-6)
    assert 0 < float(want.min()) < float(want.max()) < 1
    got = cgs.strengths(RuntimeState(downsample=2.0, power_saving=0.2), cam, torch.tensor([3, 1]))  # the given anchors
    assert got["resample"].tolist() == pytest.approx([1 / 3, 1 / 3], abs=1e-7) and got["display"].tolist() == [0.25, 0.25]
    assert torch.equal(got["lens"], lam["lens"][[3, 1]])
    got = cgs.strengths(RuntimeState(), cam, torch.tensor([3, 1, 0]))
    assert got["resample"].tolist() == [0.0] * 3 and got["display"].tolist() == [0.0] * 3
    with pytest.raises(InputValueError, match=r"'lens'.*camera=Camera\(...\).*got NoneType"):
        cgs.strengths(RuntimeState())
    with pytest.raises(InputValueError, match="state.*RuntimeState.*got dict"):
        cgs.strengths({"downsample": 2.0}, cam)
    cgs.unwrap()


def test_lens_strength_follows_the_radial_distance_on_the_display():
    """16:9 camera: an anchor at the right edge's middle gets 1/sqrt 2, one at the top edge's middle
    (9/16) / sqrt 2; with placement "stretch" both get 1/sqrt 2."""
    cam = make_camera(width=64, height=36)
    fx, dist = float(cam.intrinsics[0, 0]), float(cam.world_to_camera[2, 3])
    model = ScaffoldStandIn(num_anchors=4, seed=0)
    with torch.no_grad():
        model._anchor.copy_(torch.tensor([[32 * dist / fx, 0.0, 0.0], [0.0, -18 * dist / fx, 0.0],
                                          [0.0, 0.0, 0.0], [-32 * dist / fx, 18 * dist / fx, 0.0]]))
    cgs = ControlGS.wrap(model, modules=("lens", "foveation"))
    try:
        top = (0.0, -9 / 16)  # the image's top edge's middle on the display
        gaze = tuple(VisualAngles.of_bank(PSFBank.default()).directions(torch.tensor(top, dtype=torch.float64)).tolist())
        lam = cgs.strengths(RuntimeState(gaze=gaze), cam)
        r2 = math.sqrt(2)
        assert torch.allclose(lam["lens"], torch.tensor([1 / r2, 9 / 16 / r2, 0.0, math.hypot(1, 9 / 16) / r2]), atol=1e-6)
        # the gaze is seen where that display position is: eccentricities in degrees over the default 30
        fov = [cardboard_eccentricity(p, gaze) / 30 for p in ((1.0, 0.0), top, (0.0, 0.0), (-1.0, 9 / 16))]
        assert float(lam["foveation"][1]) < 1e-4 and fov[3] > fov[0] > fov[2] > 0.2
        assert torch.allclose(lam["foveation"], torch.tensor(fov), atol=1e-5)
        square = make_camera(width=36, height=36)
        lam_sq = cgs.strengths(RuntimeState(), square)["lens"]
        xy = square.normalized_screen(model._anchor.detach())
        assert torch.equal(lam_sq, (xy.norm(dim=1) / r2).clamp(0, 1).float())
        cgs.placement = "stretch"
        assert torch.allclose(cgs.strengths(RuntimeState(), cam)["lens"][:2], torch.full((2,), 1 / r2), atol=1e-6)
    finally:
        cgs.unwrap()


def test_foveation_strength_is_the_eccentricity_in_degrees_through_the_lens():
    """"fit" placement on a 64 x 48 image: y is scaled by 48 / 64 = 0.75 on the display; an anchor seen
    in the gaze direction has eccentricity 0; the lens passed to wrap() is the one measured through."""
    model = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1)
    cam = make_camera()
    cgs = ControlGS.wrap(model, modules=("foveation",))
    screen = cam.normalized_screen(model._anchor.detach()[[2]])[0].double()
    shown = (float(screen[0]), 0.75 * float(screen[1]))
    cardboard = VisualAngles.of_bank(PSFBank.default())
    gaze = tuple(cardboard.directions(torch.tensor(shown, dtype=torch.float64)).tolist())
    lam = cgs.strengths(RuntimeState(gaze=gaze), cam, torch.tensor([2]))["foveation"]
    assert float(lam[0]) < 1e-6
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    assert math.isclose(float(lam[0]), cardboard_eccentricity(shown, (0.0, 0.0)) / 30, rel_tol=1e-5)
    cgs.placement = "stretch"  # stretched: display positions are the screen positions
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    want = cardboard_eccentricity((float(screen[0]), float(screen[1])), (0.0, 0.0)) / 30
    assert math.isclose(float(lam[0]), want, rel_tol=1e-5)
    with pytest.raises(InputValueError, match=r"^gaze \(40, 0\) deg is outside the lens's field"):
        cgs.strengths(RuntimeState(gaze=(40.0, 0.0)), cam)
    cgs.unwrap()
    # through another lens: tan(angle) = 0.3 q (helpers.banks.radial_lens_bank without distortion)
    cgs = ControlGS.wrap(model, modules=("foveation",), lens=radial_lens_bank(0.0, C=9))
    lam = cgs.strengths(RuntimeState(gaze=(0.0, 0.0)), cam, torch.tensor([2]))["foveation"]
    assert math.isclose(float(lam[0]), math.degrees(math.atan(0.3 * math.hypot(*shown))) / 30, rel_tol=1e-5)
    cgs.unwrap()


_MODEL = ScaffoldStandIn(num_anchors=25, seed=3)


@settings(max_examples=20, deadline=None)
@given(STATES, st.floats(0.0, 0.5), st.floats(0.6, 2.0), st.integers(0, 2**31 - 1))
def test_strengths_follow_eqs_10_11_at_each_anchors_display_position(state, lo, hi, seed):
    cam = make_camera(width=40, height=30)
    cgs = ControlGS.wrap(_MODEL, modules=("lens", "resample", "display", "foveation"),
                         endpoints={"lens": (lo, hi), "foveation": (10 * lo, 10 * hi)})
    try:
        # independent pinhole projection in float64 of every anchor
        pts = _MODEL._anchor.detach().double()
        k = cam.intrinsics.double()
        z = pts[:, 2] + float(cam.world_to_camera[2, 3])
        u = k[0, 0] * pts[:, 0] / z + k[0, 2]
        v = k[1, 1] * pts[:, 1] / z + k[1, 2]
        xy_all = torch.stack([2 * u / cam.width - 1, 2 * v / cam.height - 1], dim=1)
        # 9 random anchors and the one farthest off screen
        far = int(xy_all.abs().amax(dim=1).argmax())
        perm = torch.randperm(25, generator=torch.Generator().manual_seed(seed))
        ids = torch.cat([perm[perm != far][:9], torch.tensor([far])])
        got = cgs.strengths(state, cam, ids)
        xy = xy_all[ids]
        assert bool((xy.abs() > 1).any())  # some anchors are off screen
        # anchors on the display ("fit" placement: the 40 px width spans it, the height 30/40)
        xy = xy * torch.tensor([1.0, 30 / 40], dtype=torch.float64)
        for i in range(len(ids)):
            want = reference_strengths(state, (float(xy[i, 0]), float(xy[i, 1])), (lo, hi), (10 * lo, 10 * hi))
            for m in want:
                assert math.isclose(float(got[m][i]), want[m], abs_tol=2e-6), (m, i)
    finally:
        cgs.unwrap()


def test_state_blind_strength_is_one_whatever_the_state():
    """The state-blind ablation injects at full strength, needing no camera: at the neutral state
    (where every schedule gives 0 at the centre) the outputs still change."""
    model, cam = ScaffoldStandIn(6, feat_dim=4, n_offsets=2, seed=1), make_camera()
    x = model.decoder_input(cam.center)
    ref = decode(model, x)
    blind = ControlGS.wrap(model, modules=("resample", "lens"), state_blind=True)
    got = blind.strengths(RuntimeState(), anchor_ids=torch.tensor([0, 5, 2]))
    assert {m: v.tolist() for m, v in got.items()} == {"resample": [1.0] * 3, "lens": [1.0] * 3}
    assert got["lens"].dtype == torch.float32
    with torch.no_grad():
        for p in blind.trainable_parameters():
            p.normal_(generator=torch.Generator().manual_seed(1))
    with torch.no_grad(), blind.conditioned(RuntimeState()):  # no camera
        out = model.decode(x)
    assert not torch.equal(out["color"], ref["color"])
    blind.unwrap()


@pytest.mark.parametrize("kw, pattern", [
    (dict(modules=("lens", "vignetting")), r"\['vignetting'\].*'resample'"),
    (dict(modules=()), r"modules.*at least one.*'display'"),
    (dict(modules=("lens", "display", "lens")), r"modules.*\['lens'\] more than once"),
    (dict(modules=("display", "resample", "display")), r"modules.*\['display'\] more than once"),
    (dict(modules=5), "modules.*got 5"),
    (dict(cond_dim=0), "cond_dim.*got 0"),
    (dict(cond_dim=-2), "cond_dim.*got -2"),
    (dict(cond_dim=True), "cond_dim.*got True"),
    (dict(cond_dim=2.0), r"cond_dim.*got 2\.0"),
    (dict(endpoints={"lens": (1.0, 1.0)}), r"'lens'.*differ.*1\.0"),
    (dict(endpoints={"lens": (0.1, 0.5, 0.9)}), r"endpoints\['lens'\].*\(lo, hi\).*\(0\.1, 0\.5, 0\.9\)"),
    (dict(endpoints={"display": (0, 1)}, modules=("lens",)), r"endpoints.*\['display'\].*\['lens'\]"),
], ids=["unknown module", "no module", "lens twice", "display twice", "modules 5", "cond_dim 0", "cond_dim -2",
        "cond_dim True", "cond_dim 2.0", "lo = hi", "three endpoints", "endpoints of another module"])
@pytest.mark.parametrize("kind", ["eager", "script"])
def test_modules_cond_dim_and_endpoints_are_checked_before_the_model_changes(kind: str, kw: dict[str, Any],
                                                                             pattern: str) -> None:
    model = refusing_stand_in(kind)
    before = model_record(model)
    with pytest.raises(InputValueError, match=pattern):
        ControlGS.wrap(model, **kw)
    assert_unchanged(before, model)
    assert ControlGS.attached(model) is None


def test_endpoints_take_a_headers_lo_hi_mapping():
    cgs = ControlGS.wrap(ScaffoldStandIn(10, seed=1), modules=("lens",), endpoints={"lens": {"lo": 0.2, "hi": 0.9, "x": 1}})
    assert (cgs.schedules["lens"].lo, cgs.schedules["lens"].hi) == (0.2, 0.9)
    cgs.unwrap()


_A = ((0.75, 0.125), (-0.25, 1.5))  # the decentred lens's green chief rays: G(d) = A d + b


@settings(max_examples=20, deadline=None)
@given(st.sampled_from(["radius", "xy"]), st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5)),
       st.floats(0.0, 0.5), st.floats(0.6, 2.0))
def test_lens_strengths_in_a_decentred_lens_frame_at_each_anchors_display_position(mode, axis, lo, hi):
    """radius: clamp((||p - axis|| - lo) / (hi - lo), 0, 1); xy: clamp(A (p - axis) / hi, -1, 1) per axis, p
    clamped to the display, in plain floats from an independent float64 projection."""
    cam = make_camera(width=40, height=30)
    cgs = ControlGS.wrap(_MODEL, modules=("lens",), cond_dim=2, endpoints={"lens": (lo, hi)},
                         lens=affine_bank(_A, (0.0625, -0.125), axis=axis), lens_conditioning=mode)
    try:
        pts = _MODEL._anchor.detach().double()
        k = cam.intrinsics.double()
        z = pts[:, 2] + float(cam.world_to_camera[2, 3])
        x = (2 * (k[0, 0] * pts[:, 0] / z + k[0, 2]) / cam.width - 1).tolist()
        y = ((2 * (k[1, 1] * pts[:, 1] / z + k[1, 2]) / cam.height - 1) * 30 / 40).tolist()  # "fit" on the display
        got = cgs.strengths(RuntimeState(), cam)["lens"]
        for i, (px, py) in enumerate(zip(x, y)):
            if mode == "radius":
                r = math.hypot(px - axis[0], py - axis[1])
                assert math.isclose(float(got[i]), min(max((r - lo) / (hi - lo), 0.0), 1.0), abs_tol=2e-6), i
                continue
            dx, dy = min(max(px, -1.0), 1.0) - axis[0], min(max(py, -1.0), 1.0) - axis[1]
            q = (_A[0][0] * dx + _A[0][1] * dy, _A[1][0] * dx + _A[1][1] * dy)
            for j in range(2):
                assert math.isclose(float(got[i, j]), min(max(q[j] / hi, -1.0), 1.0), abs_tol=2e-6), (i, j)
    finally:
        cgs.unwrap()
