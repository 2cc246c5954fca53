"""The evaluation report: every number as JSON, the paper's tables in Markdown, and plots.

Files written by :func:`write_report` into a folder:
- ``results.json``: every per-view, per-setting value, grid means, overall means, run info;
- ``report.md``: Tbl. 1 (end-to-end quality averaged over views and the 20 settings), the
  ablation table (when ablations ran), the per-setting grids and what the numbers show;
- ``heatmap.png``: ControlGS minus SS-backbone per setting (paper Fig. 4);
- ``comparison.png``: rendered and eye-space images of the three methods at two settings (Fig. 1);
- ``condition_response.png``: raw renders while one condition varies and the others are off (Fig. 8).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from .evaluation import GridResult
from .io import atomic_write

__all__ = ["METHOD_LABELS", "ABLATIONS", "markdown_tables", "plot_heatmaps", "plot_comparison",
           "plot_condition_response", "write_report"]

METHOD_LABELS: dict[str, str] = {
    "no_ss": "Backbone (no SS)",
    "ss": "SS-backbone",
    "controlgs": "ControlGS",
    "wo_lens": "w/o Lens",
    "wo_display": "w/o Display Mapping",
    "wo_resample": "w/o Resampling",
    "state_blind": "w/o State-Aware",
}
#: ablation name -> (modules trained, state_blind), paper Tbl. 4
ABLATIONS: dict[str, tuple[tuple[str, ...], bool]] = {
    "wo_lens": (("resample", "display"), False),
    "wo_display": (("lens", "resample"), False),
    "wo_resample": (("lens", "display"), False),
    "state_blind": (("lens", "resample", "display"), True),
}
_HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "flip": False, "cvvdp": True}
_FMT = {"psnr": "{:.2f}", "ssim": "{:.4f}", "flip": "{:.4f}", "cvvdp": "{:.3f}"}


def _label(method: str) -> str:
    return METHOD_LABELS.get(method, method)


def _arrow(metric: str) -> str:
    return "↑" if _HIGHER_IS_BETTER.get(metric, True) else "↓"


def _table(result: GridResult, methods: Sequence[str]) -> list[str]:
    metrics = result.metrics
    lines = ["| Method | " + " | ".join(f"{m.upper()}{_arrow(m)}" for m in metrics) + " |",
             "|---|" + "---:|" * len(metrics)]
    best = {}
    for k in metrics:
        vals = [result.mean(m, k) for m in methods]
        best[k] = max(vals) if _HIGHER_IS_BETTER.get(k, True) else min(vals)
    for m in methods:
        cells = []
        for k in metrics:
            v = result.mean(m, k)
            s = _FMT.get(k, "{:.4f}").format(v)
            cells.append(f"**{s}**" if v == best[k] else s)
        lines.append(f"| {_label(m)} | " + " | ".join(cells) + " |")
    return lines


def _grid_table(result: GridResult, values: torch.Tensor, fmt: str) -> list[str]:
    head = "| d \\ ρ | " + " | ".join(f"{p:.0%}" for p in result.power_saving) + " |"
    lines = [head, "|---|" + "---:|" * len(result.power_saving)]
    for i, d in enumerate(result.downsample):
        lines.append(f"| {d:g}× | " + " | ".join(fmt.format(float(v)) for v in values[i]) + " |")
    return lines


def _findings(result: GridResult) -> list[str]:
    """What the numbers show, stated as measured (no claim beyond them)."""
    out = []
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
    ablations = [a for a in ABLATIONS if a in result.methods]
    if ablations:
        drop = {a: result.mean("controlgs", "psnr") - result.mean(a, "psnr") for a in ablations}
        order = ", ".join(f"{_label(a)} {v:+.3f} dB" for a, v in sorted(drop.items(), key=lambda kv: -kv[1]))
        out.append(f"- PSNR lost by each ablation (ControlGS minus ablation, larger = that part matters more): {order}.")
    return out


def markdown_tables(result: GridResult, info: Mapping[str, Any] | None = None) -> str:
    """The report's Markdown: Tbl. 1, the ablation table, per-setting grids, findings."""
    main = [m for m in ("no_ss", "ss", "controlgs") if m in result.methods]
    lines = ["# ControlGS evaluation report", ""]
    if info:
        lines += ["Run: " + ", ".join(f"{k} = {v}" for k, v in info.items() if not isinstance(v, (dict, list))), ""]
    lines += [f"End-to-end quality after the XR pipeline (optics `{result.optics_mode}`), averaged over the "
              f"{result.per_view[main[0]]['psnr'].shape[-1]} test views and the {len(result.downsample) * len(result.power_saving)} "
              "run-time settings (paper Tbl. 1):", ""]
    lines += _table(result, main) + [""]
    ablations = [a for a in ABLATIONS if a in result.methods]
    if ablations:
        lines += ["Ablations (paper Tbl. 4):", ""]
        lines += _table(result, ["controlgs", *ablations, *(["ss"] if "ss" in result.methods else [])]) + [""]
    lines += ["## What the numbers show", ""] + (_findings(result) or ["- (needs ss and controlgs)"]) + [""]
    lines += ["## Per setting", ""]
    for k in result.metrics:
        fmt = _FMT.get(k, "{:.4f}")
        for m in result.methods:
            lines += [f"{k.upper()} of {_label(m)}:", ""] + _grid_table(result, result.grid(m, k), fmt) + [""]
        if {"ss", "controlgs"} <= set(result.methods):
            delta = result.grid("controlgs", k) - result.grid("ss", k)
            lines += [f"{k.upper()} of ControlGS minus SS-backbone:", ""] + _grid_table(result, delta, "{:+." + fmt[-3:]) + [""]
    return "\n".join(lines)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_heatmaps(result: GridResult, path: str | Path, *, method: str = "controlgs", baseline: str = "ss") -> Path:
    """Heatmaps of ``method`` minus ``baseline`` per setting, one panel per metric (paper Fig. 4)."""
    plt = _pyplot()
    metrics = result.metrics
    fig, axes = plt.subplots(1, len(metrics), figsize=(4.2 * len(metrics), 3.6), squeeze=False)
    for ax, k in zip(axes[0], metrics):
        delta = (result.grid(method, k) - result.grid(baseline, k)).numpy()
        lim = max(float(abs(delta).max()), 1e-12)
        good_positive = _HIGHER_IS_BETTER.get(k, True)
        im = ax.imshow(delta, cmap="RdBu" if good_positive else "RdBu_r", vmin=-lim, vmax=lim)
        for i in range(delta.shape[0]):
            for j in range(delta.shape[1]):
                ax.text(j, i, _FMT.get(k, "{:.3f}").replace("{:", "{:+").format(delta[i, j]), ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(result.power_saving)), [f"{p:.0%}" for p in result.power_saving])
        ax.set_yticks(range(len(result.downsample)), [f"{d:g}×" for d in result.downsample])
        ax.set_xlabel("display power saving ρ")
        ax.set_ylabel("downsample d")
        ax.set_title(f"Δ{k.upper()} ({_label(method)} − {_label(baseline)})", fontsize=9)
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


def write_report(out: str | Path, result: GridResult, *, info: Mapping[str, Any] | None = None,
                 comparison: Mapping[str, Any] | None = None,
                 response: Mapping[str, Sequence[tuple[str, torch.Tensor]]] | None = None) -> list[Path]:
    """Write ``results.json``, ``report.md`` and the plots into folder ``out``; returns the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    data = result.to_json()
    data = {"info": {**data.pop("info"), **dict(info or {})}, **data}
    paths = [atomic_write(out / "results.json", lambda tmp: Path(tmp).write_text(json.dumps(data, indent=1)))]
    md = markdown_tables(result, data["info"])
    figures = []
    if {"ss", "controlgs"} <= set(result.methods):
        paths.append(plot_heatmaps(result, out / "heatmap.png"))
        figures.append("![ControlGS minus SS-backbone per setting](heatmap.png)")
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
