"""controlgs_adapter.evaluation wired by hand: every (method, d, rho, view) cell of a 2 x 3 grid on
two views recomputed here (each render, the state, a pipeline built afresh, PSNR in float64), with
a non-zero adapter so that a wrong state or render would change the numbers; the comparison figure
and the condition strips likewise; every refusal of ``evaluate_grid``."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from controlgs_adapter import ControlGS
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import (IDEAL, condition_response, evaluate_grid, make_pipeline, side_by_side)
from controlgs_adapter.metrics import flip, ssim
from controlgs_adapter.rendering.protocol import render_view
from controlgs_adapter.state import RuntimeState
from controlgs_adapter.training import DEFAULT_EFFECTS

D, P = (1.0, 2.0), (0.0, 0.3, 0.6)


@pytest.fixture(scope="module")
def setup(tiny, tmp_path_factory):
    """The tiny scene's first two training views and an adapter file with random (non-zero) conditions."""
    scene, model = tiny
    views = scene.data.views("train", first=2)
    cgs = ControlGS.wrap(model, cond_dim=4)
    with torch.no_grad(), torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        for p in cgs.trainable_parameters():
            p.add_(0.5 * torch.randn_like(p))
    path = cgs.save(tmp_path_factory.mktemp("adapter") / "a.controlgs.safetensors")
    cgs.unwrap()
    return model, views, path


#: the cheap downstream path (no optics) of the every-cell test
CHEAP = {"lens": True, "resample": True, "display": True}


def _pipe(mode: str = "fast", effects: dict | None = None) -> Pipeline:
    pipe = Pipeline.from_config(dict(DEFAULT_EFFECTS if effects is None else effects))
    if "optics" in pipe:
        pipe["optics"].mode = mode
    return pipe.eval()


def _psnr64(eye: torch.Tensor, gt: torch.Tensor) -> float:
    mse = float((eye.clamp(0, 1).double() - gt.double()).square().mean())
    return 10 * math.log10(1.0 / mse)


def test_every_cell_recomputed_by_hand(setup):
    model, views, path = setup
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


def test_baselines_ideal_and_extra_metrics_options(setup):
    model, views, path = setup
    r = evaluate_grid(model, views, {}, downsample=(2.0,), power_saving=(0.6,), baselines=("ss",), ideal=False,
                      progress=False, optics_mode="distortion")
    assert r.methods == ["ss"] and r.metrics == ["psnr", "ssim", "flip"] and r.optics_mode == "distortion"
    cam, gt = views[1]
    with torch.no_grad():
        eye = _pipe("distortion")(render_view(None, model, cam, None, views.background),
                                  RuntimeState(downsample=2.0, power_saving=0.6), reference=gt)
    assert float(r.per_view["ss"]["flip"][0, 0, 1]) == pytest.approx(flip(eye.clamp(0, 1).double(), gt.double()), abs=1e-9)
    assert float(r.per_view["ss"]["psnr"][0, 0, 1]) == pytest.approx(_psnr64(eye, gt), abs=1e-9)
    only = evaluate_grid(model, views, {}, downsample=(1.0,), power_saving=(0.0,), baselines=("no_ss",),
                         extra_metrics=False, progress=False)
    assert only.methods == ["no_ss", IDEAL]
    # the default grid is the paper's 4 x 5
    none = evaluate_grid(model, views, {}, baselines=(), extra_metrics=False, progress=False)
    assert none.downsample == (1.0, 2.0, 4.0, 8.0) and none.power_saving == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert none.methods == [IDEAL]


class _Plain:
    """A Views dataset with nothing but the protocol (no describe)."""

    def __init__(self, views):
        self.inner, self.background = views, views.background

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i: int):
        return self.inner[i]


def test_views_without_describe_and_refusals(setup):
    model, views, path = setup
    r = evaluate_grid(model, _Plain(views), {}, downsample=(1.0,), power_saving=(0.0,), baselines=(),
                      extra_metrics=False, progress=False)
    assert r.info == {"test_views": 2, "test_sizes": ["16x16"]}
    for bad in (torch.zeros(2, 3, 16, 16), [views[0]], []):
        with pytest.raises(InputValueError, match="views must be a non-empty dataset of \\(camera, image\\)"):
            evaluate_grid(model, bad, {}, progress=False)

    class Empty(_Plain):
        def __len__(self) -> int:
            return 0

    with pytest.raises(InputValueError, match="got Empty"):
        evaluate_grid(model, Empty(views), {}, progress=False)
    with pytest.raises(InputValueError, match=r"baselines must be among \('no_ss', 'ss'\), got \['both'\]"):
        evaluate_grid(model, views, {}, baselines=("ss", "both"), progress=False)
    for name in ("ss", "no_ss", IDEAL):
        with pytest.raises(InputValueError, match=rf"adapter names \['{name}'\] clash with the baselines"):
            evaluate_grid(model, views, {name: path}, progress=False)


def test_make_pipeline_defaults_and_modes():
    p = make_pipeline()
    assert not p.training and p["optics"].mode == "fast"
    assert [type(s).__name__ for s in p.stages] == [type(s).__name__ for s in _pipe().stages]
    assert make_pipeline(optics_mode="exact")["optics"].mode == "exact"
    q = make_pipeline({"lens": True, "display": True})
    assert "optics" not in q and "resample" not in q


def test_side_by_side_by_hand(setup):
    model, views, path = setup
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


def test_condition_response_by_hand(setup):
    model, views, path = setup
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


def test_an_adapter_with_fewer_modules_shows_only_those(setup, tmp_path: Path):
    model, views, _ = setup
    cgs = ControlGS.wrap(model, modules=("display",), cond_dim=2)
    path = cgs.save(tmp_path / "d.controlgs.safetensors")
    cgs.unwrap()
    strips = condition_response(model, path, views[0][0], background=views.background)
    assert list(strips) == ["display"]


def test_evaluate_seeds_shares_the_baselines(setup, tmp_path: Path):
    from controlgs_adapter.commands.demo import evaluate_seeds, report_figures

    model, views, path = setup
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


def test_make_renderer_of_the_options(setup):
    import argparse

    from controlgs_adapter.commands.common import RasterizerRenderer, make_renderer

    model, views, _ = setup
    ns = lambda **kw: argparse.Namespace(**{"rasterizer": None, "renderer": None, **kw})  # noqa: E731
    assert make_renderer(ns(), model) is None and make_renderer(ns(rasterizer="auto"), model) is None
    r = make_renderer(ns(rasterizer="torch"), model)
    assert isinstance(r, RasterizerRenderer) and r.rasterizer == "torch"
    cam, _ = views[0]
    with torch.no_grad():
        assert torch.equal(render_view(None, model, cam, None, views.background, renderer=r),
                           render_view(None, model, cam, None, views.background))
    with pytest.raises(InputValueError, match=r"--rasterizer gsplat cannot render on cpu: .*; it needs --device cuda "
                                              r"and the gsplat extra: pip install 'controlgs-adapter\[gsplat\]'"):
        make_renderer(ns(rasterizer="gsplat"), model)
    with pytest.raises(InputValueError, match="--rasterizer 'nope' is not registered; available: gsplat, torch, auto"):
        make_renderer(ns(rasterizer="nope"), model)


def test_progress_bar_counts_every_scored_image(setup, capsys):
    model, views, _ = setup
    evaluate_grid(model, views, {}, downsample=(1.0, 2.0), power_saving=(0.0,), baselines=("ss",), ideal=True,
                  extra_metrics=False, effects=CHEAP, progress=True)
    err = capsys.readouterr().err
    assert "evaluating grid" in err and "8/8" in err  # 2 views x 2 d x 1 rho x (ss + ideal)
    evaluate_grid(model, views, {}, downsample=(1.0,), power_saving=(0.0,), baselines=("ss",), extra_metrics=False,
                  effects=CHEAP, progress=False)
    assert "evaluating grid" not in capsys.readouterr().err


def test_anchor_positions_are_plain_cpu_values(setup):
    from controlgs_adapter.commands.common import anchor_positions

    model, _, _ = setup
    pos = anchor_positions(model)
    assert pos.dtype == torch.float32 and pos.device.type == "cpu" and pos.shape[1] == 3
    assert not pos.requires_grad and pos.grad_fn is None  # no autograd graph back into the model
    assert anchor_positions(object()) is None  # no backend recognises it
