"""Tests of ``controlgs_adapter.evaluation``: the evaluation grid (baselines, the ideal render, adapters,
extra metrics, refusals, progress), the scores of an eye image, the downstream pipeline it builds, and
:class:`GridResult` (accessors, equality, JSON)."""

from __future__ import annotations

import json
import math
from importlib.util import find_spec
from pathlib import Path

import pytest
import torch
from helpers.banks import affine_bank, random_bank, tiny_bank
from helpers.cvvdp_reference import CVVDP_COLUMN, direct_cvvdp, needs_cvvdp
from helpers.grid_results import DOWNSAMPLE, POWER_SAVING, PSNR, grid_result
from helpers.lpips_weights import random_lpips_weights
from helpers.progress import record_bars

from controlgs_adapter import ControlGS, RuntimeState, evaluation, plugins
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.downstream.lens import LensPrewarp
from controlgs_adapter.downstream.optics.bank import PSFBank
from controlgs_adapter.downstream.optics.visual_angles import VisualAngles
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import (
    BASELINES,
    GRID_DOWNSAMPLE,
    GRID_POWER_SAVING,
    IDEAL,
    GridResult,
    condition_response,
    evaluate_grid,
    lens_ppd,
    make_pipeline,
    pipeline_lens,
    scores,
    side_by_side,
)
from controlgs_adapter.metrics import flip, psnr, ssim
from controlgs_adapter.perceptual import LPIPS
from controlgs_adapter.rendering.protocol import render_view
from controlgs_adapter.scene import load_builtin_scene
from controlgs_adapter.state import Camera
from controlgs_adapter.training import DEFAULT_EFFECTS

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
pytest.importorskip("skimage")  # the built-in scene

F64 = torch.float64
#: the cheap downstream path (no optics)
CHEAP = {"lens": True, "resample": True, "display": True}


def _pipe(mode: str = "fast", effects: dict | None = None) -> Pipeline:
    pipe = Pipeline.from_config(dict(DEFAULT_EFFECTS if effects is None else effects))
    if "optics" in pipe:
        pipe["optics"].mode = mode
    return pipe.eval()


class _GroundTruths:
    """A Views dataset of two 32 x 32 ground truths (cameras only name their size)."""

    background = None

    def __init__(self) -> None:
        g = torch.Generator().manual_seed(4)
        k = torch.tensor([[32.0, 0, 16], [0, 32, 16], [0, 0, 1]])
        self.items = [(Camera(torch.eye(4), k, 32, 32), torch.rand(3, 32, 32, generator=g)) for _ in range(2)]

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int):
        return self.items[i]


class _OnWhite:
    """The first view of a dataset, its renders to be made on a white background."""

    background = torch.ones(3)

    def __init__(self, views) -> None:
        self.view = views[0]

    def __len__(self) -> int:
        return 1

    def __getitem__(self, i: int):
        return self.view


class _Plain:
    """A Views dataset with nothing but the protocol (no describe)."""

    def __init__(self, views):
        self.inner, self.background = views, views.background

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i: int):
        return self.inner[i]


# ------------------------------------------------------------------------------ evaluate_grid
def test_ideal_bound_is_the_ground_truth_through_the_pipeline(tiny):
    """No baselines and no adapters: nothing is rendered, only the ground truth goes through E_s, scored
    as PSNR, SSIM, FLIP and ColorVideoVDP (at the shipped Cardboard lens's on-axis ppd) of the clamped eye image."""
    scene, model = tiny
    views = scene.views("test")
    r = evaluate_grid(model, views, {}, downsample=(2.0,), power_saving=(0.4,), baselines=(), progress=False)
    assert r.methods == [IDEAL] and r.metrics == ["psnr", "ssim", "flip", *CVVDP_COLUMN]
    pipe = _pipe()
    for v in range(len(views)):
        _, gt = views[v]
        with torch.no_grad():
            eye = pipe(gt, RuntimeState(downsample=2.0, power_saving=0.4), reference=gt).clamp(0, 1).double()
        want = {"psnr": float(psnr(eye, gt.double())), "ssim": float(ssim(eye, gt.double())), "flip": flip(eye, gt.double())}
        if CVVDP_COLUMN:
            want["cvvdp"] = direct_cvvdp(eye, gt.double(), lens_ppd(PSFBank.default(), gt.shape[-2], gt.shape[-1]))
        for k, value in want.items():
            assert float(r.per_view[IDEAL][k][0, 0, v]) == pytest.approx(value, rel=1e-9, abs=1e-12), k
        assert want["psnr"] < 60  # the pipeline is not the identity: the bound means something


def test_baselines_ideal_and_extra_metrics_options(tiny_adapter):
    model, views, path = tiny_adapter
    r = evaluate_grid(model, views, {}, downsample=(2.0,), power_saving=(0.6,), baselines=("ss",), ideal=False,
                      progress=False, optics_mode="distortion")
    assert r.methods == ["ss"] and r.metrics == ["psnr", "ssim", "flip", *CVVDP_COLUMN] and r.optics_mode == "distortion"
    cam, gt = views[1]
    with torch.no_grad():
        eye = _pipe("distortion")(render_view(None, model, cam, None, views.background),
                                  RuntimeState(downsample=2.0, power_saving=0.6), reference=gt)
    eye64 = eye.clamp(0, 1).double()
    assert float(r.per_view["ss"]["flip"][0, 0, 1]) == pytest.approx(flip(eye64, gt.double()), abs=1e-9)
    mse = float((eye64 - gt.double()).square().mean())
    assert float(r.per_view["ss"]["psnr"][0, 0, 1]) == pytest.approx(10 * math.log10(1.0 / mse), abs=1e-9)
    only = evaluate_grid(model, views, {}, downsample=(1.0,), power_saving=(0.0,), baselines=("no_ss",),
                         extra_metrics=False, progress=False)
    assert only.methods == ["no_ss", IDEAL]
    # the default grid is the paper's 4 x 5
    none = evaluate_grid(model, views, {}, baselines=(), extra_metrics=False, progress=False)
    assert none.downsample == (1.0, 2.0, 4.0, 8.0) and none.power_saving == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert none.methods == [IDEAL]


def test_evaluate_grid_scores_lpips_with_the_network_it_is_given():
    """``evaluate_grid(..., lpips=net)`` adds an ``lpips`` metric: ``net`` of each clamped eye image
    against its ground truth (here the ideal render, the ground truth through the display stage)."""
    net = LPIPS(random_lpips_weights(2))
    views = _GroundTruths()
    effects = {"display": True}
    r = evaluate_grid(torch.nn.Linear(1, 1), views, {}, effects=effects, downsample=(1.0,), power_saving=(0.0, 0.6),
                      baselines=(), lpips=net, progress=False, renderer=lambda *a, **k: None)
    assert r.methods == [IDEAL] and r.metrics == ["psnr", "ssim", "flip", "lpips", *CVVDP_COLUMN]
    pipe = make_pipeline(effects)
    with torch.no_grad():
        for j, rho in enumerate((0.0, 0.6)):
            for v in range(2):
                gt = views[v][1]
                eye = pipe(gt, RuntimeState(power_saving=rho), reference=gt).clamp(0, 1)
                want = float(net(eye.double(), gt.double()))
                assert float(r.per_view[IDEAL]["lpips"][0, j, v]) == pytest.approx(want, rel=1e-6, abs=1e-9)
    assert float(r.per_view[IDEAL]["lpips"][0, 1].min()) > 0  # dimmed: a distance, not 0


def test_evaluate_grid_scores_through_the_lens_it_is_given():
    """``lens=`` (a bank here): the ideal render is scored through that lens's chief-ray pre-warp, as through a
    pipeline holding the stage built by hand; the default (Cardboard radial map) scores otherwise."""
    bank = random_bank(C=9, pincushion=0.08)
    views = _GroundTruths()
    kw = dict(effects={"lens": True}, downsample=(1.0,), power_saving=(0.0,), baselines=(), extra_metrics=False,
              progress=False, renderer=lambda *a, **k: None)
    got = evaluate_grid(torch.nn.Linear(1, 1), views, {}, lens=bank, **kw).per_view[IDEAL]["psnr"][0, 0]
    default = evaluate_grid(torch.nn.Linear(1, 1), views, {}, **kw).per_view[IDEAL]["psnr"][0, 0]
    pipe = make_pipeline({"lens": LensPrewarp.from_psf_bank(bank)})
    with torch.no_grad():
        want = [float(psnr(pipe(gt, RuntimeState(), reference=gt).clamp(0, 1).double(), gt.double())) for _, gt in
                views.items]
    assert got.tolist() == pytest.approx(want, rel=1e-6)
    assert not torch.allclose(got, default)
    assert make_pipeline({"optics": True}, lens=bank)["optics"].bank is bank


def test_lens_ppd_is_the_angle_a_pixel_subtends_on_axis():
    """A pixel of pitch p on the display is M p wide on the virtual image plane at D: ppd = 1 / (its angle in
    degrees); for a stretched image the geometric mean of the two axes'. The Cardboard bank at 1024 px: 1.76 arcmin."""
    bank = tiny_bank(display_mm=(20.0, 10.0), meta={"figures": {"reference_magnification": 8.0},
                                                   "prescription": {"virtual_image_distance_mm": 400.0}})

    def exact(pitch: float) -> float:  # the angle of a pixel centred on the axis
        return 1.0 / math.degrees(2 * math.atan(8.0 * pitch / 2 / 400.0))

    assert lens_ppd(bank, 40, 80) == pytest.approx(exact(0.25), rel=1e-12)      # width-limited: 20 mm / 80 px
    assert lens_ppd(bank, 50, 60) == pytest.approx(exact(0.2), rel=1e-12)       # height-limited: 10 mm / 50 px
    assert lens_ppd(bank, 40, 40, "stretch") == pytest.approx(math.sqrt(exact(0.5) * exact(0.25)), rel=1e-12)
    assert 60 / lens_ppd(PSFBank.default(), 1024, 1024) == pytest.approx(1.76, abs=0.005)
    for meta in ({}, {"figures": {"reference_magnification": 8.0}}):
        with pytest.raises(InputValueError, match=r"^PSF bank: no visual angles"):
            lens_ppd(tiny_bank(meta=meta), 40, 40)
    with pytest.raises(InputValueError, match=r"must be > 0, got 400.0, 'x'$"):
        lens_ppd(tiny_bank(meta={"figures": {"reference_magnification": "x"},
                                 "prescription": {"virtual_image_distance_mm": 400.0}}), 40, 40)
    with pytest.raises(InputValueError, match=r"reference_magnification must be > 0, got 400.0, -8.0$"):
        lens_ppd(tiny_bank(meta={"figures": {"reference_magnification": -8.0},
                                 "prescription": {"virtual_image_distance_mm": 400.0}}), 40, 40)


def test_pipeline_lens_is_the_optics_stage_bank():
    bank = tiny_bank()
    assert pipeline_lens(make_pipeline({"optics": {"bank": bank, "placement": "stretch"}})) == (bank, "stretch")
    assert pipeline_lens(make_pipeline({"display": True})) == (PSFBank.default(), "fit")


@needs_cvvdp
def test_evaluate_grid_scores_cvvdp_at_the_simulated_lens_ppd():
    """The ``cvvdp`` column is ColorVideoVDP at the ppd of the optics stage's lens (a synthetic bank here), and
    ``info["cvvdp"]`` records it per image size; a bank without the figures leaves the column out and says why."""
    bank = tiny_bank(meta={"figures": {"reference_magnification": 12.0},
                           "prescription": {"virtual_image_distance_mm": 600.0, "name": "synthetic"}})
    views, effects = _GroundTruths(), {"optics": {"bank": bank}, "display": True}
    r = evaluate_grid(torch.nn.Linear(1, 1), views, {}, effects=effects, downsample=(1.0,), power_saving=(0.6,),
                      baselines=(), progress=False, renderer=lambda *a, **k: None)
    ppd = 1.0 / math.degrees(2 * math.atan(12.0 * 24.0 / 32 / 2 / 600.0))  # a pixel centred on the axis
    assert r.metrics == ["psnr", "ssim", "flip", "cvvdp"]
    assert r.info["cvvdp"]["ppd"]["32x32"] == pytest.approx(ppd, rel=1e-12)
    assert r.info["cvvdp"] == {"lens": "synthetic", "placement": "fit", "display": "standard_4k",
                               "ppd": {"32x32": r.info["cvvdp"]["ppd"]["32x32"]}}
    pipe = make_pipeline(effects)
    with torch.no_grad():
        for v in range(2):
            gt = views[v][1]
            eye = pipe(gt, RuntimeState(power_saving=0.6), reference=gt).clamp(0, 1).double()
            assert float(r.per_view[IDEAL]["cvvdp"][0, 0, v]) == pytest.approx(direct_cvvdp(eye, gt.double(), ppd), abs=1e-6)
            assert float(r.per_view[IDEAL]["cvvdp"][0, 0, v]) != pytest.approx(direct_cvvdp(eye, gt.double(), 2 * ppd), abs=1e-3)
    bare = evaluate_grid(torch.nn.Linear(1, 1), views, {}, effects={"optics": {"bank": tiny_bank()}}, downsample=(1.0,),
                         power_saving=(0.0,), baselines=(), progress=False, renderer=lambda *a, **k: None)
    assert bare.metrics == ["psnr", "ssim", "flip"]
    assert bare.info["cvvdp"]["skipped"].startswith("PSF bank: no visual angles")


def test_evaluate_grid_renders_on_the_views_background(tiny):
    """``evaluate_grid`` renders on ``views.background`` (documented: "its background is the renders'"):
    the SS-backbone's score is that of the render on white, which differs from the model's own black."""
    scene, model = tiny
    views = _OnWhite(scene.data.views("train", first=1))
    effects = {"display": True}
    r = evaluate_grid(model, views, {}, effects=effects, downsample=(1.0,), power_saving=(0.0,), baselines=("ss",),
                      ideal=False, extra_metrics=False, progress=False)
    cam, gt = views[0]
    pipe = make_pipeline(effects)
    with torch.no_grad():
        scored = {}
        for name, bg in (("white", torch.ones(3)), ("black", torch.zeros(3))):
            eye = pipe(render_view(None, model, cam, None, bg), RuntimeState(), reference=gt).clamp(0, 1)
            scored[name] = float(psnr(eye.double(), gt.double()))
    assert scored["white"] != pytest.approx(scored["black"], abs=1e-3)  # the background shows in this view
    assert float(r.per_view["ss"]["psnr"][0, 0, 0]) == pytest.approx(scored["white"], abs=1e-9)


def test_views_without_describe_and_refusals(tiny_adapter):
    model, views, path = tiny_adapter
    r = evaluate_grid(model, _Plain(views), {}, downsample=(1.0,), power_saving=(0.0,), baselines=(),
                      extra_metrics=False, progress=False)
    assert r.info == {"test_views": 2, "test_sizes": ["16x16"]}
    for bad, name in ((torch.zeros(2, 3, 16, 16), "Tensor"), ([views[0]], "list"), ([], "list")):
        with pytest.raises(InputValueError, match=rf"^views .*got {name}"):
            evaluate_grid(model, bad, {}, progress=False)

    class Empty(_Plain):
        def __len__(self) -> int:
            return 0

    with pytest.raises(InputValueError, match="^views .*got Empty"):
        evaluate_grid(model, Empty(views), {}, progress=False)
    with pytest.raises(InputValueError, match=r"^baselines .*got \['both'\]"):
        evaluate_grid(model, views, {}, baselines=("ss", "both"), progress=False)
    for name in ("ss", "no_ss", IDEAL):
        with pytest.raises(InputValueError, match=rf"adapter names \['{name}'\] clash"):
            evaluate_grid(model, views, {name: path}, progress=False)


def test_progress_bar_is_on_by_default_and_counts_every_scored_image(tiny_adapter, capsys, monkeypatch):
    """``evaluate_grid`` shows its bar ("evaluating grid", on stderr) unless ``progress=False``; the bar
    counts one step per scored image: views x d x rho x methods."""
    model, views, _ = tiny_adapter
    kw = dict(power_saving=(0.0,), baselines=("ss",), extra_metrics=False, effects=CHEAP)
    capsys.readouterr()
    evaluate_grid(model, views, {}, downsample=(1.0,), ideal=False, **kw)
    assert "evaluating grid" in capsys.readouterr().err
    evaluate_grid(model, views, {}, downsample=(1.0,), ideal=False, progress=False, **kw)
    assert "evaluating grid" not in capsys.readouterr().err
    bars = record_bars(monkeypatch, evaluation)
    evaluate_grid(model, views, {}, downsample=(1.0, 2.0), ideal=True, **kw)
    (bar,) = bars
    assert bar.total == bar.n == 8 and not bar.disable and bar.closed  # 2 views x 2 d x 1 rho x (ss + ideal)


# ------------------------------------------------------------------------------ scores and pipeline
def test_scores_clamp_the_eye_image():
    """A saturated eye image is clamped to [0, 1] (what the display can hold) before PSNR, SSIM and the extra
    metrics, which get float64 images."""
    gt = torch.full((3, 11, 11), 0.5)
    seen = []

    def extra(e: torch.Tensor, g: torch.Tensor) -> float:
        seen.append((e.dtype, g.dtype, float(e.max()), float(e.min())))
        return 7.0

    out = scores(gt + 1.2, gt, {"x": extra})  # clamped to 1: error 0.5 everywhere
    assert list(out) == ["psnr", "ssim", "x"] and out["x"] == 7.0
    assert out["psnr"] == pytest.approx(10 * math.log10(1 / 0.25), abs=1e-12)  # 6.0206 dB
    # constant images: no variance, SSIM = (2 * 1 * 0.5 + C1) / (1 + 0.25 + C1), C1 = 1e-4
    assert out["ssim"] == pytest.approx((1.0 + 1e-4) / (1.25 + 1e-4), abs=1e-12)
    assert seen == [(F64, F64, 1.0, 1.0)]
    assert scores(gt - 0.9, gt, {})["psnr"] == pytest.approx(10 * math.log10(4.0), abs=1e-12)  # clamped to 0
    # half the pixels overshoot (clamped to 1.0, error 0.1), a negative corner (clamped to 0, error 0.9)
    gt = torch.full((3, 16, 16), 0.9, dtype=F64)
    eye = gt.clone()
    eye[:, :8] = 1.4
    eye[0, 8:, :2] = -0.3
    err = torch.zeros(3, 16, 16, dtype=F64)
    err[:, :8] = 0.1
    err[0, 8:, :2] = 0.9
    got = scores(eye, gt, {})["psnr"]
    assert got == pytest.approx(10 * math.log10(1.0 / float((err ** 2).mean())), abs=1e-9)
    assert got == pytest.approx(16.60051938305649, abs=1e-9)  # = 10 log10(768 / 16.8)


def test_an_oled_off_eye_image_scores_as_box_pixels_at_full_size():
    """The scores of a pipeline without the ``oled`` stage (eye image at S/d) are those of the same pipeline
    with it (box emission to S is all that stage does), at every d."""
    g = torch.Generator().manual_seed(5)
    gt = torch.rand(3, 24, 24, generator=g)
    image = (gt + 0.1 * torch.randn(3, 24, 24, generator=g)).clamp(0, 1)
    on = make_pipeline({"resample": True, "display": True, "oled": True}).eval()
    off = make_pipeline({"resample": True, "display": True, "oled": False}).eval()
    for d, rho in ((1.0, 0.0), (2.0, 0.4), (3.0, 0.0)):
        state = RuntimeState(downsample=d, power_saving=rho)
        with torch.no_grad():
            e_on, e_off = on(image, state, reference=gt), off(image, state, reference=gt)
        assert e_off.shape[-1] == round(24 / d)
        want, got = scores(e_on, gt, {}), scores(e_off, gt, {})
        assert got == pytest.approx(want, rel=1e-6, abs=0)
        assert math.isfinite(got["psnr"]) and 0 < got["ssim"] < 1


def test_make_pipeline_defaults_and_modes():
    p = make_pipeline()
    assert not p.training and p["optics"].mode == "fast"
    assert [type(s).__name__ for s in p.stages] == [type(s).__name__ for s in _pipe().stages]
    assert make_pipeline(optics_mode="exact")["optics"].mode == "exact"
    q = make_pipeline({"lens": True, "display": True})
    assert "optics" not in q and "resample" not in q


# ------------------------------------------------------------------------------ GridResult
def test_grid_result_accessors():
    r = grid_result()
    assert r.methods == list(PSNR) and r.metrics == ["psnr", "flip"]
    assert torch.equal(r.grid("ss", "psnr"), torch.tensor(PSNR["ss"], dtype=F64))
    assert r.mean("ss", "psnr") == 19.0  # (20 + 22 + 18 + 16) / 4, views -1 / +1 cancel
    assert r.mean("no_ss", "psnr") == 18.25
    empty = GridResult(DOWNSAMPLE, POWER_SAVING)
    assert empty.metrics == [] and empty.methods == [] and empty.optics_mode == "fast" and empty.info == {}
    assert GRID_DOWNSAMPLE == (1.0, 2.0, 4.0, 8.0) and GRID_POWER_SAVING == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert BASELINES == ("no_ss", "ss") and IDEAL == "ideal"


def test_grid_result_equality_looks_at_every_part():
    a, b = grid_result(), grid_result()
    assert a == b and not (a != b)
    assert (a == 3) is False and a.__eq__(3) is NotImplemented
    for change in (lambda r: setattr(r, "optics_mode", "exact"), lambda r: r.info.update(x=1),
                   lambda r: setattr(r, "downsample", (1.0, 4.0)), lambda r: setattr(r, "power_saving", (0.0, 0.6)),
                   lambda r: r.per_view.pop("wo_lens"), lambda r: r.per_view["ss"].pop("flip"),
                   lambda r: r.per_view["ss"]["flip"].add_(1e-15)):
        c = grid_result()
        change(c)
        assert a != c and c != a


def test_grid_result_json_layout_and_round_trip():
    per_view = {"ss": {"psnr": torch.tensor([[[1.0, 3.0]]], dtype=F64)}}
    r = GridResult((2.0,), (0.4,), per_view, "exact", {"test_views": 2})
    assert r.to_json() == {"info": {"test_views": 2}, "downsample": [2.0], "power_saving": [0.4], "optics_mode": "exact",
                           "methods": {"ss": {"psnr": {"mean": 2.0, "grid": [[2.0]], "per_view": [[[1.0, 3.0]]]}}}}
    back = GridResult.from_json(r.to_json())
    assert back == r and back.per_view["ss"]["psnr"].dtype == F64
    # random values through a JSON text come back bit for bit; one changed by 1e-12 does not compare equal
    g = torch.Generator().manual_seed(1)
    per_view = {m: {"psnr": torch.rand(4, 5, 3, generator=g, dtype=F64) * 30,
                    "ssim": torch.rand(4, 5, 3, generator=g, dtype=F64)} for m in ("no_ss", "ss", "controlgs")}
    r = GridResult(GRID_DOWNSAMPLE, GRID_POWER_SAVING, per_view, "exact", {"test_views": 3, "test_sizes": ["48x27"]})
    back = GridResult.from_json(json.loads(json.dumps(r.to_json())))
    assert back == r and back.info == r.info and back.optics_mode == "exact"
    other = GridResult.from_json(r.to_json())
    other.per_view["ss"]["psnr"][0, 0, 0] += 1e-12
    assert back != other
    # optics mode and info may be missing (older files): "fast" and {}
    bare = GridResult.from_json({"downsample": [2], "power_saving": [0], "methods": {"ss": {"psnr": {"per_view": [[[5]]]}}}})
    assert (bare.optics_mode, bare.info, bare.downsample, bare.power_saving) == ("fast", {}, (2.0,), (0.0,))


def test_grid_result_from_json_refuses_what_is_not_one():
    for bad in ({"downsample": [1.0]}, {"downsample": [1.0], "power_saving": [0.0], "methods": {"ss": 3}},
                {"downsample": [1.0], "power_saving": ["x"], "methods": {}}):
        with pytest.raises(InputValueError, match="GridResult"):
            GridResult.from_json(bad)
    r = GridResult((2.0,), (0.4,), {"ss": {"psnr": torch.tensor([[[1.0, 3.0]]], dtype=F64)}})
    wrong = r.to_json()
    wrong["power_saving"] = [0.0, 0.4]  # [1, 2] grid, values [1, 1, 2]
    with pytest.raises(InputValueError, match=r"\['ss.psnr'\].*\[1, 2, V\]"):
        GridResult.from_json(wrong)
    flat = r.to_json()
    flat["methods"]["ss"]["psnr"]["per_view"] = [[1.0, 3.0]]  # 2-D
    with pytest.raises(InputValueError, match=r"\['ss.psnr'\]"):
        GridResult.from_json(flat)


needs_builtin_scene = pytest.mark.skipif(find_spec("skimage") is None,
                                         reason="the built-in scene's textures come from scikit-image")


# ------------------------------------------------------------------------------ the adapter in evaluation
@needs_builtin_scene
def test_grid_invariants_zero_adapter_equals_ss(tmp_path):
    """An adapter at initialisation (zero conditions) is the backbone: its grid equals the
    SS-backbone's exactly; at d = 1 the no-SS render is the SS render."""
    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    xyz, rgb = scene.points(0.3)
    with torch.random.fork_rng(devices=[]):  # decoder weights: a fixed draw whose Gaussians are visible
        torch.manual_seed(1)
        model = NeuralGaussianModel.from_points(xyz, rgb, feat_dim=8, n_offsets=2, voxel_size=0.4, color_fit_steps=10).eval()
        with torch.no_grad():
            model.mlp_opacity[2].bias.fill_(1.0)
    with torch.no_grad():
        assert float(model.render(scene.test_cameras[0]).alpha.mean()) > 0.05
    cgs = ControlGS.wrap(model, cond_dim=4)
    path = cgs.save(tmp_path / "zero.safetensors")
    cgs.unwrap()
    r = evaluate_grid(model, scene.views("test"), {"controlgs": path}, downsample=(1.0, 4.0),
                      power_saving=(0.0, 0.6), optics_mode="fast", extra_metrics=False, progress=False)
    for k in ("psnr", "ssim"):
        assert torch.equal(r.per_view["controlgs"][k], r.per_view["ss"][k])
        assert torch.equal(r.per_view["no_ss"][k][0], r.per_view["ss"][k][0])
        assert not torch.equal(r.per_view["no_ss"][k][1], r.per_view["ss"][k][1])


@needs_builtin_scene
def test_side_by_side_scores_against_the_unclamped_ground_truth(tiny, tmp_path):
    scene, model = tiny
    views = scene.data.views("train", first=1)
    cgs = ControlGS.wrap(model, cond_dim=4)
    path = cgs.save(tmp_path / "a.controlgs.safetensors")
    cgs.unwrap()
    cam, gt = views[0]
    bright = gt + 0.5  # a reference brighter than a display shows: only the eye image is clamped to [0, 1]
    assert float(bright.max()) > 1.2
    out = side_by_side(model, path, cam, bright, settings=[(1.0, 0.0)], background=views.background,
                       effects={"lens": True, "resample": True, "display": True})
    for method, row in out["rows"].items():
        _, eye, p, q = row[0]
        assert float(eye.max()) <= 1.0
        mse = float((eye.double() - bright.double()).square().mean())  # float64 PSNR against the unclamped gt
        assert p == pytest.approx(10 * math.log10(1.0 / mse), abs=1e-9), method
        assert q == pytest.approx(float(ssim(eye.double(), bright.double())), abs=1e-9), method
        clamped = float((eye.double() - bright.double().clamp(0, 1)).square().mean())
        assert abs(10 * math.log10(1.0 / clamped) - p) > 0.1  # the clamped reference would score differently


D, P = (1.0, 2.0), (0.0, 0.3, 0.6)


def _psnr64(eye: torch.Tensor, gt: torch.Tensor) -> float:
    mse = float((eye.clamp(0, 1).double() - gt.double()).square().mean())
    return 10 * math.log10(1.0 / mse)


@needs_builtin_scene
def test_every_cell_recomputed_by_hand(tiny_adapter):
    model, views, path = tiny_adapter
    r = evaluate_grid(model, views, {"mine": path}, downsample=(1, 2), power_saving=P, extra_metrics=False,
                      progress=False, effects=CHEAP)
    assert ControlGS.attached(model) is None  # the adapter is removed afterwards
    assert r.methods == ["no_ss", "ss", IDEAL, "mine"] and r.metrics == ["psnr", "ssim"]
    assert (r.downsample, r.power_saving, r.optics_mode) == (D, P, "fast")
    assert r.info == {"test_views": 2, "test_sizes": ["16x16"]}
    assert all(t.shape == (2, 3, 2) and t.dtype == torch.float64 for mv in r.per_view.values() for t in mv.values())
    pipe, bg = _pipe(effects=CHEAP), views.background
    cgs = ControlGS.load(path, model)
    try:
        with torch.no_grad():
            for v in range(2):
                cam, gt = views[v]
                for i, d in enumerate(D):
                    for j, rho in enumerate(P):
                        state = RuntimeState(downsample=d, power_saving=rho)
                        renders = {"no_ss": render_view(None, model, cam.scaled(d), None, bg),
                                   "ss": render_view(None, model, cam, None, bg), IDEAL: gt,
                                   "mine": render_view(cgs, model, cam, state, bg)}
                        for m, img in renders.items():
                            eye = pipe(img, state, reference=gt)
                            assert float(r.per_view[m]["psnr"][i, j, v]) == pytest.approx(_psnr64(eye, gt), abs=1e-9), (m, d, rho, v)
                            want_ssim = float(ssim(eye.clamp(0, 1).double(), gt.double()))
                            assert float(r.per_view[m]["ssim"][i, j, v]) == pytest.approx(want_ssim, abs=1e-12)
    finally:
        cgs.unwrap()
    # the adapter and the state matter: not the SS-backbone's numbers, not the same in every cell
    assert not torch.allclose(r.per_view["mine"]["psnr"], r.per_view["ss"]["psnr"])
    assert torch.equal(r.per_view["no_ss"]["psnr"][0], r.per_view["ss"]["psnr"][0])  # d = 1: the same render


@needs_builtin_scene
def test_side_by_side_by_hand(tiny_adapter):
    model, views, path = tiny_adapter
    cam, gt = views[0]
    out = side_by_side(model, path, cam, gt, background=views.background)
    assert ControlGS.attached(model) is None
    assert out["settings"] == [(1.0, 0.0), (8.0, 0.8)] and out["gt"] is gt
    assert list(out["rows"]) == ["no_ss", "ss", "controlgs"]
    pipe = _pipe()
    cgs = ControlGS.load(path, model)
    try:
        with torch.no_grad():
            for s, (d, rho) in enumerate(out["settings"]):
                state = RuntimeState(downsample=d, power_saving=rho)
                want = {"no_ss": render_view(None, model, cam.scaled(d), None, views.background),
                        "ss": render_view(None, model, cam, None, views.background),
                        "controlgs": render_view(cgs, model, cam, state, views.background)}
                for m, img in want.items():
                    rendered, eye, p, q = out["rows"][m][s]
                    assert torch.equal(rendered, img), (m, d)
                    ref = pipe(img, state, reference=gt).clamp(0, 1)
                    assert torch.allclose(eye, ref, atol=1e-6) and float(eye.min()) >= 0 and float(eye.max()) <= 1
                    assert p == pytest.approx(_psnr64(ref, gt), abs=1e-6)
                    assert q == pytest.approx(float(ssim(ref.double(), gt.double())), abs=1e-6)
    finally:
        cgs.unwrap()
    assert out["rows"]["no_ss"][1][0].shape == (3, 2, 2)  # rendered at 16 / 8
    one = side_by_side(model, path, cam, gt, settings=[(2, 0.5)], background=views.background)
    assert one["settings"] == [(2.0, 0.5)] and all(len(v) == 1 for v in one["rows"].values())


@needs_builtin_scene
def test_condition_response_by_hand(tiny_adapter):
    model, views, path = tiny_adapter
    cam, _ = views[0]
    bg = views.background
    strips = condition_response(model, path, cam, background=bg)
    assert ControlGS.attached(model) is None
    assert list(strips) == ["resample", "display", "lens"]
    assert [k for k, _ in strips["resample"]] == ["d=1", "d=2", "d=4", "d=8"]
    assert [k for k, _ in strips["display"]] == ["ρ=0%", "ρ=20%", "ρ=40%", "ρ=60%", "ρ=80%"]
    assert [k for k, _ in strips["lens"]] == ["off", "on", "|on - off| x 10"]
    cgs = ControlGS.load(path, model)
    try:
        with torch.no_grad():
            for (_, img), d in zip(strips["resample"], (1.0, 2.0, 4.0, 8.0)):
                assert torch.equal(img, render_view(cgs, model, cam, RuntimeState(downsample=d), bg, modules=("resample",)))
            for (_, img), rho in zip(strips["display"], (0.0, 0.2, 0.4, 0.6, 0.8)):
                assert torch.equal(img, render_view(cgs, model, cam, RuntimeState(power_saving=rho), bg, modules=("display",)))
            off = render_view(None, model, cam, None, bg)
            on = render_view(cgs, model, cam, RuntimeState(), bg, modules=("lens",))
    finally:
        cgs.unwrap()
    assert torch.equal(strips["lens"][0][1], off) and torch.equal(strips["lens"][1][1], on)
    diff = strips["lens"][2][1]
    assert torch.allclose(diff, ((on - off).abs() * 10).clamp(0, 1)) and float(diff.max()) > 0
    # the strips differ along d (the adapter is not zero)
    assert not torch.equal(strips["resample"][0][1], strips["resample"][3][1])
    assert not torch.equal(strips["display"][0][1], strips["display"][4][1])


@needs_builtin_scene
def test_an_adapter_with_fewer_modules_shows_only_those(tiny_adapter, tmp_path: Path):
    model, views, _ = tiny_adapter
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=2)
    path = cgs.save(tmp_path / "d.controlgs.safetensors")
    cgs.unwrap()
    strips = condition_response(model, path, views[0][0], background=views.background)
    assert list(strips) == ["display"]


def test_make_pipeline_sets_each_optics_mode():
    if "optics" not in plugins.stages():
        pytest.skip("optics stage not registered")
    for mode in ("distortion", "fast", "exact"):
        assert make_pipeline({"optics": True}, mode)["optics"].mode == mode


# ------------------------------------------------------------------------------ seeds (the demo's evaluation)
def test_evaluate_seeds_shares_the_baselines(tiny_adapter, tmp_path):
    from controlgs_adapter.commands.demo import evaluate_seeds, report_figures

    model, views, path = tiny_adapter
    zero = ControlGS.wrap(model, cond_dim=4)
    zpath = zero.save(tmp_path / "zero.controlgs.safetensors")
    zero.unwrap()
    kw = dict(downsample=(2.0,), power_saving=(0.6,), extra_metrics=False, progress=False, effects=CHEAP)
    runs = evaluate_seeds(model, views, {4: {"controlgs": path}, 7: {"controlgs": zpath}}, **kw)
    assert [r.info["seed"] for r in runs] == [4, 7] and [r.methods for r in runs] == [["no_ss", "ss", IDEAL, "controlgs"]] * 2
    for m in ("no_ss", "ss", IDEAL):  # evaluated once, the same numbers in both seeds
        assert runs[1].per_view[m] is runs[0].per_view[m]
    # each seed's own adapter: the zero one renders as the backbone (SS), the other does not
    assert torch.equal(runs[1].per_view["controlgs"]["psnr"], runs[0].per_view["ss"]["psnr"])
    assert not torch.equal(runs[0].per_view["controlgs"]["psnr"], runs[0].per_view["ss"]["psnr"])
    alone = evaluate_grid(model, views, {"controlgs": path}, **kw)
    assert torch.equal(alone.per_view["controlgs"]["psnr"], runs[0].per_view["controlgs"]["psnr"])
    comparison, response = report_figures(model, path, views, effects=CHEAP, optics_mode="fast")
    cam, gt = views[0]
    assert torch.equal(comparison["gt"], gt) and list(response) == ["resample", "display", "lens"]
    assert torch.equal(response["lens"][0][1], render_view(None, model, cam, None, views.background))


# ------------------------------------------------------------------------------ the foveation axis
#: an affine lens: chief rays G(d) = A d, seen at tan(angle) = G * radians(DPU) per axis (square display)
AFFINE, DPU = [[0.8, 0.1], [0.0, 0.6]], 30.0
FOVEATED = {**CHEAP, "foveation": True}


def _affine_angles() -> VisualAngles:
    bank = affine_bank(AFFINE, [0.0, 0.0])
    bank.meta["lens"]["deg_per_output_unit"] = DPU
    return VisualAngles.of_bank(bank)


def test_band_masks_match_the_hand_eccentricities_of_an_affine_lens():
    """Each pixel centre d of a 64 x 48 image ("fit" on the square display: |y| <= 0.75) is seen along
    (tan az, tan el) = A d radians(DPU); its eccentricity from the gaze is the angle between the two direction
    vectors, banded < 5, 5-15, >= 15 degrees. Pixels within 1e-3 deg of a boundary (float32 chief rays) are skipped."""
    h, w, gaze = 48, 64, (5.0, -3.0)
    x = (2 * torch.arange(w, dtype=F64) + 1) / w - 1
    y = ((2 * torch.arange(h, dtype=F64) + 1) / h - 1) * h / w
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    a = torch.tensor(AFFINE, dtype=F64)
    t = torch.stack([xx, yy], -1) @ a.T * math.radians(DPU)
    u = torch.cat([t, torch.ones(h, w, 1, dtype=F64)], -1)
    g = torch.tensor([math.tan(math.radians(gaze[0])), math.tan(math.radians(gaze[1])), 1.0], dtype=F64)
    ecc = torch.rad2deg(torch.acos((u @ g / (u.norm(dim=-1) * g.norm())).clamp(-1, 1)))
    want = torch.stack([ecc < 5, (ecc >= 5) & (ecc < 15), ecc >= 15])
    got = evaluation.band_masks(_affine_angles(), h, w, gaze)
    assert got.shape == (3, h, w) and got.dtype == torch.bool
    clear = ((ecc - 5).abs() > 1e-3) & ((ecc - 15).abs() > 1e-3)
    assert bool(clear.all()) and torch.equal(got, want)
    assert all(int(m.sum()) > 0 for m in want)  # every band is exercised
    assert torch.equal(got.sum(0), torch.ones(h, w, dtype=torch.long))  # the bands partition the image


def test_band_scores_are_the_masked_brute_force_psnr_and_skimage_ssim():
    """PSNR of a band: 10 log10(1 / MSE) over its pixels and channels (a float64 loop); SSIM of a band: skimage's
    SSIM map (Gaussian 1.5, population covariance), mean over channels, averaged over the band's pixels whose
    11 x 11 window lies inside the image. A band without pixels is NaN, not 0."""
    from skimage.metrics import structural_similarity

    g = torch.Generator().manual_seed(5)
    gt = torch.rand(3, 20, 24, generator=g, dtype=F64)
    eye = (gt + 0.2 * torch.randn(3, 20, 24, generator=g, dtype=F64)).clamp(0, 1)
    masks = torch.zeros(3, 20, 24, dtype=torch.bool)
    masks[0, 2:9, 3:20] = True   # partly in the border (no window there)
    masks[1, 9:, :] = True
    got = evaluation.band_scores(eye, gt, masks, ["a", "b", "empty"])
    _, smap = structural_similarity(eye.permute(1, 2, 0).numpy(), gt.permute(1, 2, 0).numpy(), channel_axis=2,
                                    gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=1.0,
                                    full=True)
    smap = torch.from_numpy(smap).mean(-1)
    for name, m in (("a", 0), ("b", 1)):
        sq, n = 0.0, 0
        for c in range(3):
            for i in range(20):
                for j in range(24):
                    if masks[m, i, j]:
                        sq, n = sq + float(eye[c, i, j] - gt[c, i, j]) ** 2, n + 1
        assert got[f"psnr_{name}"] == pytest.approx(10 * math.log10(n / sq), abs=1e-10)
        inner = torch.zeros_like(masks[m])
        inner[5:-5, 5:-5] = masks[m, 5:-5, 5:-5]
        assert got[f"ssim_{name}"] == pytest.approx(float(smap[inner].mean()), abs=1e-6)
    assert math.isnan(got["psnr_empty"]) and math.isnan(got["ssim_empty"])
    border = torch.zeros_like(masks)
    border[0, :3] = True  # pixels, but no window centred on them
    only = evaluation.band_scores(eye, gt, border, ["edge", "x", "y"])
    assert math.isfinite(only["psnr_edge"]) and math.isnan(only["ssim_edge"])


def test_the_foveation_axis_appears_only_with_the_foveation_effect(tiny_adapter):
    """Without the stage: no axis. With it: the gazes x settings for the SS-backbone, the ideal render and the
    adapters but the ablations other than wo_foveation; the whole-image score is the stage's eye image's, and the
    bands partition it (the whole MSE is the pixel-weighted mean of the bands')."""
    model, views, path = tiny_adapter
    kw = dict(downsample=(2.0,), power_saving=(0.0,), extra_metrics=False, progress=False)
    adapters = {"controlgs": path, "wo_lens": path, "wo_foveation": path}
    assert evaluate_grid(model, views, {}, effects=CHEAP, **kw).foveation is None
    gazes, settings = [(0.0, 0.0), (10.0, 0.0)], [(2.0, 0.4)]
    r = evaluate_grid(model, views, adapters, effects=FOVEATED, gazes=gazes, foveation_settings=settings, **kw)
    fov = r.foveation
    assert fov is not None and fov.gazes == ((0.0, 0.0), (10.0, 0.0)) and fov.settings == ((2.0, 0.4),)
    assert list(fov.per_view) == ["ss", IDEAL, "controlgs", "wo_foveation"] and r.methods[-3:] == list(adapters)
    assert fov.model == {"omega0": 1 / 60, "slope": 0.022, "max_scale": None}
    assert fov.per_view["ss"]["psnr_foveal"].shape == (2, 1, len(views))
    pipe = make_pipeline(FOVEATED)
    cam, gt = views[1]
    state = RuntimeState(downsample=2.0, power_saving=0.4, gaze=(10.0, 0.0))
    with torch.no_grad():
        eye = pipe(render_view(None, model, cam, None, views.background), state, reference=gt)
    assert float(fov.per_view["ss"]["psnr"][1, 0, 1]) == pytest.approx(scores(eye, gt, {})["psnr"], abs=1e-12)
    masks = evaluation.band_masks(pipe["foveation"].angles, gt.shape[-2], gt.shape[-1], (10.0, 0.0))
    mse = sum(int(m.sum()) * 10 ** (-float(fov.per_view["ss"][f"psnr_{b}"][1, 0, 1]) / 10)
              for m, b in zip(masks, ("foveal", "parafoveal", "periphery")) if m.any()) / masks[0].numel()
    assert -10 * math.log10(mse) == pytest.approx(float(fov.per_view["ss"]["psnr"][1, 0, 1]), abs=1e-9)
    # the default gazes; the axis round-trips through JSON, a band without pixels as null
    d = evaluate_grid(model, views, {}, effects=FOVEATED, baselines=(), foveation_settings=settings, **kw)
    assert d.foveation is not None and d.foveation.gazes == evaluation.FOVEATION_GAZES
    data = json.loads(json.dumps(d.to_json()))
    assert GridResult.from_json(data) == d
    assert None in data["foveation"]["methods"][IDEAL]["ssim_foveal"]["per_view"][1][0]  # 16 px: no window < 5 deg off axis


def test_foveation_axis_refusals_before_any_render(tiny_adapter):
    model, views, path = tiny_adapter
    kw = dict(downsample=(2.0,), power_saving=(0.0,), extra_metrics=False, progress=False, effects=FOVEATED)
    with pytest.raises(InputValueError, match=r"^gaze \(40, 0\) deg is outside the lens's field"):
        evaluate_grid(model, views, {"controlgs": "/nonexistent"}, gazes=[(40.0, 0.0)], **kw)
    with pytest.raises(InputValueError, match=r"^gazes must be a non-empty list of"):
        evaluate_grid(model, views, {}, gazes=[(1.0,)], **kw)
    with pytest.raises(InputValueError, match=r"^foveation_settings must be a non-empty list of finite"):
        evaluate_grid(model, views, {}, foveation_settings=[], **kw)


def test_evaluate_seeds_shares_the_foveation_baselines(tiny_adapter):
    from controlgs_adapter.commands.demo import evaluate_seeds

    model, views, path = tiny_adapter
    kw = dict(downsample=(2.0,), power_saving=(0.0,), extra_metrics=False, progress=False, effects=FOVEATED,
              gazes=[(10.0, 0.0)], foveation_settings=[(2.0, 0.4)])
    runs = evaluate_seeds(model, views, {1: {"controlgs": path}, 2: {"controlgs": path}}, **kw)
    a, b = runs[0].foveation, runs[1].foveation
    assert a is not None and b is not None and list(b.per_view) == ["ss", IDEAL, "controlgs"]
    assert b.per_view["ss"] is a.per_view["ss"] and b.per_view[IDEAL] is a.per_view[IDEAL]
    assert a == b  # the same adapter in both seeds: the same numbers
