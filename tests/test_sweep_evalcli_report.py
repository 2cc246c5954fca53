"""controlgs_adapter.report and GridResult by hand: a 2 x 2 grid of two views whose every cell is a
number written here, and the report's lines (tables, bold best, findings, spread, per-setting grids,
notes, files) compared with the text those numbers give, worked out in the comments."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from controlgs_adapter.errors import InputValueError
from controlgs_adapter.evaluation import BASELINES, GRID_DOWNSAMPLE, GRID_POWER_SAVING, IDEAL, GridResult, scores
from controlgs_adapter.metrics import FLIP_PPD
from controlgs_adapter.report import (LPIPS_NOT_COMPUTED, METHOD_LABELS, SPREAD_FACTOR, markdown_tables,
                                      plot_comparison, plot_condition_response, plot_heatmaps, read_results,
                                      seed_summary, write_report)

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


# ------------------------------------------------------------------------------ files
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
