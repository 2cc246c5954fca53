"""Tests of ``controlgs_adapter.evaluation``."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import pytest
import torch

from controlgs_adapter import ControlGS, RuntimeState
from controlgs_adapter.backends.models.reference_model import NeuralGaussianModel
from controlgs_adapter.downstream.pipeline import Pipeline
from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import (
    BASELINES,
    GRID_DOWNSAMPLE,
    GRID_POWER_SAVING,
    IDEAL,
    GridResult,
    evaluate_grid,
    make_pipeline,
    scores,
)
from controlgs_adapter.metrics import flip, ssim
from controlgs_adapter.perceptual import LPIPS, _expected
from controlgs_adapter.rendering.protocol import render_view
from controlgs_adapter.report import markdown_tables, plot_heatmaps, seed_summary
from controlgs_adapter.state import Camera
from controlgs_adapter.training import DEFAULT_EFFECTS

pytest.importorskip("skimage")

pytest.importorskip("matplotlib")



def test_markdown_tables_state_what_was_measured():
    g = torch.Generator().manual_seed(0)
    per_view = {m: {"psnr": torch.rand(4, 5, 2, generator=g, dtype=torch.float64) * 5 + 20,
                    "ssim": torch.rand(4, 5, 2, generator=g, dtype=torch.float64)} for m in ("no_ss", "ss", "controlgs")}
    per_view["controlgs"]["psnr"][0, 0] = per_view["ss"]["psnr"][0, 0] - 1.0  # one losing cell
    per_view["controlgs"]["psnr"][1:] = per_view["ss"]["psnr"][1:] + 0.5
    per_view["controlgs"]["psnr"][0, 1:] = per_view["ss"]["psnr"][0, 1:] + 0.5
    r = GridResult((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8), per_view)
    md = markdown_tables(r)
    assert "ControlGS better than SS-backbone in 19/20 settings" in md
    want = f"{r.mean('controlgs', 'psnr'):.2f}"
    assert f"| ControlGS | {want}" in md or f"| ControlGS | **{want}**" in md


def test_grid_result_json_round_trip_is_exact(tmp_path):
    g = torch.Generator().manual_seed(1)
    per_view = {m: {"psnr": torch.rand(4, 5, 3, generator=g, dtype=torch.float64) * 30,
                    "ssim": torch.rand(4, 5, 3, generator=g, dtype=torch.float64)} for m in ("no_ss", "ss", "controlgs")}
    r = GridResult((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8), per_view, "exact",
                   {"test_views": 3, "test_sizes": ["48x27"]})
    back = GridResult.from_json(json.loads(json.dumps(r.to_json())))
    assert back == r and back.info == r.info and back.optics_mode == "exact"
    other = GridResult.from_json(r.to_json())
    other.per_view["ss"]["psnr"][0, 0, 0] += 1e-12
    assert back != other
    from controlgs_adapter.errors import InputValueError

    with pytest.raises(InputValueError, match="GridResult"):
        GridResult.from_json({"downsample": [1.0]})


def test_findings_count_strict_wins_ties_and_worst_cells_by_hand():
    """2 x 3 grid, one view. PSNR ControlGS - SS per cell: +1, 0, 0, -0.5, +2, 0 -> 2 wins of 6 (ties are
    not wins), mean +0.4167, worst -0.5. FLIP (lower is better) ControlGS - SS: -0.1, 0, +0.2, 0, 0, 0 ->
    1 win; printed in FLIP units: mean +0.01667, worst cell +0.2. SS vs no-SS PSNR: +1 in 4 cells, equal in 2."""
    ss_psnr = torch.full((2, 3, 1), 20.0, dtype=torch.float64)
    cg_psnr = ss_psnr + torch.tensor([[1.0, 0.0, 0.0], [-0.5, 2.0, 0.0]], dtype=torch.float64)[..., None]
    ss_flip = torch.full((2, 3, 1), 0.5, dtype=torch.float64)
    cg_flip = ss_flip - torch.tensor([[0.1, 0.0, -0.2], [0.0, 0.0, 0.0]], dtype=torch.float64)[..., None]
    no_ss_psnr = ss_psnr - torch.tensor([[0.0, 1.0, 1.0], [0.0, 1.0, 1.0]], dtype=torch.float64)[..., None]
    result = GridResult((1.0, 2.0), (0.0, 0.2, 0.4), {
        "no_ss": {"psnr": no_ss_psnr, "flip": ss_flip.clone()},
        "ss": {"psnr": ss_psnr, "flip": ss_flip},
        "controlgs": {"psnr": cg_psnr, "flip": cg_flip}})
    md = markdown_tables(result)
    assert ("- PSNR: ControlGS better than SS-backbone in 2/6 settings (mean difference +0.4167, worst cell -0.5)."
            in md), md
    assert "- FLIP: ControlGS better than SS-backbone in 1/6 settings (mean difference +0.01667, worst cell +0.2)." in md, md
    assert ("- PSNR: SS-backbone better than no-SS in 4/6 settings, equal in 2 (at d = 1 both render at S) "
            "(mean difference +0.6667)." in md), md
    # Tbl. 1: the best mean in bold (highest PSNR, lowest FLIP; ties all bold). Means by hand: PSNR 19.33,
    # 20, 20.42; FLIP 0.5, 0.5, 3.1 / 6 = 0.5167
    assert "| Backbone (no SS) | 19.33 | **0.5000** |" in md, md
    assert "| SS-backbone | 20.00 | **0.5000** |" in md and "| ControlGS | **20.42** | 0.5167 |" in md, md


def test_metrics_clamp_the_eye_image():
    """A saturated eye image is clamped to [0, 1] before PSNR/SSIM (what the display can hold)."""
    gt = torch.full((3, 16, 16), 0.9, dtype=torch.float64)
    eye = gt.clone()
    eye[:, :8] = 1.4  # half the pixels overshoot: clamped to 1.0, error 0.1
    eye[0, 8:, :2] = -0.3  # a negative corner: clamped to 0, error 0.9
    err = torch.full((3, 16, 16), 0.0, dtype=torch.float64)
    err[:, :8] = 0.1
    err[0, 8:, :2] = 0.9
    want = 10 * math.log10(1.0 / float((err ** 2).mean()))
    got = scores(eye, gt, {})
    assert got["psnr"] == pytest.approx(want, abs=1e-9)
    assert got["psnr"] == pytest.approx(16.60051938305649, abs=1e-9)  # = 10 log10(768 / 16.8)


def test_ideal_bound_is_the_ground_truth_through_the_pipeline():
    from controlgs_adapter.downstream.pipeline import Pipeline
    from controlgs_adapter.evaluation import evaluate_grid
    from controlgs_adapter.metrics import psnr
    from controlgs_adapter.scene import load_builtin_scene
    from controlgs_adapter.state import RuntimeState
    from controlgs_adapter.training import DEFAULT_EFFECTS


    scene = load_builtin_scene("ar", 16, views=4, test_every=4, samples=1)
    views = scene.views("test")
    model = NeuralGaussianModel.from_points(*scene.points(0.3), feat_dim=8, n_offsets=2, voxel_size=0.4,
                                            color_fit_steps=1).eval()
    # no baselines and no adapters: nothing is rendered, only the ground truth goes through E_s
    r = evaluate_grid(model, views, {}, downsample=(2.0,), power_saving=(0.4,), baselines=(), progress=False)
    assert r.methods == [IDEAL] and r.metrics == ["psnr", "ssim", "flip"]
    pipe = Pipeline.from_config(dict(DEFAULT_EFFECTS))
    pipe["optics"].mode = "fast"
    pipe.eval()
    for v in range(len(views)):
        _, gt = views[v]
        with torch.no_grad():
            eye = pipe(gt, RuntimeState(downsample=2.0, power_saving=0.4), reference=gt).clamp(0, 1).double()
        want = {"psnr": float(psnr(eye, gt.double())), "ssim": float(ssim(eye, gt.double())), "flip": flip(eye, gt.double())}
        for k, value in want.items():
            assert float(r.per_view[IDEAL][k][0, 0, v]) == pytest.approx(value, rel=1e-9, abs=1e-12), k
        assert want["psnr"] < 60  # the pipeline is not the identity: the bound means something


# ------------------------------------------------------------------------------ heatmap labels
def _heatmap_pixels(tmp_path: Path, d: int, p: int, cell: tuple[int, int], value: float, name: str):
    """The heatmap (ControlGS minus SS-backbone, PSNR) of a d x p grid: one cell of +10 dB sets the colour
    range, ``cell`` is +``value``, the rest 0."""
    import matplotlib.image

    delta = torch.zeros(d, p, 1, dtype=torch.float64)
    delta[d - 1, 0, 0] = 10.0
    delta[cell[0], cell[1], 0] = value
    ss = torch.full((d, p, 1), 20.0, dtype=torch.float64)
    r = GridResult(tuple(float(2 ** i) for i in range(d)), tuple(0.2 * j for j in range(p)),
                   {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    return torch.from_numpy(matplotlib.image.imread(plot_heatmaps(r, tmp_path / name)))


@pytest.mark.parametrize("d, p", [(2, 3), (3, 2)])
def test_every_heatmap_cell_carries_its_value(tmp_path, d, p):
    """Every cell of the grid is labelled with its difference, for grids wider than tall and taller than wide:
    +0.01 and +0.04 dB against a +/-10 dB range get the same colour, so only the label tells them apart."""
    for cell in ((0, p - 1), (d - 1, p - 1), (0, 0)):
        a = _heatmap_pixels(tmp_path, d, p, cell, 0.01, "a.png")
        b = _heatmap_pixels(tmp_path, d, p, cell, 0.04, "b.png")
        assert a.shape == b.shape and not torch.equal(a, b), cell


def test_evaluation_scores_an_oled_off_eye_image_as_box_pixels_at_full_size():
    """The grid's scores of a pipeline without the ``oled`` stage (eye image at S/d) are those of the same
    pipeline with it (box emission to S is all that stage does), at every d; they used to stop with a
    ShapeError for d > 1."""
    from controlgs_adapter.evaluation import make_pipeline, scores
    from controlgs_adapter.state import RuntimeState

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


# ------------------------------------------------------------------------------ heatmap colour range
def test_heatmap_colour_range_spans_the_largest_difference(tmp_path):
    """The colour scale of each panel is symmetric at the largest |difference|: a cell of +5 dB next to a
    cell of +10 dB is drawn in the colour half-way up the positive side (RdBu at 0.75), not saturated."""
    import matplotlib
    import matplotlib.image

    ss = torch.full((2, 2, 1), 20.0, dtype=torch.float64)
    delta = torch.tensor([[10.0, 5.0], [0.0, -10.0]], dtype=torch.float64)[..., None]
    r = GridResult((1.0, 2.0), (0.0, 0.2), {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    img = torch.from_numpy(matplotlib.image.imread(plot_heatmaps(r, tmp_path / "h.png")))[..., :3].double()
    mid = torch.tensor(matplotlib.colormaps["RdBu"](0.75)[:3], dtype=torch.float64)
    full = torch.tensor(matplotlib.colormaps["RdBu"](1.0)[:3], dtype=torch.float64)
    n_mid = int(((img - mid).abs().amax(-1) < 0.02).sum())
    n_full = int(((img - full).abs().amax(-1) < 0.02).sum())
    # one cell each (about 100 x 100 px, less its label); the colour bar alone holds a few hundred
    assert n_mid > 3000 and n_full > 3000, (n_mid, n_full)


# ------------------------------------------------------------------------------ evaluation progress bar
def test_evaluate_grid_shows_its_progress_bar_by_default(tiny, capsys):
    """``evaluate_grid`` reports its progress ("evaluating grid", on stderr) unless ``progress=False``."""
    scene, model = tiny
    views = scene.data.views("train", first=1)
    kw = dict(downsample=(1.0,), power_saving=(0.0,), baselines=(), extra_metrics=False)
    capsys.readouterr()
    evaluate_grid(model, views, {}, **kw)
    assert "evaluating grid" in capsys.readouterr().err
    evaluate_grid(model, views, {}, progress=False, **kw)
    assert "evaluating grid" not in capsys.readouterr().err


# ------------------------------------------------------------------------------ report heatmaps
def test_heatmap_cell_labels_carry_the_sign_of_the_difference(tmp_path, monkeypatch):
    """The heatmaps show method minus baseline; each cell's label is signed (``+0.50`` where the method gains,
    ``-0.25`` where it loses), in the metric's format (PSNR: two decimals), at that cell's (column, row)."""
    from matplotlib.figure import Figure

    from controlgs_adapter.evaluation import GridResult
    from controlgs_adapter.report import plot_heatmaps

    labels: list[tuple[float, float, str]] = []
    save = Figure.savefig

    def recording_savefig(fig, *args, **kwargs):
        for ax in fig.axes:
            labels.extend((t.get_position()[0], t.get_position()[1], t.get_text()) for t in ax.texts)
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", recording_savefig)
    ss = torch.full((2, 3, 1), 20.0, dtype=torch.float64)
    delta = torch.tensor([[0.5, -0.25, 0.0], [1.0, 2.0, -3.0]], dtype=torch.float64)[..., None]
    r = GridResult((1.0, 2.0), (0.0, 0.2, 0.4), {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    plot_heatmaps(r, tmp_path / "h.png", baselines=("ss",))
    assert sorted(labels) == sorted([(0, 0, "+0.50"), (1, 0, "-0.25"), (2, 0, "+0.00"),
                                     (0, 1, "+1.00"), (1, 1, "+2.00"), (2, 1, "-3.00")])


def _lpips_weights(seed: int = 0) -> dict[str, torch.Tensor]:
    """Random AlexNet + head tensors of the shapes LPIPS expects (head weights >= 0, as LPIPS' are)."""
    g = torch.Generator().manual_seed(seed)
    w = {k: (torch.rand(s, generator=g) - 0.3) * 0.1 for k, s in _expected().items()}
    for i in range(5):
        w[f"lin{i}"] = w[f"lin{i}"].abs()
    return w


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


class _OnWhite:
    """The first view of a dataset, its renders to be made on a white background."""

    background = torch.ones(3)

    def __init__(self, views) -> None:
        self.view = views[0]

    def __len__(self) -> int:
        return 1

    def __getitem__(self, i: int):
        return self.view


# ------------------------------------------------------------------------------ report
def _cell(v: float) -> torch.Tensor:
    return torch.full((1, 1, 1), v, dtype=torch.float64)


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


class _Plain:
    """A Views dataset with nothing but the protocol (no describe)."""

    def __init__(self, views):
        self.inner, self.background = views, views.background

    def __len__(self) -> int:
        return len(self.inner)

    def __getitem__(self, i: int):
        return self.inner[i]


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


def test_progress_bar_counts_every_scored_image(setup, capsys):
    model, views, _ = setup
    evaluate_grid(model, views, {}, downsample=(1.0, 2.0), power_saving=(0.0,), baselines=("ss",), ideal=True,
                  extra_metrics=False, effects=CHEAP, progress=True)
    err = capsys.readouterr().err
    assert "evaluating grid" in err and "8/8" in err  # 2 views x 2 d x 1 rho x (ss + ideal)
    evaluate_grid(model, views, {}, downsample=(1.0,), power_saving=(0.0,), baselines=("ss",), extra_metrics=False,
                  effects=CHEAP, progress=False)
    assert "evaluating grid" not in capsys.readouterr().err


D, P = (1.0, 2.0), (0.0, 0.5)


#: [D, P] grids of each method (the mean over the two views, which are the grid -/+ 1 dB, -/+ 0.01)
PSNR = {"no_ss": [[20, 21], [17, 15]], "ss": [[20, 22], [18, 16]], "controlgs": [[21, 21], [19, 18]],
        IDEAL: [[25, 20], [22, 15]], "wo_lens": [[18.75] * 2] * 2, "wo_display": [[19.25] * 2] * 2}


FLIP = {"no_ss": [[0.3] * 2] * 2, "ss": [[0.2] * 2] * 2, "controlgs": [[0.1, 0.25], [0.15, 0.1]],
        IDEAL: [[0.05] * 2] * 2, "wo_lens": [[0.18] * 2] * 2, "wo_display": [[0.22] * 2] * 2}


def _views(grid: list[list[float]], spread: float) -> torch.Tensor:
    g = torch.tensor(grid, dtype=torch.float64)
    return torch.stack([g - spread, g + spread], dim=-1)  # [D, P, 2]


def _result(methods=tuple(PSNR), offset: float = 0.0, info=None) -> GridResult:
    per_view = {m: {"psnr": _views(PSNR[m], 1.0) + offset, "flip": _views(FLIP[m], 0.01)} for m in methods}
    return GridResult(D, P, per_view, info=dict(info or {}))


# ------------------------------------------------------------------------------ GridResult
def test_grid_result_accessors_by_hand():
    r = _result()
    assert r.methods == list(PSNR) and r.metrics == ["psnr", "flip"]
    assert torch.equal(r.grid("ss", "psnr"), torch.tensor(PSNR["ss"], dtype=torch.float64))
    assert r.mean("ss", "psnr") == 19.0  # (20 + 22 + 18 + 16) / 4, views -1 / +1 cancel
    assert r.mean("no_ss", "psnr") == 18.25
    assert GridResult(D, P).metrics == [] and GridResult(D, P).methods == []
    assert GridResult(D, P).optics_mode == "fast" and GridResult(D, P).info == {}
    assert GRID_DOWNSAMPLE == (1.0, 2.0, 4.0, 8.0) and GRID_POWER_SAVING == (0.0, 0.2, 0.4, 0.6, 0.8)
    assert BASELINES == ("no_ss", "ss") and IDEAL == "ideal"


def test_grid_result_equality_looks_at_every_part():
    a, b = _result(), _result()
    assert a == b and not (a != b)
    assert (a == 3) is False and a.__eq__(3) is NotImplemented
    for change in (lambda r: setattr(r, "optics_mode", "exact"), lambda r: r.info.update(x=1),
                   lambda r: setattr(r, "downsample", (1.0, 4.0)), lambda r: setattr(r, "power_saving", (0.0, 0.6)),
                   lambda r: r.per_view.pop("wo_lens"), lambda r: r.per_view["ss"].pop("flip"),
                   lambda r: r.per_view["ss"]["flip"].add_(1e-15)):
        c = _result()
        change(c)
        assert a != c and c != a


def test_to_json_by_hand_and_from_json():
    per_view = {"ss": {"psnr": torch.tensor([[[1.0, 3.0]]], dtype=torch.float64)}}
    r = GridResult((2.0,), (0.4,), per_view, "exact", {"test_views": 2})
    assert r.to_json() == {"info": {"test_views": 2}, "downsample": [2.0], "power_saving": [0.4], "optics_mode": "exact",
                           "methods": {"ss": {"psnr": {"mean": 2.0, "grid": [[2.0]], "per_view": [[[1.0, 3.0]]]}}}}
    back = GridResult.from_json(r.to_json())
    assert back == r and back.per_view["ss"]["psnr"].dtype == torch.float64
    # optics mode and info may be missing (older files): "fast" and {}
    bare = GridResult.from_json({"downsample": [2], "power_saving": [0], "methods": {"ss": {"psnr": {"per_view": [[[5]]]}}}})
    assert (bare.optics_mode, bare.info, bare.downsample, bare.power_saving) == ("fast", {}, (2.0,), (0.0,))
    for bad in ({"downsample": [1.0]}, {"downsample": [1.0], "power_saving": [0.0], "methods": {"ss": 3}},
                {"downsample": [1.0], "power_saving": ["x"], "methods": {}}):
        with pytest.raises(InputValueError, match="not a GridResult JSON"):
            GridResult.from_json(bad)
    wrong = r.to_json()
    wrong["power_saving"] = [0.0, 0.4]  # [1, 2] grid, values [1, 1, 2]
    with pytest.raises(InputValueError, match=r"per_view of \['ss.psnr'\] is not \[1, 2, V\]"):
        GridResult.from_json(wrong)
    flat = r.to_json()
    flat["methods"]["ss"]["psnr"]["per_view"] = [[1.0, 3.0]]  # 2-D
    with pytest.raises(InputValueError, match="is not"):
        GridResult.from_json(flat)


def test_scores_clamp_the_eye_image_by_hand():
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
    assert seen == [(torch.float64, torch.float64, 1.0, 1.0)]
    low = scores(gt - 0.9, gt, {})  # clamped to 0
    assert low["psnr"] == pytest.approx(10 * math.log10(4.0), abs=1e-12)


def test_spread_threshold_is_strict_and_scaled():
    # ControlGS - SS = 0.3 with pooled std 0.1414 (seeds 0.1 apart, x2 = 0.2828 < 0.3) exceeds; 0.25 does not
    def runs(gap: float) -> list[GridResult]:
        out = []
        for k, c in enumerate((gap - 0.1, gap + 0.1)):
            out.append(GridResult((1.0,), (0.0,), {"ss": {"psnr": torch.zeros(1, 1, 1, dtype=torch.float64)},
                                                   "controlgs": {"psnr": torch.full((1, 1, 1), c, dtype=torch.float64)}},
                                  info={"seed": k}))
        return out

    assert "PSNR +0.3 (exceeds the spread, pooled std 0.1)" in markdown_tables(runs(0.3))  # 0.3 > 2 x 0.1
    assert "PSNR +0.15 (within the spread, pooled std 0.1)" in markdown_tables(runs(0.15))  # 0.15 < 0.2
    assert "PSNR -0.3 (exceeds the spread" in markdown_tables([GridResult(r.downsample, r.power_saving,
                                                                           {"ss": r.per_view["controlgs"],
                                                                            "controlgs": r.per_view["ss"]})
                                                                for r in runs(0.3)])


def test_runs_must_share_grid_methods_and_metrics():
    with pytest.raises(InputValueError, match="no results to report"):
        markdown_tables([])
    a = _result(("ss", "controlgs"))
    for other in (_result(("ss",)), GridResult((1.0, 4.0), P, a.per_view), GridResult(D, (0.0, 0.6), a.per_view),
                  GridResult(D, P, {m: {"psnr": v["psnr"]} for m, v in a.per_view.items()})):
        with pytest.raises(InputValueError, match="cannot be pooled"):
            seed_summary([a, other])


pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
