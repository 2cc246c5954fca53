"""Tests of ``controlgs_adapter.report``."""

from __future__ import annotations

import json
import math
import struct
from pathlib import Path

import pytest
import torch

from controlgs_adapter.evaluation import IDEAL, GridResult
from controlgs_adapter.metrics import FLIP_PPD
from controlgs_adapter.report import (
    LPIPS_NOT_COMPUTED,
    METHOD_LABELS,
    SPREAD_FACTOR,
    markdown_tables,
    plot_comparison,
    plot_condition_response,
    plot_heatmaps,
    read_results,
    seed_summary,
    write_report,
)


def test_difference_tables_appear_with_exactly_the_two_methods():
    """A result holding only ``ss`` and ``controlgs`` gets the per-setting ControlGS-minus-SS table, its
    cells the differences by hand, signed."""
    ss = torch.full((1, 2, 1), 20.0, dtype=torch.float64)
    cg = ss + torch.tensor([[0.5, -0.25]], dtype=torch.float64)[..., None]
    md = markdown_tables(GridResult((1.0,), (0.0, 0.4), {"ss": {"psnr": ss}, "controlgs": {"psnr": cg}}))
    section = md.split("PSNR of ControlGS minus SS-backbone:", 1)[1].split("\n\n", 2)[1]
    assert "+0.50" in section and "-0.25" in section, section


GRID = ((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8))


def _seed_result(seed: int, values: dict[str, float]) -> GridResult:
    """Every view and cell of a method holds one known PSNR (so its overall mean is that number)."""
    per_view = {m: {"psnr": torch.full((4, 5, 2), v, dtype=torch.float64)} for m, v in values.items()}
    return GridResult(*GRID, per_view, info={"seed": seed})


def test_seeds_mean_std_and_which_differences_exceed_the_spread(tmp_path):
    runs = [_seed_result(0, {"ss": 20.0, "controlgs": 21.0, "wo_lens": 21.0, "state_blind": 20.0}),
            _seed_result(1, {"ss": 20.0, "controlgs": 21.2, "wo_lens": 21.1, "state_blind": 20.2})]
    s = seed_summary(runs)
    assert s["controlgs"]["psnr"]["mean"] == pytest.approx(21.1)
    assert s["controlgs"]["psnr"]["std"] == pytest.approx(math.sqrt(0.02))  # sample std of (21.0, 21.2)
    assert s["ss"]["psnr"]["std"] == 0.0
    md = markdown_tables(runs)
    assert "| ControlGS | **21.10 ± 0.14** |" in md and "| SS-backbone | 20.00 ± 0.00 |" in md
    # ControlGS - SS = 1.1, pooled std sqrt((0.02 + 0) / 2) = 0.1: exceeds 2 x 0.1
    assert "ControlGS minus SS-backbone: PSNR +1.1 (exceeds the spread, pooled std 0.1)" in md
    # w/o Lens - ControlGS = -0.05, pooled sqrt((0.005 + 0.02) / 2) = 0.112: within
    assert "w/o Lens minus ControlGS: PSNR -0.05 (within the spread, pooled std 0.11)" in md
    # state-blind - ControlGS = -1.0, pooled 0.141: exceeds
    assert "w/o State-Aware minus ControlGS: PSNR -1 (exceeds the spread, pooled std 0.14)" in md
    assert "over 2 seeds" in md
    write_report(tmp_path, runs)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["seeds"] == [0, 1] and data["summary"]["controlgs"]["psnr"]["per_seed"] == [21.0, 21.2]
    assert read_results(data) == runs
    assert "One seed: no spread was measured" in markdown_tables(runs[0])


def _runs(mask) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of True in a 1-D boolean array."""
    out, start = [], None
    for i, v in enumerate(list(mask) + [False]):
        if v and start is None:
            start = i
        elif not v and start is not None:
            out.append((start, i))
            start = None
    return out


def test_comparison_figure_titles_fit_over_their_panels(tmp_path):
    """Fig. 1's panel titles (the rows :func:`evaluation.side_by_side` gives, two-line settings, metrics)
    are set small enough to sit over their own image: in the written PNG, every dark title pixel lies within the columns of the
    image panel below it, never over the gap or a neighbour's panel."""
    from matplotlib.image import imread

    from controlgs_adapter.report import plot_comparison

    img = torch.full((3, 32, 32), 0.5)
    rows = {m: [(img, img, 31.25, 0.912), (img, img, 28.5, 0.88)] for m in ("no_ss", "ss", "controlgs")}
    path = plot_comparison({"gt": img, "settings": [(2.0, 0.4), (1.0, 0.0)], "rows": rows}, tmp_path / "fig.png")
    px = torch.from_numpy(imread(str(path))[..., :3].copy()).double()
    grey = ((px - 0.5).abs() < 0.02).all(-1)
    dark = px.max(-1).values < 0.35
    panel_rows = _runs((grey.sum(1) > 0.2 * grey.sum(1).max()).tolist())
    assert len(panel_rows) == 1 + len(rows)
    top = 0
    for y0, y1 in panel_rows:
        cols = _runs((grey[y0:y1].sum(0) > 0.5 * (y1 - y0)).tolist())
        assert len(cols) in (1, 4)  # the ground truth alone, then rendered/eye for two settings
        ys, xs = torch.nonzero(dark[top:y0], as_tuple=True)
        assert len(xs) > 50, "no title above the panels"
        for x0, x1 in cols:
            near = (xs >= x0 - 10) & (xs < x1 + 10)
            assert near.any(), "a panel without a title"
        inside = torch.zeros_like(xs, dtype=torch.bool)
        for x0, x1 in cols:
            inside |= (xs >= x0) & (xs < x1)
        assert inside.all(), f"title pixels outside their panel at x={sorted(set(xs[~inside].tolist()))[:5]}"
        top = y1


def test_condition_response_figure_has_a_column_for_the_longest_strip(tmp_path):
    """Strips of unequal length: the figure has as many columns as the longest (2 in by 120 dpi each), the
    shorter row's missing panels left blank."""

    pytest.importorskip("matplotlib")
    from controlgs_adapter.report import plot_condition_response

    img = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    strips = {"resample": [("d=1", img), ("d=2", img)], "display": [("p=0", img), ("p=0.3", img), ("p=0.6", img)]}
    path = plot_condition_response(strips, tmp_path / "response.png")
    width, height = struct.unpack(">II", path.read_bytes()[16:24])  # the PNG's IHDR
    assert (width, height) == (round(2.0 * 3 * 120), round(2.1 * 2 * 120))


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


# ------------------------------------------------------------------------------ Markdown
def test_main_table_bold_best_and_ideal_row():
    md = markdown_tables(_result(), {"scene": "s", "views": [1, 2], "n": 3, "d": {"a": 1}})
    lines = md.splitlines()
    assert "Run: scene = s, n = 3" in lines  # lists and dicts are left out
    assert ("End-to-end quality after the XR pipeline (optics `fast`), averaged over the 2 test views and the 4 "
            "run-time settings (paper Tbl. 1)") in md
    assert "over 1 seeds" not in md and "±" not in md
    i = lines.index("| Method | PSNR↑ | FLIP↓ |")
    assert lines[i + 1:i + 6] == ["|---|---:|---:|",
                                  "| Backbone (no SS) | 18.25 | 0.3000 |",
                                  "| SS-backbone | 19.00 | 0.2000 |",
                                  "| ControlGS | **19.75** | **0.1500** |",  # best PSNR (highest), best FLIP (lowest)
                                  "| Ideal render (GT through E_s) | 20.50 | 0.0500 |"]  # above all, never bold
    # the ablation table: ControlGS, the ablations in ABLATIONS order, SS-backbone
    j = lines.index("Ablations (paper Tbl. 4):")
    assert lines[j + 2:j + 8] == ["| Method | PSNR↑ | FLIP↓ |", "|---|---:|---:|",
                                  "| ControlGS | **19.75** | **0.1500** |", "| w/o Lens | 18.75 | 0.1800 |",
                                  "| w/o Display Mapping | 19.25 | 0.2200 |", "| SS-backbone | 19.00 | 0.2000 |"]
    assert f"FLIP is NVIDIA's LDR-FLIP (flip-evaluator) at {67.02:.2f} pixels per degree" in md
    assert LPIPS_NOT_COMPUTED in md


def test_findings_by_hand():
    md = markdown_tables(_result())
    # ControlGS - SS = [[1, -1], [1, 2]]: 3 wins, mean 0.75, worst -1
    assert "- PSNR: ControlGS better than SS-backbone in 3/4 settings (mean difference +0.75, worst cell -1)." in md
    # SS - no-SS = [[0, 1], [1, 1]]: 3 wins, 1 tie at d = 1
    assert ("- PSNR: SS-backbone better than no-SS in 3/4 settings, equal in 1 (at d = 1 both render at S) "
            "(mean difference +0.75).") in md
    # ControlGS - ideal = [[-4, 1], [-3, 3]]: above in 2, mean -0.75
    assert ("- PSNR: the ideal render (ground truth through the pipeline) scores 20.5, the pipeline's own cost to a "
            "perfect render; ControlGS is above that bound in 2/4 settings (pre-compensating beyond it; mean "
            "ControlGS minus ideal -0.75).") in md
    # FLIP, lower is better: SS - ControlGS = [[0.1, -0.05], [0.05, 0.1]]; printed as ControlGS - SS
    assert "- FLIP: ControlGS better than SS-backbone in 3/4 settings (mean difference -0.05, worst cell +0.05)." in md
    assert "- FLIP: SS-backbone better than no-SS in 4/4 settings (mean difference -0.1)." in md  # no tie clause
    assert "ControlGS is above that bound in 0/4 settings (pre-compensating beyond it; mean ControlGS minus ideal +0.1)" in md
    # ablations, largest PSNR loss first: w/o Lens 19.75 - 18.75 = 1, w/o Display 19.75 - 19.25 = 0.5
    assert ("- PSNR lost by each ablation (ControlGS minus ablation, larger = that part matters more): "
            "w/o Lens +1.000 dB, w/o Display Mapping +0.500 dB.") in md
    assert "- One seed: no spread was measured, so no difference is shown to exceed it (`--seeds K`)." in md
    # without ss or controlgs there is nothing to compare
    only = markdown_tables(_result(("no_ss", "ss")))
    assert "- (needs ss and controlgs)" in only and "Differences against the seed spread" not in only
    assert "Ablations" not in only and "minus" not in only
    # no no_ss and no ideal: only the ControlGS-vs-SS lines
    two = markdown_tables(_result(("ss", "controlgs")))  # exactly the two methods the findings need
    assert "- PSNR: ControlGS better than SS-backbone in 3/4 settings" in two and "(needs ss and controlgs)" not in two
    assert "better than no-SS" not in two and "ideal render (ground truth" not in two
    assert "Ideal render" not in two


def test_per_setting_grids_by_hand():
    lines = markdown_tables(_result()).splitlines()
    i = lines.index("PSNR of SS-backbone:")
    assert lines[i + 2:i + 6] == ["| d \\ ρ | 0% | 50% |", "|---|---:|---:|", "| 1× | 20.00 | 22.00 |",
                                  "| 2× | 18.00 | 16.00 |"]
    i = lines.index("PSNR of ControlGS minus SS-backbone:")
    assert lines[i + 4:i + 6] == ["| 1× | +1.00 | -1.00 |", "| 2× | +1.00 | +2.00 |"]
    i = lines.index("PSNR of ControlGS minus Ideal render (GT through E_s):")
    assert lines[i + 4:i + 6] == ["| 1× | -4.00 | +1.00 |", "| 2× | -3.00 | +3.00 |"]
    i = lines.index("FLIP of ControlGS minus SS-backbone:")
    assert lines[i + 4:i + 6] == ["| 1× | -0.1000 | +0.0500 |", "| 2× | -0.0500 | -0.1000 |"]
    i = lines.index("FLIP of w/o Lens:")
    assert lines[i + 4] == "| 1× | 0.1800 | 0.1800 |"
    assert "## Per setting" in lines and "PSNR of Backbone (no SS):" in lines


def test_metric_formats_and_arrows():
    per_view = {m: {k: torch.full((1, 1, 1), v, dtype=torch.float64) for k, v in
                    (("ssim", 0.123456), ("lpips", 0.5), ("cvvdp", 9.87654), ("other", 1.23456))} for m in ("ss", "controlgs")}
    per_view["ss"]["lpips"] = torch.full((1, 1, 1), 0.25, dtype=torch.float64)
    r = GridResult((1.0,), (0.0,), per_view)
    md = markdown_tables(r, {"lpips_weights": "a.pth, b.pth"})
    assert "| Method | SSIM↑ | LPIPS↓ | CVVDP↑ | OTHER↑ |" in md
    # equal values are both best; LPIPS: the lower (SS 0.25) is bold
    assert "| SS-backbone | **0.1235** | **0.2500** | **9.877** | **1.2346** |" in md
    assert "| ControlGS | **0.1235** | 0.5000 | **9.877** | **1.2346** |" in md
    assert "LPIPS (AlexNet) from a.pth, b.pth." in md and LPIPS_NOT_COMPUTED not in md
    assert "FLIP is" not in md
    # weights named but no LPIPS column: not computed
    no = GridResult((1.0,), (0.0,), {m: {"psnr": torch.zeros(1, 1, 1, dtype=torch.float64)} for m in ("ss",)})
    assert LPIPS_NOT_COMPUTED in markdown_tables(no, {"lpips_weights": "a.pth"})
    assert METHOD_LABELS["state_blind"] == "w/o State-Aware" and METHOD_LABELS["wo_resample"] == "w/o Resampling"


# ------------------------------------------------------------------------------ seeds
def test_seed_pooling_std_and_spread_by_hand():
    r0 = _result(("ss", "controlgs", "wo_lens"), info={"seed": 5})
    r1 = _result(("ss", "controlgs", "wo_lens"), info={"seed": 6})
    r1.per_view["controlgs"]["psnr"] += 0.4  # ControlGS 19.75 and 20.15 over the seeds; the others equal
    r1.per_view["wo_lens"]["psnr"] -= 0.2  # 18.75 and 18.55
    s = seed_summary([r0, r1])
    assert s["controlgs"]["psnr"]["per_seed"] == [19.75, 20.15]
    assert s["controlgs"]["psnr"]["mean"] == pytest.approx(19.95, abs=1e-12)
    assert s["controlgs"]["psnr"]["std"] == pytest.approx(0.4 / math.sqrt(2), abs=1e-12)  # ddof 1: |a - b| / sqrt 2
    assert s["ss"]["psnr"]["std"] == 0.0 and seed_summary(r0)["ss"]["psnr"] == {"mean": 19.0, "std": 0.0, "per_seed": [19.0]}
    md = markdown_tables([r0, r1])
    assert " and over 2 seeds (mean ± sample std of the seeds' means)" in md
    assert "| ControlGS | **19.95 ± 0.28** | **0.1500 ± 0.0000** |" in md
    assert "## Per setting (means over 2 seeds)" in md
    lines = md.splitlines()
    i = lines.index("PSNR of ControlGS:")
    assert lines[i + 4] == "| 1× | 21.20 | 21.20 |"  # the cell's mean over the seeds: (21 + 21.4) / 2
    assert SPREAD_FACTOR == 2.0
    # FLIP: -0.05 with no spread at all exceeds it
    # ControlGS - SS = 0.95; pooled std sqrt((0.2828^2 + 0) / 2) = 0.2: 0.95 > 2 x 0.2 exceeds
    assert "- ControlGS minus SS-backbone: PSNR +0.95 (exceeds the spread, pooled std 0.2); FLIP -0.05 (exceeds the spread, pooled std 0)." in md
    # w/o Lens - ControlGS = 18.65 - 19.95 = -1.3, pooled sqrt((0.1414^2 + 0.2828^2) / 2) = 0.2236: exceeds
    assert "- w/o Lens minus ControlGS: PSNR -1.3 (exceeds the spread, pooled std 0.22)" in md
    assert "larger than 2 x the pooled std over seeds" in md


def test_plots_of_one_row_and_ragged_strips(tmp_path: Path):
    r = _result(("ss", "controlgs"))  # one heatmap row (no ideal), two metric panels
    assert plot_heatmaps(r, tmp_path / "h.png").stat().st_size > 0
    zero = _result(("ss", "controlgs"))
    zero.per_view["controlgs"] = zero.per_view["ss"]  # an all-zero difference still plots
    assert plot_heatmaps([zero, zero], tmp_path / "z.png", baselines=("ss",)).is_file()
    img = torch.rand(3, 6, 6)
    assert plot_condition_response({"a": [("x", img)], "b": [("y", img), ("z", img), ("w", img)]},
                                   tmp_path / "c.png").is_file()
    assert plot_comparison({"gt": img, "settings": [(2.0, 0.4)], "rows": {"ss": [(img, img, 1.0, 0.1)]}},
                           tmp_path / "p.png").is_file()
    assert FLIP_PPD == pytest.approx(67.02064327658225, rel=1e-12)
