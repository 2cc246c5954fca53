"""Tests of ``controlgs_adapter.report``: the Markdown tables, the seed summary and spread test, the lines
saying what the numbers show (their counts and differences read back from the text), the per-setting
grids, the figures and results.json."""

from __future__ import annotations

import json
import math
import re
import struct
from pathlib import Path

import pytest
import torch
from helpers.grid_results import DOWNSAMPLE, POWER_SAVING, grid_result

from controlgs_adapter.errors import InputValueError
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
    seed_independent,
    seed_summary,
    write_report,
)

F64 = torch.float64
NUMBER = re.compile(r"[+-]?\d+(?:\.\d+)?(?:e[+-]?\d+)?")
SPREAD = re.compile(r"(\w+) ([+-]\S+) \((exceeds|within) the spread, pooled std ([^)]+)\)")


def _line(md: str, *words: str) -> str:
    """The one line of ``md`` that holds every one of ``words``."""
    found = [line for line in md.splitlines() if all(w in line for w in words)]
    assert len(found) == 1, (words, found)
    return found[0]


def _numbers(line: str) -> list[float]:
    return [float(v) for v in NUMBER.findall(line)]


def _spread(md: str, a: str, b: str) -> dict[str, tuple[float, bool, float]]:
    """The spread line of ``a`` minus ``b``: metric -> (difference, exceeds the spread, pooled std)."""
    line = _line(md, f"- {a} minus {b}:")
    return {k: (float(d), word == "exceeds", float(p)) for k, d, word, p in SPREAD.findall(line)}


def _cell(v: float) -> torch.Tensor:
    return torch.full((1, 1, 1), v, dtype=F64)


def _seeds(values: dict[str, tuple[float, ...]], grid=((1.0, 2.0), (0.0, 0.5)), ssim: bool = False) -> list[GridResult]:
    """One result per seed, every view and cell of a method holding that seed's value (PSNR; SSIM = PSNR / 100)."""
    runs = []
    for seed in range(len(next(iter(values.values())))):
        shape = (len(grid[0]), len(grid[1]), 2)
        per_view = {m: {"psnr": torch.full(shape, v[seed], dtype=F64)} for m, v in values.items()}
        if ssim:
            for m, v in values.items():
                per_view[m]["ssim"] = torch.full(shape, v[seed] / 100.0, dtype=F64)
        runs.append(GridResult(*grid, per_view, info={"seed": seed}))
    return runs


# ------------------------------------------------------------------------------ tables
def test_main_table_bold_best_and_ideal_row():
    md = markdown_tables(grid_result(), {"scene": "s", "views": [1, 2], "n": 3, "d": {"a": 1}})
    lines = md.splitlines()
    assert "Run: scene = s, n = 3" in lines  # lists and dicts are left out
    head = _line(md, "End-to-end")
    assert "`fast`" in head and _numbers(head) == [2, 4, 1]  # 2 test views, 4 run-time settings, Tbl. 1
    assert "±" not in md
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
    assert 67.02 in _numbers(_line(md, "LDR-FLIP"))  # FLIP's observer, in pixels per degree
    assert LPIPS_NOT_COMPUTED in md


def test_metric_formats_and_arrows():
    per_view = {m: {k: torch.full((1, 1, 1), v, dtype=F64) for k, v in
                    (("ssim", 0.123456), ("lpips", 0.5), ("cvvdp", 9.87654), ("other", 1.23456))} for m in ("ss", "controlgs")}
    per_view["ss"]["lpips"] = torch.full((1, 1, 1), 0.25, dtype=F64)
    r = GridResult((1.0,), (0.0,), per_view)
    md = markdown_tables(r, {"lpips_weights": "a.pth, b.pth"})
    assert "| Method | SSIM↑ | LPIPS↓ | CVVDP↑ | OTHER↑ |" in md
    # equal values are both best; LPIPS: the lower (SS 0.25) is bold
    assert "| SS-backbone | **0.1235** | **0.2500** | **9.877** | **1.2346** |" in md
    assert "| ControlGS | **0.1235** | 0.5000 | **9.877** | **1.2346** |" in md
    assert "a.pth, b.pth" in _line(md, "LPIPS", "AlexNet") and LPIPS_NOT_COMPUTED not in md  # the weights it was computed with
    assert "LDR-FLIP" not in md
    # weights named but no LPIPS column: not computed
    no = GridResult((1.0,), (0.0,), {m: {"psnr": torch.zeros(1, 1, 1, dtype=F64)} for m in ("ss",)})
    assert LPIPS_NOT_COMPUTED in markdown_tables(no, {"lpips_weights": "a.pth"})
    assert METHOD_LABELS["state_blind"] == "w/o State-Aware" and METHOD_LABELS["wo_resample"] == "w/o Resampling"


def test_cvvdp_note_gives_the_pixels_per_degree_or_why_it_was_skipped():
    r = GridResult((1.0,), (0.0,), {m: {k: torch.full((1, 1, 1), 9.5, dtype=F64) for k in ("psnr", "cvvdp")}
                                    for m in ("ss", "controlgs")})
    info = {"cvvdp": {"lens": "google-cardboard", "placement": "fit", "display": "standard_4k",
                      "ppd": {"256x256": 8.532851, "128x96": 4.2664}}}
    line = _line(markdown_tables(r, info), "ColorVideoVDP")
    assert _numbers(line) == [8.53, 256, 256, 4.27, 128, 96, 4] and "google-cardboard" in line and "standard_4k" in line
    skipped = markdown_tables(GridResult((1.0,), (0.0,), {"ss": {"psnr": torch.zeros(1, 1, 1, dtype=F64)}}),
                              {"cvvdp": {"skipped": "ColorVideoVDP does not import (no pycvvdp)"}})
    assert "ColorVideoVDP was not computed: ColorVideoVDP does not import (no pycvvdp)" in skipped
    assert "ColorVideoVDP" not in markdown_tables(r, {})


def test_per_setting_grids():
    """One grid per method and metric, and ControlGS minus SS-backbone / the ideal render, signed; the
    difference grids need both methods, and two methods alone are enough."""
    lines = markdown_tables(grid_result()).splitlines()
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
    # exactly ss and controlgs: the difference table, its cells signed
    ss = torch.full((1, 2, 1), 20.0, dtype=F64)
    cg = ss + torch.tensor([[0.5, -0.25]], dtype=F64)[..., None]
    lines = markdown_tables(GridResult((1.0,), (0.0, 0.4), {"ss": {"psnr": ss}, "controlgs": {"psnr": cg}})).splitlines()
    i = lines.index("PSNR of ControlGS minus SS-backbone:")
    assert lines[i + 4] == "| 1× | +0.50 | -0.25 |"
    assert not any("minus" in line for line in markdown_tables(grid_result(("no_ss", "ss"))).splitlines())


# ------------------------------------------------------------------------------ what the numbers show
def test_what_the_numbers_show_counts_wins_ties_bounds_and_ablations():
    md = markdown_tables(grid_result())
    # ControlGS - SS = [[1, -1], [1, 2]]: 3 wins of 4, mean +0.75, worst cell -1
    assert _numbers(_line(md, "- PSNR:", "ControlGS", "SS-backbone")) == [3, 4, 0.75, -1]
    # SS - no-SS = [[0, 1], [1, 1]]: 3 wins, 1 tie (at d = 1 both render at S), mean +0.75
    assert _numbers(_line(md, "- PSNR:", "no-SS")) == [3, 4, 1, 1, 0.75]
    # the ideal render scores 20.5; ControlGS - ideal = [[-4, 1], [-3, 3]]: above it in 2 of 4, mean -0.75
    assert _numbers(_line(md, "- PSNR:", "ideal")) == [20.5, 2, 4, -0.75]
    # FLIP, lower is better: SS - ControlGS = [[0.1, -0.05], [0.05, 0.1]]; printed as ControlGS - SS
    assert _numbers(_line(md, "- FLIP:", "ControlGS", "SS-backbone")) == [3, 4, -0.05, 0.05]
    assert _numbers(_line(md, "- FLIP:", "no-SS")) == [4, 4, -0.1]  # no tie
    assert _numbers(_line(md, "- FLIP:", "ideal")) == [0.05, 0, 4, 0.1]
    # ablations, largest PSNR loss first: w/o Lens 19.75 - 18.75 = 1, w/o Display 19.75 - 19.25 = 0.5
    lost = _line(md, "ablation", "dB")
    assert _numbers(lost) == [1.0, 0.5] and lost.index("w/o Lens") < lost.index("w/o Display Mapping")
    _line(md, "One seed")  # no spread measured, none claimed
    # without ss or controlgs there is nothing to compare
    only = markdown_tables(grid_result(("no_ss", "ss")))
    _line(only, "needs ss and controlgs")
    assert "Differences against the seed spread" not in only and "Ablations" not in only
    # exactly the two methods the comparison needs: no no-SS and no ideal lines
    two = markdown_tables(grid_result(("ss", "controlgs")))
    assert _numbers(_line(two, "- PSNR:", "ControlGS", "SS-backbone")) == [3, 4, 0.75, -1]
    assert "needs ss and controlgs" not in two and "no-SS" not in two and "Ideal render" not in two
    assert "ideal" not in "\n".join(line for line in two.splitlines() if line.startswith("- "))


def test_what_the_numbers_show_counts_strict_wins_ties_and_worst_cells():
    """2 x 3 grid, one view. PSNR ControlGS - SS per cell: +1, 0, 0, -0.5, +2, 0 -> 2 wins of 6 (ties are
    not wins), mean +0.4167, worst -0.5. FLIP (lower is better) ControlGS - SS: -0.1, 0, +0.2, 0, 0, 0 ->
    1 win; printed in FLIP units: mean +0.01667, worst cell +0.2. SS vs no-SS PSNR: +1 in 4 cells, equal in 2."""
    ss_psnr = torch.full((2, 3, 1), 20.0, dtype=F64)
    cg_psnr = ss_psnr + torch.tensor([[1.0, 0.0, 0.0], [-0.5, 2.0, 0.0]], dtype=F64)[..., None]
    ss_flip = torch.full((2, 3, 1), 0.5, dtype=F64)
    cg_flip = ss_flip - torch.tensor([[0.1, 0.0, -0.2], [0.0, 0.0, 0.0]], dtype=F64)[..., None]
    no_ss_psnr = ss_psnr - torch.tensor([[0.0, 1.0, 1.0], [0.0, 1.0, 1.0]], dtype=F64)[..., None]
    result = GridResult((1.0, 2.0), (0.0, 0.2, 0.4), {
        "no_ss": {"psnr": no_ss_psnr, "flip": ss_flip.clone()},
        "ss": {"psnr": ss_psnr, "flip": ss_flip},
        "controlgs": {"psnr": cg_psnr, "flip": cg_flip}})
    md = markdown_tables(result)
    assert _numbers(_line(md, "- PSNR:", "ControlGS", "SS-backbone")) == [2, 6, 0.4167, -0.5]
    assert _numbers(_line(md, "- FLIP:", "ControlGS", "SS-backbone")) == [1, 6, 0.01667, 0.2]
    assert _numbers(_line(md, "- PSNR:", "no-SS")) == [4, 6, 2, 1, 0.6667]
    # Tbl. 1: the best mean in bold (highest PSNR, lowest FLIP; ties all bold). Means: PSNR 19.33,
    # 20, 20.42; FLIP 0.5, 0.5, 3.1 / 6 = 0.5167
    assert "| Backbone (no SS) | 19.33 | **0.5000** |" in md, md
    assert "| SS-backbone | 20.00 | **0.5000** |" in md and "| ControlGS | **20.42** | 0.5167 |" in md, md


# ------------------------------------------------------------------------------ seeds
def test_seed_summary_pools_mean_and_sample_std():
    r0 = grid_result(("ss", "controlgs", "wo_lens"), info={"seed": 5})
    r1 = grid_result(("ss", "controlgs", "wo_lens"), info={"seed": 6})
    r1.per_view["controlgs"]["psnr"] += 0.4  # ControlGS 19.75 and 20.15 over the seeds; the others equal
    r1.per_view["wo_lens"]["psnr"] -= 0.2  # 18.75 and 18.55
    s = seed_summary([r0, r1])
    assert s["controlgs"]["psnr"]["per_seed"] == [19.75, 20.15]
    assert s["controlgs"]["psnr"]["mean"] == pytest.approx(19.95, abs=1e-12)
    assert s["controlgs"]["psnr"]["std"] == pytest.approx(0.4 / math.sqrt(2), abs=1e-12)  # ddof 1: |a - b| / sqrt 2
    assert s["ss"]["psnr"]["std"] == 0.0 and seed_summary(r0)["ss"]["psnr"] == {"mean": 19.0, "std": 0.0, "per_seed": [19.0]}
    md = markdown_tables([r0, r1])
    assert _numbers(_line(md, "End-to-end")) == [2, 4, 2, 1]  # 2 views, 4 settings, over 2 seeds
    assert "| ControlGS | **19.95 ± 0.28** | **0.1500 ± 0.0000** |" in md
    assert _numbers(_line(md, "## Per setting")) == [2]  # means over the 2 seeds
    lines = md.splitlines()
    i = lines.index("PSNR of ControlGS:")
    assert lines[i + 4] == "| 1× | 21.20 | 21.20 |"  # the cell's mean over the seeds: (21 + 21.4) / 2


def test_seed_summary_of_runs_that_differ_is_refused():
    with pytest.raises(InputValueError, match="no results"):
        markdown_tables([])
    a = grid_result(("ss", "controlgs"))
    for other in (grid_result(("ss",)), GridResult((1.0, 4.0), POWER_SAVING, a.per_view),
                  GridResult(DOWNSAMPLE, (0.0, 0.6), a.per_view),
                  GridResult(DOWNSAMPLE, POWER_SAVING, {m: {"psnr": v["psnr"]} for m, v in a.per_view.items()})):
        with pytest.raises(InputValueError, match="cannot be pooled"):
            seed_summary([a, other])


def test_differences_against_the_seed_spread():
    """A difference of seed means exceeds the spread when strictly larger than SPREAD_FACTOR pooled std,
    sqrt((s_a^2 + s_b^2) / 2); ControlGS is compared with SS-backbone and each ablation with ControlGS."""
    assert SPREAD_FACTOR == 2.0
    runs = _seeds({"ss": (20.0, 20.0), "controlgs": (21.0, 21.2), "wo_lens": (21.0, 21.1), "state_blind": (20.0, 20.2)},
                  grid=((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8)))
    s = seed_summary(runs)
    assert s["controlgs"]["psnr"]["mean"] == pytest.approx(21.1)
    assert s["controlgs"]["psnr"]["std"] == pytest.approx(math.sqrt(0.02))  # sample std of (21.0, 21.2)
    assert s["ss"]["psnr"]["std"] == 0.0
    md = markdown_tables(runs)
    assert _numbers(_line(md, "pooled std over seeds"))[0] == SPREAD_FACTOR
    # ControlGS - SS = 1.1, pooled std sqrt((0.02 + 0) / 2) = 0.1: exceeds 2 x 0.1
    assert _spread(md, "ControlGS", "SS-backbone") == {"PSNR": (1.1, True, 0.1)}
    # w/o Lens - ControlGS = -0.05, pooled sqrt((0.005 + 0.02) / 2) = 0.112: within
    assert _spread(md, "w/o Lens", "ControlGS") == {"PSNR": (-0.05, False, 0.11)}
    # state-blind - ControlGS = -1.0, pooled 0.141: exceeds
    assert _spread(md, "w/o State-Aware", "ControlGS") == {"PSNR": (-1.0, True, 0.14)}
    # two seeds of the 2 x 2 result: ControlGS 19.75 / 20.15, w/o Lens 18.75 / 18.55, FLIP equal in both
    r0, r1 = (grid_result(("ss", "controlgs", "wo_lens"), info={"seed": k}) for k in (5, 6))
    r1.per_view["controlgs"]["psnr"] += 0.4
    r1.per_view["wo_lens"]["psnr"] -= 0.2
    md = markdown_tables([r0, r1])
    # ControlGS - SS = 0.95, pooled sqrt((0.2828^2 + 0) / 2) = 0.2: exceeds; FLIP -0.05 with no spread at all exceeds
    assert _spread(md, "ControlGS", "SS-backbone") == {"PSNR": (0.95, True, 0.2), "FLIP": (-0.05, True, 0.0)}
    # w/o Lens - ControlGS = 18.65 - 19.95 = -1.3, pooled sqrt((0.1414^2 + 0.2828^2) / 2) = 0.2236: exceeds
    assert _spread(md, "w/o Lens", "ControlGS")["PSNR"] == (-1.3, True, 0.22)
    # the threshold is strict: no difference and no spread is within it
    assert _spread(markdown_tables(_seeds({"ss": (20.0, 20.0), "controlgs": (20.0, 20.0)}, grid=((1.0,), (0.0,)))),
                   "ControlGS", "SS-backbone") == {"PSNR": (0.0, False, 0.0)}
    # ControlGS - SS = 0.3 with pooled std 0.1414 (seeds 0.1 apart, x2 = 0.2828 < 0.3) exceeds; 0.15 does not;
    # the sign does not matter
    for gap, exceeds in ((0.3, True), (0.15, False), (-0.3, True)):
        md = markdown_tables(_seeds({"ss": (0.0, 0.0), "controlgs": (gap - 0.1, gap + 0.1)}, grid=((1.0,), (0.0,))))
        assert _spread(md, "ControlGS", "SS-backbone") == {"PSNR": (gap, exceeds, 0.1)}, gap


def test_seed_independent_rows_show_the_value_alone():
    """Rows that do not depend on the seed (the same per-view values in every seed: the backbone without and
    with supersampling, the ideal render, any method that happens to be equal) show their value without ±
    and are listed in a note; one differing metric keeps a row's spread; one seed has no spread and no note."""
    runs = _seeds({"no_ss": (18.0, 18.0), "ss": (20.0, 20.0), IDEAL: (20.5, 20.5), "controlgs": (21.0, 21.2),
                   "wo_lens": (20.9, 20.9)}, ssim=True)
    assert seed_independent(runs) == {"no_ss", "ss", IDEAL, "wo_lens"}
    md = markdown_tables(runs)
    assert "| Backbone (no SS) | 18.00 | 0.1800 |" in md
    assert "| SS-backbone | 20.00 | 0.2000 |" in md
    assert "| Ideal render (GT through E_s) | 20.50 | 0.2050 |" in md
    assert "| ControlGS | **21.10 ± 0.14** | **0.2110 ± 0.0014** |" in md
    assert "| w/o Lens | 20.90 | 0.2090 |" in md
    assert "± 0.00 " not in md and "± 0.0000 " not in md
    note = _line(md, "without ±")
    assert all(METHOD_LABELS[m] in note for m in ("no_ss", "ss", IDEAL, "wo_lens")) and "ControlGS" not in note
    # one seed: no spread and no note
    one = _seeds({"ss": (20.0,), "controlgs": (21.0,)}, ssim=True)
    assert seed_independent(one) == set()
    md = markdown_tables(one)
    assert "±" not in md and "without ±" not in md
    # a row differing in one metric keeps its spread
    a, b = _seeds({"ss": (20.0, 20.0), "controlgs": (21.0, 21.0)}, ssim=True)
    b.per_view["controlgs"]["ssim"] = b.per_view["controlgs"]["ssim"] + 0.01
    assert seed_independent([a, b]) == {"ss"}
    assert "| ControlGS | **21.00 ± 0.00** | **0.2150 ± 0.0071** |" in markdown_tables([a, b])


# ------------------------------------------------------------------------------ results.json
def test_write_report_keeps_every_seed_in_results_json(tmp_path):
    runs = _seeds({"ss": (20.0, 20.0), "controlgs": (21.0, 21.2)})
    write_report(tmp_path, runs)
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["seeds"] == [0, 1] and data["summary"]["controlgs"]["psnr"]["per_seed"] == [21.0, 21.2]
    assert read_results(data) == runs


# ------------------------------------------------------------------------------ heatmaps
def _heatmap(tmp_path: Path, r: GridResult, name: str = "h.png", **kw) -> torch.Tensor:
    import matplotlib.image

    return torch.from_numpy(matplotlib.image.imread(plot_heatmaps(r, tmp_path / name, **kw)))[..., :3].double()


def test_heatmap_colour_scale_is_symmetric_at_the_largest_difference(tmp_path: Path):
    """Each panel's colour scale runs from -L to +L (L the largest |difference|), so that zero is the neutral
    middle even when every difference has one sign: with PSNR differences of +10 / +5 dB the +5 cells are
    RdBu at 0.75 and the +10 cells at 1, with SSIM differences of -10 / -5 the -5 cells are RdBu at 0.25 and
    the -10 cells at 0 (an automatic range would put the +5 / -5 cells at the ends of the scale)."""
    import matplotlib

    half = torch.tensor([[10.0, 5.0], [5.0, 10.0]], dtype=F64)[..., None]
    base = torch.full((2, 2, 1), 20.0, dtype=F64)
    img = _heatmap(tmp_path, GridResult((1.0, 2.0), (0.0, 0.2), {"ss": {"psnr": base, "ssim": base},
                                                                  "controlgs": {"psnr": base + half, "ssim": base - half}}))

    def count(at: float) -> int:
        colour = torch.tensor(matplotlib.colormaps["RdBu"](at)[:3], dtype=F64)
        return int(((img - colour).abs().amax(-1) < 0.02).sum())

    # two cells of about 100 x 100 px each (less their labels); a colour bar holds a few hundred at most
    counts = {at: count(at) for at in (0.0, 0.25, 0.75, 1.0)}
    assert all(n > 6000 for n in counts.values()), counts


@pytest.mark.parametrize("d, p", [(2, 3), (3, 2)])
def test_every_heatmap_cell_carries_its_signed_value(tmp_path, monkeypatch, d, p):
    """The heatmaps show method minus baseline; every cell, in grids wider than tall and taller than wide,
    is labelled at its (column, row) with its difference, signed, in the metric's format (PSNR: two
    decimals): +0.01 and +0.04 dB against a +/-3 dB range share a colour, only the label tells them apart."""
    from matplotlib.figure import Figure

    labels: list[tuple[float, float, str]] = []
    save = Figure.savefig

    def recording_savefig(fig, *args, **kwargs):
        for ax in fig.axes:
            labels.extend((t.get_position()[0], t.get_position()[1], t.get_text()) for t in ax.texts)
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", recording_savefig)
    values = [0.5, -0.25, 0.0, 0.01, 0.04, -3.0][:d * p]
    ss = torch.full((d, p, 1), 20.0, dtype=F64)
    delta = torch.tensor(values, dtype=F64).view(d, p, 1)
    r = GridResult(tuple(float(2 ** i) for i in range(d)), tuple(0.2 * j for j in range(p)),
                   {"ss": {"psnr": ss}, "controlgs": {"psnr": ss + delta}})
    plot_heatmaps(r, tmp_path / "h.png", baselines=("ss",))
    assert sorted(labels) == sorted((k % p, k // p, f"{v:+.2f}") for k, v in enumerate(values))


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


# ------------------------------------------------------------------------------ other figures
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
    are set small enough to sit over their own image: in the written PNG, every dark title pixel lies
    within the columns of the image panel below it, never over the gap or a neighbour's panel."""
    from matplotlib.image import imread

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
    img = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0))
    strips = {"resample": [("d=1", img), ("d=2", img)], "display": [("p=0", img), ("p=0.3", img), ("p=0.6", img)]}
    path = plot_condition_response(strips, tmp_path / "response.png")
    width, height = struct.unpack(">II", path.read_bytes()[16:24])  # the PNG's IHDR
    assert (width, height) == (round(2.0 * 3 * 120), round(2.1 * 2 * 120))


def test_plots_of_one_row_and_ragged_strips(tmp_path: Path):
    r = grid_result(("ss", "controlgs"))  # one heatmap row (no ideal), two metric panels
    assert plot_heatmaps(r, tmp_path / "h.png").stat().st_size > 0
    zero = grid_result(("ss", "controlgs"))
    zero.per_view["controlgs"] = zero.per_view["ss"]  # an all-zero difference still plots
    assert plot_heatmaps([zero, zero], tmp_path / "z.png", baselines=("ss",)).is_file()
    img = torch.rand(3, 6, 6)
    assert plot_condition_response({"a": [("x", img)], "b": [("y", img), ("z", img), ("w", img)]},
                                   tmp_path / "c.png").is_file()
    assert plot_comparison({"gt": img, "settings": [(2.0, 0.4)], "rows": {"ss": [(img, img, 1.0, 0.1)]}},
                           tmp_path / "p.png").is_file()
    assert FLIP_PPD == pytest.approx(67.02064327658225, rel=1e-12)


GRID = ((1.0, 2.0, 4.0, 8.0), (0.0, 0.2, 0.4, 0.6, 0.8))


D, P = (1.0, 2.0), (0.0, 0.5)


#: [D, P] grids of each method (the mean over the two views, which are the grid -/+ 1 dB, -/+ 0.01)
PSNR = {"no_ss": [[20, 21], [17, 15]], "ss": [[20, 22], [18, 16]], "controlgs": [[21, 21], [19, 18]],
        IDEAL: [[25, 20], [22, 15]], "wo_lens": [[18.75] * 2] * 2, "wo_display": [[19.25] * 2] * 2}


FLIP = {"no_ss": [[0.3] * 2] * 2, "ss": [[0.2] * 2] * 2, "controlgs": [[0.1, 0.25], [0.15, 0.1]],
        IDEAL: [[0.05] * 2] * 2, "wo_lens": [[0.18] * 2] * 2, "wo_display": [[0.22] * 2] * 2}


def _constructed(methods=("no_ss", "ss", IDEAL, "controlgs"), offset: float = 0.0, views: int = 2) -> GridResult:
    g = torch.Generator().manual_seed(3)
    base = {"no_ss": 18.0, "ss": 20.0, IDEAL: 22.0, "controlgs": 21.0, "wo_lens": 20.9}
    per_view = {m: {"psnr": base[m] + offset + 0.1 * torch.rand(4, 5, views, generator=g, dtype=torch.float64),
                    "ssim": torch.rand(4, 5, views, generator=g, dtype=torch.float64),
                    "flip": torch.rand(4, 5, views, generator=g, dtype=torch.float64)} for m in methods}
    return GridResult(*GRID, per_view)


def _views(grid: list[list[float]], spread: float) -> torch.Tensor:
    g = torch.tensor(grid, dtype=torch.float64)
    return torch.stack([g - spread, g + spread], dim=-1)  # [D, P, 2]


def _result(methods=tuple(PSNR), offset: float = 0.0, info=None) -> GridResult:
    per_view = {m: {"psnr": _views(PSNR[m], 1.0) + offset, "flip": _views(FLIP[m], 0.01)} for m in methods}
    return GridResult(D, P, per_view, info=dict(info or {}))


def test_write_report_files_and_results_json(tmp_path: Path):
    r = _result(("ss", "controlgs"), info={"test_views": 2, "seed": 3})
    img = torch.rand(3, 8, 8)
    comparison = {"gt": img, "settings": [(1.0, 0.0), (8.0, 0.8)],
                  "rows": {"ss": [(img, img, 20.0, 0.5)] * 2, "controlgs": [(img, img, 21.0, 0.6)] * 2}}
    response = {"resample": [("d=1", img), ("d=2", img)], "lens": [("off", img)]}
    paths = write_report(tmp_path / "a", r, info={"scene": "x"}, comparison=comparison, response=response)
    assert [p.name for p in paths] == ["results.json", "heatmap.png", "comparison.png", "condition_response.png",
                                       "report.md"]
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths)
    data = json.loads((tmp_path / "a" / "results.json").read_text())
    assert data["info"] == {"test_views": 2, "seed": 3, "scene": "x"}  # the run's info with the call's merged in
    assert read_results(data) == [GridResult.from_json(data)]
    md = (tmp_path / "a" / "report.md").read_text()
    assert md.endswith("\n## Figures\n\n![ControlGS minus SS-backbone and minus the ideal render per setting](heatmap.png)"
                       "\n\n![rendered and eye-space images at two settings](comparison.png)\n\n"
                       "![condition response: one condition varies, the others are off](condition_response.png)\n")
    assert "Run: test_views = 2, seed = 3, scene = x" in md
    # no SS-backbone: no heatmap; no figures at all: no Figures section
    paths = write_report(tmp_path / "b", _result(("controlgs", "no_ss")))
    assert [p.name for p in paths] == ["results.json", "report.md"]
    assert "## Figures" not in (tmp_path / "b" / "report.md").read_text()


def test_write_report_of_several_seeds(tmp_path: Path):
    runs = [_result(("ss", "controlgs"), info={"seed": s, "test_views": 2}) for s in (4, 9)]
    runs[1].per_view["ss"]["psnr"] += 1.0
    write_report(tmp_path, runs, info={"scene": "x"})
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["info"] == {"test_views": 2, "scene": "x"} and data["seeds"] == [4, 9]
    assert data["summary"]["ss"]["psnr"]["per_seed"] == [19.0, 20.0]
    assert [r.info["seed"] for r in read_results(data)] == [4, 9] and read_results(data) == runs
    for bad in ({"runs": []}, {"runs": {"a": 1}}):
        with pytest.raises(InputValueError, match="'runs' must be a non-empty list"):
            read_results(bad)


def test_ideal_row_in_results_json_and_report(tmp_path):
    r = _constructed()
    r.per_view["controlgs"]["psnr"][3, 4] = r.per_view[IDEAL]["psnr"][3, 4] + 0.5  # one cell above the bound
    write_report(tmp_path, r, info={"scene": "test"})
    data = json.loads((tmp_path / "results.json").read_text())
    assert data["methods"][IDEAL]["psnr"]["mean"] == pytest.approx(r.mean(IDEAL, "psnr"), rel=1e-12)
    md = (tmp_path / "report.md").read_text()
    assert f"| Ideal render (GT through E_s) | {r.mean(IDEAL, 'psnr'):.2f} |" in md  # a row, never bold
    assert "PSNR of Ideal render (GT through E_s):" in md and "PSNR of ControlGS minus Ideal render" in md
    assert "ControlGS is above that bound in 1/20 settings" in md
    assert "LPIPS was not computed" in md and "--lpips-weights" in md
    assert (tmp_path / "heatmap.png").stat().st_size > 0
    assert read_results(data)[0] == GridResult.from_json(data)


def _seed_result(seed: int, values: dict[str, float]) -> GridResult:
    """Every view and cell of a method holds one known PSNR (so its overall mean is that number)."""
    per_view = {m: {"psnr": torch.full((4, 5, 2), v, dtype=torch.float64)} for m, v in values.items()}
    return GridResult(*GRID, per_view, info={"seed": seed})


def test_pooled_seeds_must_hold_the_same_methods() -> None:
    with pytest.raises(InputValueError, match="pooled"):
        markdown_tables([_seed_result(0, {"ss": 1.0}), _seed_result(1, {"controlgs": 1.0})])


def test_foveation_tables_per_gaze_with_missing_bands_and_seed_means(tmp_path: Path):
    """A table per gaze: PSNR / SSIM per band, the mean over settings and views without the views that lack the
    band ("–" when none has it); over two seeds the per-view values are averaged; results.json keeps the axis."""
    from controlgs_adapter.evaluation import FoveationAxis

    def axis(offset: float) -> FoveationAxis:
        names = ["psnr", "ssim", *(f"{k}_{b}" for b in ("foveal", "parafoveal", "periphery") for k in ("psnr", "ssim"))]
        pv = {k: torch.full((2, 1, 2), 0.5 if k.startswith("ssim") else 20.0, dtype=torch.float64) for k in names}
        pv["psnr_foveal"][0, 0] = torch.tensor([30.0, 34.0]) + offset   # gaze 0: mean 32 + offset
        pv["psnr_foveal"][1, 0] = torch.tensor([math.nan, 10.0])       # gaze 1: one view has no foveal pixel
        pv["ssim_periphery"][1] = math.nan                              # gaze 1: no periphery window at all
        return FoveationAxis(((0.0, 0.0), (10.0, 0.0)), ((2.0, 0.4),), {"omega0": 1 / 60, "slope": 0.022,
                                                                      "max_scale": 4.0}, per_view={"ss": pv})

    runs = [grid_result(("ss", "controlgs")), grid_result(("ss", "controlgs"))]
    runs[0].foveation, runs[1].foveation = axis(0.0), axis(2.0)
    md = markdown_tables(runs)
    rows = [line for line in md.splitlines() if line.startswith("| SS-backbone | 20.00 / 0.5000")]
    assert rows == ["| SS-backbone | 20.00 / 0.5000 | 33.00 / 0.5000 | 20.00 / 0.5000 | 20.00 / 0.5000 |",
                    "| SS-backbone | 20.00 / 0.5000 | 10.00 / 0.5000 | 20.00 / 0.5000 | 20.00 / – |"]
    assert "Gaze (0°, 0°):" in md and "Gaze (10°, 0°):" in md and "blur scale at most 4" in md
    write_report(tmp_path, runs[:1])
    back = read_results(json.loads((tmp_path / "results.json").read_text()))[0]
    assert back.foveation == runs[0].foveation
