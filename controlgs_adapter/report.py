"""The evaluation report: every number as JSON, the paper's tables in Markdown, and plots.

Files written by :func:`write_report` into a folder:
- ``results.json``: every per-view, per-setting value, grid means, overall means, run info; with
  several seeds, each seed's run and the mean / std over seeds (read back by :func:`read_results`);
- ``report.md``: Tbl. 1 (end-to-end quality averaged over views and the 20 settings; mean ± std
  over seeds when there are several), the ablation table (when ablations ran), the ideal-render
  bound (the ground truth through the same pipeline), which differences exceed the seed spread,
  the per-setting grids and what the numbers show;
- ``heatmap.png``: ControlGS minus SS-backbone per setting (paper Fig. 4) and ControlGS minus the
  ideal render;
- ``comparison.png``: rendered and eye-space images of the three methods at two settings (Fig. 1);
- ``condition_response.png``: raw renders while one condition varies and the others are off (Fig. 8).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from .ablations import ABLATIONS
from .errors import InputValueError
from .evaluation import IDEAL, FoveationAxis, GridResult
from controlgs_adapter.formats.safetensors import atomic_write
from .metrics import FLIP_PPD

__all__ = ["METHOD_LABELS", "ABLATIONS", "SPREAD_FACTOR", "markdown_tables", "plot_heatmaps", "plot_comparison",
           "plot_condition_response", "write_report", "read_results", "seed_summary", "LPIPS_NOT_COMPUTED"]

METHOD_LABELS: dict[str, str] = {
    "no_ss": "Backbone (no SS)",
    "ss": "SS-backbone",
    "controlgs": "ControlGS",
    "wo_lens": "w/o Lens",
    "wo_display": "w/o Display Mapping",
    "wo_resample": "w/o Resampling",
    "state_blind": "w/o State-Aware",
    "wo_foveation": "w/o Foveation",
    IDEAL: "Ideal render (GT through E_s)",
}
#: a difference of seed means "exceeds the spread" when larger than this many pooled std over seeds
SPREAD_FACTOR = 2.0
_HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "flip": False, "lpips": False, "cvvdp": True}
_FMT = {"psnr": "{:.2f}", "ssim": "{:.4f}", "flip": "{:.4f}", "lpips": "{:.4f}", "cvvdp": "{:.3f}"}
LPIPS_NOT_COMPUTED = ("LPIPS was not computed: it needs the AlexNet backbone weights, which no package ships and "
                      "which are never downloaded; give local files with `--lpips-weights PATH` (torchvision's "
                      "alexnet-owt-7be5be79.pth, plus the lpips package's weights/v0.1/alex.pth head unless "
                      "`pip install --no-deps lpips` provides it).")


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def _arrow(metric: str) -> str:
    return "↑" if _HIGHER_IS_BETTER.get(metric, True) else "↓"


def _runs(results: GridResult | Sequence[GridResult]) -> list[GridResult]:
    """The seeds' results as a list, checked to share grid, methods and metrics."""
    runs = [results] if isinstance(results, GridResult) else list(results)
    if not runs:
        raise InputValueError("no results to report")
    first = runs[0]
    for r in runs[1:]:
        if (r.downsample, r.power_saving, r.methods, r.metrics) != (first.downsample, first.power_saving, first.methods,
                                                                    first.metrics):
            raise InputValueError("the seeds' results differ in grid, methods or metrics; they cannot be pooled")
    return runs


def _pooled(runs: Sequence[GridResult]) -> GridResult:
    """One result whose per-view values are the mean over the seeds (the per-setting grids, findings, plots)."""
    if len(runs) == 1:
        return runs[0]
    first = runs[0]
    per_view = {m: {k: torch.stack([r.per_view[m][k] for r in runs]).mean(dim=0) for k in first.metrics}
                for m in first.methods}
    fov = first.foveation
    if fov is not None and all(r.foveation is not None for r in runs):
        fov = FoveationAxis(fov.gazes, fov.settings, fov.model, fov.bands,
                            {m: {k: torch.stack([r.foveation.per_view[m][k] for r in runs if r.foveation]).mean(dim=0)
                                 for k in mv} for m, mv in fov.per_view.items()})
    return GridResult(first.downsample, first.power_saving, per_view, first.optics_mode, dict(first.info), fov)


def _foveation_tables(fov: FoveationAxis) -> list[str]:
    """The foveation axis: per gaze, PSNR / SSIM of each method on the whole image and per eccentricity band
    (means over the settings and views; "–" for a band without pixels)."""
    def band(lo: float, hi: float) -> str:
        return f"< {hi:g}°" if lo == 0 else (f"≥ {lo:g}°" if hi == float("inf") else f"{lo:g}-{hi:g}°")

    settings = ", ".join(f"(d={d:g}, ρ={r:g})" for d, r in fov.settings)
    m = fov.model
    lines = ["## Foveation", "",
             f"At each gaze the foveation stage (ω(e) = {m['omega0']:.4g}° + {m['slope']:g} e"
             + (f", blur scale at most {m['max_scale']:g}" if m.get("max_scale") is not None else "")
             + f") runs with the gaze in the state, at the settings {settings}; PSNR / SSIM on the whole image and "
             "per eccentricity band, in visual degrees through the lens from the gaze (PSNR from the band's MSE, SSIM "
             "the SSIM map over the windows centred in the band; – : no pixel in that band), means over the settings "
             "and the test views.", ""]
    cols = [("", "All")] + [(f"_{n}", f"{n.capitalize()} ({band(lo, hi)})") for n, lo, hi in fov.bands]
    for g, (az, el) in enumerate(fov.gazes):
        lines += [f"Gaze ({az:g}°, {el:g}°):", "", "| Method | " + " | ".join(c[1] for c in cols) + " |",
                  "|---|" + "---:|" * len(cols)]
        for method in fov.per_view:
            cells = []
            for suffix, _ in cols:
                p, q = fov.mean(method, "psnr" + suffix, g), fov.mean(method, "ssim" + suffix, g)
                cells.append(f"{'–' if p is None else f'{p:.2f}'} / {'–' if q is None else f'{q:.4f}'}")
            lines.append(f"| {_label(method)} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def seed_summary(results: GridResult | Sequence[GridResult]) -> dict[str, dict[str, dict[str, Any]]]:
    """``{method: {metric: {"mean", "std", "per_seed"}}}`` of the overall means (views x grid) over
    the seeds; ``std`` is the sample standard deviation (ddof 1), 0 for one seed."""
    runs = _runs(results)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for m in runs[0].methods:
        out[m] = {}
        for k in runs[0].metrics:
            vals = torch.tensor([r.mean(m, k) for r in runs], dtype=torch.float64)
            out[m][k] = {"mean": float(vals.mean()), "std": float(vals.std()) if len(vals) > 1 else 0.0,
                         "per_seed": vals.tolist()}
    return out


def seed_independent(runs: Sequence[GridResult]) -> set[str]:
    """The methods whose every per-view value is the same in each seed's result: they do not depend on
    the seed (the backbone without and with supersampling and the ideal render are evaluated once and
    shared by the seeds). With one seed: none (no spread was measured)."""
    if len(runs) < 2:
        return set()
    first = runs[0]
    return {m for m in first.methods
            if all(torch.equal(r.per_view[m][k], first.per_view[m][k]) for r in runs[1:] for k in first.metrics)}


def _table(summary: Mapping[str, Mapping[str, Mapping[str, Any]]], methods: Sequence[str], metrics: Sequence[str],
           seeds: int, fixed: set[str] | frozenset[str] = frozenset()) -> list[str]:
    """Rows ``method | metric...``: the mean (± std over seeds when several, but for the ``fixed``
    methods, which do not depend on the seed); the best non-ideal mean in bold."""
    lines = ["| Method | " + " | ".join(f"{m.upper()}{_arrow(m)}" for m in metrics) + " |",
             "|---|" + "---:|" * len(metrics)]
    best = {}
    for k in metrics:
        vals = [summary[m][k]["mean"] for m in methods if m != IDEAL]
        best[k] = (max(vals) if _HIGHER_IS_BETTER.get(k, True) else min(vals)) if vals else None
    for m in methods:
        cells = []
        for k in metrics:
            fmt = _FMT.get(k, "{:.4f}")
            v = summary[m][k]["mean"]
            s = fmt.format(v) + (f" ± {fmt.format(summary[m][k]['std'])}" if seeds > 1 and m not in fixed else "")
            cells.append(f"**{s}**" if m != IDEAL and v == best[k] else s)
        lines.append(f"| {_label(m)} | " + " | ".join(cells) + " |")
    return lines


def _grid_table(result: GridResult, values: torch.Tensor, fmt: str) -> list[str]:
    head = "| d \\ ρ | " + " | ".join(f"{p:.0%}" for p in result.power_saving) + " |"
    lines = [head, "|---|" + "---:|" * len(result.power_saving)]
    for i, d in enumerate(result.downsample):
        lines.append(f"| {d:g}× | " + " | ".join(fmt.format(float(v)) for v in values[i]) + " |")
    return lines


def _spread(summary: Mapping[str, Mapping[str, Mapping[str, Any]]], metrics: Sequence[str], methods: Sequence[str],
            seeds: int) -> list[str]:
    """Which differences of seed means (ControlGS vs SS-backbone, each ablation vs ControlGS) exceed
    :data:`SPREAD_FACTOR` pooled std over seeds, sqrt((s_a² + s_b²) / 2)."""
    pairs = [("controlgs", "ss")] if {"controlgs", "ss"} <= set(methods) else []
    pairs += [(a, "controlgs") for a in ABLATIONS if a in methods and "controlgs" in methods]
    if not pairs:
        return []
    if seeds < 2:
        return ["- One seed: no spread was measured, so no difference is shown to exceed it (`--seeds K`)."]
    out = []
    for a, b in pairs:
        parts = []
        for k in metrics:
            diff = summary[a][k]["mean"] - summary[b][k]["mean"]
            pooled = math.sqrt((summary[a][k]["std"] ** 2 + summary[b][k]["std"] ** 2) / 2.0)
            exceeds = abs(diff) > SPREAD_FACTOR * pooled
            parts.append(f"{k.upper()} {diff:+.3g} ({'exceeds' if exceeds else 'within'} the spread, pooled std {pooled:.2g})")
        out.append(f"- {_label(a)} minus {_label(b)}: " + "; ".join(parts) + ".")
    return out


def _findings(result: GridResult) -> list[str]:
    """What the numbers show, stated as measured (no claim beyond them)."""
    out: list[str] = []
    if not {"ss", "controlgs"} <= set(result.methods):
        return out
    for k in result.metrics:
        sign = 1.0 if _HIGHER_IS_BETTER.get(k, True) else -1.0
        delta = sign * (result.grid("controlgs", k) - result.grid("ss", k))
        wins = int((delta > 0).sum())
        out.append(f"- {k.upper()}: ControlGS better than SS-backbone in {wins}/{delta.numel()} settings "
                   f"(mean difference {sign * float(delta.mean()):+.4g}, worst cell {sign * float(delta.min()):+.4g}).")
        if "no_ss" in result.methods:
            d2 = sign * (result.grid("ss", k) - result.grid("no_ss", k))
            ties = int((d2 == 0).sum())
            out.append(f"- {k.upper()}: SS-backbone better than no-SS in {int((d2 > 0).sum())}/{d2.numel()} settings"
                       + (f", equal in {ties} (at d = 1 both render at S)" if ties else "")
                       + f" (mean difference {sign * float(d2.mean()):+.4g}).")
        if IDEAL in result.methods:
            d3 = sign * (result.grid("controlgs", k) - result.grid(IDEAL, k))
            out.append(f"- {k.upper()}: the ideal render (ground truth through the pipeline) scores "
                       f"{result.mean(IDEAL, k):.4g}, the pipeline's own cost to a perfect render; ControlGS is above "
                       f"that bound in {int((d3 > 0).sum())}/{d3.numel()} settings (pre-compensating beyond it; mean "
                       f"ControlGS minus ideal {sign * float(d3.mean()):+.4g}).")
    ablations = [a for a in ABLATIONS if a in result.methods]
    if ablations and "psnr" in result.metrics:
        drop = {a: result.mean("controlgs", "psnr") - result.mean(a, "psnr") for a in ablations}
        order = ", ".join(f"{_label(a)} {v:+.3f} dB" for a, v in sorted(drop.items(), key=lambda kv: -kv[1]))
        out.append(f"- PSNR lost by each ablation (ControlGS minus ablation, larger = that part matters more): {order}.")
    return out


def markdown_tables(results: GridResult | Sequence[GridResult], info: Mapping[str, Any] | None = None) -> str:
    """The report's Markdown from one result or one per seed: Tbl. 1 (mean ± std over seeds), the
    ablation table, the ideal-render bound, the spread test, per-setting grids (means over seeds),
    findings."""
    runs = _runs(results)
    result = _pooled(runs)
    summary = seed_summary(runs)
    seeds, metrics = len(runs), result.metrics
    fixed = seed_independent(runs)
    main = [m for m in ("no_ss", "ss", "controlgs") if m in result.methods]
    lines = ["# ControlGS evaluation report", ""]
    if info:
        lines += ["Run: " + ", ".join(f"{k} = {v}" for k, v in info.items() if not isinstance(v, (dict, list))), ""]
    over = f" and over {seeds} seeds (mean ± sample std of the seeds' means)" if seeds > 1 else ""
    lines += [f"End-to-end quality after the XR pipeline (optics `{result.optics_mode}`), averaged over the "
              f"{result.per_view[result.methods[0]][metrics[0]].shape[-1]} test views and the "
              f"{len(result.downsample) * len(result.power_saving)} run-time settings{over} (paper Tbl. 1); the last row "
              "is the ideal-render bound, the ground truth itself through the same pipeline:", ""]
    lines += _table(summary, main + ([IDEAL] if IDEAL in result.methods else []), metrics, seeds, fixed) + [""]
    notes = []
    if fixed:
        notes.append(f"Rows without ± ({', '.join(_label(m) for m in result.methods if m in fixed)}) do not depend on the "
                     "seed: they are the same in every seed's evaluation.")
    if "flip" in metrics:
        notes.append(f"FLIP is NVIDIA's LDR-FLIP (flip-evaluator) at {FLIP_PPD:.2f} pixels per degree (its default observer), mean error per image.")
    notes.append(f"LPIPS (AlexNet) from {info['lpips_weights']}." if info and info.get("lpips_weights") and "lpips" in metrics
                 else LPIPS_NOT_COMPUTED)
    cvvdp = info.get("cvvdp") if info else None
    if isinstance(cvvdp, Mapping) and "cvvdp" in metrics and isinstance(cvvdp.get("ppd"), Mapping):
        ppd = ", ".join(f"{v:.2f} at {k}" for k, v in cvvdp["ppd"].items())
        notes.append(f"CVVDP is ColorVideoVDP's JOD (cvvdp) on the display seen through {cvvdp.get('lens')}: {ppd} pixels per "
                     f"degree (on axis), {cvvdp.get('display')} photometry.")
    elif isinstance(cvvdp, Mapping) and cvvdp.get("skipped"):
        notes.append(f"ColorVideoVDP was not computed: {cvvdp['skipped']}")
    lines += notes + [""]
    ablations = [a for a in ABLATIONS if a in result.methods]
    if ablations:
        lines += ["Ablations (paper Tbl. 4):", ""]
        lines += _table(summary, ["controlgs", *ablations, *(["ss"] if "ss" in result.methods else [])], metrics, seeds,
                        fixed) + [""]
    if result.foveation is not None:
        lines += _foveation_tables(result.foveation)
    spread = _spread(summary, metrics, result.methods, seeds)
    if spread:
        lines += ["## Differences against the seed spread", "",
                  f"A difference of seed means exceeds the spread when it is larger than {SPREAD_FACTOR:g} x the pooled "
                  "std over seeds, sqrt((s_a² + s_b²) / 2):", ""] + spread + [""]
    lines += ["## What the numbers show", ""] + (_findings(result) or ["- (needs ss and controlgs)"]) + [""]
    lines += ["## Per setting" + (f" (means over {seeds} seeds)" if seeds > 1 else ""), ""]
    for k in metrics:
        fmt = _FMT.get(k, "{:.4f}")
        for m in result.methods:
            lines += [f"{k.upper()} of {_label(m)}:", ""] + _grid_table(result, result.grid(m, k), fmt) + [""]
        for base in ("ss", IDEAL):
            if {base, "controlgs"} <= set(result.methods):
                delta = result.grid("controlgs", k) - result.grid(base, k)
                lines += [f"{k.upper()} of ControlGS minus {_label(base)}:", ""] + _grid_table(result, delta, "{:+." + fmt[-3:]) + [""]
    return "\n".join(lines)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_heatmaps(results: GridResult | Sequence[GridResult], path: str | Path, *, method: str = "controlgs",
                  baselines: Sequence[str] = ("ss", IDEAL)) -> Path:
    """Heatmaps of ``method`` minus each of ``baselines`` that was evaluated (one row each: SS-backbone,
    paper Fig. 4, and the ideal render), one panel per metric; means over the seeds."""
    plt = _pyplot()
    result = _pooled(_runs(results))
    metrics = result.metrics
    rows = [b for b in baselines if b in result.methods]
    fig, axes = plt.subplots(len(rows), len(metrics), figsize=(4.2 * len(metrics), 3.6 * len(rows)), squeeze=False)
    for r, baseline in enumerate(rows):
        for ax, k in zip(axes[r], metrics):
            delta = (result.grid(method, k) - result.grid(baseline, k)).numpy()
            lim = max(float(abs(delta).max()), 1e-12)
            good_positive = _HIGHER_IS_BETTER.get(k, True)
            im = ax.imshow(delta, cmap="RdBu" if good_positive else "RdBu_r", vmin=-lim, vmax=lim)
            for i in range(delta.shape[0]):
                for j in range(delta.shape[1]):
                    ax.text(j, i, _FMT.get(k, "{:.3f}").replace("{:", "{:+").format(delta[i, j]), ha="center", va="center",
                            fontsize=8)
            ax.set_xticks(range(len(result.power_saving)), [f"{p:.0%}" for p in result.power_saving])
            ax.set_yticks(range(len(result.downsample)), [f"{d:g}×" for d in result.downsample])
            ax.set_xlabel("display power saving ρ")
            ax.set_ylabel("downsample d")
            ax.set_title(f"Δ{k.upper()} ({_label(method)} − {'ideal' if baseline == IDEAL else _label(baseline)})", fontsize=9)
            fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    path = Path(path)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    plt.close(fig)
    return path


def _show(ax, img: torch.Tensor, title: str) -> None:
    ax.imshow(img.detach().clamp(0, 1).permute(1, 2, 0).cpu().numpy(), interpolation="nearest")
    ax.set_title(title, fontsize=7)
    ax.axis("off")


def plot_comparison(panels: Mapping[str, Any], path: str | Path) -> Path:
    """Rendered and eye-space images (paper Fig. 1) from :func:`evaluation.side_by_side`'s output:
    ``{"gt": [3,S,S], "settings": [(d, rho)], "rows": {method: [(rendered, eye, psnr, ssim) per setting]}}``."""
    plt = _pyplot()
    settings, rows = panels["settings"], panels["rows"]
    ncol = 2 * len(settings)
    fig, axes = plt.subplots(len(rows) + 1, ncol, figsize=(2.0 * ncol, 2.1 * (len(rows) + 1)), squeeze=False)
    for c in range(ncol):
        axes[0, c].axis("off")
    _show(axes[0, 0], panels["gt"], "ground truth")
    for r, (method, cells) in enumerate(rows.items(), start=1):
        for s, ((d, rho), (rendered, eye, p, q)) in enumerate(zip(settings, cells)):
            _show(axes[r, 2 * s], rendered, f"{_label(method)}: rendered\nd={d:g}, ρ={rho:.0%}")
            _show(axes[r, 2 * s + 1], eye, f"eye  {p:.2f} dB / {q:.3f}")
    fig.tight_layout()
    path = Path(path)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    plt.close(fig)
    return path


def plot_condition_response(strips: Mapping[str, Sequence[tuple[str, torch.Tensor]]], path: str | Path) -> Path:
    """Raw renders (before the pipeline) while one condition varies and the others are off
    (paper Fig. 8): ``{module: [(label, image [3,S,S]), ...]}``."""
    plt = _pyplot()
    ncol = max(len(v) for v in strips.values())
    fig, axes = plt.subplots(len(strips), ncol, figsize=(2.0 * ncol, 2.1 * len(strips)), squeeze=False)
    for r, (module, row) in enumerate(strips.items()):
        for c in range(ncol):
            if c < len(row):
                _show(axes[r, c], row[c][1], f"{module}: {row[c][0]}")
            else:
                axes[r, c].axis("off")
    fig.tight_layout()
    path = Path(path)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=120))
    plt.close(fig)
    return path


def _results_json(runs: Sequence[GridResult], info: Mapping[str, Any]) -> dict[str, Any]:
    """One run: :meth:`GridResult.to_json` with ``info`` merged in. Several seeds: ``info``, ``seeds``,
    ``summary`` (:func:`seed_summary`) and each seed's ``to_json()`` in ``runs``."""
    if len(runs) == 1:
        data = runs[0].to_json()
        return {"info": {**data.pop("info"), **dict(info)}, **data}
    return {"info": {**{k: v for k, v in runs[0].info.items() if k != "seed"}, **dict(info)},
            "seeds": [r.info.get("seed") for r in runs], "summary": seed_summary(runs), "runs": [r.to_json() for r in runs]}


def read_results(data: Mapping[str, Any]) -> list[GridResult]:
    """The results a report's ``results.json`` holds: one :class:`GridResult` per seed (one for a
    single run)."""
    if "runs" in data:
        if not isinstance(data["runs"], list) or not data["runs"]:
            raise InputValueError("results.json: 'runs' must be a non-empty list of GridResult JSON")
        return _runs([GridResult.from_json(r) for r in data["runs"]])
    return [GridResult.from_json(data)]


def write_report(out: str | Path, results: GridResult | Sequence[GridResult], *, info: Mapping[str, Any] | None = None,
                 comparison: Mapping[str, Any] | None = None,
                 response: Mapping[str, Sequence[tuple[str, torch.Tensor]]] | None = None) -> list[Path]:
    """Write ``results.json``, ``report.md`` and the plots into folder ``out`` from one result or one
    per seed (each with its ``info["seed"]``); returns the paths."""
    runs = _runs(results)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = _results_json(runs, info or {})
    paths = [atomic_write(out / "results.json", lambda tmp: Path(tmp).write_text(json.dumps(data, indent=1)))]
    md = markdown_tables(runs, data["info"])
    figures = []
    if {"ss", "controlgs"} <= set(runs[0].methods):
        paths.append(plot_heatmaps(runs, out / "heatmap.png"))
        figures.append("![ControlGS minus SS-backbone and minus the ideal render per setting](heatmap.png)")
    if comparison:
        paths.append(plot_comparison(comparison, out / "comparison.png"))
        figures.append("![rendered and eye-space images at two settings](comparison.png)")
    if response:
        paths.append(plot_condition_response(response, out / "condition_response.png"))
        figures.append("![condition response: one condition varies, the others are off](condition_response.png)")
    if figures:
        md += "\n## Figures\n\n" + "\n\n".join(figures) + "\n"
    paths.append(atomic_write(out / "report.md", lambda tmp: Path(tmp).write_text(md)))
    return paths
