"""``controlgs optics bench``: error vs time of the PSF operators on natural images (scikit-image's
public-domain photographs), forward and forward+backward, against :func:`psf_exact`; plus the
kernel-size scaling of the fast mode. Writes ``optics_bench.md`` and ``optics_bench.png``."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Callable, Sequence

import torch

from .bank import PSFBank
from .operators import psf_distortion, psf_exact, psf_fast

__all__ = ["run"]

TOLS = (0.1, 0.05, 0.02, 0.01)


def _image(size: int) -> torch.Tensor:
    from skimage import data, transform

    img = transform.resize(data.astronaut(), (size, size), anti_aliasing=True)
    return torch.tensor(img, dtype=torch.float32).permute(2, 0, 1).contiguous()


def _time(fn: Callable[[], object], repeat: int = 3) -> tuple[float, float]:
    """Best wall-clock and best process-CPU seconds of ``repeat`` runs (CPU time is the steadier
    figure on a shared machine; on an idle one, wall ~ CPU / threads)."""
    wall = cpu = float("inf")
    for _ in range(repeat):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return wall, cpu


def _fwd_bwd(op, x: torch.Tensor, w: torch.Tensor) -> None:
    xr = x.clone().requires_grad_(True)
    (op(xr) * w).sum().backward()


def _kernel_scaling(size: int, zone: int) -> list[tuple[int, float]]:
    """Fast-mode fwd+bwd time for banks of Gaussian PSFs spanning k = 33 and 129 px."""
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
        op = lambda a: psf_fast(a, rb, 0.02, zone)  # noqa: E731
        _fwd_bwd(op, x, w)
        out.append((rb.k, _time(lambda: _fwd_bwd(op, x, w))[1]))
    return out


def run(sizes: Sequence[int] = (256, 512, 1024), exact_max: int = 1024,
        threads: int = 2, out: Path | None = None, zone: int = 5, tols: Sequence[float] = TOLS) -> list[dict]:
    """Time and compare the operators; ``out``: folder for ``optics_bench.md`` / ``.png`` (None: print only)."""
    torch.set_num_threads(threads)
    bank = PSFBank.default()
    rows: list[dict] = []
    for size in sizes:
        x = _image(size)
        w = torch.rand(3, size, size, generator=torch.Generator().manual_seed(0))
        t0 = time.perf_counter()
        rb = bank.resample_to(size, size)
        t_res = time.perf_counter() - t0
        t0 = time.perf_counter()
        with torch.no_grad():
            ref = psf_exact(x, rb)
        t_exact_build = time.perf_counter() - t0
        ops: list[tuple[str, str, Callable]] = [("distortion", "-", lambda a: psf_distortion(a, rb))]
        ops += [("fast", f"tol={t:g}, zone={zone}", (lambda tt: lambda a: psf_fast(a, rb, tt, zone))(t)) for t in tols]
        if size <= exact_max:
            ops.append(("exact", "-", lambda a: psf_exact(a, rb)))
        for name, knob, op in ops:
            t0 = time.perf_counter()
            with torch.no_grad():
                y = op(x)                                               # also builds the cached tables
            t_first = time.perf_counter() - t0
            with torch.no_grad():
                t_f, c_f = _time(lambda: op(x))
            t_fb, c_fb = _time(lambda: _fwd_bwd(op, x, w))
            err = (y - ref).norm() / ref.norm()
            mx = (y - ref).abs().max() / ref.abs().max()
            rows.append(dict(size=size, op=name, knob=knob, fwd_s=t_f, fwd_bwd_s=t_fb, fwd_cpu=c_f, fwd_bwd_cpu=c_fb,
                             rel_l2=err.item(),
                             max_rel=mx.item(), first_call_s=t_first))
            print(f"{size:5d} {name:10s} {knob:18s} fwd {t_f:7.3f} s ({c_f:6.3f} cpu)  fwd+bwd {t_fb:7.3f} s "
                  f"({c_fb:6.3f} cpu)  "
                  f"relL2 {err.item():.2e}  max {mx.item():.2e}  (first call {t_first:.2f} s)", flush=True)
        print(f"{size:5d} resample_to {t_res:.2f} s, exact reference incl. its tables {t_exact_build:.2f} s")
    scaling = _kernel_scaling(max(sizes), zone=6)
    print(f"kernel-size scaling at {max(sizes)}^2 (fast, fwd+bwd): " + ", ".join(f"k={k}: {t:.3f} s" for k, t in scaling))
    if out is not None:
        _write(rows, scaling, max(sizes), threads, Path(out))
    return rows


def _write(rows: list[dict], scaling, size: int, threads: int, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"Operators vs `psf_exact` on `skimage.data.astronaut` (3 primaries), float32, {threads} CPU threads, "
             "best of 3 (wall clock, and process CPU time summed over threads). fwd+bwd = forward and backward "
             "w.r.t. the image. first call = forward incl. building the cached tables for that knob.", "",
             "| size | operator | knob | fwd wall (s) | fwd CPU (s) | fwd+bwd wall (s) | fwd+bwd CPU (s) | rel. L2 vs exact "
             "| max err / max | first call (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['size']} | {r['op']} | {r['knob']} | {r['fwd_s']:.3f} | {r['fwd_cpu']:.3f} | "
                     f"{r['fwd_bwd_s']:.3f} | {r['fwd_bwd_cpu']:.3f} | "
                     f"{r['rel_l2']:.2e} | {r['max_rel']:.2e} | {r['first_call_s']:.2f} |")
    lines += ["", f"Kernel-size scaling of the fast mode at {size}^2 (Gaussian PSF banks, fwd+bwd CPU time): "
              + ", ".join(f"k = {k}: {t:.3f} s" for k, t in scaling)
              + f" (ratio {scaling[1][1] / scaling[0][1]:.2f})", ""]
    (out / "optics_bench.md").write_text("\n".join(lines))
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # pragma: no cover
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    for size in sorted({r["size"] for r in rows}):
        rs = [r for r in rows if r["size"] == size and r["op"] != "exact"]
        ax.plot([r["fwd_bwd_cpu"] for r in rs], [max(r["rel_l2"], 1e-7) for r in rs], "o-", label=f"{size}^2")
        for r in rs:
            ax.annotate(r["knob"].split(",")[0] if r["op"] == "fast" else "distortion",
                        (r["fwd_bwd_cpu"], max(r["rel_l2"], 1e-7)), fontsize=6)
        ex = [r for r in rows if r["size"] == size and r["op"] == "exact"]
        if ex:
            ax.axvline(ex[0]["fwd_bwd_cpu"], ls=":", lw=0.8, color=ax.lines[-1].get_color())
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("forward + backward CPU time (s, summed over threads)")
    ax.set_ylabel("relative L2 error vs exact")
    ax.set_title("PSF operators: accuracy vs time (dotted: exact)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "optics_bench.png", dpi=120)
