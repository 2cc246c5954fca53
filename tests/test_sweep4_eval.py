"""Mutation audit (sweep 4) of the evaluation side: metrics, LPIPS, the grid evaluation, the report and
the distributed helpers. Each test pins one behaviour that a plausible one-line bug would change and
that no other test observed: where a computation's device comes from, which argument an error names,
the hints of a refusal, that LPIPS is frozen, ... (docs/testing.md)."""

from __future__ import annotations

import struct
import sys
from pathlib import Path

import pytest
import torch

from controlgs_adapter.errors import InputValueError, ShapeError
from controlgs_adapter.evaluation import IDEAL, GridResult, evaluate_grid, make_pipeline
from controlgs_adapter.metrics import flip
from controlgs_adapter.perceptual import LPIPS, _expected
from controlgs_adapter.report import markdown_tables, plot_heatmaps
from controlgs_adapter.state import Camera, RuntimeState

from _two_ranks import peer_rank


def _lpips_weights(seed: int = 0) -> dict[str, torch.Tensor]:
    """Random AlexNet + head tensors of the shapes LPIPS expects (head weights >= 0, as LPIPS' are)."""
    g = torch.Generator().manual_seed(seed)
    w = {k: (torch.rand(s, generator=g) - 0.3) * 0.1 for k, s in _expected().items()}
    for i in range(5):
        w[f"lin{i}"] = w[f"lin{i}"].abs()
    return w


# ------------------------------------------------------------------------------ metrics
def test_flip_refusals_name_test_and_reference():
    """FLIP's shape refusals name its own arguments, ``test`` first (its other refusals already do)."""
    a, b = torch.rand(3, 12, 12), torch.rand(3, 12, 13)
    with pytest.raises(ShapeError, match=r"^test and reference must have the same shape, got \[3, 12, 12\] and \[3, 12, 13\]"):
        flip(a, b)
    with pytest.raises(ShapeError, match=r"^test and reference must have the same shape, got \[3, 12, 13\] and \[3, 12, 12\]"):
        flip(b, a)
    with pytest.raises(Exception, match="^reference"):
        flip(a, torch.rand(2, 12, 12))
    with pytest.raises(Exception, match="^test"):
        flip(torch.rand(2, 12, 12), a)


def test_flip_without_its_package_says_how_to_install_it(monkeypatch):
    """Without ``flip-evaluator`` importable, FLIP is refused with the install line (not a NameError)."""
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # what Python does for a package that is absent
    x = torch.rand(3, 8, 8)
    with pytest.raises(InputValueError, match=r"^FLIP needs the flip-evaluator package .*: pip install flip-evaluator$"):
        flip(x, x)


def test_flip_takes_any_positive_pixels_per_degree():
    """``ppd`` must be > 0 (documented refusal); an observer below one pixel per degree is still one: FLIP
    at ppd 0.5 and 1 is the package's own value there."""
    import flip_evaluator

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(3, 12, 12, generator=g, dtype=torch.float64), torch.rand(3, 12, 12, generator=g, dtype=torch.float64)
    hwc = lambda t: t.permute(1, 2, 0).contiguous().numpy()  # noqa: E731
    for ppd in (0.5, 1.0):
        want = float(flip_evaluator.evaluate(hwc(b), hwc(a), "LDR", applyMagma=False, parameters={"ppd": ppd})[1])
        assert flip(a, b, ppd=ppd) == pytest.approx(want, abs=1e-9)


# ------------------------------------------------------------------------------ LPIPS
def test_lpips_missing_both_parts_hints_at_both_files():
    """Weights missing backbone and head tensors alike: the refusal points at both files to get."""
    w = _lpips_weights()
    del w["conv0.weight"], w["lin3"]
    with pytest.raises(InputValueError) as e:
        LPIPS(w, "mix.pth")
    msg = str(e.value)
    assert msg.startswith("LPIPS weights mix.pth: missing ['conv0.weight', 'lin3']")
    assert "(the AlexNet backbone: torchvision's alexnet-owt-7be5be79.pth)" in msg
    assert "(the LPIPS head: the lpips package's weights/v0.1/alex.pth; pip install --no-deps lpips)" in msg


def test_lpips_is_frozen_even_from_weights_that_require_grad():
    """LPIPS is documented as frozen: weights taken from a trainable module (parameters that require
    grad) become plain buffers, so the distance of two constant images carries no graph."""
    w = {k: torch.nn.Parameter(v) for k, v in _lpips_weights(1).items()}
    net = LPIPS(w)
    assert not any(b.requires_grad for b in net.buffers())
    assert [p for p in net.parameters()] == []
    x, y = torch.rand(1, 3, 31, 31), torch.rand(1, 3, 31, 31)
    out = net(x, y)
    assert not out.requires_grad and out.grad_fn is None
    # the image being scored still gets its gradient
    xr = x.clone().requires_grad_(True)
    net(xr, y).sum().backward()
    assert xr.grad is not None and all(p.grad is None for p in w.values())


# ------------------------------------------------------------------------------ evaluation
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


def test_evaluate_grid_scores_lpips_with_the_network_it_is_given():
    """``evaluate_grid(..., lpips=net)`` adds an ``lpips`` metric: ``net`` of each clamped eye image
    against its ground truth (here the ideal render, the ground truth through the display stage)."""
    net = LPIPS(_lpips_weights(2))
    views = _GroundTruths()
    effects = {"display": True}
    r = evaluate_grid(torch.nn.Linear(1, 1), views, {}, effects=effects, downsample=(1.0,), power_saving=(0.0, 0.6),
                      baselines=(), lpips=net, progress=False, renderer=lambda *a, **k: None)
    assert r.methods == [IDEAL] and r.metrics == ["psnr", "ssim", "flip", "lpips"]
    pipe = make_pipeline(effects)
    with torch.no_grad():
        for j, rho in enumerate((0.0, 0.6)):
            for v in range(2):
                gt = views[v][1]
                eye = pipe(gt, RuntimeState(power_saving=rho), reference=gt).clamp(0, 1)
                want = float(net(eye.double(), gt.double()))
                assert float(r.per_view[IDEAL]["lpips"][0, j, v]) == pytest.approx(want, rel=1e-6, abs=1e-9)
    assert float(r.per_view[IDEAL]["lpips"][0, 1].min()) > 0  # dimmed: a distance, not 0



class _OnWhite:
    """The first view of a dataset, its renders to be made on a white background."""

    background = torch.ones(3)

    def __init__(self, views) -> None:
        self.view = views[0]

    def __len__(self) -> int:
        return 1

    def __getitem__(self, i: int):
        return self.view


def test_evaluate_grid_renders_on_the_views_background(tiny):
    """``evaluate_grid`` renders on ``views.background`` (documented: "its background is the renders'"):
    the SS-backbone's score is that of the render on white, which differs from the model's own black."""
    from controlgs_adapter.metrics import psnr
    from controlgs_adapter.rendering.protocol import render_view

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


# ------------------------------------------------------------------------------ report
def _cell(v: float) -> torch.Tensor:
    return torch.full((1, 1, 1), v, dtype=torch.float64)


def test_no_difference_and_no_spread_is_within_the_spread():
    """A difference "exceeds the spread" only when strictly larger than SPREAD_FACTOR pooled std (the
    report's own wording): two seeds where ControlGS equals the SS-backbone exactly, with no spread at all,
    show a difference of 0 *within* the spread, not exceeding it."""
    runs = [GridResult((1.0,), (0.0,), {"ss": {"psnr": _cell(20.0)}, "controlgs": {"psnr": _cell(20.0)}},
                       info={"seed": k}) for k in range(2)]
    md = markdown_tables(runs)
    assert "- ControlGS minus SS-backbone: PSNR +0 (within the spread, pooled std 0)." in md
    assert "larger than 2 x the pooled std" in md


def test_heatmap_colour_scale_is_centred_on_zero_for_one_sided_differences(tmp_path: Path):
    """Each heatmap panel's colour scale runs from -L to +L (L the largest |difference|), so that zero is the
    neutral middle even when every difference has one sign: with PSNR differences of +10 / +5 dB the +5 cells
    are RdBu at 0.75, and with SSIM differences of -10 / -5 the -5 cells are RdBu at 0.25 (an automatic
    range would put the +5 / -5 cells at the ends of the scale)."""
    import matplotlib
    import matplotlib.image

    half = torch.tensor([[10.0, 5.0], [5.0, 10.0]], dtype=torch.float64)[..., None]
    base = torch.full((2, 2, 1), 20.0, dtype=torch.float64)
    r = GridResult((1.0, 2.0), (0.0, 0.2), {"ss": {"psnr": base, "ssim": base},
                                            "controlgs": {"psnr": base + half, "ssim": base - half}})
    img = torch.from_numpy(matplotlib.image.imread(plot_heatmaps(r, tmp_path / "h.png")))[..., :3].double()

    def count(at: float) -> int:
        colour = torch.tensor(matplotlib.colormaps["RdBu"](at)[:3], dtype=torch.float64)
        return int(((img - colour).abs().amax(-1) < 0.02).sum())

    # two cells of about 100 x 100 px each (less their labels); a colour bar holds a few hundred at most
    assert count(0.75) > 6000 and count(0.25) > 6000, (count(0.75), count(0.25))


def test_heatmap_figure_grows_with_its_panels(tmp_path: Path):
    """One panel per metric and one row per baseline, each the same size: two metrics and two rows
    (SS-backbone and the ideal render) make a figure twice as wide and twice as tall as one of each."""
    def size(methods: tuple[str, ...], metrics: tuple[str, ...], name: str) -> tuple[int, int]:
        r = GridResult((1.0,), (0.0,), {m: {k: _cell(float(i)) for k in metrics} for i, m in enumerate(methods)})
        head = plot_heatmaps(r, tmp_path / name).read_bytes()[:24]
        return struct.unpack(">II", head[16:24])  # the PNG's IHDR: width, height

    w1, h1 = size(("ss", "controlgs"), ("psnr",), "one.png")
    w2, h2 = size(("ss", "controlgs", IDEAL), ("psnr", "flip"), "four.png")
    assert (w2, h2) == (2 * w1, 2 * h1) and w1 > 0 and h1 > 0


# ------------------------------------------------------------------------------ distributed
_RANK1 = """
import os, sys, torch
from torch import nn
from controlgs_adapter.distributed import init_distributed
os.environ.update({"RANK": "1", "WORLD_SIZE": "2", "LOCAL_RANK": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": sys.argv[1]})
with init_distributed("gloo", timeout=60.0, exchange="sparse") as ctx:
    t = nn.Parameter(torch.zeros(3, 2))
    t.grad = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, -1.0]])
    ctx.sync_gradients([t], row_sparse=[t], step=2)
"""


def test_sparse_exchange_sends_rows_that_are_only_partly_non_zero(monkeypatch):
    """A row of a row-sparse gradient is "touched" when any of its entries is non-zero: two real gloo ranks
    whose only gradient rows are half zero ([0.5, 0] on rank 0, [0, -1] on rank 1) end with their sum,
    not with a zero gradient, and each rank counts its one row."""
    from controlgs_adapter.distributed import init_distributed

    with peer_rank(monkeypatch, _RANK1), init_distributed("gloo", timeout=60.0, exchange="sparse") as ctx:
        t = torch.nn.Parameter(torch.zeros(3, 2))
        t.grad = torch.tensor([[0.5, 0.0], [0.0, 0.0], [0.0, 0.0]])
        ctx.sync_gradients([t], row_sparse=[t], step=2)
        last = dict(ctx.stats.last)
    assert torch.equal(t.grad, torch.tensor([[0.5, 0.0], [0.0, 0.0], [0.0, -1.0]]))
    assert last["rows"] == 1 and last["exchange"] == "sparse"
