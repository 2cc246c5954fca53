"""``controlgs optics``: build a PSF bank from a lens prescription, print lens figures, benchmark
the PSF operators (``controlgs optics bench``), fit the lens pre-warp for a lens (``fit-prewarp``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from .common import check_out_path, load_lens_arg


def add_parser(sub: "argparse._SubParsersAction") -> None:
    p = sub.add_parser("optics", help="PSF banks from lens prescriptions; optics operator benchmark")
    osub = p.add_subparsers(dest="optics_command", metavar="ACTION", required=True)

    b = osub.add_parser("build-bank", help="trace a PSF bank (built-in ray tracer; Google Cardboard by default)")
    _add_lens(b, "the prescription to trace")
    b.add_argument("--out", type=Path, default=Path("psf_bank.safetensors"), help="output .safetensors file")
    b.add_argument("--grid", type=int, nargs=2, default=(30, 30), metavar=("GY", "GX"), help="PSF field grid")
    b.add_argument("--psf-size", type=int, default=33, help="samples per PSF side (odd)")
    b.add_argument("--pupil-samples", type=int, default=192, help="pupil grid side (rays per PSF ~ 0.785 n^2)")
    b.add_argument("--min-pitch-px", type=float, default=0.125,
                   help="finest PSF sample pitch, in display pixels at 1024 px across")
    b.set_defaults(func=run_build)

    f = osub.add_parser("figures", help="print paraxial and real-ray figures of a prescription")
    _add_lens(f, "the prescription whose figures to print")
    f.set_defaults(func=run_figures)

    c = osub.add_parser("bench", help="speed and error of the PSF operators, both radiometries: table build, fwd, "
                                      "fwd+bwd (printed; table + plot with --out / --doc)")
    c.add_argument("--sizes", nargs="+", default=["256", "512", "1024", "576x1024"],
                   help="image sizes: N (square) or HxW")
    c.add_argument("--radiometry", nargs="+", choices=["radiance", "energy"], default=["radiance", "energy"],
                   help="radiometries to time (both by default: their ratios are printed)")
    c.add_argument("--tols", type=float, nargs="+", default=[0.02],
                   help="fast-mode tolerances (default: the stage's 0.02; 0.1 0.05 0.02 0.01 for the error-vs-time curve)")
    c.add_argument("--repeat", type=int, default=3, help="timed runs per figure (best is kept)")
    c.add_argument("--no-scaling", dest="scaling", action="store_false", help="skip the fast mode's kernel-size scaling")
    c.add_argument("--zone", type=int, default=5, help="fast-mode field-group size")
    c.add_argument("--exact-max", type=int, default=1024,
                   help="largest size where the exact operator is also timed (it is always the reference)")
    c.add_argument("--threads", type=int, default=2, help="torch intra-op threads of the timings (default 2)")
    c.add_argument("--out", type=Path, default=None, help="folder for optics_bench.md / optics_bench.png (default: print only)")
    c.add_argument("--doc", dest="out", action="store_const", const=Path("docs") / "benchmarks", help="write them into ./docs/benchmarks")
    c.set_defaults(func=run_bench)

    w = osub.add_parser("fit-prewarp", help="fit the lens pre-warp (map + gain per primary) through a lens's optics")
    w.add_argument("--lens", default="cardboard", metavar="LENS",
                   help="the lens whose bank to fit through, as `controlgs train --lens` takes it: a shipped lens "
                        "(cardboard, compact), a PSF bank .safetensors, a prescription or distortion-profile .json "
                        "(default cardboard)")
    w.add_argument("--out", type=Path, required=True, help="output LUT .safetensors ({'lens': {'lut': OUT}})")
    w.add_argument("--size", type=int, nargs="+", default=[64, 96, 128, 192, 256],
                   help="display pixels along its shorter side for the fit; several: one table per size, an image uses "
                        "those bracketing its pixel pitch (default: 64 96 128 192 256)")
    w.add_argument("--modes", nargs="+", default=["distortion", "exact"], choices=["distortion", "exact", "fast"],
                   help="optics modes to fit the pre-warp for (default: distortion exact)")
    w.add_argument("--radiometry", choices=["radiance", "energy"], default="radiance", help="the optics' radiometry")
    w.set_defaults(func=run_fit_prewarp)


def _add_lens(p: argparse.ArgumentParser, what: str) -> None:
    """``--lens NAME|PRESCRIPTION.json`` of ``build-bank`` and ``figures``."""
    p.add_argument("--lens", default="cardboard", metavar="LENS",
                   help=f"{what}: a shipped lens's (cardboard, compact) or a JSON prescription file (same keys as "
                        "controlgs_adapter.downstream.optics.prescription.CARDBOARD; default cardboard)")


def _prescription(lens: str):
    """The prescription of ``--lens``: a shipped lens's or a JSON file's; errors are one line naming
    ``--lens FILE``."""
    from controlgs_adapter.downstream.optics.lenses import SHIPPED_LENSES, shipped_prescription
    from controlgs_adapter.downstream.optics.prescription import Prescription
    from controlgs_adapter.errors import FileFormatError, InputValueError

    if lens in SHIPPED_LENSES:
        return Prescription(shipped_prescription(lens))
    path = Path(lens)
    if not path.exists():
        raise InputValueError(f"--lens {path}: no such file (nor a shipped lens: {', '.join(SHIPPED_LENSES)})")
    if not path.is_file():
        raise InputValueError(f"--lens {path}: not a regular file")
    if path.stat().st_size > 1 << 20:
        raise FileFormatError(f"--lens {path}: {path.stat().st_size} bytes, too large for a prescription")
    try:
        spec = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:  # a special file that stat calls regular (/proc/self/mem)
        raise FileFormatError(f"--lens {path}: not readable: {e.strerror or e}") from None
    except (ValueError, RecursionError) as e:
        raise FileFormatError(f"--lens {path}: not a JSON file: {e}") from None
    try:
        return Prescription(spec)
    except InputValueError as e:
        raise InputValueError(f"--lens {path}: {e}") from None


def run_build(args: argparse.Namespace) -> int:
    import time

    from controlgs_adapter.downstream.optics.generate import build_bank
    from controlgs_adapter.errors import InputValueError

    if args.psf_size < 5 or args.psf_size % 2 == 0:
        raise InputValueError(f"--psf-size must be an odd integer >= 5, got {args.psf_size}")
    if min(args.grid) < 1:
        raise InputValueError(f"--grid GY GX must both be >= 1, got {' '.join(map(str, args.grid))}")
    if args.pupil_samples < 4:
        raise InputValueError(f"--pupil-samples must be >= 4, got {args.pupil_samples}")
    if not (args.min_pitch_px > 0 and args.min_pitch_px < float("inf")):
        raise InputValueError(f"--min-pitch-px must be a finite number > 0, got {args.min_pitch_px}")
    check_out_path(args.out, "--out", folder=False)
    rx = _prescription(args.lens)
    t0 = time.perf_counter()
    bank = build_bank(rx, grid=tuple(args.grid), psf_size=args.psf_size, pupil_samples=args.pupil_samples,
                      min_pitch_px=args.min_pitch_px, progress=True)
    bank.save(args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.1f} MB) in {time.perf_counter() - t0:.1f} s")
    return 0


def run_figures(args: argparse.Namespace) -> int:
    from controlgs_adapter.downstream.optics.generate import lens_figures

    print(json.dumps(lens_figures(_prescription(args.lens)), indent=2))
    return 0


def run_bench(args: argparse.Namespace) -> int:
    from controlgs_adapter.downstream.optics.bench import run

    import shlex

    from controlgs_adapter.downstream.optics.bench import parse_size
    from controlgs_adapter.errors import InputValueError

    if args.out is not None:
        check_out_path(args.out, "--out", folder=True)
    for s in args.sizes:
        try:
            parse_size(s)
        except ValueError as e:
            raise InputValueError(f"--sizes: {e}") from None
    run(sizes=args.sizes, tols=args.tols, zone=args.zone, exact_max=args.exact_max, threads=args.threads, out=args.out,
        radiometries=args.radiometry, repeat=args.repeat, scaling=args.scaling,
        command="controlgs " + " ".join(shlex.quote(a) for a in args.argv))
    return 0




def run_fit_prewarp(args: argparse.Namespace) -> int:
    from controlgs_adapter.downstream.optics.stage import PSFOptics
    from controlgs_adapter.downstream.prewarp_fit import fit_bank_prewarp
    from controlgs_adapter.errors import FileFormatError, InputValueError

    check_out_path(args.out, "--out", folder=False)
    bad = [n for n in args.size if n < 8 or n % 2]
    if bad or len(set(args.size)) < len(args.size):
        raise InputValueError(f"--size must be different even integers >= 8, got {' '.join(map(str, args.size))}")
    try:
        bank = load_lens_arg(args).bank
    except (InputValueError, FileFormatError) as e:
        if str(e).startswith("--lens "):
            raise
        raise type(e)(f"--lens {e}") from None
    lut = fit_bank_prewarp(PSFOptics(bank, radiometry=args.radiometry), list(args.size), modes=tuple(args.modes))
    lut.save(args.out)
    print(json.dumps(lut.meta, indent=2))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1e6:.2f} MB)")
    return 0
