"""``controlgs optics bench``: speed and error of the PSF operators on natural images (scikit-image's
public-domain photographs) in both radiometries: the per-size table build (first call), forward and
forward+backward of every operator, their error against :func:`psf_exact` of the same radiometry,
and the radiance / energy ratios measured in the same run; plus the kernel-size scaling of the fast
mode. Prints the tables; ``out`` (``--doc``: ``docs/benchmarks/``) writes ``optics_bench.md`` and ``.png``."""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import torch

from .bank import PSFBank
from .operators import psf_distortion, psf_exact, psf_fast
from .resampled import RADIOMETRIES, ResampledBank
from .stage import DEFAULT_TOL

__all__ = ["run", "parse_size", "SIZES"]

#: fast-mode tolerances timed by default: the stage's default only (``--tols 0.1 0.05 0.02 0.01``
#: gives the error-vs-time curve)
TOLS = (DEFAULT_TOL,)
SIZES = ("256", "512", "1024", "576x1024")


def parse_size(text: str | int) -> tuple[int, int]:
    """``"1024"`` -> (1024, 1024); ``"576x1024"`` -> (576, 1024) (height x width)."""
    parts = str(text).lower().split("x")
    if len(parts) not in (1, 2) or not all(p.isdigit() and int(p) >= 2 for p in parts):
        raise ValueError(f"size must be N or HxW with N, H, W >= 2, got {text!r}")
    h = int(parts[0])
    return (h, int(parts[-1]))


def _image(h: int, w: int | None = None) -> torch.Tensor:
    from skimage import data, transform

    img = transform.resize(data.astronaut(), (h, w or h), anti_aliasing=True)
    return torch.tensor(img, dtype=torch.float32).permute(2, 0, 1).contiguous()


def _clock(fn: Callable[[], object]) -> tuple[object, float, float]:
    """Result, wall-clock and process-CPU seconds of one call."""
    t, c = time.perf_counter(), time.process_time()
    r = fn()
    return r, time.perf_counter() - t, time.process_time() - c


def _time(fn: Callable[[], object], repeat: int = 3) -> tuple[float, float]:
    """Best wall-clock and best process-CPU seconds of ``repeat`` runs (CPU time is the steadier
    figure on a shared machine; on an idle one, wall ~ CPU / threads)."""
    wall = cpu = float("inf")
    for _ in range(repeat):
        _, w, c = _clock(fn)
        wall, cpu = min(wall, w), min(cpu, c)
    return wall, cpu


def _fwd_bwd(op, x: torch.Tensor, w: torch.Tensor) -> None:
    xr = x.clone().requires_grad_(True)
    (op(xr) * w).sum().backward()


def _kernel_scaling(size: int, zone: int) -> list[tuple[int, float]]:
    """Fast-mode (the stage's default tol) fwd+bwd time for banks of Gaussian PSFs spanning k = 33 and 129 px."""
    out = []
    for k in (33, 129):
        G, K = 6, 33
        t = torch.arange(K, dtype=torch.float64) - K // 2
        sig = k / 6 / (k / K)                                          # in stored samples
        g = torch.exp(-0.5 * (t[:, None] ** 2 + t[None, :] ** 2) / sig ** 2)
        c = torch.linspace(-1, 1, 9, dtype=torch.float64)
        cy, cx = torch.meshgrid(c, c, indexing="ij")
        f = -1 + (2 * torch.arange(G, dtype=torch.float64) + 1) / G
        bank = PSFBank(psf=(g / g.sum()).expand(3, G, G, K, K).clone(),
                       psf_pitch_mm=torch.full((3, G, G), 24 / size * k / K, dtype=torch.float64), field_x=f, field_y=f,
                       chief=torch.stack([cx * (1 + 0.1 * cx ** 2), cy * (1 + 0.1 * cy ** 2)], -1).expand(3, 9, 9, 2).clone(),
                       chief_x=c, chief_y=c, wavelengths_nm=(656.0, 550.0, 486.0), display_mm=(24.0, 24.0))
        rb = bank.resample_to(size, size)
        x, w = _image(size), torch.rand(3, size, size)
        op = lambda a: psf_fast(a, rb, DEFAULT_TOL, zone)  # noqa: E731
        _fwd_bwd(op, x, w)
        out.append((rb.k, _time(lambda: _fwd_bwd(op, x, w))[1]))
    return out


def _case(bank: PSFBank, H: int, W: int, rad: str, x: torch.Tensor, w: torch.Tensor, zone: int,
          tols: Sequence[float], exact_max: int, repeat: int) -> list[dict]:
    """The rows of one size and radiometry: its table build, then every operator."""
    label = f"{H}x{W}"
    rb, t_res, c_res = _clock(lambda: bank.resample_to(H, W, radiometry=rad))  # type: ignore[arg-type]
    assert isinstance(rb, ResampledBank)
    _, t_ex, c_ex = _clock(lambda: rb.zones(1, 0.0))
    build: dict = dict(size=label, radiometry=rad, op="tables", knob="-", resample_s=t_res, resample_cpu=c_res,
                       exact_s=t_ex, exact_cpu=c_ex, fast_s={}, fast_cpu={})
    for t in tols:
        _, t_f, c_f = _clock(lambda: rb.zones(zone, float(t)))
        build["fast_s"][t], build["fast_cpu"][t] = t_f, c_f
    rows = [build]
    print(f"{label:>9s} {rad:8s} tables: resample_to {t_res:.2f} s ({c_res:.2f}), exact {t_ex:.2f} s ({c_ex:.2f})"
          + "".join(f", fast tol={t:g} {build['fast_s'][t]:.2f} s ({build['fast_cpu'][t]:.2f})" for t in tols), flush=True)
    with torch.no_grad():
        ref = psf_exact(x, rb)
    ops: list[tuple[str, str, Callable]] = [("distortion", "-", lambda a: psf_distortion(a, rb))]
    ops += [("fast", f"tol={t:g}, zone={zone}", (lambda tt: lambda a: psf_fast(a, rb, tt, zone))(t)) for t in tols]
    if max(H, W) <= exact_max:
        ops.append(("exact", "-", lambda a: psf_exact(a, rb)))
    for name, knob, op in ops:
        with torch.no_grad():
            y = op(x)
            t_f, c_f = _time(lambda: op(x), repeat)
        t_fb, c_fb = _time(lambda: _fwd_bwd(op, x, w), repeat)
        err = (y - ref).norm() / ref.norm()
        mx = (y - ref).abs().max() / ref.abs().max()
        rows.append(dict(size=label, radiometry=rad, op=name, knob=knob, fwd_s=t_f, fwd_bwd_s=t_fb, fwd_cpu=c_f,
                         fwd_bwd_cpu=c_fb, rel_l2=err.item(), max_rel=mx.item()))
        print(f"{label:>9s} {rad:8s} {name:10s} {knob:18s} fwd {t_f:7.3f} s ({c_f:6.3f})  fwd+bwd {t_fb:7.3f} s "
              f"({c_fb:6.3f})  relL2 {err.item():.2e}  max {mx.item():.2e}", flush=True)
    return rows


def run(sizes: Sequence[int | str] = SIZES, exact_max: int = 1024, threads: int = 2, out: Path | None = None,
        zone: int = 5, tols: Sequence[float] = TOLS, radiometries: Sequence[str] = RADIOMETRIES, repeat: int = 3,
        scaling: bool = True, command: str = "controlgs optics bench --doc") -> list[dict]:
    """Time and compare the operators on the shipped bank, per size (``N`` or ``"HxW"``) and
    radiometry; ``out``: folder for ``optics_bench.md`` / ``.png`` (None: print only). Returns the
    operator rows; build rows carry ``op="tables"``."""
    from controlgs_adapter.checks import check_number

    check_number("repeat", repeat, integer=True, low=1, high=10**6)
    check_number("zone", zone, integer=True, low=1, high=2**31 - 1)
    check_number("threads", threads, integer=True, low=1, high=4096)
    torch.set_num_threads(threads)
    env = {k: os.environ.get(k) or "unset" for k in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads ({', '.join(f'{k}={v}' for k, v in env.items())}), "
          f"load average {load:.1f}, float32, best of {repeat}; wall s (process CPU s)", flush=True)
    bank = PSFBank.default()
    rows: list[dict] = []
    for size in sizes:
        H, W = parse_size(size)
        x = _image(H, W)
        w = torch.rand(3, H, W, generator=torch.Generator().manual_seed(0))
        for rad in radiometries:
            bank._cache.clear()                     # every (size, radiometry) starts from nothing
            rows += _case(bank, H, W, rad, x, w, zone, tols, exact_max, repeat)
            bank._cache.clear()
    ratios = _ratios(rows)
    for line in _ratio_lines(ratios):
        print(line)
    sc: list[tuple[int, float]] = []
    if scaling:
        side = max(max(parse_size(s)) for s in sizes)
        sc = _kernel_scaling(side, zone=6)
        print(f"kernel-size scaling at {side}^2 (fast, fwd+bwd): " + ", ".join(f"k={k}: {t:.3f} s" for k, t in sc))
    if out is not None:
        _write(rows, ratios, sc, threads, repeat, Path(out), f"{command}` (load average at the start {load:.1f}, "
               f"{', '.join(f'{k}={v}' for k, v in env.items())})")
    return rows


def _ratios(rows: list[dict]) -> list[dict]:
    """radiance / energy per size and operator, from the rows of one run."""
    by = {(r["size"], r["radiometry"], r["op"], r["knob"]): r for r in rows}
    out = []
    for (size, rad, op, knob), r in by.items():
        e = by.get((size, "energy", op, knob))
        if rad != "radiance" or e is None:
            continue
        if op == "tables":
            tot = lambda x, k: x[f"resample_{k}"] + x[f"exact_{k}"]  # noqa: E731
            out.append(dict(size=size, op="tables (resample_to + exact)", wall=tot(r, "s") / tot(e, "s"),
                            cpu=tot(r, "cpu") / tot(e, "cpu"), rad_s=tot(r, "s"), en_s=tot(e, "s")))
        else:
            out.append(dict(size=size, op=f"{op} fwd+bwd" + ("" if knob == "-" else f" ({knob})"),
                            wall=r["fwd_bwd_s"] / e["fwd_bwd_s"], cpu=r["fwd_bwd_cpu"] / e["fwd_bwd_cpu"],
                            rad_s=r["fwd_bwd_s"], en_s=e["fwd_bwd_s"]))
    return out


def _ratio_lines(ratios: list[dict]) -> list[str]:
    if not ratios:
        return []
    lines = ["| size | what | radiance (s) | energy (s) | radiance / energy, wall | ... CPU |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['size']} | {r['op']} | {r['rad_s']:.3f} | {r['en_s']:.3f} | {r['wall']:.2f} | {r['cpu']:.2f} |"
              for r in ratios]
    return lines


def _write(rows: list[dict], ratios: list[dict], scaling, threads: int, repeat: int, out: Path, command: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    ops = [r for r in rows if r["op"] != "tables"]
    builds = [r for r in rows if r["op"] == "tables"]
    lines = ["# PSF operators: speed and error", "", f"Operators of the shipped Cardboard bank on `skimage.data.astronaut` (3 primaries), float32, {threads} CPU "
             f"threads, best of {repeat} (wall clock, and process CPU time summed over threads). fwd+bwd = forward and "
             f"backward w.r.t. the image; error vs `psf_exact` of the same radiometry. Command: `{command}; "
             "the operators: docs/explanation/optics.md.", "",
             "Tables, first call for a size (`resample_to`: footprints, field blends; exact / fast: the per-field or "
             "per-group FFT tables of `psf_exact` / `psf_fast`):", "",
             "| size | radiometry | resample_to wall (CPU) s | exact tables wall (CPU) s | fast tables wall (CPU) s |",
             "|---|---|---|---|---|"]
    for b in builds:
        fast = ", ".join(f"tol {t:g}: {b['fast_s'][t]:.2f} ({b['fast_cpu'][t]:.2f})" for t in b["fast_s"])
        lines.append(f"| {b['size']} | {b['radiometry']} | {b['resample_s']:.2f} ({b['resample_cpu']:.2f}) | "
                     f"{b['exact_s']:.2f} ({b['exact_cpu']:.2f}) | {fast or '-'} |")
    lines += ["", "| size | radiometry | operator | knob | fwd wall (s) | fwd CPU (s) | fwd+bwd wall (s) | fwd+bwd CPU (s) "
              "| rel. L2 vs exact | max err / max |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in ops:
        lines.append(f"| {r['size']} | {r['radiometry']} | {r['op']} | {r['knob']} | {r['fwd_s']:.3f} | {r['fwd_cpu']:.3f} | "
                     f"{r['fwd_bwd_s']:.3f} | {r['fwd_bwd_cpu']:.3f} | {r['rel_l2']:.2e} | {r['max_rel']:.2e} |")
    if ratios:
        lines += ["", "Radiance (default) vs energy in this run:", ""] + _ratio_lines(ratios)
    if scaling:
        lines += ["", "Kernel-size scaling of the fast mode (Gaussian PSF banks, fwd+bwd CPU time): "
                  + ", ".join(f"k = {k}: {t:.3f} s" for k, t in scaling) + f" (ratio {scaling[1][1] / scaling[0][1]:.2f})"]
    lines += ["", "![error vs fwd+bwd time of the PSF operators](optics_bench.png)"]
    (out / "optics_bench.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover
        return
    fig = _figure(plt, ops)
    fig.savefig(out / "optics_bench.png", dpi=120)
    plt.close(fig)


def _figure(plt: Any, ops: list[dict]) -> Any:
    """Error vs fwd+bwd CPU time: one line per (size, radiometry) through its distortion and fast rows
    (radiance ``o-``, energy ``s--``; errors floored at 1e-7 for the log axis), each point labelled with
    its tolerance or ``distortion``, and a dotted vertical line at the exact operator's time."""
    fig, ax = plt.subplots(figsize=(6, 4))
    for key in dict.fromkeys((r["size"], r["radiometry"]) for r in ops):
        rs = [r for r in ops if (r["size"], r["radiometry"]) == key and r["op"] != "exact"]
        ls = "o-" if key[1] == "radiance" else "s--"
        ax.plot([r["fwd_bwd_cpu"] for r in rs], [max(r["rel_l2"], 1e-7) for r in rs], ls, label=f"{key[0]} {key[1]}")
        for r in rs:
            ax.annotate(r["knob"].split(",")[0] if r["op"] == "fast" else "distortion",
                        (r["fwd_bwd_cpu"], max(r["rel_l2"], 1e-7)), fontsize=6)
        ex = [r for r in ops if (r["size"], r["radiometry"]) == key and r["op"] == "exact"]
        if ex:
            ax.axvline(ex[0]["fwd_bwd_cpu"], ls=":", lw=0.8, color=ax.lines[-1].get_color())
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward + backward CPU time (s, summed over threads)")
    ax.set_ylabel("relative L2 error vs exact")
    ax.set_title("PSF operators: accuracy vs time (dotted: exact)")
    ax.legend(fontsize=6)
    fig.tight_layout()
    return fig
