"""PSF-bank build time: the rotation shortcut of a rotationally symmetric lens vs the 2-D path any other lens takes.

Three builds of a 30 x 30 field grid (3 wavelengths, 33 x 33 PSFs, 65 x 65 chief rays): the Cardboard lens
by its symmetric path (spots traced once per distinct field radius, rotated to each field), the same lens
forced through the 2-D path (``use_symmetry=False``: every field point's spot and every chief ray traced in
2-D), and the Cardboard lens with both surfaces decentred by 0.5 mm in y (which can only take the 2-D
path). Times are CPU time of the calling thread (one thread), so other jobs on a shared machine inflate
them little; the tables also give how far the forced 2-D bank is from the symmetric one (same lens).
By default at 96 and at 192 pupil samples (the shipped bank's setting).

    python benchmarks/bench_bank_build.py                        # ~3 min on one core
    python benchmarks/bench_bank_build.py --pupil-samples 48     # quicker
    python benchmarks/bench_bank_build.py --doc                  # also writes docs/benchmarks/bank_build.md
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from controlgs_adapter import __version__
from controlgs_adapter.downstream.optics.generate import build_bank
from controlgs_adapter.downstream.optics.prescription import CARDBOARD, Prescription

DOC = Path(__file__).resolve().parents[1] / "docs" / "benchmarks" / "bank_build.md"


def decentred_cardboard(dy: float = 0.5) -> Prescription:
    spec = dict(CARDBOARD, surfaces=[dict(sf, decenter_mm=[0.0, dy]) for sf in CARDBOARD["surfaces"]])
    return Prescription(spec)


def timed(rx: Prescription, grid: int, pupil_samples: int, use_symmetry: bool) -> tuple[Any, float]:
    t0 = time.thread_time()
    bank = build_bank(rx, grid=(grid, grid), pupil_samples=pupil_samples, use_symmetry=use_symmetry)
    return bank, time.thread_time() - t0


def distinct_radii(grid: int) -> int:
    """How many distinct field radii a ``grid x grid`` field grid on a square display has (what the
    symmetric path traces)."""
    f = -1 + (2 * np.arange(grid) + 1) / grid
    return len(np.unique(np.round(np.hypot(*np.meshgrid(f, f)), 9)))


def render_markdown(args: argparse.Namespace, rows: list[dict[str, Any]]) -> str:
    load = " ".join(f"{v:.1f}" for v in os.getloadavg())
    lines = [
        "# PSF-bank build time (`benchmarks/bench_bank_build.py`)",
        "",
        f"controlgs-adapter {__version__}, numpy {np.__version__}, torch {torch.__version__}, "
        f"{platform.processor() or platform.machine()}, 1 thread; load average at the end of the run: {load}.",
        "Times are CPU time of the calling thread on a shared 2-core machine (other jobs were running). "
        "Re-run on your machine: `python benchmarks/bench_bank_build.py` (prints; `--doc` rewrites this page).",
        "",
        f"Bank: {args.grid} x {args.grid} fields, 3 wavelengths, 33 x 33 PSFs, 65 x 65 chief rays; pupil samples "
        "(rays across the pupil) as in the first column: 192 is the shipped bank's setting.",
        "",
        "| pupil samples | lens | path | build (s) | vs symmetric path |",
        "| ---: | --- | --- | ---: | ---: |",
    ]
    for r in rows:
        lines += [f"| {r['n']} | {lens} | {path} | {t:.1f} | {t / r['times'][0][2]:.2f} x |" for lens, path, t in r["times"]]
    lines += [
        "",
        "Forced 2-D path vs the rotation shortcut on the same (Cardboard) lens (launch grids aimed along the "
        "axes instead of along each field's direction; PSFs have unit sum; centroids in px at 1024 px across):",
        "",
        "| pupil samples | chief rays (max, normalised) | PSF centroids (max, px) | PSFs (max L1) | transmission (max) |",
        "| ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [f"| {r['n']} | {r['chief']:.1e} | {r['centroid_px']:.4f} | {r['psf_l1']:.4f} | {r['transmission']:.1e} |"
              for r in rows]
    lines += [
        "",
        "## Reading the numbers",
        "",
        f"- The symmetric path traces one spot per distinct field radius ({distinct_radii(args.grid)} of the "
        f"{args.grid ** 2} fields) and one meridional chief-ray search; the 2-D path traces every field's spot "
        "and a 2-D Newton search (three traces per step instead of two) for the chief rays. Binning each spot "
        "and convolving it with the Airy pattern is per field in both paths, which is why the ratio is below "
        f"{args.grid ** 2} / {distinct_radii(args.grid)}.",
        "- A lens that is decentred, tilted or has its display off the axis always takes the 2-D path (the "
        "decentred rows); the forced rows are the same work on the centred lens.",
        "- The two paths' differences are sampling differences of the same spots: they shrink as the pupil "
        "samples grow. Chief rays are stored in float32.",
    ]
    return "\n".join(lines) + "\n"


def compare(sym: Any, forced: Any) -> dict[str, float]:
    """How far the forced 2-D bank is from the symmetric one (same lens)."""
    K = sym.psf.shape[-1]
    g = torch.arange(K, dtype=torch.float64) - K // 2

    def centroids(b: Any) -> tuple[torch.Tensor, torch.Tensor]:
        p = b.psf.double()
        return (p * g).sum((-1, -2)) * b.psf_pitch_mm, (p * g[:, None]).sum((-1, -2)) * b.psf_pitch_mm

    px_mm = CARDBOARD["display_mm"][0] / 1024
    return {"chief": float((sym.chief - forced.chief).abs().max()),
            "centroid_px": max(float((a - b).abs().max()) for a, b in zip(centroids(sym), centroids(forced))) / px_mm,
            "psf_l1": float((sym.psf - forced.psf).abs().sum((-1, -2)).max()),
            "transmission": float(np.abs(np.array(sym.meta["transmission"]) - np.array(forced.meta["transmission"])).max())}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--grid", type=int, default=30, help="field grid side (default 30)")
    ap.add_argument("--pupil-samples", type=int, nargs="+", default=[96, 192], help="rays across the pupil (shipped: 192)")
    ap.add_argument("--out", type=Path, default=None, help="write the report to this file (default: print only)")
    ap.add_argument("--doc", dest="out", action="store_const", const=DOC, help="write docs/benchmarks/bank_build.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    card = Prescription.cardboard()
    rows = []
    for n in args.pupil_samples:
        sym, t_sym = timed(card, args.grid, n, True)
        print(f"{n} pupil samples, Cardboard, symmetric path: {t_sym:.1f} s", flush=True)
        forced, t_forced = timed(card, args.grid, n, False)
        print(f"{n} pupil samples, Cardboard, forced 2-D path: {t_forced:.1f} s", flush=True)
        _, t_dec = timed(decentred_cardboard(), args.grid, n, True)
        print(f"{n} pupil samples, decentred Cardboard (2-D path): {t_dec:.1f} s", flush=True)
        rows.append({"n": n, **compare(sym, forced),
                     "times": [("Cardboard", "symmetric (rotation shortcut)", t_sym), ("Cardboard", "2-D (forced)", t_forced),
                               ("Cardboard, surfaces decentred 0.5 mm in y", "2-D", t_dec)]})
    text = render_markdown(args, rows)
    print(text)
    if args.out is not None:
        args.out.write_text(text)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
